"""Issue 38: the track's own noise and the camera check against it (fast)."""
import numpy as np
import pytest

from sysid_bench.core.estimator import Check
from sysid_bench.core.footage import camera_check, track_noise


def _flight(t):
    # a thrown ball: parabola in y, uniform in x (third differences exactly zero)
    return np.stack([0.1 + 0.8 * t, 0.2 + 3.0 * t - 4.9 * t * t], axis=-1)


def test_track_noise_smooth_track_known_noise():
    rng = np.random.default_rng(0)
    t = np.arange(400) * 0.05
    x = np.stack([0.3 * np.sin(2.0 * t), 0.5 * np.cos(1.3 * t)], -1)
    x += rng.normal(0, 0.005, x.shape)
    assert track_noise(x) == pytest.approx(0.005, rel=0.15)


def test_track_noise_ignores_bounces_and_unseen_frames():
    rng = np.random.default_rng(1)
    t = np.arange(60) * 0.05
    seg = _flight(t[:20])
    # three flights, each restarting at the floor with a velocity flip: bounces
    x = np.concatenate([seg, seg[::-1], seg]) + rng.normal(0, 0.004, (60, 2))
    x[10:13] = np.nan
    clean = track_noise(x)
    assert clean == pytest.approx(0.004, rel=0.3)
    # (T, K, D) of two objects
    assert track_noise(np.stack([x, x[::-1]], 1)) == pytest.approx(0.004, rel=0.3)


def test_track_noise_bad_input():
    with pytest.raises(ValueError, match="positions"):
        track_noise(np.zeros(10))
    assert np.isnan(track_noise(np.zeros((5, 2))))


def test_camera_check_fails_a_fit_far_above_the_track_noise():
    # passes the method's 10 mm check, misses a 2 mm-noise track by 4x its noise
    chk = Check(rms_m=0.008, noise_m=0.010, ok=True, n=200, note="passes at the posterior mean")
    out = camera_check(chk, 0.002)
    assert not out.ok and "track's own noise" in out.note
    assert out.rms_m == chk.rms_m and out.noise_m == chk.noise_m
    # a fit at the track's noise stands, as does a check already failed or an unknown noise
    assert camera_check(Check(0.0022, 0.010, True, 200), 0.002).ok
    failed = Check(0.05, 0.010, False, 200, "intervals widened")
    assert camera_check(failed, 0.002) is failed
    assert camera_check(chk, float("nan")) is chk


def test_camera_check_bad_input():
    chk = Check(0.008, 0.010, True, 200)
    with pytest.raises(TypeError, match="check"):
        camera_check({"ok": True}, 0.002)
    with pytest.raises(TypeError, match="noise_m"):
        camera_check(chk, "2 mm")
    with pytest.raises(ValueError, match="noise_m"):
        camera_check(chk, -1.0)
    with pytest.raises(ValueError, match="factor"):
        camera_check(chk, 0.002, factor=0)
