"""``lsq``: maximum likelihood by batch simulation, the paper's Galileo-style baseline.

Draw ``n_samples`` parameter vectors from the uniform prior, simulate them in one batch, score
each against the observed positions (unseen frames skipped) and report the best fit. When the
initial state is not given, each draw also gets an initial state sampled uniformly in a small box
around the state estimated from the first tracked frames (the paper's real-video variant); the
floor, when unknown, is the track's estimate (see :mod:`methods._tracks`).

Refinement (``refine=True``, the default): from the best draw, ``scipy.optimize.least_squares``
(trust region, bounds: the prior box and the initial-state box) on the parameters and, when not
given, the initial state, with forward-difference Jacobians simulated in one batch; at most
``max_refine`` simulations, all counted. The best of 2000 random draws alone is a coarse search:
on 20 clean test cases its residual was 0.1-1 m RMS (median ~0.2 m at 200 frames) against a
noise of 0.02 m, so its model check failed on nearly every case; refined, the point estimate is a
true maximum-likelihood fit and the check means something (a failed check then says the model
does not explain the track, not that the search was coarse).

Spread: the draws weighted by the Gaussian likelihood of :mod:`sysid_bench.core.simulator`, with the noise
scale raised to the best fit's RMS residual when that is larger than ``sigma`` (the draws cannot
fit better than their resolution) and the weights tempered until ``min_ess`` draws carry them.
The standard deviation is taken about the reported (refined) fit, so it also covers that fit's
offset from the weighted mean.

Model check (``Posterior.check``): the reported fit simulated from its own initial state against
the seen positions, judged against ``sigma``; a failed check widens the spread to what the data
supports (:func:`methods._simulation.widen_to_support`): to hold a best fit that passes, else to
at least the prior's (samples: prior draws). Measured on the report's 20 test videos (200 frames):
residual RMS median 0.008 m, 0 checks failed (unrefined: 0.2 m, 20 failed); the refinement
costs ~200-400 simulations and ~0.1 s per case.

On any other registered system (``system=``; the generic points likelihood of
:mod:`methods._points`): the cross-entropy search (``n_samples`` simulations over
``search_rounds`` rounds), then ``least_squares`` from its ``n_starts`` best distinct points
(``max_opt_evals`` each); mean the optimum, spread its Laplace approximation (widened by the
residual RMS when that exceeds ``sigma``), samples drawn from it inside the box; a parameter
the track does not inform (its Laplace variance at the uniform prior's) answers the prior's
centre and spread (``extras["uninformed"]``); a failed model check widens the intervals to the
prior. (Best-of-a-batch alone cannot resolve periods over 200
frames of an oscillator.)
"""

from __future__ import annotations

import numpy as np

from methods._points import (
    Points,
    PointsFit,
    SimulationOnSystems,
    answer_prior,
    draw_inside,
    refine,
    search,
    uninformed_params,
)
from methods._simulation import (
    Fit,
    Stopwatch,
    make_rng,
    refine_fit,
    state0_box,
    state0_half,
)
from methods._tracks import clip_state
from methods._weights import resample, tempered_weights
from sysid_bench.core._validate import check_positive_int
from sysid_bench.core.estimator import Observation, Posterior
from sysid_bench.core.simulator import (
    CountingSimulator,
    check_sigma,
    gaussian_loglik,
    mean_sq_error,
)

__all__ = ["LSQ"]


