"""NUTS on the JAX simulator: its likelihood, its gradients, accuracy, diagnostics, bad input.

Accuracy (normalised MSE over e, g, d; guessing the prior mean scores 0.083) on test-split cases
of ``make_dataset("test", n=20, seed=5)``, clean positions, 200 frames, floor known, the initial
state *unknown* (sampled by NUTS). Default run: the first 3 cases with short chains
(100 warm-up + 100 samples), bound 1e-3, every case inside its 90% interval; slow run: all 20
with the defaults, same bound.
Measured on the 2-core development machine: see the report of the session that wrote this.
"""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from methods import nuts as N
from sysid_bench.core import physics
from sysid_bench.core import simulator as C
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Forecast, Observation, Posterior
from sysid_bench.core.metrics import interval_coverage, param_mse
from sysid_bench.core.physics import PRIOR_HI, PRIOR_LO

GUESS = 0.083
BOUND = 1e-3
FAST = {"num_warmup": 100, "num_samples": 100}


@pytest.fixture(scope="module")
def ds():
    return make_dataset("test", n=20, seed=5)


def _obs(ds, i, known_state=False, n=None):
    n = ds.states.shape[1] if n is None else n
    return Observation(
        positions=ds.states[i, :n, :2],
        floor=float(ds.floor[i]),
        state0=ds.states[i, 0] if known_state else None,
    )


# ------------------------------------------------------------------------------------------
# the likelihood and its gradient
def test_loglik_mirrors_common_gaussian_loglik():
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(40, 2))
    obs[[2, 9, 30]] = np.nan
    mask = np.isfinite(obs).all(axis=1)
    sim = rng.normal(size=(6, 40, 2))
    want = C.gaussian_loglik(sim, obs, mask, 0.05)
    got = np.asarray(N.loglik_jax(jnp.asarray(sim), jnp.asarray(obs), jnp.asarray(mask), 0.05))
    np.testing.assert_allclose(got, want, rtol=1e-13)


