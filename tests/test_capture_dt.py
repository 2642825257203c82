"""The capture's own time (issue 38 §2 "time"): methods that simulate at any step read every frame
at the clip's own dt; a method built for one frame rate (Vid2Param, 20 frames/s) gets the clip
resampled and says so; variable frame rate; ``--fps`` for slow-motion files."""

from __future__ import annotations

from fractions import Fraction

import av
import numpy as np
import pytest

from sysid_bench.apps.video import identify_video
from sysid_bench.core import systems
from sysid_bench.core.estimator import (
    EXPENSIVE_MAX_FRAMES,
    Estimator,
    Observation,
    frame_cap_of,
    frame_rate_of,
)
from sysid_bench.core.footage import read_video, thin_clip, write_video
from sysid_bench.core.physics import simulate
from sysid_bench.core.render import render

THETA = np.array([[0.87, -9.3, 0.012, 0.35]])
STATE0 = np.array([[2.0, 7.0, 5.5, 3.2]])


def _numbered(n: int) -> np.ndarray:
    """``n`` grey 16x16 frames, frame k holding the value 6 k (which one was kept is readable)."""
    return (np.arange(n)[:, None, None] * 6 * np.ones((1, 16, 16))).astype(np.uint8)


def _write_vfr(path, frames, times):
    """A lossless file whose frames carry the given presentation times (ms), as a browser
    recording's variable frame rate does."""
    with av.open(str(path), "w") as out:
        st = out.add_stream("ffv1", rate=30)
        st.width, st.height, st.pix_fmt = frames.shape[2], frames.shape[1], "gray"
        st.time_base = st.codec_context.time_base = Fraction(1, 1000)
        for f, t in zip(frames, times):
            vf = av.VideoFrame.from_ndarray(f, format="gray")
            vf.pts, vf.time_base = int(round(t * 1000)), Fraction(1, 1000)
            for pkt in st.encode(vf):
                out.mux(pkt)
        for pkt in st.encode():
            out.mux(pkt)
    return path


@pytest.fixture(scope="module")
def ball_60fps(tmp_path_factory):
    """A ball rendered from ``simulate`` at dt = 1/60 for 1 s (60 frames), H.264 at 60 fps."""
    states = simulate(THETA, STATE0, n_frames=60, dt=1 / 60)
    path = tmp_path_factory.mktemp("dt") / "ball60.mp4"
    write_video(path, render(states, size=(128, 128))[0], fps=60)
    return path


def test_frame_rate_is_declared_on_the_method():
    import methods

    assert frame_rate_of(methods.get_class("lsq")) is None
    assert frame_rate_of(methods.get_class("vid2param")) == 20.0
    assert frame_rate_of(methods.get_class("vid2param-physics")) == 20.0

    class Bad(Estimator):
        name = "bad-rate"
        frame_rate = -5

        def identify(self, obs):  # pragma: no cover - never called
            raise NotImplementedError

    with pytest.raises(ValueError, match=r"Bad.frame_rate: expected None or frames/s > 0"):
        frame_rate_of(Bad)
    with pytest.raises(TypeError, match="method: expected an Estimator"):
        frame_rate_of(int)


