"""The shared points model holds known values and prior ranges (issue 38 §4, first step)."""

import numpy as np
import pytest

from methods._points import Points, PointsSimulator, Problem
from sysid_bench.core import systems
from sysid_bench.core.estimator import Observation


def _obs():
    system = systems.get("pendulum")
    rng = np.random.default_rng([0, 38])
    theta = system.sample_theta(1, rng, "test")
    try:
        state0 = system.sample_state0(1, rng, theta=theta)
    except TypeError:
        state0 = system.sample_state0(1, rng)
    pts = system.observe(system.simulate(theta, state0, n_frames=40), theta)[0]
    return system, Observation(positions=pts, system="pendulum")


def test_known_is_held_and_prior_replaces_the_range():
    system, obs = _obs()
    part = Points(system, sigma=0.01)
    track = part.track(obs)
    plain = Problem(track, 0.01, PointsSimulator(system))
    g = system.params.index("g") if "g" in system.params else 0
    name = system.params[g]
    other = 1 - g if system.n_params > 1 else None
    val = float(system.prior_lo[g] + 0.3 * (system.prior_hi[g] - system.prior_lo[g]))
    prior = {}
    if other is not None:
        lo, hi = system.prior_lo[other], system.prior_hi[other]
        prior = {system.params[other]: (lo + 0.25 * (hi - lo), lo + 0.5 * (hi - lo))}
    held = Problem(track, 0.01, PointsSimulator(system), known={name: val}, prior=prior)
    u = np.random.default_rng(1).random((64, held.ndim))
    theta, _ = held.split(u)
    assert np.all(theta[:, g] == val)  # held exactly, whatever the unit coordinate
    if other is not None:
        (lo, hi), = prior.values()
        assert theta[:, other].min() >= lo and theta[:, other].max() <= hi
    # without knowledge: the system's own range, as before
    np.testing.assert_array_equal(plain.plo, system.prior_lo)
    np.testing.assert_array_equal(plain.plo + plain.pspan, system.prior_hi)
    with pytest.raises(ValueError, match="known/prior"):
        Problem(track, 0.01, PointsSimulator(system), known={"nope": 1.0})


def _lsq(**kw):
    import methods

    return methods.get("lsq", system="pendulum", n_samples=200, search_rounds=2, n_starts=1,
                       max_opt_evals=20, **kw)


def _noisy_pendulum():
    system = systems.get("pendulum")
    rng = np.random.default_rng([5, 38])
    theta = system.sample_theta(1, rng, "test")
    try:
        state0 = system.sample_state0(1, rng, theta=theta)
    except TypeError:
        state0 = system.sample_state0(1, rng)
    pts = system.observe(system.simulate(theta, state0, n_frames=40), theta)[0]
    pts = pts + rng.normal(0.0, 0.01, pts.shape)
    return system, theta[0], Observation(positions=pts, system="pendulum")


def test_lsq_holds_a_known_parameter_and_keeps_inside_a_range():
    system, theta, obs = _noisy_pendulum()
    g, L = system.params.index("g"), system.params.index("L")
    free = _lsq().identify(obs)
    held = _lsq(known={"g": float(theta[g])}).identify(obs)
    assert held.mean[g] == theta[g] and held.std[g] == 0.0
    assert np.all(held.samples[:, g] == theta[g])
    assert held.extras["known"] == {"g": float(theta[g])}
    # knowing g leaves one free parameter: L no further from the truth than without it
    assert abs(held.mean[L] - theta[L]) <= abs(free.mean[L] - theta[L]) + 1e-12
    lo, hi = float(theta[L]) * 1.05, float(theta[L]) * 1.2  # a range that excludes the truth
    ranged = _lsq(prior={"L": (lo, hi)}).identify(obs)
    assert lo <= ranged.mean[L] <= hi
    assert ranged.samples[:, L].min() >= lo and ranged.samples[:, L].max() <= hi
    assert ranged.extras["prior"] == {"L": [lo, hi]}


@pytest.mark.parametrize("kw, match", [
    ({"known": {"nope": 1.0}}, "known: 'nope' is no parameter"),
    ({"known": {"g": "x"}}, "known: expected a number"),
    ({"prior": {"L": (2.0, 1.0)}}, "prior: L"),
    ({"prior": {"L": 3.0}}, "prior: expected a"),
    ({"known": [("g", 9.8)]}, "known: expected a dict"),
])
def test_bad_knowledge_is_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        _lsq(**kw)
    with pytest.raises(ValueError, match="known: g = 9.8 is outside what the ball"):
        import methods

        methods.get("lsq", known={"g": 9.8})  # the ball's fit holds g, inside its physics only


@pytest.mark.parametrize("name, budget", [
    ("bo", {"n_calls": 6, "n_initial_points": 3, "n_surrogate": 256}),
    ("emcee", {"n_walkers": 12, "n_steps": 10, "n_burn": 4}),
])
def test_bo_and_emcee_hold_a_known_parameter(name, budget):
    import methods

    system, theta, obs = _noisy_pendulum()
    g, L = system.params.index("g"), system.params.index("L")
    post = methods.get(name, system="pendulum", known={"g": float(theta[g])},
                       prior={"L": (0.5, 1.0)}, **budget).identify(obs)
    assert post.mean[g] == theta[g] and post.std[g] == 0.0
    assert np.all(post.samples[:, g] == theta[g])
    assert 0.5 <= post.samples[:, L].min() and post.samples[:, L].max() <= 1.0
