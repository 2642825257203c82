"""Widening a failed model check by a measured model discrepancy (issue 29):
:func:`methods._simulation.widen_by_discrepancy`, :func:`residual_tau` and the default
(:data:`DISCREPANCY_READING` None: the prior, as before)."""

from __future__ import annotations

import numpy as np
import pytest

import methods._simulation as S
from methods._tracks import prepare
from sysid_bench.core import physics
from sysid_bench.core.estimator import Check, Observation, Posterior
from sysid_bench.core.physics import PRIOR_STD
from sysid_bench.core.simulator import CountingSimulator

NOISE = 0.02


@pytest.fixture(scope="module")
def perturbed_fit():
    """A 100-frame track of physics that is not ours (spin 0.25, dwell 8 ms), its best fit by
    our physics (started at the truth: the widening, not the search, is under test) and a
    noise-only posterior about it (the Laplace spread at the assumed noise, with samples)."""
    rng = np.random.default_rng(0)
    theta = physics.sample_theta(1, rng)
    s0 = physics.sample_state0(1, rng)
    states = physics.simulate_perturbed(theta, s0, spin=0.25, dwell=0.008, n_frames=100)
    pos = states[0, :, :2] + NOISE * rng.standard_normal((100, 2))
    track = prepare(Observation(positions=pos))
    sim = CountingSimulator()
    lo, hi = S.state0_box(track)
    best, s0_best, rms = S.refine_fit(sim, track, theta[0], np.clip(track.state0, lo, hi), lo,
                                      hi, 450, tol=1e-4)
    check = S.model_check(sim, best, s0_best, track.floor, track, NOISE)
    # the method's answer: a little off the best fit, narrow as the noise alone would say
    std = S._discrepancy_std(sim, track, best, s0_best, NOISE)
    mean = np.clip(best + 0.5 * std, physics.PRIOR_LO, physics.PRIOR_HI)
    samples = mean + std * np.random.default_rng(1).standard_normal((400, 4))
    post = Posterior(mean=mean, std=std, samples=samples)
    return track, sim, best, s0_best, rms, check, post


def test_residual_tau_white_and_correlated():
    rng = np.random.default_rng(0)
    white = rng.standard_normal((400, 2))
    assert S.residual_tau(white) < 2.0
    t = np.arange(400)[:, None]
    slow = np.hstack([np.sin(t / 20.0), np.cos(t / 30.0)]) + 0.05 * rng.standard_normal((400, 2))
    assert S.residual_tau(slow) > 10.0
    gaps = white.copy()
    gaps[::3] = np.nan  # unseen frames are skipped
    assert 1.0 <= S.residual_tau(gaps) < 2.0
    with pytest.raises(ValueError, match="resid"):
        S.residual_tau(np.zeros(10))


@pytest.mark.parametrize("reading", ["tau", "worst", "scale"])
def test_failed_check_on_perturbed_track_widens_by_the_discrepancy(perturbed_fit, reading):
    track, sim, best, s0_best, rms, check, post = perturbed_fit
    assert not check.ok and rms > 2 * NOISE  # the model misses this track
    out = S.widen_by_discrepancy(post, check, sim, track, best, s0_best, reading=reading)
    d = out.extras["discrepancy"]
    assert not out.check.ok and "widened" in out.check.note and "correlated" in out.check.note
    assert d["rms_m"] == pytest.approx(rms, rel=1e-6) and d["tau"] >= 1.0
    assert d["factor"] > 1.0 and d["reading"] == reading
    # wider than the noise-only posterior for e, g, d, never wider than the prior
    assert np.all(out.std[:3] > post.std[:3])
    assert np.all(out.std <= PRIOR_STD + 1e-12)
    lo, hi = out.interval(0.9)
    # the interval holds the best fit (a parameter given the prior: its central 90%)
    informed = np.array([p not in d["prior"] for p in physics.PARAMS])
    assert informed[:3].all()
    assert np.all(((best >= lo) & (best <= hi))[informed])
    assert np.all((out.samples >= physics.PRIOR_LO) & (out.samples <= physics.PRIOR_HI))
    plo, phi = Posterior(mean=post.mean, std=PRIOR_STD,
                         samples=physics.sample_theta(4000, np.random.default_rng(2))
                         ).interval(0.9)
    assert np.all(hi - lo <= (phi - plo) * 1.02)
    # and the posterior mean is the method's
    np.testing.assert_allclose(out.mean, post.mean)


