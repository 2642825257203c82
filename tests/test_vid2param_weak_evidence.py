"""The weak-form evidence (``methods.vid2param.weak_evidence``) and its stage: the statistics
read each system's damping (and the collision's friction and wall restitution) off a clean
track, a stream gives a batch's bits, the blend weighs by inverse variance and keeps the
network's answer where the track says nothing, and the stage refuses what it cannot use."""

from __future__ import annotations

import numpy as np
import pytest

from methods.vid2param.weak_evidence import WEAK_FORMS, blend, fit_blend, window_weights
from sysid_bench.core import systems


def _tracks(name: str, n: int, n_frames: int = 200, seed: int = 0, noise_px: float = 0.0):
    """``n`` test-split cases of ``name``: the parameters (n, P) and the tracked points
    (n, T, K, 2) m, with Gaussian noise of ``noise_px`` pixels of a 64-pixel-wide view."""
    s = systems.get(name)
    rng = np.random.default_rng(seed)
    theta, state0 = s.sample_cases(n, rng, split="test")
    pts = s.observe(s.simulate(theta, state0, n_frames=n_frames, dt=0.05), theta)
    if noise_px:
        pts = pts + rng.normal(size=pts.shape) * noise_px * (s.extent[1] - s.extent[0]) / 64
    return s, theta, pts


def test_the_test_functions_differences_sum_a_constant_to_nothing():
    phi, dphi, ddphi = window_weights(16, 0.05)
    assert phi.shape == dphi.shape == ddphi.shape == (17,)
    assert phi[0] == phi[-1] == 0.0 and phi.max() == pytest.approx(0.05)
    # summed by parts against a track: no contribution of a constant or (first) of a ramp
    assert abs(ddphi.sum()) < 1e-12 and abs(dphi.sum()) < 1e-12
    t = np.arange(17.0)
    assert abs((ddphi * t).sum()) < 1e-9
    # and a parabola's second derivative comes back exactly: sum phi'' x = a sum phi
    x = 0.5 * 3.0 * (t * 0.05) ** 2
    assert (ddphi * x).sum() == pytest.approx(3.0 * phi.sum(), rel=1e-9)


@pytest.mark.parametrize("name,tol", [("pendulum", {"b": 0.03, "mu": 0.04}),
                                      ("spring", {"k3": 1.0, "c": 0.002}),
                                      ("collision", {"mu": 1e-6, "ew": 0.002})])
def test_each_form_reads_its_parameters_off_clean_tracks(name, tol):
    s, theta, pts = _tracks(name, 40)
    form = WEAK_FORMS[name]
    est, var = form.track(pts)
    assert est.shape == var.shape == (40, 200, len(form.blends))
    assert np.isnan(est[:, :16]).all() and np.isinf(var[:, :16]).all()  # no window yet
    for j, p in enumerate(form.blends):
        truth = theta[:, s.params.index(p)]
        e = est[:, -1, j]
        have = np.isfinite(e)
        assert have.mean() > 0.85, (p, have.mean())  # a collision without a wall bounce: no ew
        err = np.abs(e[have] - truth[have])
        assert np.median(err) < tol[p] / 3, (p, np.median(err))
        assert np.quantile(err, 0.9) < tol[p], (p, np.sort(err)[-5:])
        assert (var[have, -1, j] >= 0).all()  # 0 where a clean track fits exactly


@pytest.mark.parametrize("name", sorted(WEAK_FORMS))
def test_a_stream_gives_the_batchs_bits(name):
    _, _, pts = _tracks(name, 6, n_frames=90, seed=1, noise_px=0.03)
    form = WEAK_FORMS[name]
    est, var = form.track(pts)
    st = form.statistic(6)
    for t in range(90):
        st.update(pts[:, t])
        e, v = st.summary()
        np.testing.assert_array_equal(e, est[:, t])
        np.testing.assert_array_equal(v, var[:, t])
    # the overlapping windows' variance factor widens the intervals, not the estimates
    est2, var2 = form.track(pts, gain=4.0)
    np.testing.assert_array_equal(est2, est)
    have = np.isfinite(var) & (var > 0)
    assert (var2[have] >= var[have]).all() and (var2[have] > var[have]).any()  # ew: bounces
    # one track alone (a stream's batch of one) gives its row of the batch
    one = form.statistic(1)
    for t in range(90):
        one.update(pts[2:3, t])
    np.testing.assert_array_equal(one.summary()[0][0], est[2, -1])


