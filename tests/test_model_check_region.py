"""The model check is a check of the posterior (issue 29): the mean, else a parameter vector
inside the 90% interval with its own start; narrow and wrong still fails; prefixes are cheap."""

from __future__ import annotations

import numpy as np
import pytest

from methods._simulation import (
    MEAN_NOTE,
    REGION_NOTE,
    UNSEARCHED_NOTE,
    check_posterior,
    check_prefixes,
    model_check,
    region_box,
)
from methods._tracks import prepare
from sysid_bench.core import physics
from sysid_bench.core.estimator import Observation, Posterior
from sysid_bench.core.physics import PRIOR_SPAN, PRIOR_STD
from sysid_bench.core.simulator import DEFAULT_SIGMA, CountingSimulator

T = 120
THETA = np.array([0.85, -9.5, 0.02, 0.3])
#: the posterior mean off the truth: its trajectory misses a 120-frame track by decimetres
OFF = np.array([0.03, 0.4, 0.006, 0.0])


def _clean(seed: int = 5) -> Observation:
    rng = np.random.default_rng(seed)
    s0 = np.array([[2.0, 7.0, 5.0, 3.5]])
    pos = physics.simulate(THETA[None], s0, n_frames=T)[0, :, :2]
    return Observation(positions=pos + 0.005 * rng.standard_normal(pos.shape), floor=0.0)


def _posterior(mean, std, n_samples: int = 0, seed: int = 0) -> Posterior:
    mean, std = np.asarray(mean, float), np.asarray(std, float)
    samples = None
    if n_samples:
        samples = mean + std * np.random.default_rng(seed).standard_normal((n_samples, 4))
    return Posterior(mean=mean, std=std, samples=samples)


def _check(post: Posterior, obs: Observation) -> tuple[Posterior, bool]:
    """(checked posterior, whether the mean alone passed)."""
    track = prepare(obs)
    mean_ok = model_check(CountingSimulator(), post.mean, track.state0, track.floor, track,
                          DEFAULT_SIGMA, fit_state0=True).ok
    return check_posterior(post, CountingSimulator(), track, track.state0, track.floor,
                           DEFAULT_SIGMA, fit_state0=True), mean_ok


@pytest.mark.parametrize("n_samples", [0, 400], ids=["gaussian", "samples"])
def test_a_wide_honest_posterior_whose_mean_misses_passes_inside_its_interval(n_samples):
    # the mean is off by ~2 std: its own trajectory misses, the truth is inside the 90% box
    post = _posterior(THETA + OFF, np.abs(OFF) / 1.5 + [0, 0, 0, 0.2], n_samples)
    lo, hi = post.interval(0.9)
    assert np.all((THETA >= lo) & (THETA <= hi))
    std = post.std.copy()
    checked, mean_ok = _check(post, _clean())
    assert not mean_ok
    c = checked.check
    assert c.ok and c.note.startswith(REGION_NOTE), c
    assert c.rms_m <= 2 * c.noise_m < checked.extras["mean_rms_m"]
    assert c.n == 2 * T
    # an honest answer is not widened (r: no rolling seen, the prior's: uninformed)
    assert np.all(checked.std[:3] == std[:3]) and "check_failed" not in checked.extras


def test_a_narrow_wrong_posterior_fails_and_is_widened():
    # the same mean, but claiming 1/1000 of the prior: nothing inside its box explains the track
    post = _posterior(THETA + OFF, PRIOR_SPAN * 1e-3, 400)
    checked, mean_ok = _check(post, _clean())
    assert not mean_ok
    c = checked.check
    assert not c.ok and checked.extras["check_failed"]
    assert checked.extras["region_rms_m"] > 2 * c.noise_m
    # the verdict keeps the mean's RMS; the intervals now hold the truth (what the data support)
    assert c.rms_m == checked.extras["mean_rms_m"]
    lo, hi = checked.interval(0.9)
    assert np.all((THETA[:3] >= lo[:3]) & (THETA[:3] <= hi[:3]))


def test_the_mean_passing_says_so():
    post = _posterior(THETA, PRIOR_SPAN * 0.01)
    checked, mean_ok = _check(post, _clean())
    assert mean_ok and checked.check.ok and checked.check.note == MEAN_NOTE
    assert "region_rms_m" not in checked.extras  # no region refit when the mean passes


def test_region_box_is_the_interval_inside_the_prior():
    post = _posterior(THETA, [np.inf, 0.1, 0.001, 0.01])
    lo, hi = region_box(post)
    assert lo[0] == physics.PRIOR_LO[0] and hi[0] == physics.PRIOR_HI[0]
    z = 1.6448536
    assert np.allclose([lo[1], hi[1]], [THETA[1] - 0.1 * z, THETA[1] + 0.1 * z])
    s = _posterior(THETA, [0.01, 0.1, 0.001, 0.01], 1000)
    assert np.allclose(region_box(s), np.quantile(s.samples, [0.05, 0.95], axis=0))


def test_prefixes_warm_start_and_pass_cheaply():
    obs = _clean()
    lengths = list(range(1, T + 1))
    posts = [_posterior(THETA, PRIOR_SPAN * 0.01) for _ in lengths]
    out = check_prefixes(posts, obs, lengths, DEFAULT_SIGMA)
    assert not out[0].check.ok and not out[1].check.ok  # fewer than 3 frames
    assert all(p.check.ok and p.check.note == MEAN_NOTE for p in out[2:])
    sims = np.array([p.extras["check_simulations"] for p in out[2:]])
    # from the previous prefix's start: mostly 1 judgement + 8 for `uninformed`, a refit of
    # the start now and then (a cold start fits it every time: ~45-200 simulations each)
    assert np.median(sims) <= 10 and sims.mean() < 40, sims


def test_prefixes_that_nothing_explains_stop_searching():
    rng = np.random.default_rng(2)
    obs = Observation(positions=rng.uniform(1.0, 9.0, (60, 2)), floor=0.0)
    lengths = list(range(3, 61))
    posts = [_posterior(physics.PRIOR_MEAN, PRIOR_STD * 0.2) for _ in lengths]
    out = check_prefixes(posts, obs, lengths, DEFAULT_SIGMA)
    assert not any(p.check.ok for p in out)
    assert all(np.all(p.std >= PRIOR_STD - 1e-12) for p in out)
    skipped = [p.check.note == UNSEARCHED_NOTE for p in out]
    assert not skipped[0] and sum(skipped) >= len(out) // 2
    sims = [p.extras["check_simulations"] for p in out]
    assert max(s for s, k in zip(sims, skipped) if k) <= 2


def test_a_prefix_far_longer_than_the_last_gets_a_full_search(monkeypatch):
    """Vid2Param's posteriors after 50 and 200 frames of the report's test video 9: the
    200-frame check used to start warm from the 50-frame fits with 90 simulations a search and
    failed, though a vector inside the 90% box explains the track (as the 200-frame check
    alone finds). Only a prefix at most SEARCH_GROWTH times the last starts warm now."""
    import methods
    from methods import _simulation
    from sysid_bench.bench.cases import observation, test_set

    ds = test_set("interleaved", 10, 2024)
    obs = observation(ds, 9, "video")
    est = methods.get("vid2param")
    alone = est.identify_prefixes(obs, [200])[0]
    assert alone.check.ok
    after_50 = est.identify_prefixes(obs, [50, 200])[1]
    assert after_50.check.ok
    # the old rule (every later prefix warm, whatever it grew by) fails it
    monkeypatch.setattr(_simulation, "SEARCH_GROWTH", float("inf"))
    assert not est.identify_prefixes(obs, [50, 200])[1].check.ok
