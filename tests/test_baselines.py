"""The classical baselines (lsq, bo, emcee, sindy, dmd) and their shared machinery.

Accuracy (the issue's check): normalised MSE over e, g, d on 20 test-split cases
(``make_dataset("test", n=20, seed=5)``: sub-ranges 1, 3, 5, 7, 9), clean positions, 200 frames.
Guessing the prior mean scores 0.083. Measured on the shared 2-core machine:

=========  =========================  =========  ==========
method     input                      measured   asserted
=========  =========================  =========  ==========
lsq        positions + state0, floor  0.0043     < 0.01
lsq        positions only             0.0039     < 0.015
sindy      positions (either)         3e-6       < 0.002
emcee      positions + state0, floor  1e-6       < 0.002 (slow)
bo         positions + state0, floor  0.047      < 0.065 (slow)
=========  =========================  =========  ==========

bo's figure is what 20 evaluations in four dimensions give: 0.02-0.05 over other seeds and case
sets, with g the weak parameter; it is below guessing, not far below it.
"""

import numpy as np
import pytest

from methods import _simulation, _tracks, _weights
from methods.bo import BayesOpt
from methods.dmd import DMD
from methods.ensemble import Emcee
from methods.lsq import LSQ
from methods.sindy import SINDy
from sysid_bench.core import physics, simulator
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Forecast, Observation, Posterior
from sysid_bench.core.metrics import param_mse

GUESS = 0.083  # normalised MSE of the prior mean on e, g, d
N_CASES = 20


@pytest.fixture(scope="module")
def ds():
    """20 test-split videos (sub-ranges 1, 3, 5, 7, 9), 200 frames, floor 0."""
    return make_dataset("test", n=N_CASES, seed=5)


def _obs(ds, i, known=True, n=None):
    n = ds.states.shape[1] if n is None else n
    return Observation(
        positions=ds.states[i, :n, :2],
        floor=float(ds.floor[i]) if known else None,
        state0=ds.states[i, 0] if known else None,
    )


def _nmse_egd(est, ds, known=True, cases=range(N_CASES)):
    means = np.array([est.identify(_obs(ds, i, known)).mean for i in cases])
    truth = ds.theta[list(cases), 0]
    return float(param_mse(truth, means)[:3].mean())


# ------------------------------------------------------------------------------------------
# the shared machinery: harness simulator, tracks, weights, the simulation skeleton
def test_loglik_is_gaussian_over_seen_frames():
    from scipy.stats import norm

    rng = np.random.default_rng(0)
    obs = rng.normal(size=(30, 2))
    obs[[3, 7]] = np.nan
    mask = np.isfinite(obs).all(axis=1)
    sim = rng.normal(size=(5, 30, 2))
    got = simulator.gaussian_loglik(sim, obs, mask, 0.3)
    want = norm.logpdf(obs[mask][None], sim[:, mask], 0.3).sum(axis=(1, 2))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    mse = simulator.mean_sq_error(sim, obs, mask)
    np.testing.assert_allclose(mse, ((sim[:, mask] - obs[mask]) ** 2).mean(axis=(1, 2)))
    assert got.shape == (5,) and np.isfinite(got).all()


def test_counting_simulator_counts_trajectories():
    sim = simulator.CountingSimulator()
    rng = np.random.default_rng(1)
    sim(physics.sample_theta(3, rng), physics.sample_state0(3, rng), 10, 0.05, 0.0)
    sim.positions(physics.sample_theta(5, rng), physics.sample_state0(5, rng), 10, 0.05, 0.0)
    assert sim.n_simulations == 8


def test_counting_simulator_enforces_its_budget():
    sim = simulator.CountingSimulator(max_simulations=5)
    rng = np.random.default_rng(1)
    sim(physics.sample_theta(3, rng), physics.sample_state0(3, rng), 10, 0.05, 0.0)
    with pytest.raises(simulator.SimulationBudgetExceeded, match="budget of 5"):
        sim(physics.sample_theta(3, rng), physics.sample_state0(3, rng), 10, 0.05, 0.0)
    assert sim.n_simulations == 3  # the refused batch was not simulated
    with pytest.raises(ValueError, match="max_simulations"):
        simulator.CountingSimulator(max_simulations=-1)


def test_simulation_methods_share_one_skeleton():
    from methods.bo import BayesOpt
    from methods.ensemble import Emcee
    from methods.lsq import LSQ

    for cls in (LSQ, BayesOpt, Emcee):
        assert issubclass(cls, _simulation.SimulationMethod)
        assert "identify" not in vars(cls) and "forecast" not in vars(cls)