def test_a_pendulum_at_rest_and_a_track_never_seen_say_nothing():
    form = WEAK_FORMS["pendulum"]
    still = np.zeros((2, 60, 1, 2))
    still[..., 1] = -1.0  # hanging straight down, for good
    still[1] = np.nan  # never seen
    est, var = form.track(still)
    assert np.isnan(est).all() and np.isinf(var).all()


def test_the_blend_weighs_by_inverse_variance_and_keeps_the_network_without_evidence():
    mu, sd = np.array([0.2, 0.2]), np.array([0.1, 0.1])
    lo, width = 0.0, 2.0
    est, var = np.array([1.0, np.nan]), np.array([0.04, np.inf])  # u = 0.5, sd_u 0.1
    m, s = blend(mu, sd, est, var, lo, width, 1.0, 0.0)
    assert m[0] == pytest.approx(0.35) and s[0] == pytest.approx(0.1 / np.sqrt(2))
    assert m[1] == 0.2 and s[1] == 0.1  # no estimate: the network's posterior
    # a parameter only its evidence shows (the collision's ew before a wall bounce): the prior
    m3, s3 = blend(mu, sd, est, var, lo, width, 1.0, 0.0, np.array([False, True]))
    assert m3[0] == m[0] and (m3[1], s3[1]) == (0.5, pytest.approx(1 / np.sqrt(12)))
    assert WEAK_FORMS["collision"].unseen_prior == ("ew",)
    # kappa and tau widen the estimate's variance
    m2, s2 = blend(mu, sd, est, var, lo, width, 2.0, 0.1)
    assert 0.2 < m2[0] < m[0] and s2[0] > s[0]


def test_the_blend_fit_finds_the_estimates_own_scale():
    rng = np.random.default_rng(0)
    N, T = 400, 200
    truth = rng.uniform(0, 1, N)
    sd_est = 0.02  # the estimate's true std is 3x what its variance says
    est = np.broadcast_to((truth + 3 * sd_est * rng.standard_normal(N))[:, None], (N, T))
    var = np.full((N, T), sd_est**2)
    mu = np.full((N, T), 0.5)
    sd = np.full((N, T), 0.29)
    kappa, tau, nll = fit_blend(mu, sd, est, var, truth, 0.0, 1.0)
    assert 2.0 < kappa < 4.5 and tau <= 0.02 and np.isfinite(nll)


@pytest.mark.parametrize("state,match", [
    ({"system": "ball", "params": ["e"], "kappa": [1], "tau": [0], "window": 16, "dt": 0.05},
     "expected a state"),
    ({"system": "spring", "params": ["k3", "c"], "kappa": [1, -1], "tau": [0, 0],
      "window": 16, "dt": 0.05}, "kappa > 0"),
    ({"system": "spring", "params": ["c"], "kappa": [1], "tau": [0], "window": 16,
      "dt": 0.05}, "expected params"),
    ({"system": "pendulum", "params": ["b", "mu"], "kappa": [1, 1], "tau": [0, 0],
      "window": 16, "dt": 0.05, "gain": -1.0}, "gain >= 0"),
])
def test_the_stage_refuses_a_state_it_cannot_use(state, match):
    from methods.vid2param.stages import WeakEvidence

    with pytest.raises(ValueError, match=match) as got:
        WeakEvidence(state, "f.pt")
    assert "checkpoint f.pt: stage 'weak_evidence'" in str(got.value)
