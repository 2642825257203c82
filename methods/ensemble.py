"""``emcee``: affine-invariant ensemble MCMC on the NumPy simulator.

The posterior is the Gaussian position likelihood of :func:`sysid_bench.core.simulator.gaussian_loglik`
(fixed noise ``sigma``, the same as ``nuts``) times the uniform prior of
:data:`sysid_bench.core.physics.PRIOR`. When the initial state is not given it is sampled too, as a
nuisance with a flat prior on a box of ``state0_box`` standard errors around the state estimated
from the first tracked frames (see :mod:`methods._tracks`; refitted on the frames before the first
contact when it was extrapolated back across one, ``prepare``'s
:func:`methods._tracks.start_before_contact`, ``extras["state0_before_contact"]``: a wall bounce
in frame 2 put the box 170 errors from the truth); so is an unknown floor, on a box of
as many of its standard errors around its estimate. (With the floor fixed at its estimate from
tracked 28x28 frames, a 1-2 cm error in it put the truth outside the 90% interval of g in 6 of 6
test videos; sampled, the intervals hold it.)

With positions precise to centimetres the posterior is a narrow peak (widths ~1e-3 of the prior)
in a likelihood that is rugged far from it, so walkers started from the prior would spend the
whole budget finding it. The chain therefore starts where the likelihood says: the best of
``n_init`` prior draws (one batch, as ``lsq``), refined by ``scipy.optimize.least_squares``
(dogbox) on the whitened residuals, and walkers drawn from the Laplace approximation there. emcee then runs
``n_steps`` with differential-evolution moves (efficient for the near-Gaussian shape this gives);
the first ``n_burn`` are discarded. The log-probability is vectorised (``vectorize=True``): emcee
passes half the ensemble at once and the simulator runs it as one batch.

Diagnostics in ``Posterior.extras``: ``acceptance`` (mean fraction), ``tau`` (integrated
autocorrelation time per parameter, emcee's estimate), ``tau_reliable`` (the chain is at least
50 tau long, emcee's own rule), ``ess`` (kept samples / max tau), ``converged`` (acceptance in
[0.05, 0.9] and at least 10 tau kept) and the optimiser's ``opt_status``/``opt_message``. When
not converged the reported std is the larger of the chain's and the Laplace approximation's,
so a stuck chain cannot report a falsely narrow posterior.

Model check (``Posterior.check``, :meth:`methods._simulation.Fit.checked`): the posterior mean
simulated from the mean of the draws' initial states (and floors) against the seen positions, judged against ``sigma``
(:meth:`sysid_bench.core.estimator.Check.from_residuals`). A failed check keeps the mean and widens
the intervals to what the data supports (:func:`methods._simulation.widen_to_support`: to hold
the best fit a local least-squares refinement from the mean finds, or to at least the prior's
when even that fit fails); its simulations are in ``extras["check_simulations"]``.

On any other registered system (``system=``; the generic points likelihood of
:mod:`methods._points`): walkers start from the Laplace approximation at the optimum that the
cross-entropy search (``n_init`` simulations over ``search_rounds`` rounds) and ``least_squares``
from its ``n_starts`` best points find; the same moves, diagnostics and convergence rule (no
``tau_reliable``); a failed model check widens the intervals to the prior.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np

from methods._points import (
    Points,
    PointsFit,
    SimulationOnSystems,
    draw_inside,
    inflate,
    inflate_in_box,
    noise_inflation,
    refine,
    residual_inflation,
    search,
)
from methods._simulation import (
    Fit,
    Stopwatch,
    _residuals,
    box_of,
    make_rng,
    one_blas_thread,
)
from methods._tracks import clip_state
from sysid_bench.core import physics
from sysid_bench.core._validate import check_number, check_positive_int
from sysid_bench.core.estimator import Observation, Posterior
from sysid_bench.core.simulator import (
    CountingSimulator,
    check_sigma,
    gaussian_loglik,
    mean_sq_error,
)

__all__ = ["Emcee"]

_FD_STEP = 1e-6  # forward-difference step in the sampler's (unit) coordinates
_MIN_STATE_SCALE = np.array([1e-3, 1e-3, 5e-3, 5e-3])


class _Problem:
    """The sampler's coordinates and log-posterior for one track.

    Coordinates ``z``: ``z[:4]`` the parameters mapped to [0, 1] by the prior; when the initial
    state is unknown, the next four its offset from the estimate in units of ``scale``; when the
    floor is unknown, the last one its offset from the estimate in units of ``floor_std``.
    """

    def __init__(self, track, sigma: float, state0_box: float, sim: CountingSimulator):
        self.track = track
        self.sigma = sigma
        self.sim = sim
        # the prior's box, or the user's (a held parameter's coordinate then moves nothing:
        # every draw holds its value, as the generic path's Problem does)
        self.box = box_of(track)
        self.nuisance = not track.state0_known
        self.floor_free = not track.floor_known
        self.ndim = 4 + 4 * self.nuisance + self.floor_free
        self.scale = np.maximum(track.state0_std, _MIN_STATE_SCALE)
        self.lo = np.zeros(self.ndim)
        self.hi = np.ones(self.ndim)
        self.lo[4:] = -state0_box
        self.hi[4:] = state0_box
        self.seen = np.flatnonzero(track.mask)
        self.n_sim_frames = int(self.seen[-1]) + 1  # nothing after the last seen frame matters

    def split(self, z: np.ndarray):
        """(..., ndim) -> theta (..., 4), state0 (..., 4), floor (...) in physical units."""
        theta = self.box.denormalise(z[..., :4])
        if self.nuisance:
            s0 = self.track.state0 + z[..., 4:8] * self.scale
        else:
            s0 = np.broadcast_to(self.track.state0, theta.shape)
        floor = np.full(theta.shape[:-1], self.track.floor)
        if self.floor_free:
            floor = floor + z[..., -1] * self.track.floor_std
        return theta, s0, floor

    def inside(self, z: np.ndarray) -> np.ndarray:
        """(B,) prior support: the bounds, and an initial state inside the box."""
        ok = np.all((z >= self.lo) & (z <= self.hi), axis=-1)
        if self.nuisance or self.floor_free:
            _, s0, fl = self.split(z)
            ok &= (s0[:, 0] >= 0) & (s0[:, 0] <= physics.BOX_WIDTH)
            ok &= (s0[:, 1] >= fl) & (s0[:, 1] <= fl + physics.BOX_WIDTH)
        return ok

    def simulate(self, z: np.ndarray) -> np.ndarray:
        """Positions (B, n_sim_frames, 2); states outside the box are moved onto its edge (only
        the optimiser asks for those; the sampler's prior excludes them)."""
        theta, s0, fl = self.split(z)
        s0 = clip_state(s0, fl)
        return self.sim.positions(theta, s0, self.n_sim_frames, self.track.dt, fl)

    def log_prob(self, z: np.ndarray) -> np.ndarray:
        """Vectorised log-posterior (up to a constant): (B, ndim) -> (B,)."""
        z = np.atleast_2d(z)
        out = np.full(z.shape[0], -np.inf)
        ok = self.inside(z)
        if ok.any():
            pos = self.simulate(z[ok])
            n = self.n_sim_frames
            out[ok] = gaussian_loglik(pos, self.track.positions[:n], self.track.mask[:n], self.sigma)
        return out

    def residuals(self, pos: np.ndarray) -> np.ndarray:
        """Whitened residuals (B, 2 * n_seen) of simulated positions (B, n, 2)."""
        r = (pos[:, self.seen] - self.track.positions[self.seen]) / self.sigma
        return r.reshape(pos.shape[0], -1)



def _sample(log_prob, p0: np.ndarray, n_steps: int, n_burn: int, rng: np.random.Generator,
            progress, info: dict):
    """Run the ensemble (differential-evolution moves) from the walkers ``p0`` (W, D) and judge it.

    Returns
    -------
    chain : ndarray, shape (W * (n_steps - n_burn), D)
    tau : ndarray, shape (D,)
        Integrated autocorrelation times (NaN where emcee cannot estimate them: the reason goes
        to ``info["tau_error"]``).
    tau_max, acceptance, kept, converged
        ``converged``: acceptance in [0.05, 0.9] and at least 10 tau kept.
    """
    import emcee

    sampler = emcee.EnsembleSampler(
        p0.shape[0], p0.shape[1], log_prob, vectorize=True,
        moves=[(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)],
    )
    state = emcee.State(p0, random_state=np.random.RandomState(rng.integers(2**31)).get_state())
    sampler.run_mcmc(state, n_steps, progress=bool(progress))
    chain = sampler.get_chain(discard=n_burn, flat=True)
    kept = n_steps - n_burn
    # emcee logs a warning when the chain is under 50 tau; we report that as tau_reliable
    autocorr_log = logging.getLogger("emcee.autocorr")
    level = autocorr_log.level
    autocorr_log.setLevel(logging.ERROR)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            tau = sampler.get_autocorr_time(discard=n_burn, quiet=True)
        except (emcee.autocorr.AutocorrError, ValueError, FloatingPointError) as exc:
            # a degenerate chain (e.g. every walker stuck): report, do not fail
            tau = np.full(p0.shape[1], np.nan)
            info["tau_error"] = str(exc)
        finally:
            autocorr_log.setLevel(level)
    tau_max = float(np.nanmax(tau)) if np.isfinite(tau).any() else np.inf
    acc = float(np.mean(sampler.acceptance_fraction))
    converged = bool(0.05 <= acc <= 0.9 and kept >= 10 * tau_max)
    return chain, tau, tau_max, acc, kept, converged


def _ball_noise_inflation(prob: _Problem, theta: np.ndarray, state0: np.ndarray,
                          floor: float) -> tuple[float, dict]:
    """:func:`methods._points.residual_inflation` of the residuals of ``theta`` (4,) from
    ``state0`` (4,) on ``floor`` against the ball's track (1 simulation)."""
    tr = prob.track
    s0 = tr.state0 if tr.state0_known else state0
    fl = tr.floor if tr.floor_known else floor
    return residual_inflation(_residuals(prob.sim, theta, s0, fl, tr), prob.sigma)


class Emcee(SimulationOnSystems):
    """Ensemble MCMC (``emcee``) of the physical parameters, started at the likelihood's peak.

    Parameters
    ----------
    system : str
        A registered system (:func:`sysid_bench.core.systems.available`); the class runs on any.
    n_walkers : int
        Walkers (even, at least twice the dimension: 4, or 8 with an unknown initial state;
        another system: its parameters plus, when unknown, its state variables).
    n_steps : int
        Steps per walker, burn-in included.
    n_burn : int
        Steps discarded.
    sigma : float, optional
        Position noise standard deviation (m) of the likelihood; None: ``DEFAULT_SIGMA`` on the
        ball, the system's :func:`methods._points.default_sigma` elsewhere.
    n_init : int, optional
        Prior draws simulated in one batch to find the start of the local optimiser (another
        system: simulations of the search); None: 500 on the ball, 2000 elsewhere.
    max_opt_evals : int, optional
        Residual evaluations allowed to ``scipy.optimize.least_squares``; None: 60 on the
        ball, 100 elsewhere.
    state0_box : float
        The ball only: half-width, in standard errors of the estimate, of the flat prior on an
        unknown initial state or floor (elsewhere the box comes from the system).
    search_rounds, n_starts : int
        Another system only: rounds of the search and best distinct points refined.
    n_forecast : int
        Posterior samples simulated forward by ``forecast``.
    progress : bool
        Show emcee's tqdm progress bar.
    known : dict of str -> float, optional
        Another system only: parameters held at these values (every sample holds the value,
        std 0; the held unit coordinate stays in the sampler but changes nothing); checked as
        ``--known`` is (:func:`sysid_bench.core.footage.parse_known`).
    prior : dict of str -> (float, float), optional
        Another system only: ranges replacing the system's prior for these parameters
        (:func:`sysid_bench.core.footage.parse_prior`).
    seed : int
        Seeds the draws, the walkers' start and emcee's generator.
    """

    name = "emcee"
    input_kind = "positions"
    min_frames = 3
    forecasts = True
    cost = 20
    #: its fit (``_fit``/``_fit_points``) is a pure function of its hyperparameters and the
    #: observation (random streams seeded per call): a run computes each fit once
    #: (:mod:`sysid_bench.bench.fitcache`)
    pure_fit = True
    # 0.3-1.8 s per cell at the default budget (the committed run of 4e20acf): every case, so
    # its figures rest on as many cases as lsq's (issue 29: 4 cases let a reading turn on one)
    scale_cases = {"smoke": 1}
    scale_options = {"smoke": {"n_walkers": 20, "n_steps": 20, "n_burn": 10}}
    #: cheap budgets for check_estimator (same code path)
    contract_options = {"n_walkers": 18, "n_steps": 12, "n_burn": 4, "n_init": 100, "max_opt_evals": 10,
                        "search_rounds": 2, "n_starts": 1}
    per_system_defaults = {"n_init": (500, 2000), "max_opt_evals": (60, 100)}

    def __init__(
        self,
        *,
        system: str = "ball",
        n_walkers: int = 32,
        n_steps: int = 120,
        n_burn: int = 40,
        sigma: float | None = None,
        n_init: int | None = None,
        max_opt_evals: int | None = None,
        state0_box: float = 20.0,
        search_rounds: int = 4,
        n_starts: int = 5,
        n_forecast: int = 64,
        progress: bool = False,
        known: dict | None = None,
        prior: dict | None = None,
        seed: int = 0,
    ):
        self.system = system
        self.n_walkers = n_walkers
        self.n_steps = n_steps
        self.n_burn = n_burn
        self.sigma = sigma
        self.n_init = n_init
        self.max_opt_evals = max_opt_evals
        self.state0_box = state0_box
        self.search_rounds = search_rounds
        self.n_starts = n_starts
        self.n_forecast = n_forecast
        self.progress = progress
        self.known = known
        self.prior = prior
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        n_walkers = check_positive_int(self.n_walkers, "n_walkers", minimum=8)
        if n_walkers % 2:
            raise ValueError(f"n_walkers: expected an even number >= 8, got {n_walkers}")
        n_steps = check_positive_int(self.n_steps, "n_steps")
        n_burn = check_positive_int(self.n_burn, "n_burn", minimum=0)
        if n_burn >= n_steps:
            raise ValueError(f"n_burn: expected fewer than n_steps={n_steps}, got {n_burn}")
        for k in ("n_init", "max_opt_evals"):
            check_positive_int(self._hp(k), k)
        for k in ("search_rounds", "n_starts"):
            check_positive_int(getattr(self, k), k)
        check_positive_int(self.n_forecast, "n_forecast")
        check_number(self.state0_box, "state0_box", lo=1e-9)

    # -- pieces -----------------------------------------------------------------------------
    def _start(self, prob: _Problem, rng: np.random.Generator):
        """Best prior draw, refined by least squares; returns (z_opt, laplace_cov, opt_info)."""
        from scipy.optimize import least_squares

        n_init = check_positive_int(self._hp("n_init"), "n_init")
        z = np.zeros((n_init, prob.ndim))
        z[:, :4] = rng.random((n_init, 4))
        pos = prob.simulate(z)
        n = prob.n_sim_frames
        mse = mean_sq_error(pos, prob.track.positions[:n], prob.track.mask[:n])
        z0 = z[int(np.argmin(mse))]
        steps = _FD_STEP * np.eye(prob.ndim)

        def fun(x):
            return prob.residuals(prob.simulate(x[None]))[0]

        def jac(x):
            # forward differences, all columns in one simulated batch; step inward at a bound
            sgn = np.where(x + _FD_STEP > prob.hi, -1.0, 1.0)
            batch = np.vstack([x, x + sgn[:, None] * steps])
            r = prob.residuals(prob.simulate(batch))
            return ((r[1:] - r[0]) / (sgn[:, None] * _FD_STEP)).T

        info = {"opt_status": None, "opt_message": "", "opt_cost": None}
        try:
            # dogbox, not trf: on 25 calibration cases trf crawled along the e-g valley and hit
            # max_nfev in 4-7 of them (left 3-8 sd off the mode); dogbox converged in all, in 6-9
            # evaluations
            with one_blas_thread():
                res = least_squares(
                    fun, z0, jac=jac, bounds=(prob.lo, prob.hi), method="dogbox",
                    max_nfev=check_positive_int(self._hp("max_opt_evals"), "max_opt_evals"),
                )
            z_opt, J = res.x, res.jac
            info.update(opt_status=int(res.status), opt_message=str(res.message), opt_cost=float(res.cost))
        except (ValueError, np.linalg.LinAlgError, RuntimeError) as exc:  # report, do not raise
            z_opt, J = z0, jac(z0)
            info.update(opt_status=-99, opt_message=f"least_squares failed: {exc}")
        H = J.T @ J
        # Laplace covariance; flat directions (e.g. r before any rolling) get the prior's width
        evals, evecs = np.linalg.eigh(H)
        width2 = ((prob.hi - prob.lo) ** 2 / 12.0).max()
        var = np.where(evals > 1.0 / width2, 1.0 / np.maximum(evals, 1e-300), width2)
        cov = (evecs * var) @ evecs.T
        prior_var = (prob.hi - prob.lo) ** 2 / 12.0
        d = np.sqrt(np.minimum(np.diag(cov), prior_var) / np.maximum(np.diag(cov), 1e-300))
        cov = cov * np.outer(d, d)  # cap each marginal at the prior's variance
        return z_opt, cov, info

    def _walkers(self, prob: _Problem, z_opt, cov, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` starting points from N(z_opt, cov), redrawn until inside the prior's support."""
        out = np.empty((n, prob.ndim))
        need = np.arange(n)
        for _ in range(100):
            cand = rng.multivariate_normal(z_opt, cov, size=need.size, method="eigh")
            ok = prob.inside(cand)
            out[need[ok]] = cand[ok]
            need = need[~ok]
            if need.size == 0:
                return out
        # support too thin for the Gaussian: tiny jitter about the optimum, kept in the bounds
        jitter = 1e-6 * rng.standard_normal((need.size, prob.ndim))
        out[need] = np.clip(z_opt + jitter, prob.lo, prob.hi)
        return out

    def _fit(self, obs: Observation) -> Fit:
        """Posterior samples of ``(e, g, d, r)`` from the ensemble after burn-in.

        The posterior's mean/std are those of the kept samples (std widened to the Laplace one
        when not converged), ``samples`` (n_walkers * (n_steps - n_burn), 4), diagnostics in
        ``extras``. A forecast continues ``n_forecast`` samples (with their initial states and
        floors) past the end.
        """

        clock = Stopwatch()
        sigma = check_sigma(self._sigma())
        n_walkers = check_positive_int(self.n_walkers, "n_walkers")
        n_steps = check_positive_int(self.n_steps, "n_steps")
        n_burn = check_positive_int(self.n_burn, "n_burn", minimum=0)
        if n_burn >= n_steps:
            raise ValueError(f"n_burn: expected fewer than n_steps={n_steps}, got {n_burn}")
        box = float(self.state0_box)
        if not np.isfinite(box) or box <= 0:
            raise ValueError(f"state0_box: expected a number > 0, got {self.state0_box!r}")
        # a start extrapolated back across an early contact is refitted on the frames before it
        # (``prepare``: ``start_before_contact``): else the start's prior box (standard errors
        # around it) can exclude the truth
        track = self._prepare(obs)  # with the user's knowledge, if any, as its box
        sim = CountingSimulator()
        prob = _Problem(track, sigma, box, sim)
        if n_walkers < 2 * prob.ndim or n_walkers % 2:
            raise ValueError(
                f"n_walkers: expected an even number >= {2 * prob.ndim} for {prob.ndim} dimensions, "
                f"got {n_walkers}"
            )
        rng = make_rng(self.seed, 0)
        z_opt, cov, info = self._start(prob, rng)
        p0 = self._walkers(prob, z_opt, cov, n_walkers, rng)

        chain, tau, tau_max, acc, kept, converged = _sample(
            prob.log_prob, p0, n_steps, n_burn, rng, self.progress, info)

        theta, s0, floors = prob.split(chain)
        std = theta.std(axis=0)
        lap_std = np.sqrt(np.diag(cov)[:4]) * prob.box.span
        if not converged:
            std = np.maximum(std, lap_std)
        mean = theta.mean(axis=0)
        # white-noise likelihood: widened where the track errs by more than sigma, in runs of
        # frames, as on every other system (``_fit_points``); a render's track (under sigma,
        # white) keeps factor 1 and its samples as they are. A camera's ball (tracked centres
        # biased near the floor) read e 4 stds off with the check passing without it.
        k, noise = _ball_noise_inflation(prob, mean, np.asarray(s0).mean(axis=0),
                                         float(np.mean(floors)))
        theta, std = inflate_in_box(theta, mean, std, k, prob.box.lo, prob.box.span)
        extras = {
            "n_simulations": sim.n_simulations,
            "wall_s": clock(),
            "acceptance": acc,
            "tau": tau[:4].tolist(),
            "tau_reliable": bool(kept >= 50 * tau_max),
            "ess": float(n_walkers * kept / tau_max) if np.isfinite(tau_max) else 0.0,
            "converged": converged,
            "laplace_std": lap_std.tolist(),
            "n_dim": prob.ndim,
            "state0_before_contact": track.state0_refit,
            **noise,
            **info,
            **track.describe(),
        }
        post = Posterior(mean=mean, std=std, samples=theta, extras=extras)
        return Fit(post, theta, np.asarray(s0), floors, track, sim, clock)

    def _fit_points(self, obs: Observation, part: Points) -> PointsFit:
        """Another system: walkers from the Laplace approximation at the refined optimum."""

        clock = Stopwatch()
        prob = part.problem(obs)
        nw, D = int(self.n_walkers), prob.ndim
        if nw < 2 * D:
            raise ValueError(f"n_walkers: expected an even number >= {2 * D} for {D} dimensions "
                             f"on the {prob.system.name} system, got {nw}")
        rng = make_rng(self.seed, 0)
        starts, info = search(prob, rng, int(self._hp("n_init")), int(self.search_rounds),
                              int(self.n_starts))
        u_opt, cov, opt = refine(prob, starts, int(self._hp("max_opt_evals")))
        p0 = draw_inside(u_opt, cov, nw, rng)
        chain, tau, tau_max, acc, kept, converged = _sample(
            prob.log_prob, p0, int(self.n_steps), int(self.n_burn), rng, self.progress, info)
        theta, s0 = prob.split(chain)
        std = theta.std(axis=0)
        lap = np.sqrt(np.diag(cov)[: prob.P]) * prob.pspan
        if not converged:
            std = np.maximum(std, lap)
        mean = theta.mean(axis=0)
        res = prob.point_residuals(mean, np.asarray(s0).mean(axis=0))
        check = prob.check(mean, None, res=res)
        # white-noise likelihood: widened where the track errs by more, in runs of frames
        k, noise = noise_inflation(prob, res=res)
        theta, std = inflate(prob, theta, std, k)
        extras = {
            "n_simulations": prob.sim.n_simulations, "wall_s": clock(), "acceptance": acc,
            **noise,
            "tau": tau[: prob.P].tolist(), "ess": float(nw * kept / tau_max)
            if np.isfinite(tau_max) else 0.0, "converged": converged,
            "laplace_std": lap.tolist(), "n_dim": D, "sigma": prob.sigma, **info, **opt,
            **prob.track.describe(),
        }
        post = part.posterior(prob, mean, std, theta, extras, check)
        return PointsFit(post, theta, np.asarray(s0), None, prob, clock)