def test_segmentation_finds_bounces_floor_and_start(ds):
    for i in range(N_CASES):
        track = _tracks.prepare(_obs(ds, i, known=False))
        seg = track.segments
        e = ds.theta[i, 0, 0]
        assert len(seg.contacts) >= 1
        ratios = np.array([c.ratio for c in seg.contacts])
        np.testing.assert_allclose(np.median(ratios), e, atol=0.005)
        assert abs(track.floor - ds.floor[i]) < 2e-3
        err = np.abs(track.state0 - ds.states[i, 0])
        assert (err[:2] < 5e-3).all() and (err[2:] < 3e-2).all(), err
        # no contact inside a flight segment: vy turns from down to up only at the floor, and
        # vx changes sign only at a wall
        vx, vy = ds.states[i, :, 2], ds.states[i, :, 3]
        for a, b in seg.flight:
            assert not ((vy[a : b - 1] < 0) & (vy[a + 1 : b] > 0)).any()
            assert not (np.sign(vx[a : b - 1]) != np.sign(vx[a + 1 : b])).any()


def test_tempered_weights_reach_the_target_ess():
    ll = np.array([0.0, -1e4, -2e4, -3e4] + [-1e5] * 96)
    w, beta, ess = _weights.tempered_weights(ll, 20)
    assert 0 < beta < 1 and ess >= 20 - 1e-6 and abs(w.sum() - 1) < 1e-12
    w, beta, ess = _weights.tempered_weights(np.zeros(50), 20)
    assert beta == 1.0 and ess == pytest.approx(50)


def test_forecast_by_simulation_continues_the_true_trajectory(ds):
    sim = simulator.CountingSimulator()
    theta = ds.theta[0, :1]
    fc = _simulation.forecast_by_simulation(sim, theta, ds.states[0, :1], 0.0, 0.05, 50, skip=99)
    np.testing.assert_allclose(fc.mean, ds.states[0, 100:150, :2], atol=1e-9)
    assert fc.samples.shape == (1, 50, 2) and fc.extras["n_simulations"] == 1


# ------------------------------------------------------------------------------------------
# accuracy (the check), fast methods in the default run
def test_lsq_accuracy_known_state0(ds):
    assert _nmse_egd(LSQ(), ds) < 0.01


def test_lsq_accuracy_positions_only(ds):
    assert _nmse_egd(LSQ(), ds, known=False) < 0.015


@pytest.mark.parametrize("known", [True, False])
def test_sindy_accuracy(ds, known):
    assert _nmse_egd(SINDy(), ds, known=known) < 0.002


def test_frames_only_input(ds):
    # tracked 28x28 video, unknown floor and start: the tracker's mm errors cost accuracy
    cases = range(6)
    truth = ds.theta[list(cases), 0]
    for est, bound in ((LSQ(), 0.03), (SINDy(), 0.06)):
        posts = [est.identify(Observation(frames=ds.frames[i])) for i in cases]
        assert all(p.extras["input"] == "frames" for p in posts)
        nmse = param_mse(truth, np.array([p.mean for p in posts]))[:3].mean()
        assert nmse < bound, (est.name, nmse)


def test_emcee_small_budget_is_accurate_and_reports_diagnostics(ds):
    est = Emcee(n_steps=40, n_burn=10)
    post = est.identify(_obs(ds, 0))
    se = ((post.mean - ds.theta[0, 0]) / physics.PRIOR_SPAN) ** 2
    assert se[:3].max() < 1e-3
    for key in ("acceptance", "tau", "tau_reliable", "ess", "converged", "opt_status"):
        assert key in post.extras
    assert post.samples.shape == (32 * 30, 4)
    assert post.extras["n_simulations"] >= 32 * 40


def test_bo_runs_20_evaluations(ds):
    post = BayesOpt().identify(_obs(ds, 1))
    assert post.extras["n_simulations"] == 20 and post.extras["ok"]
    se = ((post.mean - ds.theta[1, 0]) / physics.PRIOR_SPAN) ** 2
    assert se[:3].mean() < GUESS
    assert (post.std > 0).all()


def test_bo_quick_kernel_introspection_changes_nothing(ds, monkeypatch):
    """The bo fit's cached Kernel.hyperparameters gives the same kernels' lists and the same
    posterior bytes as sklearn's own, and sklearn's is back afterwards."""
    import contextlib

    from sklearn.gaussian_process.kernels import Kernel
    from skopt.learning.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    from methods import bo

    kernel = ConstantKernel(1.0) * Matern(length_scale=np.ones(4), nu=2.5) + WhiteKernel()
    original = Kernel.__dict__["hyperparameters"]
    want = (kernel.hyperparameters, kernel.k1.k2.hyperparameters, kernel.k2.hyperparameters)
    with bo._quick_kernel_introspection():
        assert Kernel.__dict__["hyperparameters"] is not original
        got = (kernel.hyperparameters, kernel.k1.k2.hyperparameters, kernel.k2.hyperparameters)
        np.testing.assert_array_equal(kernel.theta, np.log(np.ones(6)))
    assert Kernel.__dict__["hyperparameters"] is original
    assert got == want
    obs = _obs(ds, 1, n=40)
    fast = BayesOpt(n_calls=6, n_initial_points=3, n_surrogate=256).identify(obs)
    monkeypatch.setattr(bo, "_quick_kernel_introspection", contextlib.nullcontext)
    plain = BayesOpt(n_calls=6, n_initial_points=3, n_surrogate=256).identify(obs)
    for a, b in ((fast.mean, plain.mean), (fast.std, plain.std), (fast.samples, plain.samples)):
        assert a.tobytes() == b.tobytes()