class LSQ(SimulationOnSystems):
    """Best of a batch of prior draws by trajectory fit (the ball); least squares from a
    cross-entropy search (any other system). See the module.

    Parameters
    ----------
    system : str
        A registered system (:func:`sysid_bench.core.systems.available`); the class runs on any.
    n_samples : int
        Prior draws simulated in one batch (the paper: 2000; 5000 for its real videos); at
        least ``min_ess``, so that the reported spread rests on that many effective draws.
        Another system: simulations of the search.
    sigma : float, optional
        Position noise standard deviation (m) of the likelihood that weights the draws; None:
        ``DEFAULT_SIGMA`` on the ball, the system's :func:`methods._points.default_sigma`
        elsewhere.
    min_ess : int
        Fewest effective draws the weights are tempered to (sets the reported spread's floor);
        at least 2.
    refine : bool
        Refine the best draw by local least squares (see the module); False: the paper's
        best-of-a-batch.
    max_refine : int
        Most simulations the refinement may use.
    search_rounds, n_starts, max_opt_evals : int
        Another system only: rounds of the search, best distinct points refined, residual
        evaluations per refinement.
    n_forecast : int
        Weighted draws resampled for a forecast.
    known : dict of str -> float, optional
        Another system only: parameters held at these values (every sample holds the value,
        std 0); checked as ``--known`` is (:func:`sysid_bench.core.footage.parse_known`).
    prior : dict of str -> (float, float), optional
        Another system only: ranges replacing the system's prior for these parameters
        (:func:`sysid_bench.core.footage.parse_prior`).
    seed : int
        Seed of the draws; the same seed gives the same posterior.
    """

    name = "lsq"
    input_kind = "positions"
    min_frames = 3
    forecasts = True
    cost = 8
    #: its fit (``_fit``/``_fit_points``) is a pure function of its hyperparameters and the
    #: observation (random streams seeded per call): a run computes each fit once
    #: (:mod:`sysid_bench.bench.fitcache`)
    pure_fit = True
    #: the paper compared Vid2Param with it given true positions and the initial state
    paper_baseline = True
    online_cost = True  # a row of the online-cost table (re-identifies every prefix)
    #: cheap budgets for check_estimator (same code path)
    contract_options = {"n_samples": 200, "search_rounds": 2, "n_starts": 1, "max_opt_evals": 20}

    def __init__(
        self,
        *,
        system: str = "ball",
        n_samples: int = 2000,
        sigma: float | None = None,
        min_ess: int = 20,
        refine: bool = True,
        max_refine: int = 900,
        search_rounds: int = 4,
        n_starts: int = 5,
        max_opt_evals: int = 100,
        n_forecast: int = 64,
        known: dict | None = None,
        prior: dict | None = None,
        seed: int = 0,
    ):
        self.system = system
        self.n_samples = n_samples
        self.sigma = sigma
        self.min_ess = min_ess
        self.refine = refine
        self.max_refine = max_refine
        self.search_rounds = search_rounds
        self.n_starts = n_starts
        self.max_opt_evals = max_opt_evals
        self.n_forecast = n_forecast
        self.known = known
        self.prior = prior
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        for k in ("search_rounds", "n_starts", "max_opt_evals"):
            check_positive_int(getattr(self, k), k)
        min_ess = check_positive_int(self.min_ess, "min_ess", minimum=2)
        # fewer draws than min_ess cannot carry the tempered weights: the spread would be that
        # of a handful of draws (0 from one), a confident answer the search has not earned
        check_positive_int(self.n_samples, "n_samples", minimum=min_ess)
        check_positive_int(self.n_forecast, "n_forecast")
        if not isinstance(self.refine, (bool, np.bool_)):
            raise ValueError(f"refine: expected a bool, got {self.refine!r}")
        check_positive_int(self.max_refine, "max_refine")

    def _fit(self, obs: Observation) -> Fit:
        """Best-fitting prior draw, refined, spread from the likelihood-weighted draws.

        The posterior's ``samples`` are the weighted draws resampled (``n_samples // 4`` of
        them); ``extras`` adds ``best_rmse`` (m, the reported fit's), ``best_draw_rmse`` (the
        best draw's), ``sigma_eff``, ``ess``, ``beta`` (tempering), ``state0`` (of the
        reported fit) and the input description. A forecast continues
        ``n_forecast`` resampled draws' own trajectories.
        """
        clock = Stopwatch()
        n = check_positive_int(self.n_samples, "n_samples")
        sigma = check_sigma(self._sigma())
        min_ess = check_positive_int(self.min_ess, "min_ess")
        rng = make_rng(self.seed, 0)
        track = self._prepare(obs)  # with the user's knowledge, if any, as its box
        theta = self._box(track).sample(n, rng)
        if track.state0_known:
            s0 = np.broadcast_to(track.state0, (n, 4))
        else:
            half = state0_half(track)
            s0 = track.state0 + half * rng.uniform(-1.0, 1.0, size=(n, 4))
            s0[0] = track.state0  # the estimate itself is always one candidate
            s0 = clip_state(s0, track.floor)
        sim = CountingSimulator()
        pos = sim.positions(theta, s0, track.n_frames, track.dt, track.floor)
        mse = mean_sq_error(pos, track.positions, track.mask)
        best = int(np.argmin(mse))
        best_draw_rmse = float(np.sqrt(mse[best]))
        mean, s0_point, rmse = theta[best].copy(), np.array(s0[best]), best_draw_rmse
        if self.refine:
            if track.state0_known:
                lo_s = hi_s = None
            else:
                lo_s, hi_s = state0_box(track)
            mean, s0_point, rmse = refine_fit(sim, track, mean, s0_point, lo_s, hi_s,
                                           check_positive_int(self.max_refine, "max_refine"))
        sigma_eff = max(sigma, rmse)
        ll = gaussian_loglik(pos, track.positions, track.mask, sigma_eff)
        w, beta, ess = tempered_weights(ll, min_ess)
        std = np.sqrt(np.sum(w[:, None] * (theta - mean) ** 2, axis=0))
        idx = resample(w, max(n // 4, 1), rng)
        extras = {
            "n_simulations": sim.n_simulations,
            "wall_s": clock(),
            "best_rmse": rmse,
            "best_draw_rmse": best_draw_rmse,
            "sigma_eff": sigma_eff,
            "ess": ess,
            "beta": beta,
            "state0": np.asarray(s0_point).tolist(),
            **track.describe(),
        }
        post = Posterior(mean=mean, std=std, samples=theta[idx], extras=extras)
        return Fit(post, theta, np.asarray(s0), track.floor, track, sim, clock, weights=w,
                   state0_point=np.asarray(s0_point), floor_point=track.floor)

    def _fit_points(self, obs: Observation, part: Points) -> PointsFit:
        """Another system: search, refinement, Laplace spread (see the module)."""
        clock = Stopwatch()
        prob = part.problem(obs)
        rng = make_rng(self.seed, 0)
        starts, info = search(prob, rng, int(self.n_samples), int(self.search_rounds),
                              int(self.n_starts))
        u, cov, opt = refine(prob, starts, int(self.max_opt_evals))
        # a parameter the track does not inform (the collision's restitutions before the carts
        # meet) answers the prior (the check stays at the fit, which explains the track)
        flat = uninformed_params(prob, cov)
        rms = prob.rms(u)
        # a fit worse than the noise: the spread grows with it (the model explains less)
        inflate = max(1.0, rms / prob.sigma) ** 2
        cov = cov * inflate
        theta, s0 = prob.split(u)
        draws = draw_inside(u, cov, max(int(self.n_samples) // 4, 50), rng)
        th_d, s0_d = prob.split(draws)
        std = np.minimum(np.sqrt(np.diag(cov)[: prob.P]), np.sqrt(1.0 / 12.0)) * prob.pspan
        mean = theta.copy()
        answer_prior(prob, flat, mean, std, th_d, rng)
        check = prob.check(theta, s0)
        extras = {
            "n_simulations": prob.sim.n_simulations, "wall_s": clock(), "best_rmse": rms,
            "sigma": prob.sigma, "cov_inflation": inflate, "state0": s0.tolist(),
            "uninformed": [p for p, f in zip(prob.system.params, flat) if f],
            **info, **opt, **prob.track.describe(),
        }
        post = part.posterior(prob, mean, std, th_d, extras, check)
        return PointsFit(post, th_d, np.asarray(s0_d), None, prob, clock)
