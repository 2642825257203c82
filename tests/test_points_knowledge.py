"""The shared points model holds known values and prior ranges (issue 38 §4, first step)."""

import numpy as np
import pytest

from methods._points import CountingSystemSimulator, Points, Problem
from sysid_bench import systems
from sysid_bench.estimator import Observation


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
    plain = Problem(track, 0.01, CountingSystemSimulator(system))
    g = system.params.index("g") if "g" in system.params else 0
    name = system.params[g]
    other = 1 - g if system.n_params > 1 else None
    val = float(system.prior_lo[g] + 0.3 * (system.prior_hi[g] - system.prior_lo[g]))
    prior = {}
    if other is not None:
        lo, hi = system.prior_lo[other], system.prior_hi[other]
        prior = {system.params[other]: (lo + 0.25 * (hi - lo), lo + 0.5 * (hi - lo))}
    held = Problem(track, 0.01, CountingSystemSimulator(system), known={name: val}, prior=prior)
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
        Problem(track, 0.01, CountingSystemSimulator(system), known={"nope": 1.0})
