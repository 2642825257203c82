"""A white-noise likelihood is widened where a track errs by more than its noise, in runs of
frames (issue 38: a 120 frames/s camera clip read confidently wrong by emcee)."""

import numpy as np
import pytest

from methods._points import Points, inflate, noise_inflation, residual_tau
from sysid_bench.core import systems
from sysid_bench.core.estimator import Observation


def test_residual_tau_of_white_and_of_correlated_noise():
    rng = np.random.default_rng(0)
    white = rng.standard_normal((4000, 1, 2))
    assert residual_tau(white) == pytest.approx(1.0, abs=0.3)
    # AR(1) with rho 0.8: tau = (1 + rho) / (1 - rho) = 9
    x = np.zeros((4000, 2))
    e = rng.standard_normal((4000, 2))
    for t in range(1, 4000):
        x[t] = 0.8 * x[t - 1] + e[t]
    assert residual_tau(x) == pytest.approx(9.0, rel=0.3)
    x[::7] = np.nan  # unseen frames are left out, not read as zeros
    assert residual_tau(x) == pytest.approx(9.0, rel=0.35)
    assert residual_tau(np.full((10, 2), np.nan)) == 1.0


def _pendulum(noise):
    system = systems.get("pendulum")
    theta = np.array([[-9.81, 0.9, 0.05, 0.02]])
    state0 = np.array([[0.4, 0.0]])
    pts = system.observe(system.simulate(theta, state0, n_frames=200), theta)[0]
    return system, theta[0], state0[0], pts + noise(pts.shape)


def test_a_fit_within_the_noise_is_left_as_it_is():
    rng = np.random.default_rng(1)
    system, theta, s0, pts = _pendulum(lambda sh: 0.003 * rng.standard_normal(sh))
    prob = Points(system, sigma=0.012).problem(Observation(positions=pts, system="pendulum"))
    k, info = noise_inflation(prob, theta, s0)
    assert k == 1.0 and info["residual_rms_m"] < 0.005
    samples = np.random.default_rng(2).normal(theta, 0.01, (50, 4))
    out, std = inflate(prob, samples, samples.std(0), k)
    assert out is samples  # bitwise: nothing changes where nothing is understated


def test_a_drifting_track_error_widens_the_spread():
    # a tracker off by 2.5 cm in runs of ~25 frames: the data hold ~8 looks, not 200
    rng = np.random.default_rng(3)

    def drift(shape):
        steps = np.repeat(rng.standard_normal((shape[0] // 25 + 1,) + shape[1:]), 25, axis=0)
        return 0.025 * steps[: shape[0]]

    system, theta, s0, pts = _pendulum(drift)
    prob = Points(system, sigma=0.012).problem(Observation(positions=pts, system="pendulum"))
    k, info = noise_inflation(prob, theta, s0)
    assert info["residual_tau"] > 5 and k > 3
    samples = np.random.default_rng(4).normal(theta, [0.01, 0.001, 0.005, 0.005], (400, 4))
    out, std = inflate(prob, samples, samples.std(0), k)
    lo, hi = prob.plo, prob.plo + prob.pspan
    assert np.all(out >= lo) and np.all(out <= hi)
    assert np.all(std <= prob.pspan / np.sqrt(12) + 1e-12)
    assert std[1] == pytest.approx(k * samples.std(0)[1])


def _ball_track(noise, seed):
    from sysid_bench.core import physics

    theta = np.array([[0.75, -9.81, 0.02, 0.3]])
    state0 = np.array([[2.0, 6.0, 2.0, 0.0]])
    pos = physics.simulate(theta, state0, 120, 0.05, 0.0)[0][:, :2]
    return pos + noise(np.random.default_rng(seed), pos.shape)


def _emcee_ball(pos):
    import methods

    est = methods.get("emcee", n_steps=300, n_burn=150)
    return est.identify(Observation(positions=pos, dt=0.05, floor=0.0))


def test_the_balls_emcee_is_widened_where_its_track_errs_in_runs():
    """The ball's sampler as every system's: a clean track keeps its spread (factor 1), a
    track off by 5 cm in runs of 20 frames (a camera's centres biased near the floor) is
    widened by the factor its residuals measure."""
    clean = _emcee_ball(_ball_track(lambda r, sh: 0.004 * r.standard_normal(sh), 5))
    assert clean.extras["noise_inflation"] == 1.0

    def runs(r, sh):
        steps = np.repeat(r.standard_normal((sh[0] // 20 + 1, sh[1])), 20, axis=0)
        return 0.05 * steps[: sh[0]] + 0.004 * r.standard_normal(sh)

    drift = _emcee_ball(_ball_track(runs, 6))
    k = drift.extras["noise_inflation"]
    assert drift.extras["residual_tau"] > 5 and k > 2
    # e and g: the spread grew with the factor (capped at the prior's), the samples with it
    assert np.all(drift.std[:2] > 1.5 * clean.std[:2])
    assert np.allclose(drift.samples.std(axis=0)[:2], drift.std[:2], rtol=0.2)
