"""The appearance tracker (``identify --object-box``): a textured box followed over a textured,
changing background past a distractor, "not seen" while it is hidden, and bad boxes refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sysid_bench.core import footage
from sysid_bench.core.box_track import check_box, follow_box

SIZE = (120, 176)  # (H, W)
BOX_WH = (26, 14)
T = 48
HIDDEN = (28, 32)  # frames the object is behind an occluder


def _texture(u, v, kind=0):
    """A grey texture of continuous coordinates (not round, not one flat colour): the object's
    (``kind`` 0) or the distractor's (1: as bright and as busy, another pattern)."""
    a, b, c, d = ((9.0, 6.0, 2.0, 13.0), (5.0, 9.0, -0.5, 11.0))[kind]
    return (120 + 70 * np.sin(2 * np.pi * u / a) * np.cos(2 * np.pi * v / b)
            + 40 * np.sign(np.sin(2 * np.pi * (u + c * v) / d)))


def _paint(img, corner, wh, kind, yy, xx):
    """``img`` with a ``wh`` box of texture ``kind`` whose top-left corner is at ``corner``
    (continuous px), anti-aliased over the 4 x 4 sub-pixels of ``yy, xx``."""
    r0, c0 = max(int(corner[1]) - 1, 0), max(int(corner[0]) - 1, 0)
    part = (slice(r0, int(corner[1]) + wh[1] + 2), slice(c0, int(corner[0]) + wh[0] + 2))
    u, v = xx[part] - corner[0], yy[part] - corner[1]
    inside = (u >= 0) & (u < wh[0]) & (v >= 0) & (v < wh[1])
    cov = inside.mean(axis=(-2, -1))
    val = np.where(inside, _texture(u, v, kind), 0.0).sum(axis=(-2, -1)) / 16.0
    img[part] = img[part] * (1 - cov) + val
    return img


def _clip(seed=0):
    """Grey (T, H, W) uint8 and the box's true top-left corners (T, 2) (col, row).

    The background is a smooth random texture that scrolls and brightens over the clip; a
    distractor of another texture, the same size, crosses the object's path; in ``HIDDEN``
    a textured occluder (a hand) covers the object."""
    from scipy.ndimage import gaussian_filter

    h, w = SIZE
    rng = np.random.default_rng(seed)
    big = gaussian_filter(rng.normal(size=(h, w + T)), 3) * 300
    sub = (np.arange(4) + 0.5) / 4
    yy = (np.arange(h)[:, None, None, None] + sub[None, None, :, None]) * np.ones((1, w, 4, 4))
    xx = (np.arange(w)[None, :, None, None] + sub[None, None, None, :]) * np.ones((h, 1, 4, 4))
    t = np.arange(T)
    corner = np.stack([70 + 45 * np.sin(0.15 * t), 60 + 6 * np.cos(0.1 * t)], 1)
    other = np.stack([150 - 3.0 * t, 40 + 0.5 * t], 1)
    out = np.empty((T, h, w), np.uint8)
    for k in range(T):
        img = 100 + 0.6 * k + big[:, k:k + w]  # scrolling, brightening
        img = _paint(img, other[k], BOX_WH, 1, yy, xx)
        img = _paint(img, corner[k], BOX_WH, 0, yy, xx)
        if HIDDEN[0] <= k < HIDDEN[1]:
            c, r = (int(v) for v in corner[k])
            img[r - 6:r + BOX_WH[1] + 6, c - 6:c + BOX_WH[0] + 6] = \
                80 + 30 * rng.random((BOX_WH[1] + 12, BOX_WH[0] + 12))
        out[k] = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    return out, corner


@pytest.fixture(scope="module")
def clip():
    return _clip()


def test_follows_a_textured_box_within_a_pixel_and_says_not_seen_when_hidden(clip):
    frames, corner = clip
    c0, r0 = corner[0]
    bt = follow_box(frames, (c0, r0, *BOX_WH))  # the corner rounds to the pixel
    truth = corner + np.array(BOX_WH) / 2.0 - (corner[0] - np.round(corner[0]))
    hidden = np.zeros(T, bool)
    hidden[HIDDEN[0]:HIDDEN[1]] = True
    assert not bt.found[hidden].any(), "a hidden object must be not seen, not invented"
    assert bt.found[~hidden].all(), np.flatnonzero(~bt.found)
    err = np.hypot(*(bt.centres[~hidden] - truth[~hidden]).T)
    assert err.max() < 1.0 and np.median(err) < 0.3, err
    assert np.nanmax(bt.score[hidden]) < 0.5 < np.min(bt.score[~hidden])


def test_footage_reads_the_boxs_side_along_the_motion(clip):
    frames, corner = clip
    trk = footage.follow_object_box(frames, (*np.round(corner[0]), *BOX_WH))
    assert trk.radius == BOX_WH[0] / 2  # moves across: its width
    assert np.array_equal(np.isfinite(trk.radii), trk.found)