@pytest.mark.slow
def test_emcee_accuracy(ds):
    assert _nmse_egd(Emcee(), ds) < 0.002


@pytest.mark.slow
def test_bo_accuracy(ds):
    assert _nmse_egd(BayesOpt(), ds) < 0.065


# ------------------------------------------------------------------------------------------
# honest failure: no exception, say so, keep the spread
def test_emcee_short_chain_says_not_converged(ds):
    post = Emcee(n_walkers=16, n_steps=6, n_burn=2, n_init=50).identify(_obs(ds, 2))
    assert post.extras["converged"] is False
    assert (post.std >= np.asarray(post.extras["laplace_std"]) - 1e-15).all()


def test_bo_optimiser_failure_falls_back_to_the_prior(ds, monkeypatch):
    import skopt

    def broken(*args, **kwargs):
        raise ValueError("synthetic failure")

    monkeypatch.setattr(skopt, "gp_minimize", broken)
    post = BayesOpt().identify(_obs(ds, 0))
    assert post.extras["ok"] is False and "synthetic failure" in post.extras["message"]
    np.testing.assert_allclose(post.std, physics.PRIOR_STD)


def test_sindy_reports_uninformed_parameters_with_the_prior(ds):
    # 30 frames: in flight and bouncing, never rolling -> r is the prior
    post = SINDy().identify(_obs(ds, 0, n=30))
    assert not post.extras["informed"][3]
    assert post.std[3] == pytest.approx(physics.PRIOR_STD[3])


# ------------------------------------------------------------------------------------------
# forecasts
@pytest.mark.parametrize("est, tol", [(LSQ(), 1.0), (SINDy(), 0.1)], ids=["lsq", "sindy"])
def test_forecast_continues_after_the_last_frame(ds, est, tol):
    # lsq's draws fit to ~0.2 m RMS, so its forecast is only that good; its spread says so
    obs = _obs(ds, 3, n=100)
    fc = est.forecast(obs, 10)
    assert isinstance(fc, Forecast) and fc.mean.shape == (10, 2)
    truth = ds.states[3, 100:110, :2]
    assert np.abs(fc.mean - truth).max() < tol
    assert (np.abs(fc.mean - truth) <= 3 * fc.std + 0.02).all()
    # the first forecast frame is frame 100, not a repeat of frame 99
    assert np.linalg.norm(fc.mean[0] - truth[0]) < np.linalg.norm(fc.mean[0] - ds.states[3, 99, :2])


def test_dmd_forecast_and_no_parameters(ds):
    obs = _obs(ds, 4, n=120)
    with pytest.raises(NotImplementedError, match="DMD has no physical parameters"):
        DMD().identify(obs)
    fc = DMD().forecast(obs, 30)
    assert fc.mean.shape == (30, 2) and np.isfinite(fc.mean).all()
    assert (fc.std > 0).all() and fc.extras["n_simulations"] == 0
    # it continues the track: the first forecast frame is near the truth
    assert np.linalg.norm(fc.mean[0] - ds.states[4, 120, :2]) < 0.5


def test_same_seed_same_bytes_other_seed_other_draws(ds):
    obs = _obs(ds, 5, known=False)
    a, b, c = LSQ(seed=3).identify(obs), LSQ(seed=3).identify(obs), LSQ(seed=4).identify(obs)
    assert a.samples.tobytes() == b.samples.tobytes()
    assert a.samples.tobytes() != c.samples.tobytes()


# ------------------------------------------------------------------------------------------
# bad input
FAST = {
    "lsq": lambda: LSQ(n_samples=50),
    "bo": lambda: BayesOpt(n_calls=4, n_initial_points=2),
    "emcee": lambda: Emcee(n_walkers=16, n_steps=4, n_burn=1, n_init=20),
    "sindy": lambda: SINDy(),
}


def _call(name, obs):
    return DMD().forecast(obs, 5) if name == "dmd" else FAST[name]().identify(obs)


ALL = [*FAST, "dmd"]


