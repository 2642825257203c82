"""``vid2param-physics`` identification: the physics fitted to the network's whole track."""

from __future__ import annotations

import numpy as np
import pytest

import methods
from methods.vid2param import SHIPPED_CHECKPOINTS
from methods.vid2param.rollout import _correlation_time, fit_state, fit_track, simulations
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation
from sysid_bench.core.physics import PRIOR, simulate

needs_shipped = pytest.mark.skipif(not SHIPPED_CHECKPOINTS["28x28"].exists(),
                                   reason="shipped checkpoint missing")
TRUTH = np.array([0.8, -9.81, 0.035, 0.3])
SPAN = np.array([hi - lo for lo, hi in PRIOR.values()])


def _track(n=200, noise=0.005, seed=0, rho=0.0):
    """A 200-frame track (bounces, walls) with AR(1) noise of lag-one correlation ``rho``."""
    states = simulate(TRUTH[None], np.array([[2.0, 6.0, 5.0, 3.5]]), n)[0]
    rng = np.random.default_rng(seed)
    eps = rng.standard_normal((n, 2))
    for t in range(1, n):  # same marginal variance for every rho
        eps[t] = rho * eps[t - 1] + np.sqrt(1 - rho**2) * eps[t]
    return states[:, :2] + noise * eps


def test_fit_track_finds_the_drag_a_window_cannot():
    pos = _track()
    # the network's d is a third of the range off, with a wide std; e and g near the truth
    prior = TRUTH + [0.01, 0.05, -0.015, 0.0]
    std = np.array([0.02, 0.1, 0.015, 0.2])
    before = simulations()
    fit = fit_track(pos, prior, std)
    assert simulations() > before  # it counts what it simulates
    window = fit_state(pos, prior, std)
    assert fit.start == 0 and fit.n_used == 200
    assert abs(fit.theta[2] - TRUTH[2]) < 0.03 * SPAN[2]
    assert abs(window.theta[2] - TRUTH[2]) > 3 * abs(fit.theta[2] - TRUTH[2])
    assert np.abs(fit.theta[:2] - TRUTH[:2]).max() < 0.01 * SPAN[:2].max()
    sd = np.sqrt(np.diag(fit.cov)[4:8])
    assert (sd > 0).all() and sd[2] < std[2] / 3  # the track, not the prior, decides d
    assert abs(fit.theta[2] - TRUTH[2]) < 3 * sd[2]


def test_correlated_misreadings_widen_the_posterior():
    white = _correlation_time(np.random.default_rng(0).standard_normal((200, 2)))
    assert white < 1.5
    assert _correlation_time(_track(noise=1.0, rho=0.8) - _track(noise=0.0)) > 4.0
    a = fit_track(_track(seed=1), TRUTH, np.full(4, 0.1) * SPAN)
    b = fit_track(_track(seed=1, rho=0.8), TRUTH, np.full(4, 0.1) * SPAN)
    assert np.sqrt(b.cov[6, 6]) > 1.5 * np.sqrt(a.cov[6, 6])


def test_a_parameter_at_its_bound_keeps_a_finite_spread():
    # e at the prior's top: differenced outwards, the clamp made its Jacobian column zero and
    # its std ~1e5 (found on a camera test video)
    truth = np.array([1.0, -9.81, 0.02, 0.3])
    pos = simulate(truth[None], np.array([[2.0, 6.0, 5.0, 3.5]]), 120)[0, :, :2]
    fit = fit_track(pos, truth, np.array([0.05, 0.2, 0.01, 0.2]))
    sd = np.sqrt(np.diag(fit.cov)[4:8])
    assert np.isfinite(sd).all() and (sd < SPAN).all()
    assert abs(fit.theta[0] - 1.0) < 0.01


def test_a_short_or_unseen_track_falls_back_to_the_window_fit():
    pos = _track()[:30]
    fit = fit_track(pos, TRUTH, np.full(4, 0.1) * SPAN, stage=40)
    ref = fit_state(pos, TRUTH, np.full(4, 0.1) * SPAN, window=40)
    np.testing.assert_allclose(fit.theta, ref.theta)
    none = fit_track(np.full((10, 2), np.nan), TRUTH, np.full(4, 0.1) * SPAN)
    assert none.n_used == 0


