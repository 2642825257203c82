"""sysid_bench.apps.video: reading files, geometry, finding the ball, identify end to end, the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pytest

from sysid_bench.apps.video import (
    VideoError,
    find_ball,
    geometry_from_options,
    identify_video,
    read_video,
    write_video,
)
from sysid_bench.core.metrics import normalised_param_se
from sysid_bench.core.physics import PRIOR, simulate
from sysid_bench.core.render import render, view_geometry

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def episode():
    """A test-split ball, 200 frames: theta (4,), states (200, 4)."""
    theta = np.array([[0.87, -9.3, 0.012, 0.35]])
    s0 = np.array([[2.0, 7.0, 5.5, 3.2]])
    return theta[0], simulate(theta, s0)[0]


@pytest.fixture(scope="module")
def video_file(tmp_path_factory, episode):
    """The episode as a 128x128 H.264 file at 20 fps."""
    _, states = episode
    path = tmp_path_factory.mktemp("vid") / "ball.mp4"
    write_video(path, render(states[None], size=(128, 128))[0], fps=20)
    return path


# -- reading --------------------------------------------------------------------------------------
def test_read_colour_h264_to_grey(tmp_path, episode):
    _, states = episode
    grey = render(states[None, :20], size=(64, 64))[0]
    rgb = np.stack([grey, grey // 2, np.zeros_like(grey)], axis=-1)  # an orange-ish ball
    path = write_video(tmp_path / "c.mp4", rgb, fps=20)
    clip = read_video(path)
    assert clip.colour and clip.frames.shape == (20, 64, 64) and clip.frames.dtype == np.uint8
    assert clip.source_fps == pytest.approx(20.0) and clip.notes == []
    # BT.601 luma of (v, v/2, 0) is ~0.59 v: the ball is there, grey, at the same place
    expect = 0.299 * grey + 0.587 * (grey // 2)
    assert np.abs(clip.frames.astype(float) - expect).mean() < 3.0


def test_read_grey_lossless_and_resample_from_30fps(tmp_path):
    # frame k holds the value 8 k: which source frames were kept is readable exactly
    frames = (np.arange(30)[:, None, None] * 8 * np.ones((1, 16, 16))).astype(np.uint8)
    path = write_video(tmp_path / "g.mkv", frames, fps=30, codec="ffv1")
    clip = read_video(path)
    assert not clip.colour
    assert clip.source_fps == pytest.approx(30.0)
    assert clip.frames.shape == (20, 16, 16)
    assert "resampled from 30 to 20" in clip.notes[0]
    kept = clip.frames[:, 0, 0] // 8
    ticks = np.arange(20) * 0.05
    # each kept frame is a nearest one in time to its 50 ms tick
    assert np.all(np.abs(kept / 30 - ticks) <= 1 / 60 + 1e-9)
    assert np.all(np.diff(kept) > 0)


@pytest.mark.parametrize("start, end, fps", [(0.5, 1.2, None), (None, 0.7, 20), (1.0, None, None),
                                             (0.5, 1.2, 20)])
def test_a_window_is_read_without_the_frames_outside_it(tmp_path, monkeypatch, start, end, fps):
    # frame k holds 4 k: the window's frames, times and notes are the whole decode's, while
    # the frames before it are not kept and decoding stops after it
    from sysid_bench.core import footage

    frames = (np.arange(60)[:, None, None] * 4 * np.ones((1, 16, 16))).astype(np.uint8)
    path = write_video(tmp_path / "w.mkv", frames, fps=30, codec="ffv1")
    seen = []
    decode = footage._decode

    def spy(*args):
        out = decode(*args)
        seen.append(out)
        return out

    monkeypatch.setattr(footage, "_decode", spy)
    got = read_video(path, fps, start=start, end=end)
    (times, n_skip), = [(len(o[2]), o[7]) for o in seen]
    monkeypatch.setattr(footage, "_decode", lambda *a: decode(*a[:-1], False))
    want = read_video(path, fps, start=start, end=end)
    np.testing.assert_array_equal(got.frames, want.frames)
    np.testing.assert_array_equal(got.times, want.times)
    assert got.notes == want.notes and got.fps == want.fps
    assert n_skip == (0 if start is None else round(30 * start))
    assert times == (60 if end is None else round(30 * end) + 1)  # the last one in the window


def test_read_at_model_rate_keeps_every_frame(tmp_path):
    frames = np.zeros((7, 16, 16), np.uint8)
    clip = read_video(write_video(tmp_path / "z.mkv", frames, fps=20, codec="ffv1"))
    assert clip.frames.shape[0] == 7 and clip.notes == []


@pytest.mark.parametrize("kind, message", [
    ("missing", "no such file"),
    ("empty", "empty file"),
    ("text", "not a readable video"),
    ("dir", "directory"),
    ("zero", "zero frames"),
])
def test_read_bad_files(tmp_path, kind, message):
    path = tmp_path / "bad.mkv"
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "text":
        path.write_text("this is not a video\n" * 20)
    elif kind == "dir":
        path.mkdir()
    elif kind == "zero":
        out = av.open(str(path), "w")
        st = out.add_stream("ffv1", rate=20)
        st.width = st.height = 16
        out.start_encoding()  # writes the header: a video stream with no frames
        out.close()
        assert path.stat().st_size > 0
    with pytest.raises(VideoError) as err:
        read_video(path)
    assert str(err.value).startswith(str(path)) and message in str(err.value)


def test_write_video_validates_and_is_atomic(tmp_path):
    with pytest.raises(ValueError, match="frames"):
        write_video(tmp_path / "x.mp4", np.zeros((3, 8, 8), np.float32))
    with pytest.raises(ValueError, match="at least one"):
        write_video(tmp_path / "x.mp4", np.zeros((0, 8, 8), np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_write_video_is_reproducible_on_noisy_frames(tmp_path):
    # with x264's macroblock-tree rate control, writes of the same camera-like frames (pixel
    # noise, blur, occluders) differed every time; same frames, same bytes
    from sysid_bench.core.datasets import make_dataset

    nuis = {"blur": 0.5, "occlusion": 0.05, "drop": 0.05, "noise": 8.0}
    frames = np.asarray(make_dataset("test", 1, 5, size=(100, 200), nuisance=nuis).frames[0])
    digests = {write_video(tmp_path / f"v{i}.mp4", frames).read_bytes() for i in range(3)}
    assert len(digests) == 1


# -- geometry -------------------------------------------------------------------------------------
@pytest.mark.parametrize("size", [(28, 28), (256, 256), (50, 100), (120, 200)])
def test_default_geometry_is_the_renderers(size):
    geo = geometry_from_options(size)
    vg = view_geometry(size)
    xy = np.array([[0.0, 0.0], [10.0, 10.0], [3.3, 7.1]])
    np.testing.assert_allclose(geo.to_pixels(xy), vg.to_pixels(xy), atol=1e-12)
    np.testing.assert_allclose(geo.to_metres(geo.to_pixels(xy)), xy, atol=1e-12)


def test_geometry_options_and_corners():
    geo = geometry_from_options((300, 400), px_per_m=30.0, floor_row=290.0, wall_col=20.0,
                                ball_radius_px=10.0)
    # ball centre touching the left wall and the floor: (wall + r, floor - r)
    np.testing.assert_allclose(geo.to_pixels([0.0, 0.0]), [30.0, 280.0])
    np.testing.assert_allclose(geo.to_pixels([10.0, 2.0]), [330.0, 220.0])
    c = geometry_from_options((300, 400), corners=(20, 289, 340, 291), ball_radius_px=10.0)
    np.testing.assert_allclose(c.to_pixels([[0, 0], [10, 2]]), geo.to_pixels([[0, 0], [10, 2]]))
    assert "corners" in c.describe()


@pytest.mark.parametrize("opts", [
    {"px_per_m": 60.0},                              # right wall far outside the frame
    {"wall_col": 500.0},                             # left wall outside
    {"floor_row": 400.0, "px_per_m": 10.0},          # floor below the frame
    {"floor_row": 5.0, "px_per_m": 10.0},            # most of the box above the frame
    {"corners": (-50, 290, 600, 290)},
])
def test_geometry_box_outside_frame(opts):
    with pytest.raises(ValueError, match="geometry"):
        geometry_from_options((300, 400), ball_radius_px=10.0, **opts)


def test_geometry_rejects_mixed_and_bad_options():
    with pytest.raises(ValueError, match="corners"):
        geometry_from_options((300, 400), corners=(0, 290, 390, 290), px_per_m=30.0)
    with pytest.raises(ValueError, match="px_per_m"):
        geometry_from_options((300, 400), px_per_m=-1.0)


# -- finding the ball -----------------------------------------------------------------------------
def test_find_ball_ignores_static_clutter_and_noise(episode):
    _, states = episode
    fr = render(states[None, :80], size=(128, 128))[0].astype(np.float32) * 0.8
    rng = np.random.default_rng(0)
    fr[:, 10:40, 70:120] = 200.0      # a bright poster: static clutter, bigger than the ball
    fr[:, 90:100, 5:15] = 255.0
    fr += rng.normal(0, 6, fr.shape)
    fr = np.clip(fr, 0, 255).astype(np.uint8)
    trk = find_ball(fr)
    geo = geometry_from_options((128, 128))
    pos = geo.to_metres(trk.pixels)
    err = np.linalg.norm(pos - states[:80, :2], axis=1)
    # frames where the ball overlaps the poster may be lost; elsewhere it is followed closely
    assert trk.n_found >= 70
    assert np.nanmedian(err) < 0.05 and np.nanmax(err) < 0.5
    assert trk.radius == pytest.approx(30 / 256 * 128, rel=0.15)


def test_find_ball_never_found():
    trk = find_ball(np.full((20, 32, 32), 40, np.uint8))
    assert trk.n_found == 0 and np.isnan(trk.pixels).all() and np.isnan(trk.radius)


# -- identify end to end -----------------------------------------------------------------------
def _nmse(theta, mean, k=3):
    return float(normalised_param_se(theta, mean)[:k].mean())


def test_roundtrip_h264_lsq(video_file, episode):
    theta, states = episode
    res = identify_video(video_file, method="lsq", every=100)
    assert res.info["ball_found"] and res.info["frames_with_ball"] == 200
    np.testing.assert_allclose(res.positions, states[:, :2], atol=0.06)
    assert _nmse(theta, res.mean[-1]) < 0.01
    assert res.info["estimated_frames"] == [99, 199]


def test_roundtrip_h264_vid2param(video_file, episode):
    import torch  # noqa: F401 (a dependency of [test]: missing fails, not skips)
    theta, _ = episode
    res = identify_video(video_file, method="vid2param")
    assert res.mean.shape == (200, 4) and np.isfinite(res.mean).all()
    assert _nmse(theta, res.mean[-1]) < 0.01
    # uncertainty shrinks from the first frame to the last
    assert np.all(res.std[-1, :3] < res.std[0, :3])
    assert res.forecast_mean.shape == (20, 2)


def test_ball_never_found(tmp_path):
    path = write_video(tmp_path / "blank.mp4", np.full((30, 64, 64), 30, np.uint8))
    with pytest.raises(VideoError, match="found in 0 of 30"):
        identify_video(path, method="lsq")
    import torch  # noqa: F401 (a dependency of [test]: missing fails, not skips)
    res = identify_video(path, method="vid2param")
    assert res.info["ball_found"] is False and "never found" in " ".join(res.info["notes"])
    assert res.forecast_mean is None
    # prior-wide: at least half the prior's std (uniform: span / sqrt(12)) on e, g and d
    span = np.array([PRIOR[p][1] - PRIOR[p][0] for p in ("e", "g", "d", "r")])
    assert np.all(res.std[-1, :3] > 0.5 * span[:3] / np.sqrt(12))


# -- CLI -------------------------------------------------------------------------------------------
def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "sysid_bench", "identify", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd or ROOT, timeout=300)


def test_cli_writes_three_files(tmp_path, video_file):
    out = tmp_path / "out"
    r = _cli(video_file, "--method", "lsq", "--every", "100", "--out", out, "--no-progress")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["estimates.csv", "estimates.json",
                                                     "track.png"]
    rows = (out / "estimates.csv").read_text().splitlines()
    assert rows[0].startswith("frame,t_s,e_mean,e_std,g_mean,g_std,d_mean,d_std,r_mean,r_std")
    assert len(rows) == 201
    info = json.loads((out / "estimates.json").read_text())
    for k in ("method", "file", "fps", "frames", "geometry", "ball_found", "estimates"):
        assert k in info
    assert info["frames"] == 200 and "renderer" in info["geometry"]["mapping"]


@pytest.mark.parametrize("make, message", [
    (lambda d: d / "missing.mp4", "no such file"),
    (lambda d: (d / "e.mp4").write_bytes(b"") or d / "e.mp4", "empty"),
    (lambda d: (d / "t.mp4").write_text("x" * 100) and d / "t.mp4", "not a readable video"),
])
def test_cli_bad_file_one_line_no_outputs(tmp_path, make, message):
    path = make(tmp_path)
    out = tmp_path / "out"
    r = _cli(path, "--method", "lsq", "--out", out)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and message in lines[0]
    assert "Traceback" not in r.stderr
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")] == []


def test_cli_bad_geometry_and_existing_out_untouched(tmp_path, video_file):
    out = tmp_path / "out"
    r = _cli(video_file, "--method", "lsq", "--out", out, "--px-per-m", "500", "--wall-col", "0")
    line = r.stderr.strip()
    assert r.returncode == 2 and "outside" in line and len(line.splitlines()) == 1
    assert "--px-per-m/--wall-col" in line  # the options that placed the box are named
    assert not out.exists()
    # a folder of files identify did not write is refused before any work, untouched
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = _cli(video_file, "--method", "lsq", "--out", out)
    assert r.returncode == 2 and "--out" in r.stderr and "keep.txt" in r.stderr
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_run_identify_registered():
    """`sysid-bench identify` is a sub-command of the one CLI."""
    from sysid_bench.apps import video
    from sysid_bench.apps.cli import _parser

    args = _parser("identify").parse_args(["identify", "v.mp4", "--checkpoint", "camera"])
    assert args.fn is video.run and args.checkpoint == "camera"


def test_vid2param_physics_reads_a_file_and_a_blank_one(video_file, episode, tmp_path):
    import torch  # noqa: F401 (a dependency of [test]: missing fails, not skips)
    theta, _ = episode
    res = identify_video(video_file, method="vid2param-physics", every=100)
    assert res.info["checkpoint"] == "28x28" and res.info["estimated_frames"] == [99, 199]
    assert _nmse(theta, res.mean[-1]) < 0.001
    # no ball: every frame unseen for the fit, so the network's prior-wide answer stands
    path = write_video(tmp_path / "blank.mp4", np.full((30, 64, 64), 30, np.uint8))
    blank = identify_video(path, method="vid2param-physics")
    span = np.array([PRIOR[p][1] - PRIOR[p][0] for p in ("e", "g", "d", "r")])
    assert np.all(blank.std[-1, :3] > 0.5 * span[:3] / np.sqrt(12))


def test_frame_store_takes_frames_as_the_stacked_list_did():
    """read_video's store: each frame copied once; a raw luma plane goes through the table once
    (also when taken twice, as resampling repeats frames); a frame of another size is refused
    only when taken with the others; a long run of frames is a view, a sparse pick a copy."""
    from sysid_bench.core.footage import VideoError, _FrameStore

    table = (255 - np.arange(256)).astype(np.uint8)
    st = _FrameStore(4)
    frames = [np.full((2, 3), v, np.uint8) for v in (10, 20, 30)]
    for f in frames:
        st.put(f, raw=True)
    st.put(np.full((4, 4), 7, np.uint8))  # another size (frame 3), FFmpeg's grey
    got = st.take([0, 1, 1, 2], "clip.mp4", table)
    assert np.array_equal(got[:, 0, 0], [245, 235, 235, 225])
    assert np.array_equal(st.take([2], "clip.mp4", table)[0], np.full((2, 3), 225))  # once
    with pytest.raises(VideoError, match="frames change size"):
        st.take([2, 3], "clip.mp4", table)
    assert st.take([3], "clip.mp4", table).shape == (1, 4, 4)
    run = st.take([0, 1, 2], "clip.mp4", table)
    assert np.shares_memory(run, st.buf)  # 3 of 4 rows: a view
    win = _FrameStore(2)
    for f in frames:
        win.put(f)
    win.subset(np.array([False, True, True]))
    assert len(win) == 2 and np.array_equal(win.take([0, 1], "c")[:, 0, 0], [20, 30])
    empty = _FrameStore(2)  # the colour copy not asked for: a window leaves it empty
    assert len(empty.subset(np.array([False, True]))) == 0