@pytest.mark.parametrize("name", ALL)
def test_too_few_observed_frames(name, ds):
    pos = ds.states[0, :10, :2].copy()
    pos[2:] = np.nan
    with pytest.raises(ValueError, match="positions"):
        _call(name, Observation(positions=pos))
    with pytest.raises(ValueError, match="positions"):
        _call(name, Observation(positions=ds.states[0, :2, :2]))


@pytest.mark.parametrize("name", ALL)
def test_all_nan_positions(name):
    with pytest.raises(ValueError, match="positions"):
        _call(name, Observation(positions=np.full((20, 2), np.nan)))


@pytest.mark.parametrize("name", ALL)
def test_positions_outside_the_box(name, ds):
    pos = ds.states[0, :20, :2].copy()
    pos[5, 0] = 10.5
    with pytest.raises(ValueError, match="positions"):
        _call(name, Observation(positions=pos))
    pos = ds.states[0, :20, :2].copy()
    pos[5, 1] = -1.0
    with pytest.raises(ValueError, match="positions"):
        _call(name, Observation(positions=pos, floor=0.0))


def test_frames_and_positions_disagree_in_length(ds):
    with pytest.raises(ValueError, match="positions"):
        Observation(frames=ds.frames[0, :20], positions=ds.states[0, :19, :2])


@pytest.mark.parametrize("name", ALL)
def test_not_an_observation(name, ds):
    with pytest.raises(ValueError, match="obs"):
        _call(name, ds.states[0, :, :2])


def test_state0_outside_the_box(ds):
    with pytest.raises(ValueError, match="state0"):
        LSQ(n_samples=20).identify(
            Observation(positions=ds.states[0, :, :2], floor=0.0, state0=[12.0, 5.0, 1.0, 1.0])
        )


@pytest.mark.parametrize(
    "make, arg",
    [
        (lambda: LSQ(n_samples=0), "n_samples"),
        (lambda: LSQ(sigma=-1.0), "sigma"),
        (lambda: BayesOpt(n_calls=5, n_initial_points=8), "n_initial_points"),
        (lambda: BayesOpt(acq_func="XX"), "acq_func"),
        (lambda: Emcee(n_walkers=7), "n_walkers"),
        (lambda: Emcee(n_steps=10, n_burn=10), "n_burn"),
        (lambda: SINDy(smoothing_window=4), "smoothing_window"),
        (lambda: SINDy(threshold=-1.0), "threshold"),
        (lambda: DMD(delays=-2), "delays"),
        # issue 14: accepted before
        (lambda: LSQ(n_samples=-5), "n_samples"),
        (lambda: LSQ(n_samples=1), "n_samples"),  # one draw: a std of 0, a dishonest spread
        (lambda: LSQ(n_samples=10, min_ess=20), "n_samples"),
        (lambda: DMD(svd_rank=-1), "svd_rank"),
        (lambda: DMD(svd_rank=5.5), "svd_rank"),
        (lambda: DMD(svd_rank=1.0), "svd_rank"),
        (lambda: LSQ(seed="x"), "seed"),
        (lambda: SINDy(n_forecast=0), "n_forecast"),
        (lambda: BayesOpt(n_surrogate=5), "n_surrogate"),
    ],
)
def test_bad_hyperparameters_name_themselves(make, arg):
    # validated where they are given: at construction
    with pytest.raises(ValueError, match=arg):
        make()


@pytest.mark.parametrize("est", [LSQ(n_samples=20), SINDy(), DMD()], ids=["lsq", "sindy", "dmd"])
@pytest.mark.parametrize("horizon", [0, -3, 2.5, "10", 10**6])
def test_bad_horizon(est, horizon, ds):
    from sysid_bench.core.estimator import MAX_HORIZON

    with pytest.raises(ValueError, match="horizon"):
        est.forecast(_obs(ds, 0, n=40), horizon)
    assert MAX_HORIZON < 10**6


def test_set_params_validates_too():
    est = LSQ(n_samples=20)
    with pytest.raises(ValueError, match="n_samples"):
        est.set_params(n_samples=-5)


def test_lsq_with_an_absurd_dt_names_dt(ds):
    # was: "std: expected non-negative values, got [nan ...]" from a Posterior, naming no input
    with pytest.raises(ValueError, match="dt"):
        LSQ(n_samples=20).identify(Observation(positions=ds.states[0, :40, :2], dt=1e6))


def test_posteriors_are_in_physical_units(ds):
    post = LSQ(n_samples=100).identify(_obs(ds, 0))
    assert isinstance(post, Posterior)
    assert (post.mean >= physics.PRIOR_LO).all() and (post.mean <= physics.PRIOR_HI).all()
    assert isinstance(post.extras["n_simulations"], int) and post.extras["wall_s"] >= 0