def test_capture_rate_keeps_every_frame(tmp_path):
    path = write_video(tmp_path / "g.mkv", _numbered(30), fps=60, codec="ffv1")
    clip = read_video(path, None)
    assert clip.fps == 60.0 and clip.frames.shape[0] == 30 and clip.notes == []
    assert np.array_equal(clip.frames[:, 0, 0] // 6, np.arange(30))
    # the default (a method's 20 frames/s) still resamples, and says so
    assert "resampled from 60 to 20" in read_video(path).notes[0]
    with pytest.raises(ValueError, match="fps: expected None or a frame rate > 0"):
        read_video(path, 0)


def test_fps_override_of_a_slow_motion_file(tmp_path):
    # captured at 240 frames/s, stored at 30: every frame kept, 1/240 s apart
    path = write_video(tmp_path / "slow.mkv", _numbered(24), fps=30, codec="ffv1")
    clip = read_video(path, None, capture_fps=240)
    assert clip.fps == 240.0 and clip.frames.shape[0] == 24
    assert clip.times[-1] == pytest.approx(23 / 240, abs=2e-4)  # the 1 ms clock, stretched
    assert "capture rate 240 frames/s" in clip.notes[0]


def test_variable_frame_rate_on_its_median_interval(tmp_path):
    gaps = np.r_[np.full(12, 0.033), 0.066, np.full(6, 0.033), 0.1, np.full(4, 0.034)]
    times = np.r_[0.0, np.cumsum(gaps)]  # a 30 fps recording that dropped frames
    path = _write_vfr(tmp_path / "vfr.mkv", _numbered(len(times)), times)
    clip = read_video(path, None)
    assert clip.fps == pytest.approx(1 / 0.0332, rel=0.01)  # 33/34 ms in the 1 ms clock
    assert "variable frame rate" in clip.notes[0] and "median 33 ms" in clip.notes[0]
    kept = clip.frames[:, 0, 0] // 6
    ticks = np.arange(len(kept)) / clip.fps
    # each tick holds the source frame nearest to it in time
    near = np.abs(times[None, :] - ticks[:, None]).argmin(axis=1)
    assert np.array_equal(kept, near)
    assert np.allclose(clip.times, times[kept])
    # a method's rate resamples a variable-rate file as well
    clip20 = read_video(path)
    assert clip20.fps == 20.0 and "the method's 20 frames/s" in clip20.notes[0]


def test_a_position_method_reads_a_60fps_clip_at_its_own_dt(ball_60fps):
    # prior: a position method that simulates at any step, cheap enough for the fast suite
    # (lsq on a 60 fps clip: the pendulum test below)
    res = identify_video(ball_60fps, method="prior", every=60, progress=False)
    info = res.info
    assert info["dt_s"] == 1 / 60 and info["frames"] == 60 and not info["resampled"]
    assert info["method_frame_rate"] is None
    assert not any("resampled" in n for n in info["notes"])
    # every frame tracked, each at the simulated ball's position at its own 1/60 s step
    states = simulate(THETA, STATE0, n_frames=60, dt=1 / 60)[0]
    assert res.positions.shape == (60, 2)
    assert np.nanmax(np.abs(res.positions - states[:, :2])) < 0.2


def test_vid2param_resamples_to_its_rate_and_says_so(ball_60fps):
    res = identify_video(ball_60fps, method="vid2param", progress=False)
    info = res.info
    assert info["dt_s"] == 0.05 and info["frames"] == 20 and info["resampled"]
    assert info["method_frame_rate"] == 20.0
    assert any("resampled from 60 to 20" in n for n in info["notes"])
    assert any("vid2param is built for 20 frames/s" in n for n in info["notes"])


def test_pendulum_clip_at_60fps_gives_lsq_every_frame(tmp_path):
    from sysid_bench.apps.video_systems import identify_system_video

    sys_ = systems.get("pendulum")
    theta, s0 = sys_.sample_cases(1, np.random.default_rng(0), "test")
    frames = sys_.render(sys_.simulate(theta, s0, 90, dt=1 / 60), theta)[0]
    path = write_video(tmp_path / "pend60.mp4", frames, fps=60)
    res = identify_system_video(path, "pendulum", method="lsq", every=90, progress=False)
    assert res["info"]["dt_s"] == 1 / 60 and res["info"]["frames"] == 90
    # g and L from 1.5 s (the friction mu needs a longer clip)
    assert res["mean"][-1, :2] == pytest.approx(theta[0, :2], rel=0.02)


def test_expensive_methods_take_at_most_their_cap(tmp_path):
    import methods

    assert frame_cap_of(methods.get_class("lsq")) is None
    assert frame_cap_of(methods.get_class("nuts")) == EXPENSIVE_MAX_FRAMES  # expensive tier
    clip = read_video(write_video(tmp_path / "c.mkv", _numbered(30), fps=60, codec="ffv1"), None)
    thin = thin_clip(clip, 10, "nuts")
    assert thin.fps == 20.0 and np.array_equal(thin.frames[:, 0, 0] // 6, np.arange(0, 30, 3))
    assert "nuts takes at most 10 observations: one frame in 3 kept (30 -> 10" in thin.notes[-1]
    assert thin_clip(clip, 30) is clip and thin_clip(clip, None) is clip
    with pytest.raises(ValueError, match="max_frames: expected None or an int >= 1"):
        thin_clip(clip, 0)


def test_every_system_simulates_at_the_capture_dt():
    # the kernels sub-step: 60 fps and 20 fps agree at the common times (issue 38 §2)
    rng = np.random.default_rng(0)
    for name in systems.available():
        s = systems.get(name)
        lo, hi = (np.array([s.prior[p][i] for p in s.params]) for i in (0, 1))
        th = lo + (hi - lo) * rng.random((2, len(lo)))
        s0 = s.sample_state0(2, rng)
        a = s.observe(s.simulate(th, s0, n_frames=101, dt=0.05), th)
        b = s.observe(s.simulate(th, s0, n_frames=301, dt=0.05 / 3), th)[:, ::3]
        assert np.nanmax(np.abs(a - b)) < 1e-6, name


def test_sindy_holds_its_smoothing_window_in_seconds():
    import methods
    from methods.sindy import _window_at

    assert _window_at(9, 0.05) == 9 and _window_at(15, 0.1) == 15  # 20 fps and slower: as tuned
    assert _window_at(9, 1 / 60) == 27 and _window_at(15, 1 / 60) == 45 and _window_at(0, 0.01) == 0
    # a 60 fps pendulum with 1 cm noise: the 15-frame window of 20 fps read g as -10.6 +- 2.0
    s = systems.get("pendulum")
    theta, s0 = np.array([[-9.74, 1.93, 0.07, 0.47]]), np.array([[1.0, 0.0]])
    pts = s.observe(s.simulate(theta, s0, n_frames=600, dt=1 / 60), theta)[0]
    pts = pts + np.random.default_rng(5).normal(0, 0.01, pts.shape)
    post = methods.get("sindy", system="pendulum").identify(
        Observation(positions=pts, dt=1 / 60, system="pendulum"))
    assert post.mean[0] == pytest.approx(-9.74, abs=3 * post.std[0]) and post.std[0] < 0.5