def test_readings_order_and_validation(perturbed_fit):
    track, sim, best, s0_best, _, check, post = perturbed_fit
    tau = S.widen_by_discrepancy(post, check, sim, track, best, s0_best, reading="tau")
    worst = S.widen_by_discrepancy(post, check, sim, track, best, s0_best, reading="worst")
    # the worst-shaped misfit moves the fit at least as far as the measured correlation says
    assert np.all(worst.std >= tau.std - 1e-12)
    with pytest.raises(ValueError, match="reading"):
        S.widen_by_discrepancy(post, check, sim, track, best, s0_best, reading="median")


@pytest.mark.parametrize("kind", ["random points", "hovering"])
def test_meaningless_input_still_gets_the_prior(kind):
    rng = np.random.default_rng(5)
    if kind == "random points":
        pos = rng.uniform(0.5, 9.5, (100, 2))
    else:  # still: whatever the check said, nothing informs e, g, d
        pos = np.tile([5.0, 5.0], (100, 1)) + 0.001 * rng.standard_normal((100, 2))
    track = prepare(Observation(positions=pos))
    sim = CountingSimulator()
    lo, hi = S.state0_box(track)
    best, s0_best, rms = S.refine_fit(sim, track, physics.PRIOR_LO + 0.5 * physics.PRIOR_SPAN,
                                      np.clip(track.state0, lo, hi), lo, hi, 200, tol=1e-4)
    check = Check(max(rms, 1.0), NOISE, False, 200)
    post = Posterior(mean=best, std=0.01 * PRIOR_STD,
                     samples=best + 0.01 * PRIOR_STD * rng.standard_normal((200, 4)))
    out = S.widen_by_discrepancy(post, check, sim, track, best, s0_best)
    assert not out.check.ok
    np.testing.assert_allclose(out.std, PRIOR_STD)
    lo, hi = out.interval(0.9)
    assert np.all(hi - lo >= 0.5 * 0.9 * physics.PRIOR_SPAN)
    if kind == "random points":  # the misfit is the track: nothing measured
        assert "discrepancy" not in out.extras and out.check.note == S.WIDENED_NOTE


def test_default_still_widens_to_the_prior(perturbed_fit, monkeypatch):
    """Off by default: on the perturbed cases no reading held enough truths for nuts
    (docs/reliability.md); with a reading set, widen_to_support measures instead."""
    track, sim, best, s0_best, _, check, post = perturbed_fit
    assert S.DISCREPANCY_READING is None
    failing = Check(check.rms_m, NOISE, False, check.n)
    out = S.widen_to_support(post, failing, sim, track, s0_best, track.floor, start=(best,
                             s0_best))
    np.testing.assert_allclose(out.std, np.maximum(post.std, PRIOR_STD))
    assert "discrepancy" not in out.extras
    monkeypatch.setattr(S, "DISCREPANCY_READING", "tau")
    out = S.widen_to_support(post, failing, sim, track, s0_best, track.floor, start=(best,
                             s0_best))
    assert out.extras["discrepancy"]["reading"] == "tau" and not out.check.ok


def test_point_posterior_gets_the_measured_spread(perturbed_fit):
    """A method that reported no spread (samples all at the mean) gets draws of the new std."""
    track, sim, best, s0_best, _, check, post = perturbed_fit
    point = Posterior(mean=post.mean, std=np.zeros(4), samples=np.tile(post.mean, (300, 1)))
    out = S.widen_by_discrepancy(point, check, sim, track, best, s0_best, reading="tau")
    lo, hi = out.interval(0.9)
    assert np.all(out.std[:3] > 0) and np.all(hi[:3] > lo[:3])
    assert np.all((best[:3] >= lo[:3]) & (best[:3] <= hi[:3]))