@pytest.mark.parametrize("box, words", [
    ((10, 10, 0, 8), "at least 4 px"),
    ((10, 10, -5, 8), "at least 4 px"),
    ((170, 10, 20, 8), "inside the 176x120 frame"),
    ((-1, 10, 20, 8), "inside the 176x120 frame"),
    ((10, float("nan"), 20, 8), "finite"),
])
def test_check_box_refuses_boxes_outside_or_empty(box, words):
    with pytest.raises(ValueError, match=words) as e:
        check_box(box, SIZE)
    assert str(e.value).startswith("object_box:")
    assert check_box((10.4, 9.6, 20.2, 8), SIZE) == (10, 10, 21, 8)


@pytest.fixture(scope="module")
def clip_file(clip, tmp_path_factory):
    import av  # noqa: F401 (a dependency of [test]: missing fails, not skips)

    return footage.write_video(tmp_path_factory.mktemp("box") / "box.mp4", clip[0], fps=20)


@pytest.mark.parametrize("args, words", [
    (["--object-box", "160", "10", "30", "8"], "inside the 176x120 frame"),
    (["--object-box", "10", "10", "0", "8"], "at least 4 px"),
    (["--object-box", "10", "-3", "20", "8"], "top-left corner inside"),
    (["--system", "collision", "--object-box", "10", "10", "20", "8"], "follows one object"),
])
def test_bad_object_box_one_line_nothing_written(clip_file, tmp_path, capsys, args, words):
    from sysid_bench.apps.cli import main

    out = tmp_path / "o"
    argv = ["identify", str(clip_file), "--method", "lsq", "--out", str(out), "--no-progress",
            *args]
    if "--system" not in args:
        argv += ["--system", "spring", "--px-per-m", "100"]
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "--object-box:" in err and words in err, err
    assert not out.exists() and not list(tmp_path.glob(".o*"))


def test_a_box_needs_a_scale(clip_file, tmp_path, capsys):
    from sysid_bench.apps.cli import main

    rc = main(["identify", str(clip_file), "--system", "spring", "--object-box", "70", "66",
               "26", "14", "--method", "lsq", "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "--object-box:" in err and "--px-per-m" in err


def test_identify_follows_the_box_and_shows_it(clip, clip_file, tmp_path, capsys):
    from sysid_bench.apps.cli import main

    c0, r0 = np.round(clip[1][0]).astype(int)
    out = tmp_path / "o"
    assert main(["identify", str(clip_file), "--system", "spring", "--px-per-m", "100",
                 "--object-box", str(c0), str(r0), *map(str, BOX_WH), "--method", "lsq",
                 "--every", "1000", "--out", str(out), "--no-progress"]) == 0, \
        capsys.readouterr().err
    info = json.loads((out / "estimates.json").read_text())
    assert info["object_box"] == [int(c0), int(r0), *BOX_WH]
    # the H.264 copy: the object seen outside the occluder (a frame either side at most lost)
    assert T - (HIDDEN[1] - HIDDEN[0]) - 2 <= info["points_seen"] <= T - (HIDDEN[1] - HIDDEN[0])
    xs = np.array([r["x1_m"] if r["x1_m"] is not None else np.nan for r in info["estimates"]])
    assert np.isnan(xs[HIDDEN[0]:HIDDEN[1]]).all()
    from PIL import Image

    assert Image.open(out / "track.png").size[0] > 1000  # the box's panel beside the fits


def test_a_boxed_ball_is_identified(tmp_path, capsys):
    """The ball's camera path follows a boxed ball too (it once stopped with no observation:
    the box branch built no camera)."""
    from scipy.ndimage import gaussian_filter

    from sysid_bench.apps.cli import main

    rng = np.random.default_rng(1)
    h, w, n = 200, 120, 12
    bg = 110 + gaussian_filter(rng.normal(size=(h, w)), 4) * 120
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    frames = []
    for t in range(n):  # falling from rest: 9.81 m/s^2 at 100 px/m and 20 frames/s
        cy = 30 + 0.5 * 981 * (t / 20) ** 2
        disc = np.clip(11.5 - np.hypot(yy - cy, xx - 60), 0, 1)
        img = bg * (1 - disc) + (200 - 2.5 * (yy - cy) - 1.5 * (xx - 60)) * disc
        frames.append(np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8))
    path = footage.write_video(tmp_path / "ball.mp4", np.array(frames), fps=20)
    out = tmp_path / "o"
    assert main(["identify", str(path), "--object-box", "48", "18", "24", "24", "--px-per-m",
                 "100", "--method", "lsq", "--every", "1000", "--out", str(out),
                 "--no-progress"]) == 0, capsys.readouterr().err
    info = json.loads((out / "estimates.json").read_text())
    assert info["object_box"] == [48, 18, 24, 24]
    assert info["frames_with_ball"] >= n - 1  # in view throughout