def test_loglik_gradient_matches_finite_differences(ds):
    """The forward-mode custom derivative (what NUTS uses) vs central differences of the NumPy
    likelihood, for theta and the initial state, on a 200-frame case with bounces and walls."""
    obs = _obs(ds, 0)
    T = obs.n_frames
    mask = np.ones(T, bool)
    data = (jnp.asarray(obs.positions), jnp.asarray(mask), jnp.asarray(0.0), jnp.asarray(C.DEFAULT_SIGMA))
    theta = ds.theta[0, 0] * np.array([1.01, 0.99, 1.05, 1.0])  # off the mode: gradients are large
    s0 = ds.states[0, 0] + np.array([0.05, -0.03, 0.1, 0.05])

    def np_ll(x):
        sim = physics.simulate(x[None, :4], x[None, 4:], n_frames=T)[..., :2]
        return C.gaussian_loglik(sim, obs.positions, mask, C.DEFAULT_SIGMA)[0]

    grad = jax.jit(jax.grad(lambda th, s: N._loglik(th, s, data, T, obs.dt, True), argnums=(0, 1)))
    g = np.concatenate([np.asarray(a) for a in grad(jnp.asarray(theta), jnp.asarray(s0))])
    x = np.concatenate((theta, s0))
    fd = np.empty(8)
    for i in range(8):
        h = 1e-7 * max(abs(x[i]), 1e-2)
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        fd[i] = (np_ll(xp) - np_ll(xm)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


# ------------------------------------------------------------------------------------------
# accuracy, calibration on clean data, diagnostics
def _accuracy(ds, cases, **options):
    est = N.NUTS(**options)
    posts = [est.identify(_obs(ds, i)) for i in cases]
    truth = ds.theta[list(cases), 0]
    means = np.array([p.mean for p in posts])
    nmse = float(param_mse(truth, means)[:3].mean())
    lo, hi = zip(*(p.interval(0.9) for p in posts))
    cover = interval_coverage(truth, np.array(lo), np.array(hi))
    return nmse, cover, posts


def test_accuracy_on_test_split_state_unknown(ds):
    # 3 cases, was 5 (after the sampler's compilation, 31 s of CPU here, a case costs 7.6 s):
    # 3 of 3 covered where 4 of 5 were asked; the 20-case run with the defaults is slow below
    nmse, cover, posts = _accuracy(ds, range(3), **FAST)
    print(f"\nnuts (3 cases, 100+100): nMSE(e,g,d) = {nmse:.2e}, 90% coverage {cover.round(2)}")
    assert nmse < BOUND < GUESS
    assert (cover[:3] >= 0.8).all()
    for p in posts:
        assert isinstance(p, Posterior) and p.samples.shape == (100, 4)
        ex = p.extras
        assert ex["state0_sampled"] and set(ex["rhat"]) == set(physics.PARAMS) == set(ex["ess"])
        assert isinstance(ex["divergences"], int) and ex["divergences"] >= 0
        assert ex["map_rms_m"] < 1e-3  # clean positions: the mode fits to well under sigma
        # the counting rule: search batches + potential evaluations + leapfrog steps + fit check
        assert ex["n_simulations"] >= 1000 * 4 + 200 + ex["n_potential_evals_init"] + 1
        # within the prior box, physical units
        assert np.all((p.samples >= PRIOR_LO) & (p.samples <= PRIOR_HI))


@pytest.mark.slow
def test_accuracy_on_20_cases_with_defaults(ds):
    nmse, cover, posts = _accuracy(ds, range(20))
    conv = np.mean([p.extras["converged"] for p in posts])
    print(f"\nnuts (20 cases, defaults): nMSE(e,g,d) = {nmse:.2e}, 90% coverage {cover.round(2)}, converged {conv:.0%}")
    assert nmse < BOUND
    assert conv >= 0.9


def test_known_state_is_used_and_forecast_continues_the_track(ds):
    """With the initial state given it is held fixed; the forecast follows the true future."""
    est = N.NUTS(**N.NUTS.contract_options)
    obs = _obs(ds, 1, known_state=True, n=100)
    post = est.identify(obs)
    assert not post.extras["state0_sampled"]
    assert param_mse(ds.theta[1, 0][None], post.mean[None])[:3].mean() < BOUND
    fc = est.forecast(obs, 10)
    assert isinstance(fc, Forecast) and fc.samples.shape == (20, 10, 2)
    err = np.abs(fc.mean - ds.states[1, 100:110, :2]).max()
    assert err < 0.05, f"forecast off by {err:.3g} m"
    assert fc.extras["n_simulations"] > post.extras["n_simulations"] - 1


def test_several_chains_are_pooled_and_compared(ds):
    opts = dict(N.NUTS.contract_options, num_chains=2)
    post = N.NUTS(**opts).identify(_obs(ds, 1, known_state=True, n=100))
    assert post.samples.shape == (2 * opts["num_samples"], 4)
    assert all(np.isfinite(v) for v in post.extras["rhat"].values())
    assert post.extras["rhat"]["g"] < 1.1  # two chains from the same mode agree


def test_misfit_is_reported_not_raised():
    """A track no ball can make (level flight at 5 m for 3 s) gives a posterior that says so."""
    t = np.arange(60) * 0.05
    pos = np.column_stack([1.0 + 2.0 * t, np.full(60, 5.0)])
    # padded to 200 frames: shares the compiled sampler of the accuracy test
    post = N.NUTS(**FAST, frame_bucket=200).identify(Observation(positions=pos, floor=0.0))
    assert post.extras["converged"] is False
    assert "misses the track" in post.extras["warning"]
    assert np.isfinite(post.mean).all() and (post.std >= 0).all()


def test_a_stuck_chain_stops_after_its_probe_and_says_so():
    """A ball lying still on the floor: e, g and d are flat directions, the step size collapses
    and every tree hits the depth cap. The chain stops after PROBE_ITERATIONS (not ~10x a
    normal fit's leapfrog steps for draws that do not mix) and the answer says what it is."""
    pos = np.tile([4.0, 0.0], (60, 1))
    post = N.NUTS(**FAST, frame_bucket=200).identify(Observation(positions=pos, floor=0.0))
    ex = post.extras
    assert ex["stopped_stuck"] is True and ex["converged"] is False
    assert "Laplace approximation" in ex["warning"]
    assert ex["mean_tree_size"] >= N.STUCK_TREE * (2 ** 6 - 1) and ex["step_size"] < N.STUCK_STEP
    assert post.samples.shape == (FAST["num_samples"], 4) and np.isfinite(post.samples).all()
    # a still ball informs neither e, g nor d: their intervals stay near the prior's
    lo, hi = post.interval(0.9)
    assert np.all((hi - lo)[:3] > 0.5 * 0.9 * (PRIOR_HI - PRIOR_LO)[:3])


# ------------------------------------------------------------------------------------------
# bad input and packaging
@pytest.mark.parametrize(
    "options, name",
    [
        ({"sigma": -1.0}, "sigma"),
        ({"num_samples": 0}, "num_samples"),
        ({"num_chains": 1.5}, "num_chains"),
        ({"target_accept": 1.5}, "target_accept"),
        ({"frame_bucket": 0}, "frame_bucket"),
        ({"seed": "a"}, "seed"),
    ],
)
def test_bad_hyperparameters_name_themselves(options, name):
    obs = Observation(positions=np.column_stack([np.linspace(1, 3, 10), np.linspace(5, 4, 10)]), floor=0.0)
    with pytest.raises(ValueError, match=name):  # validated at construction
        N.NUTS(**options).identify(obs)


def test_too_few_seen_frames_is_a_value_error():
    pos = np.full((10, 2), np.nan)
    pos[:2] = [[1.0, 5.0], [1.1, 5.0]]
    with pytest.raises(ValueError, match="positions"):
        N.NUTS().identify(Observation(positions=pos, floor=0.0))


def test_importing_methods_does_not_import_jax():
    code = "import sys, methods; methods.available(); assert 'jax' not in sys.modules, 'jax imported'"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=str(__import__("pathlib").Path(__file__).parents[1]))


# ------------------------------------------------------------------------------------------
# speed (pytest-benchmark; skipped in the default run)
@pytest.mark.benchmark(group="nuts")
@pytest.mark.parametrize("known_state", [True, False], ids=["state0-given", "state0-sampled"])
def test_bench_nuts_identify_200_frames(benchmark, ds, known_state):
    """One identification, 200 frames, defaults, after a warm-up round (compilation)."""
    est = N.NUTS()
    obs = _obs(ds, 2, known_state=known_state)
    post = benchmark.pedantic(est.identify, args=(obs,), rounds=3, iterations=1, warmup_rounds=1)
    assert np.isfinite(post.mean).all()
    median = benchmark.stats.stats.median
    # the 15 s target is reported, not asserted: absolute times depend on the machine (issue 14)
    benchmark.extra_info.update({"median_s": median, "n_simulations": post.extras["n_simulations"],
                                 "target_s": 15.0, "meets_target": bool(median <= 15.0)})
    print(f"\nnuts ({'given' if known_state else 'sampled'} state0): {median:.2f} s per identification "
          f"(target 15 s: {'met' if median <= 15.0 else 'MISSED'})")
