"""The collision on camera (issue 38 §1-§3): two carts told apart by colour
(:func:`sysid_bench.core.tracking.track_colours`), the track's camera and scene
(:func:`sysid_bench.core.footage.camera_for_track`), the clip's round trip through
``observe_clip`` and the bad options refused with one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sysid_bench.core import footage
from sysid_bench.core.tracking import ColourTrack, track_colours

RED, BLUE, SKIN = (0.85, 0.15, 0.15), (0.15, 0.3, 0.85), (0.87, 0.67, 0.55)


def _two_discs(c1, c2, radius=5.0, size=(60, 160), *, hand=None, seed=0):
    """RGB (T, H, W, 3) uint8: a red and a blue disc (soft edges) at ``c1``, ``c2`` (T, 2) px on
    a textured grey wall with a red poster (static: never an object); ``hand``: frames where a
    skin-coloured block covers the blue disc."""
    from scipy.ndimage import gaussian_filter

    h, w = size
    rng = np.random.default_rng(seed)
    wall = 0.7 + 0.08 * gaussian_filter(rng.normal(size=(h, w)), 3) / 0.1
    bg = np.repeat(wall[..., None], 3, axis=2) * [1.0, 0.98, 0.94]
    bg[3:12, 120:150] = RED  # a poster of the first cart's red
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    out = np.empty((len(c1), h, w, 3), np.uint8)
    for t in range(len(c1)):
        img = bg.copy()
        for c, rgb in ((c1[t], RED), (c2[t], BLUE)):
            cov = np.clip(radius + 0.5 - np.hypot(xx - c[0], yy - c[1]), 0, 1)[..., None]
            img = img * (1 - cov) + np.asarray(rgb) * (0.75 + 0.2 * (yy[..., None] < c[1])) * cov
        if hand is not None and t in hand:
            img[int(c2[t][1]) - 9:int(c2[t][1]) + 9, int(c2[t][0]) - 8:int(c2[t][0]) + 10] = SKIN
        noisy = 255 * img + rng.normal(0, 1.5, img.shape)
        out[t] = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    return out


def _approach_and_part(n=24):
    """Centres (T, 2) of two discs of radius 5 that close, touch for frames 10-13 (centres
    10 px apart) and part again, on row 40."""
    x1 = np.concatenate([np.linspace(30, 75, 11), np.full(3, 75.0), np.linspace(73, 50, n - 14)])
    x2 = np.concatenate([np.linspace(130, 85, 11), np.full(3, 85.0), np.linspace(88, 120, n - 14)])
    row = np.full(n, 40.0)
    return np.stack([x1, row], 1), np.stack([x2, row], 1)


def test_two_colours_followed_through_a_contact_without_a_swap():
    c1, c2 = _approach_and_part()
    trk = track_colours(_two_discs(c1, c2))
    assert trk.found.all()
    err = trk.pixels - np.stack([c1, c2], axis=1)
    assert np.abs(err).max() < 0.6, np.abs(err).max(axis=0)  # touching frames included
    # left to right in the first frame: red then blue; never swapped at the contact
    assert trk.colours[0, 0] > 0.5 and trk.colours[1, 2] > 0.5
    assert (trk.pixels[:, 0, 0] < trk.pixels[:, 1, 0]).all()
    assert np.allclose(trk.radius, 5.0, atol=0.6)


def test_an_object_under_a_hand_is_not_seen_never_invented():
    c1, c2 = _approach_and_part()
    trk = track_colours(_two_discs(c1, c2, hand={4, 5}))
    assert not trk.found[4:6, 1].any() and trk.found[4:6, 0].all()
    assert trk.found[[3, 6], 1].all()
    assert np.isnan(trk.pixels[4:6, 1]).all()


def test_track_colours_refuses_bad_input():
    with pytest.raises(ValueError, match="^frames:"):
        track_colours(np.zeros((3, 10, 10), np.uint8))
    with pytest.raises(ValueError, match="^colours:"):
        track_colours(np.zeros((3, 10, 10, 3), np.uint8), colours=[[1, 0, 0]])
    with pytest.raises(ValueError, match="^colours: found no frame"):  # nothing moves
        track_colours(np.full((5, 30, 40, 3), 120, np.uint8))


def _track(c1, c2, r=5.0):
    pix = np.stack([c1, c2], axis=1).astype(float)
    return ColourTrack(pix, np.full(pix.shape[:2], r), np.eye(3)[[0, 2]])


def test_camera_for_track_levels_a_tilted_track_and_places_its_ends():
    # the carts on a line rolled 2 degrees; ends given at columns 20 and 220 (100 px/m: 2 m)
    t = np.arange(30)
    a = np.radians(2.0)
    u1, u2 = 40 + 2.0 * t, 200 - 2.0 * t
    line = lambda u: np.stack([u, 100 - np.tan(a) * u], 1)  # noqa: E731 (rows run down)
    tc = footage.camera_for_track(_track(line(u1), line(u2)), (200, 240), px_per_m=100,
                                  track_ends=(20, 220))
    assert abs(tc.tilt_deg + 2.0) < 1e-6
    pos = tc.camera.to_metres(tc.pixels)
    # x from the left end along the track, y = each centre's half-length above it
    assert np.allclose(pos[:, 0, 0], (u1 - 20) / np.cos(a) / 100, atol=1e-3)
    assert np.allclose(pos[..., 1], 0.05, atol=1e-6)
    assert abs(tc.ends_m[1] - 2.0 / np.cos(a)) < 1e-6 and tc.half_sizes_m == (0.05, 0.05)


def test_ends_estimated_where_the_carts_turn_or_out_of_reach():
    # cart 1 thrown back by the left end at column 30 (its edge: centre 35); cart 2 never turns
    t = np.arange(40)
    x1 = 35 + np.abs(t - 12.3) * 3.0
    x2 = 200 - 1.0 * t
    row = np.full(40, 80.0)
    tc = footage.camera_for_track(_track(np.stack([x1, row], 1), np.stack([x2, row], 1)),
                                  (160, 240), px_per_m=100)
    assert abs(tc.camera.origin[0] - 30.0) < 0.3
    assert "turned back" in tc.camera.placement["track"] and "absent" in \
        tc.camera.placement["track"]
    assert tc.ends_m[1] > (205 - 30) / 100 + footage.ABSENT_END_M - 0.01


@pytest.mark.parametrize("kw, named", [
    ({"px_per_m": 100, "track_ends": (60, 220)}, "track: the left end"),   # inside the path
    ({"px_per_m": 100, "track_ends": (20, 150)}, "track: the right end"),
    ({"px_per_m": 100, "track_ends": (220, 20)}, "track: expected"),
    ({"object_size_m": 40.0}, "object_size_m: puts"),
    ({"px_per_m": 0.01}, "px_per_m: puts"),
    ({}, "px_per_m: the collision's scale"),
    ({"px_per_m": 100, "object_size_m": 0.1}, "object_size_m: give either"),
])
def test_camera_for_track_refuses_a_camera_that_cannot_be_right(kw, named):
    t = np.arange(30)
    row = np.full(30, 100.0)
    trk = _track(np.stack([40 + 2.0 * t, row], 1), np.stack([200 - 2.0 * t, row], 1))
    with pytest.raises(ValueError, match=f"^{named}"):
        footage.camera_for_track(trk, (200, 240), **kw)


# -- a filmed clip, end to end ------------------------------------------------------------------
@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    from sysid_bench.core.camera_footage import Shot, write_clip

    d = tmp_path_factory.mktemp("collision_clip")
    video, truth = write_clip(Shot("collision", seed=0, fps=30, duration_s=1.6, size=(180, 320),
                                   subframes=1, hand=False), d)
    return video, json.loads(truth.read_text())


def test_camera_round_trip_clip_to_metres(clip):
    video, truth = clip
    cc = footage.observe_clip(video, "collision", truth["options"])
    obs = cc.observation
    # a cart not seen in 3 of the 48 frames (two of them with the carts touching), said so
    # (NaN), not invented; read at 20 frames/s its 32 frames had skipped them
    assert obs.positions.shape[1:] == (2, 2) and cc.lost_share <= 0.1
    assert np.isnan(obs.positions[cc.lost]).any(axis=(1, 2)).all()
    assert np.isfinite(obs.positions[~cc.lost]).all()
    sc = obs.scene
    assert abs(sc.ends[0]) < 1e-9 and abs(sc.ends[1] - 2.0) < 0.02
    assert np.allclose(sc.half_sizes, 0.05, atol=0.006)
    # every frame at the capture's own dt (a position method's time base, as on every other
    # system; it had been resampled to 20 frames/s by the nearest frame, 1/60 s off every other
    # frame's time)
    pm = np.asarray(truth["positions_m"])
    assert obs.n_frames == len(pm) and abs(obs.dt - 1 / 30) < 1e-6
    err = np.abs(obs.positions - pm)[np.isfinite(obs.positions)]
    # 114 px/m and H.264's half-resolution colour: within 3 px, 1 px typically
    assert err.max() < 0.025 and np.median(err) < 0.009, (err.max(), np.median(err))


def test_camera_clip_resampled_for_a_method_built_for_a_rate_and_thinned_to_a_cap(clip):
    video, truth = clip
    pm = np.asarray(truth["positions_m"])
    obs = footage.observe_clip(video, "collision", truth["options"], fps=20).observation
    assert abs(obs.dt - 1 / 20) < 1e-9
    # the nearest frame in time, either one on a tie (every other tick falls half-way between
    # two frames, and the file's rounded times decide)
    i = np.arange(obs.n_frames) * 1.5
    err = np.minimum(np.abs(obs.positions - pm[np.floor(i).astype(int)]),
                     np.abs(obs.positions - pm[np.ceil(i).astype(int)]))
    assert err.max() < 0.025 and np.median(err) < 0.009, (err.max(), np.median(err))
    cc = footage.observe_clip(video, "collision", truth["options"], max_frames=20)
    assert cc.observation.n_frames == 16 and abs(cc.observation.dt - 3 / 30) < 1e-6  # 1 in 3
    assert any("one frame in 3 kept" in n for n in cc.notes)
    assert np.nanmax(np.abs(cc.observation.positions - pm[::3])) < 0.025


def test_identify_refuses_a_track_end_inside_the_path_with_one_line(clip, tmp_path, capsys):
    from sysid_bench.apps.cli import main

    video, truth = clip
    opts = truth["options"]
    c1 = float(opts[opts.index("--track") + 1])
    px = float(opts[opts.index("--px-per-m") + 1])
    inside = c1 + (truth["state0"][0] + 0.05) * px  # where cart 1 starts: inside its path
    bad = [*opts[:opts.index("--track")], "--track", f"{inside:.0f}",
           opts[opts.index("--track") + 2]]
    out = tmp_path / "o"
    rc = main(["identify", str(video), *bad, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "--track: the left end" in err, err
    assert not out.exists()
    rc = main(["identify", str(video), "--system", "collision", "--px-per-m", f"{px:g}",
               "--pivot", "1", "2", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "--pivot: means nothing" in err