@needs_shipped
def test_physics_identification_beats_the_network_alone_and_is_seeded():
    est = methods.get("vid2param-physics", threads=1, n_samples=50)
    net = methods.get("vid2param", threads=1, n_samples=0)
    ds = make_dataset("test", 3, 2024)
    errs = {"physics": [], "network": []}
    for i in range(3):
        obs = ds.observation(i)
        post = est.identify(obs)
        assert post.samples.shape == (50, 4) and post.extras["n_simulations"] > 0
        assert post.extras["n_frames"] == obs.n_frames
        errs["physics"].append(((post.mean - ds.theta[i, -1]) / SPAN)[:3])
        errs["network"].append(((net.identify(obs).mean - ds.theta[i, -1]) / SPAN)[:3])
    # e, g and d: the fit over every frame beats the network's own answer
    assert (np.square(errs["physics"]).mean() < 0.5 * np.square(errs["network"]).mean())
    obs = Observation(frames=ds.frames[0])
    again = methods.get("vid2param-physics", threads=1, n_samples=50).identify(obs)
    np.testing.assert_array_equal(again.samples, est.identify(obs).samples)
    # prefixes and the (re-fitting) stream answer what identify answers on the same frames
    pre = est.identify_prefixes(obs, [60, 200])
    np.testing.assert_allclose(pre[0].mean, est.identify(obs.prefix(60)).mean)
    stream = est.stream()
    for f in ds.frames[0, :60]:
        last = stream.push(f)
    np.testing.assert_allclose(last.mean, pre[0].mean)


def test_the_physics_calibration_widens_the_fits_intervals_and_is_stored(tmp_path):
    from methods.vid2param.checkpoint import load_checkpoint
    from methods.vid2param.train import fit_stages

    if not SHIPPED_CHECKPOINTS["camera"].exists():
        pytest.skip("no shipped camera checkpoint")
    out = tmp_path / "cam.pt"
    # the camera's network stages kept as shipped, the calibration refitted after them
    fit_stages("camera", out, ["prior_noise:keep=true", "drag_evidence:keep=true",
                               ("physics_calibration", {"n": 6, "seed": 3})], log=lambda s: None)
    stages = load_checkpoint(out)["stages"]
    assert [s["name"] for s in stages] == ["prior_noise", "drag_evidence", "physics_calibration"]
    rec = stages[2]["state"]
    f = np.array(rec["std_scale"])
    assert f.shape == (4,) and (f >= 1.0).all() and rec["lengths"] == [50, 100, 200]
    # coverage after is the level wherever a factor widened (pooled over the lengths)
    for k, p in enumerate(rec["targets"]):
        if f[k] > 1.0:
            assert rec["coverage90_after"][p] >= 0.9 - 1e-9 > rec["coverage90_before"][p]
    cal = methods.get("vid2param-physics", checkpoint=str(out), n_samples=0)
    raw = methods.get("vid2param-physics", checkpoint="camera", n_samples=0)
    cal._ensure_net()
    raw._ensure_net()
    raw.physics_scale_ = np.ones(4)  # the shipped file may hold a calibration of its own
    np.testing.assert_array_equal(cal.physics_scale_, f)
    ds = make_dataset("test", 1, 11, size=cal.frame_size, n_frames=80)
    a, b = cal.identify(ds.observation(0)), raw.identify(ds.observation(0))
    np.testing.assert_allclose(a.mean, b.mean)
    # where the model check left the fit's spread as it was (it widens parameters the track
    # cannot inform, and failed fits, to at least the prior's)
    kept = [p not in a.extras.get("uninformed", []) + b.extras.get("uninformed", [])
            for p in ("e", "g", "d", "r")]
    assert not a.extras.get("check_failed") and any(kept)
    np.testing.assert_allclose(a.std[kept], (b.std * f)[kept], rtol=1e-9)
