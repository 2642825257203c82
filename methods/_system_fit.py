"""The simulation methods on any registered system: one generic likelihood, shared by all.

``methods.get(name, system=S)`` for a system other than the ball builds the classes below (the
registry's ``on_systems`` entries). They share, from this module:

* :class:`SystemTrack`: the observation as the methods see it: the K tracked points (T, K, 2)
  (tracked from the frames with the system's own ``track`` when only frames are given), which
  points were seen, and the initial state: ``Observation.state0`` when known, else the
  system's ``state0_from_track`` estimate and the box around it (intersected with the system's
  ``state_bounds``) inside which it is searched or sampled;
* :class:`CountingSystemSimulator`: ``system.simulate`` then ``system.observe``, counting one
  simulation per trajectory as :class:`sysid_bench.simulator.CountingSimulator` does;
* :class:`Problem`: the likelihood. Observed points are the simulated ones plus independent
  Gaussian noise of a fixed ``sigma`` per coordinate (default :func:`default_sigma`, the
  system's ``noise_m`` and a fifth more for tracking error); unseen points contribute nothing;
  the prior is uniform on the prior box and on the initial-state box. Coordinates ``u`` in the
  unit cube: the P parameters mapped by the prior, then (when unknown) the S state variables
  mapped by their box;
* :func:`search` (cross-entropy rounds of batched simulations) and :func:`refine`
  (``scipy.optimize.least_squares`` from the best points, Jacobians by forward differences in one
  simulated batch) with the Laplace covariance at the optimum: the start of every method here and
  of ``methods._system_nuts``.

The methods:

``lsq`` (:class:`SystemLSQ`)
    Least squares: the search, then the local least-squares refinement; mean the optimum,
    spread its Laplace approximation (widened by the residual RMS when that exceeds ``sigma``),
    samples drawn from it inside the box. (The ball's ``lsq`` is the paper's best-of-a-batch; a
    batch alone cannot resolve periods over 200 frames of an oscillator.)
``bo`` (:class:`SystemBO`)
    ``skopt.gp_minimize`` of the log mean squared point error over the P parameters in [0, 1],
    the initial state held at its estimate (as the ball's ``bo``), spread from the GP surrogate
    over prior draws, tempered likelihood weights.
``emcee`` (:class:`SystemEmcee`)
    Ensemble MCMC (differential-evolution moves) on the posterior, walkers started from the
    Laplace approximation at the refined optimum.
``dmd`` (:class:`SystemDMD`)
    Hankel DMD of the 2K point coordinates (the ball's model, :class:`methods.dmd.DMD`).
``prior`` (:class:`SystemPrior`)
    The system's prior; the forecast holds the last seen points.

Forecasts are (H, 2) for a system with one tracked point and (H, K, 2) for K > 1.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import warnings
from dataclasses import dataclass

import numpy as np

from methods._simulation import Stopwatch, make_rng, one_blas_thread
from methods._weights import resample, tempered_weights
from sysid_bench._validate import check_positive_int
from sysid_bench.estimator import Check, Estimator, Forecast, Observation, Posterior
from sysid_bench.simulator import SimulationBudgetExceeded, check_sigma

__all__ = [
    "SystemTrack", "CountingSystemSimulator", "Problem", "SystemFit", "SystemFitMethod",
    "SystemLSQ", "SystemBO", "SystemEmcee", "SystemDMD", "SystemPrior", "default_sigma",
    "prepare_system", "search", "refine", "forecast_points",
]

#: ``sigma`` default: the system's ``noise_m`` times this (tracking error on top of the noise).
SIGMA_FACTOR = 1.2
_FD_STEP = 1e-6  # forward-difference step in the unit coordinates
_REFUSED = 1e4  # whitened residual of a point the system refused to simulate
_U_EPS = 1e-9


def default_sigma(system) -> float:
    """The likelihood's noise (m) on ``system`` when none is given: ``SIGMA_FACTOR * noise_m``."""
    return float(SIGMA_FACTOR * system.noise_m)


def _system(name):
    from sysid_bench import systems

    return systems.get(name)


# ------------------------------------------------------------------------------------------
# the observation
@dataclass
class SystemTrack:
    """The observation of one system as a position method sees it.

    Attributes
    ----------
    system : System
    positions : ndarray, shape (T, K, 2)
        Metres, NaN where a point is unseen.
    mask : ndarray of bool, shape (T, K)
    dt : float
    state0 : ndarray, shape (S,)
        The known initial state, or the estimate from the track.
    state0_known : bool
    lo, hi : ndarray, shape (S,)
        The box searched / sampled for an unknown initial state (``lo == hi == state0`` when known).
    input_kind : str
        ``"positions"`` or ``"frames"`` (tracked with ``system.track``).
    """

    system: object
    positions: np.ndarray
    mask: np.ndarray
    dt: float
    state0: np.ndarray
    state0_known: bool
    lo: np.ndarray
    hi: np.ndarray
    input_kind: str

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_seen(self) -> int:
        """Seen coordinates / 2 (points seen over all frames)."""
        return int(self.mask.sum())

    def describe(self) -> dict:
        return {"input": self.input_kind, "state0_known": self.state0_known,
                "state0_estimate": self.state0.tolist(), "system": self.system.name}


def prepare_system(obs: Observation, system, min_seen: int = 3) -> SystemTrack:
    """The :class:`SystemTrack` of ``obs`` (positions as given, else ``system.track(frames)``).

    Raises
    ------
    ValueError
        Fewer than ``min_seen`` frames with a seen point.
    """
    if obs.positions is not None:
        pos, kind = np.array(obs.points, dtype=np.float64), "positions"
    else:
        pos, kind = np.asarray(system.track(obs.frames), dtype=np.float64), "frames"
    mask = np.isfinite(pos).all(axis=-1)
    n_seen = int(mask.any(axis=1).sum())
    if n_seen < min_seen:
        raise ValueError(
            f"positions: expected the {system.name} system's points seen in at least {min_seen} "
            f"frames, got {n_seen} of {pos.shape[0]}"
        )
    blo = np.array([system.state_bounds.get(q, (-np.inf, np.inf))[0] for q in system.state])
    bhi = np.array([system.state_bounds.get(q, (-np.inf, np.inf))[1] for q in system.state])
    if obs.state0 is not None:
        s0 = np.asarray(obs.state0, dtype=np.float64)
        return SystemTrack(system, pos, mask, float(obs.dt), s0, True, s0.copy(), s0.copy(), kind)
    est, half = system.state0_from_track(pos, float(obs.dt))
    est, half = np.asarray(est, dtype=np.float64), np.abs(np.asarray(half, dtype=np.float64))
    lo = np.maximum(est - half, blo)
    hi = np.minimum(est + half, bhi)
    hi = np.maximum(hi, lo + 1e-9)  # an estimate on a bound still leaves a box
    est = np.clip(est, lo, hi)
    return SystemTrack(system, pos, mask, float(obs.dt), est, False, lo, hi, kind)


# ------------------------------------------------------------------------------------------
# the simulator and the likelihood
class CountingSystemSimulator:
    """``system.simulate`` and ``system.observe``, one simulation counted per trajectory.

    Parameters
    ----------
    system : System
    max_simulations : int, optional
        Budget; a batch that would exceed it raises ``SimulationBudgetExceeded``.
    """

    def __init__(self, system, max_simulations: int | None = None) -> None:
        self.system = system
        self.max_simulations = max_simulations
        self.n_simulations = 0

    def __call__(self, theta, state0, n_frames: int, dt: float) -> np.ndarray:
        """States (B, n_frames, S) of theta (B, P) from state0 (B, S)."""
        b = int(np.shape(theta)[0])
        if self.max_simulations is not None and self.n_simulations + b > self.max_simulations:
            raise SimulationBudgetExceeded(
                f"max_simulations: a batch of {b} would exceed the budget of "
                f"{self.max_simulations} simulations ({self.n_simulations} used)"
            )
        out = self.system.simulate(theta, state0, n_frames=n_frames, dt=dt)
        self.n_simulations += b
        return out

    def points(self, theta, state0, n_frames: int, dt: float) -> np.ndarray:
        """The K tracked points (B, n_frames, K, 2) of the simulated trajectories.

        A row the system refuses to simulate (``ValueError``: outside what its model is for,
        e.g. the spring's block reaching the wall) is NaN: a search or a sampler only proposes
        it, so it scores as impossible instead of failing the batch. The batch is split in
        halves until the refused rows are alone.
        """
        theta = np.asarray(theta, dtype=np.float64)
        state0 = np.asarray(state0, dtype=np.float64)
        out = np.full((theta.shape[0], n_frames, self.system.n_points, 2), np.nan)
        self._fill(out, theta, state0, np.arange(theta.shape[0]), n_frames, dt)
        return out

    def _fill(self, out, theta, state0, rows, n_frames, dt) -> None:
        try:
            st = self(theta[rows], state0[rows], n_frames, dt)
        except ValueError:
            if rows.size == 1:
                return
            half = rows.size // 2
            self._fill(out, theta, state0, rows[:half], n_frames, dt)
            self._fill(out, theta, state0, rows[half:], n_frames, dt)
            return
        out[rows] = self.system.observe(st, theta[rows])


def sq_error(pts: np.ndarray, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sum of squared errors (...) of points (..., T, K, 2) over the seen (T, K) coordinates."""
    m = mask[..., None]
    diff = np.where(m, pts - np.where(m, obs, 0.0), 0.0)
    return np.sum(diff * diff, axis=(-3, -2, -1))


class Problem:
    """Likelihood and prior of one track, in unit coordinates ``u`` (D,) = (P [+ S],).

    Parameters
    ----------
    track : SystemTrack
    sigma : float
        Noise standard deviation (m) per coordinate.
    sim : CountingSystemSimulator
    """

    def __init__(self, track: SystemTrack, sigma: float, sim: CountingSystemSimulator):
        sys_ = track.system
        self.track, self.sigma, self.sim, self.system = track, float(sigma), sim, sys_
        self.P, self.S = sys_.n_params, sys_.n_state
        self.free = not track.state0_known
        self.ndim = self.P + (self.S if self.free else 0)
        self.plo, self.pspan = sys_.prior_lo, sys_.prior_hi - sys_.prior_lo
        self.slo, self.sspan = track.lo, track.hi - track.lo
        rows = np.flatnonzero(track.mask.any(axis=1))
        self.n_sim_frames = int(rows[-1]) + 1  # nothing after the last seen frame matters
        self.obs = track.positions[: self.n_sim_frames]
        self.mask = track.mask[: self.n_sim_frames]
        self.n_coords = 2 * int(self.mask.sum())

    @property
    def u_state0(self) -> np.ndarray:
        """The initial-state estimate in unit coordinates (S,)."""
        return np.clip((self.track.state0 - self.slo) / self.sspan, 0.0, 1.0)

    def split(self, u: np.ndarray):
        """(..., D) -> theta (..., P), state0 (..., S) in physical units."""
        u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
        theta = self.plo + self.pspan * u[..., : self.P]
        if self.free:
            s0 = self.slo + self.sspan * u[..., self.P :]
        else:
            s0 = np.broadcast_to(self.track.state0, theta.shape[:-1] + (self.S,))
        return theta, s0

    def points(self, u: np.ndarray, n_frames: int | None = None) -> np.ndarray:
        """Simulated points (B, n, K, 2) of u (B, D)."""
        theta, s0 = self.split(np.atleast_2d(u))
        n = self.n_sim_frames if n_frames is None else n_frames
        return self.sim.points(theta, np.ascontiguousarray(s0), n, self.track.dt)

    def sse(self, u: np.ndarray) -> np.ndarray:
        """Sum of squared errors (B,) of u (B, D); inf where the system refused to simulate."""
        out = sq_error(self.points(u), self.obs, self.mask)
        return np.where(np.isfinite(out), out, np.inf)

    def loglik(self, sse: np.ndarray, sigma: float | None = None) -> np.ndarray:
        """Gaussian log-likelihood of sums of squared errors (up to the normaliser)."""
        s = self.sigma if sigma is None else sigma
        return -0.5 * np.asarray(sse) / s**2

    def log_prob(self, u: np.ndarray) -> np.ndarray:
        """Vectorised log-posterior (B,) of u (B, D): -inf outside the unit cube."""
        u = np.atleast_2d(u)
        out = np.full(u.shape[0], -np.inf)
        ok = np.all((u >= 0.0) & (u <= 1.0), axis=1)
        if ok.any():
            out[ok] = self.loglik(self.sse(u[ok]))
        return out

    def residuals(self, u: np.ndarray) -> np.ndarray:
        """Whitened residuals (B, n_coords) of u (B, D)."""
        pts = self.points(u)
        r = (pts[:, self.mask] - self.obs[self.mask]) / self.sigma
        # a refused simulation: far worse than any trajectory, still finite for the optimiser
        return np.nan_to_num(r.reshape(pts.shape[0], -1), nan=_REFUSED)

    def rms(self, u: np.ndarray) -> float:
        """RMS point residual (m) of one u (D,)."""
        return float(np.sqrt(self.sse(u[None])[0] / max(self.n_coords, 1)))

    def check(self, theta: np.ndarray, state0: np.ndarray, note: str = "") -> Check:
        """:class:`Check` of the trajectory of theta (P,) from state0 (S,) (all frames)."""
        pts = self.sim.points(theta[None], state0[None], self.track.n_frames, self.track.dt)[0]
        res = np.where(self.track.mask[..., None], pts - self.track.positions, np.nan)
        return Check.from_residuals(res, self.sigma, note=note)


# ------------------------------------------------------------------------------------------
# finding the posterior's peak
def search(prob: Problem, rng: np.random.Generator, n: int, rounds: int, n_starts: int):
    """Cross-entropy search: the best ``n_starts`` distinct points (D,) found, best first.

    Round 0 draws the parameters from the prior with the initial state at its estimate; each
    later round draws ``n`` points from a Gaussian fitted to the best 5% (at least 10) seen so
    far (the state's spread starting from its box). Periods and events make the likelihood
    rugged far from its peak, so a local method needs a start in the right basin.
    """
    D, P = prob.ndim, prob.P
    per = max(n // max(rounds, 1), 10)
    u = np.empty((per, D))
    u[:, :P] = rng.random((per, P))
    if prob.free:
        u[:, P:] = prob.u_state0
    pool_u, pool_f = np.empty((0, D)), np.empty(0)
    n_elite = max(10, per // 20)
    for r in range(max(rounds, 1)):
        pool_u = np.concatenate((pool_u, u))
        pool_f = np.concatenate((pool_f, prob.sse(u)))
        if r == rounds - 1:
            break
        elite = pool_u[np.argsort(pool_f)[:n_elite]]
        cov = np.cov(elite.T) + np.diag(np.full(D, 1e-10))
        if prob.free and r == 0:  # the state has not varied yet: start from its whole box
            cov[P:, :] = cov[:, P:] = 0.0
            cov[P:, P:] = np.diag(np.full(D - P, 1.0 / 12.0))
        u = np.clip(rng.multivariate_normal(elite.mean(0), cov, size=per, method="eigh"), 0.0, 1.0)
    order = np.argsort(pool_f)
    starts: list[int] = []
    for i in order:
        if len(starts) == n_starts:
            break
        if all(np.abs(pool_u[i] - pool_u[j]).max() > 1e-3 for j in starts):
            starts.append(int(i))
    return [pool_u[i].copy() for i in starts], {"search_best_rms_m": float(
        np.sqrt(pool_f[order[0]] / max(prob.n_coords, 1)))}


def refine(prob: Problem, starts, max_evals: int):
    """Local least squares from each start; the lowest cost wins, with its Laplace covariance.

    Returns
    -------
    u : ndarray, shape (D,)
    cov : ndarray, shape (D, D)
        ``(J^T J)^-1`` of the whitened residuals in unit coordinates, flat directions and every
        marginal capped at the uniform prior's variance (1/12).
    info : dict
    """
    from scipy.optimize import least_squares

    D = prob.ndim
    lo, hi = np.zeros(D), np.ones(D)
    steps = _FD_STEP * np.eye(D)

    def fun(x):
        return prob.residuals(x[None])[0]

    def jac(x):
        sgn = np.where(x + _FD_STEP > hi, -1.0, 1.0)  # step inward at the upper bound
        r = prob.residuals(np.vstack([x, x + sgn[:, None] * steps]))
        return ((r[1:] - r[0]) / (sgn[:, None] * _FD_STEP)).T

    best, info = None, {"opt_status": None, "opt_message": ""}
    for x0 in starts:
        try:
            with one_blas_thread():
                res = least_squares(fun, np.clip(x0, lo, hi), jac=jac, bounds=(lo, hi),
                                    method="trf", x_scale="jac", max_nfev=max_evals)
        except (ValueError, np.linalg.LinAlgError, RuntimeError) as exc:  # report, do not raise
            info["opt_message"] = f"least_squares failed: {exc}"
            continue
        if best is None or res.cost < best.cost:
            best = res
    if best is None:
        u = np.asarray(starts[0], dtype=np.float64)
        J = jac(u)
        info["opt_status"] = -99
    else:
        u, J = np.asarray(best.x), np.asarray(best.jac)
        info.update(opt_status=int(best.status), opt_message=str(best.message),
                    opt_nfev=int(best.nfev))
    H = J.T @ J
    w, V = np.linalg.eigh(H)
    prior_var = 1.0 / 12.0
    var = np.where(w > 1.0 / prior_var, 1.0 / np.maximum(w, 1e-300), prior_var)
    cov = (V * var) @ V.T
    d = np.sqrt(np.minimum(np.diag(cov), prior_var) / np.maximum(np.diag(cov), 1e-300))
    return u, cov * np.outer(d, d), info


def draw_inside(mean: np.ndarray, cov: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` draws of N(mean, cov) inside the unit cube (redrawn; clipped after 50 tries)."""
    out = np.empty((n, mean.size))
    need = np.arange(n)
    for _ in range(50):
        cand = rng.multivariate_normal(mean, cov, size=need.size, method="eigh")
        ok = np.all((cand >= 0.0) & (cand <= 1.0), axis=1)
        out[need[ok]] = cand[ok]
        need = need[~ok]
        if need.size == 0:
            return out
    out[need] = np.clip(rng.multivariate_normal(mean, cov, size=need.size, method="eigh"), 0, 1)
    return out


def forecast_points(sim, system, theta, state0, n_frames: int, dt: float, horizon: int,
                    extras: dict) -> Forecast:
    """Continue draws theta (N, P) from state0 (N, S) past ``n_frames`` observed frames.

    Returns
    -------
    Forecast
        (horizon, 2) for one tracked point, (horizon, K, 2) for K > 1; samples (N, ...).
    """
    pts = sim.points(theta, np.ascontiguousarray(state0), n_frames + horizon, dt)[:, n_frames:]
    ok = np.isfinite(pts).all(axis=(1, 2, 3))  # draws the system refused to run on are dropped
    if not ok.any():
        raise RuntimeError(f"the {system.name} system refused every forecast draw")
    pts = pts[ok]
    if system.n_points == 1:
        pts = pts[:, :, 0]
    ex = dict(extras)
    ex["n_simulations"] = sim.n_simulations
    return Forecast(mean=pts.mean(axis=0), std=pts.std(axis=0), samples=pts, extras=ex)


# ------------------------------------------------------------------------------------------
# the base of the generic methods
@dataclass
class SystemFit:
    """What a fit found: the posterior, draws a forecast resamples (with their initial states)
    and their weights (None: equally weighted samples), the problem and the clock."""

    posterior: Posterior
    theta: np.ndarray
    state0: np.ndarray
    weights: np.ndarray | None
    prob: Problem
    clock: Stopwatch


class SystemFitMethod(Estimator):
    """Base of the simulation methods on a registered system: implement ``_fit``.

    Subclasses declare ``_declared_by``, the ball's class of the same method: its declarations
    (name, cost, budgets per scale, colour, ...) are the generic class's too, so the harness
    treats the method alike on every system.
    """

    _declared_by: type | None = None
    input_kind = "positions"
    min_frames = 3
    forecasts = True

    def __init_subclass__(cls, **kwargs):
        src = cls.__dict__.get("_declared_by")
        if src is not None:
            from sysid_bench.spec import DECLARED

            for a in DECLARED:
                if a not in cls.__dict__:
                    setattr(cls, a, getattr(src, a))
        super().__init_subclass__(**kwargs)

    def _validate(self) -> None:
        super()._validate()
        if isinstance(self.system, str) and self.system == "ball":
            raise ValueError("system: expected a system other than the ball here "
                             "(methods.get(name) builds the ball's own method)")
        _system(self.system)  # ValueError listing the known systems
        if self.sigma is not None:
            check_sigma(self.sigma)
        check_positive_int(self.n_forecast, "n_forecast")

    def _sigma(self, system) -> float:
        return default_sigma(system) if self.sigma is None else check_sigma(self.sigma)

    def _problem(self, obs: Observation) -> Problem:
        system = _system(self.system)
        track = prepare_system(obs, system, self.min_frames)
        return Problem(track, self._sigma(system), CountingSystemSimulator(system))

    def _posterior(self, prob: Problem, mean, std, samples, extras, check) -> Posterior:
        """The posterior; where its model check failed, widened to the prior (the track is not
        explained by the mean's trajectory, so no interval narrower than the prior's is claimed:
        the mean stays, ``std`` becomes at least the prior's, the samples are prior draws, and
        ``check.note`` and ``extras["widened"]`` say so)."""
        if check is not None and not check.ok:
            system = prob.system
            lo, hi = system.prior_lo, system.prior_hi
            rng = np.random.default_rng([int(getattr(self, "seed", 0) or 0), len(samples)])
            samples = lo + (hi - lo) * rng.random((len(samples), len(lo)))
            std = np.maximum(np.asarray(std, dtype=float), (hi - lo) / np.sqrt(12.0))
            note = "intervals widened to the prior: the model does not explain the track"
            check = dataclasses.replace(check, note=f"{check.note}; {note}" if check.note else note)
            extras = {**extras, "widened": "prior"}
        return Posterior(mean=mean, std=std, samples=samples, extras=extras, check=check,
                         system=prob.system.name)

    def _fit(self, obs: Observation) -> SystemFit:  # pragma: no cover - abstract
        raise NotImplementedError

    def identify(self, obs: Observation) -> Posterior:
        """Posterior over the system's P parameters (``system.params`` order)."""
        return self._fit(obs).posterior

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Points of the ``horizon`` frames after ``obs``: ``n_forecast`` draws of the fit (with
        their initial states) continued past the last frame; (H, 2), or (H, K, 2) for K > 1."""
        m = check_positive_int(self.n_forecast, "n_forecast")
        fit = self._fit(obs)
        rng = make_rng(self.seed, 1)
        if fit.weights is not None:
            idx = resample(fit.weights, m, rng)
        else:
            idx = rng.choice(len(fit.theta), size=m, replace=len(fit.theta) < m)
        prob = fit.prob
        fc = forecast_points(prob.sim, prob.system, fit.theta[idx], fit.state0[idx],
                             prob.track.n_frames, prob.track.dt, horizon,
                             {"posterior_extras": fit.posterior.extras})
        fc.extras["wall_s"] = fit.clock()
        return fc


# ------------------------------------------------------------------------------------------
# lsq
def _lsq_class():
    from methods.lsq import LSQ

    return LSQ


class SystemLSQ(SystemFitMethod):
    """Least squares on any system: cross-entropy search, local refinement, Laplace spread.

    Parameters
    ----------
    system : str
        A registered system other than the ball.
    n_samples : int
        Simulations of the batched search (over ``search_rounds`` rounds).
    search_rounds : int
    n_starts : int
        Best distinct search points refined by ``least_squares``.
    max_opt_evals : int
        Residual evaluations per refinement.
    sigma : float, optional
        Noise (m) of the likelihood; None: :func:`default_sigma`.
    min_ess : int
        Kept for the ball's interface (unused: the spread is the Laplace approximation's).
    n_forecast : int
    seed : int
    """

    _declared_by = _lsq_class()
    contract_options = {"n_samples": 200, "max_opt_evals": 20}

    def __init__(self, *, system: str = "spring", n_samples: int = 2000, search_rounds: int = 4,
                 n_starts: int = 5, max_opt_evals: int = 100, sigma: float | None = None,
                 min_ess: int = 20, n_forecast: int = 64, seed: int = 0):
        self.system = system
        self.n_samples = n_samples
        self.search_rounds = search_rounds
        self.n_starts = n_starts
        self.max_opt_evals = max_opt_evals
        self.sigma = sigma
        self.min_ess = min_ess
        self.n_forecast = n_forecast
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        for k in ("n_samples", "search_rounds", "n_starts", "max_opt_evals", "min_ess"):
            check_positive_int(getattr(self, k), k)

    def _fit(self, obs: Observation) -> SystemFit:
        clock = Stopwatch()
        prob = self._problem(obs)
        rng = make_rng(self.seed, 0)
        starts, info = search(prob, rng, int(self.n_samples), int(self.search_rounds),
                              int(self.n_starts))
        u, cov, opt = refine(prob, starts, int(self.max_opt_evals))
        rms = prob.rms(u)
        # a fit worse than the noise: the spread grows with it (the model explains less)
        inflate = max(1.0, rms / prob.sigma) ** 2
        cov = cov * inflate
        theta, s0 = prob.split(u)
        draws = draw_inside(u, cov, max(int(self.n_samples) // 4, 50), rng)
        th_d, s0_d = prob.split(draws)
        std = np.minimum(np.sqrt(np.diag(cov)[: prob.P]), np.sqrt(1.0 / 12.0)) * prob.pspan
        check = prob.check(theta, s0)
        extras = {
            "n_simulations": prob.sim.n_simulations, "wall_s": clock(), "best_rmse": rms,
            "sigma": prob.sigma, "cov_inflation": inflate, "state0": s0.tolist(),
            **info, **opt, **prob.track.describe(),
        }
        post = self._posterior(prob, theta, std, th_d, extras, check)
        return SystemFit(post, th_d, np.asarray(s0_d), None, prob, clock)


# ------------------------------------------------------------------------------------------
# bo
def _bo_class():
    from methods.bo import BayesOpt

    return BayesOpt


class SystemBO(SystemFitMethod):
    """GP Bayesian optimisation (skopt) of the point fit on any system, start held at its
    estimate; hyperparameters as the ball's ``bo`` (``system`` added)."""

    _declared_by = _bo_class()

    def __init__(self, *, system: str = "spring", n_calls: int = 20, n_initial_points: int = 10,
                 acq_func: str = "EI", initial_point_generator: str = "sobol",
                 sigma: float | None = None, n_surrogate: int = 4096, min_ess: int = 20,
                 n_forecast: int = 64, seed: int = 0):
        self.system = system
        self.n_calls = n_calls
        self.n_initial_points = n_initial_points
        self.acq_func = acq_func
        self.initial_point_generator = initial_point_generator
        self.sigma = sigma
        self.n_surrogate = n_surrogate
        self.min_ess = min_ess
        self.n_forecast = n_forecast
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        # the ball's checks of the shared hyperparameters, on a copy of them
        _bo_class()(**{k: getattr(self, k) for k in (
            "n_calls", "n_initial_points", "acq_func", "initial_point_generator", "n_surrogate",
            "min_ess", "n_forecast", "seed")})

    def _fit(self, obs: Observation) -> SystemFit:
        from skopt import gp_minimize

        clock = Stopwatch()
        track = prepare_system(obs, _system(self.system), self.min_frames)
        fixed = Observation(positions=track.positions, dt=track.dt, state0=track.state0,
                            system=track.system.name)
        prob = self._problem(fixed)  # the start held at its estimate: P dimensions only
        prob.track.input_kind, prob.track.state0_known = track.input_kind, track.state0_known
        rng = make_rng(self.seed, 0)
        P, n_sur = prob.P, int(self.n_surrogate)

        def objective(u):
            sse = min(prob.sse(np.asarray(u, dtype=np.float64)[None])[0], 1e6)  # refused: 1e6
            return float(np.log(max(sse / max(prob.n_coords, 1), 1e-12)))

        info = {"ok": True, "message": ""}
        try:
            with warnings.catch_warnings(), one_blas_thread():
                warnings.simplefilter("ignore", UserWarning)  # re-proposed points
                res = gp_minimize(objective, [(0.0, 1.0)] * P, n_calls=int(self.n_calls),
                                  n_initial_points=int(self.n_initial_points),
                                  acq_func=self.acq_func, random_state=int(rng.integers(2**31)),
                                  initial_point_generator=self.initial_point_generator)
        except (ValueError, np.linalg.LinAlgError, RuntimeError, FloatingPointError) as exc:
            res = None
            info.update(ok=False, message=f"gp_minimize failed: {exc}")
        if res is None:
            u = rng.random((n_sur, P))
            w = np.full(n_sur, 1.0 / n_sur)
            u_best, best_mse, ess, beta = np.full(P, 0.5), np.inf, float(n_sur), 0.0
        else:
            u = np.vstack([rng.random((n_sur, P)), np.asarray(res.x_iters, dtype=np.float64)])
            model = res.models[-1] if res.models else None
            if model is not None:
                log_mse = model.predict(res.space.transform(u.tolist()))
                log_mse[n_sur:] = res.func_vals
            else:
                u = np.asarray(res.x_iters, dtype=np.float64)
                log_mse = np.asarray(res.func_vals, dtype=np.float64)
            u_best, best_mse = np.asarray(res.x, dtype=np.float64), float(np.exp(res.fun))
            sigma_eff = max(prob.sigma, np.sqrt(best_mse))
            w, beta, ess = tempered_weights(-0.5 * prob.n_coords * np.exp(log_mse) / sigma_eff**2,
                                            int(self.min_ess))
            info["sigma_eff"] = float(sigma_eff)
        samples, _ = prob.split(u)
        mean, s0 = prob.split(u_best)
        std = np.sqrt(np.sum(w[:, None] * (samples - mean) ** 2, axis=0))
        idx = resample(w, max(min(n_sur // 4, 1024), 1), rng)
        check = prob.check(mean, s0)
        extras = {"n_simulations": prob.sim.n_simulations, "wall_s": clock(),
                  "best_rmse": float(np.sqrt(best_mse)) if np.isfinite(best_mse) else None,
                  "ess": ess, "beta": beta, "state0": s0.tolist(), **info,
                  **prob.track.describe()}
        post = self._posterior(prob, mean, std, samples[idx], extras, check)
        return SystemFit(post, samples, np.broadcast_to(s0, (len(samples), prob.S)).copy(), w,
                         prob, clock)


# ------------------------------------------------------------------------------------------
# emcee
def _emcee_class():
    from methods.ensemble import Emcee

    return Emcee


class SystemEmcee(SystemFitMethod):
    """Ensemble MCMC (emcee) on any system, walkers started at the refined optimum.

    Hyperparameters as the ball's ``emcee`` (``system`` and ``search_rounds``/``n_starts`` of
    the start's search added; ``state0_box`` is not needed: the box comes from the system).
    Diagnostics in ``extras``: ``acceptance``, ``tau`` per parameter, ``ess``, ``converged``
    (acceptance in [0.05, 0.9] and at least 10 tau kept); when not converged the std is the
    larger of the chain's and the Laplace approximation's.
    """

    _declared_by = _emcee_class()

    def __init__(self, *, system: str = "spring", n_walkers: int = 32, n_steps: int = 120,
                 n_burn: int = 40, sigma: float | None = None, n_init: int = 2000,
                 search_rounds: int = 4, n_starts: int = 5, max_opt_evals: int = 100,
                 n_forecast: int = 64, progress: bool = False, seed: int = 0):
        self.system = system
        self.n_walkers = n_walkers
        self.n_steps = n_steps
        self.n_burn = n_burn
        self.sigma = sigma
        self.n_init = n_init
        self.search_rounds = search_rounds
        self.n_starts = n_starts
        self.max_opt_evals = max_opt_evals
        self.n_forecast = n_forecast
        self.progress = progress
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
        for k in ("n_init", "search_rounds", "n_starts", "max_opt_evals"):
            check_positive_int(getattr(self, k), k)

    def _fit(self, obs: Observation) -> SystemFit:
        import emcee

        clock = Stopwatch()
        prob = self._problem(obs)
        nw, D = int(self.n_walkers), prob.ndim
        if nw < 2 * D:
            raise ValueError(f"n_walkers: expected an even number >= {2 * D} for {D} dimensions "
                             f"on the {prob.system.name} system, got {nw}")
        rng = make_rng(self.seed, 0)
        starts, info = search(prob, rng, int(self.n_init), int(self.search_rounds),
                              int(self.n_starts))
        u_opt, cov, opt = refine(prob, starts, int(self.max_opt_evals))
        p0 = draw_inside(u_opt, cov, nw, rng)
        sampler = emcee.EnsembleSampler(
            nw, D, prob.log_prob, vectorize=True,
            moves=[(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)],
        )
        state = emcee.State(p0, random_state=np.random.RandomState(rng.integers(2**31)).get_state())
        sampler.run_mcmc(state, int(self.n_steps), progress=bool(self.progress))
        burn = int(self.n_burn)
        chain = sampler.get_chain(discard=burn, flat=True)
        kept = int(self.n_steps) - burn
        log = logging.getLogger("emcee.autocorr")
        level = log.level
        log.setLevel(logging.ERROR)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                tau = sampler.get_autocorr_time(discard=burn, quiet=True)
            except (emcee.autocorr.AutocorrError, ValueError, FloatingPointError) as exc:
                tau = np.full(D, np.nan)
                info["tau_error"] = str(exc)
            finally:
                log.setLevel(level)
        tau_max = float(np.nanmax(tau)) if np.isfinite(tau).any() else np.inf
        acc = float(np.mean(sampler.acceptance_fraction))
        converged = bool(0.05 <= acc <= 0.9 and kept >= 10 * tau_max)
        theta, s0 = prob.split(chain)
        std = theta.std(axis=0)
        lap = np.sqrt(np.diag(cov)[: prob.P]) * prob.pspan
        if not converged:
            std = np.maximum(std, lap)
        check = prob.check(theta.mean(axis=0), np.asarray(s0).mean(axis=0))
        extras = {
            "n_simulations": prob.sim.n_simulations, "wall_s": clock(), "acceptance": acc,
            "tau": tau[: prob.P].tolist(), "ess": float(nw * kept / tau_max)
            if np.isfinite(tau_max) else 0.0, "converged": converged,
            "laplace_std": lap.tolist(), "n_dim": D, "sigma": prob.sigma, **info, **opt,
            **prob.track.describe(),
        }
        post = self._posterior(prob, theta.mean(axis=0), std, theta, extras, check)
        return SystemFit(post, theta, np.asarray(s0), None, prob, clock)


# ------------------------------------------------------------------------------------------
# dmd and the prior
def _dmd_class():
    from methods.dmd import DMD

    return DMD


class SystemDMD(_dmd_class()):
    """Hankel DMD of the 2K coordinates of a system's K tracked points (see ``methods.dmd``)."""

    def __init__(self, *, system: str = "spring", delays: int = 0, svd_rank: float = 0.99999,
                 stabilize: bool = True, seed: int = 0):
        self.system = system
        super().__init__(delays=delays, svd_rank=svd_rank, stabilize=stabilize, seed=seed)

    def _validate(self) -> None:
        super()._validate()
        _system(self.system)

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Points of the ``horizon`` frames after ``obs``: (H, 2), or (H, K, 2) for K > 1."""
        t0 = time.perf_counter()
        system = _system(self.system)
        track = prepare_system(obs, system, self.min_frames)
        pos = track.positions.reshape(track.n_frames, -1)  # (T, 2K)
        mean, std, info = self._forecast_series(pos, horizon)
        K = system.n_points
        shape = (horizon, 2) if K == 1 else (horizon, K, 2)
        extras = {"n_simulations": 0, "wall_s": time.perf_counter() - t0, **info,
                  "input": track.input_kind}
        return Forecast(mean=mean.reshape(shape), std=std.reshape(shape), extras=extras)


class SystemPrior(Estimator):
    """A system's uniform prior as the posterior; the forecast holds the last seen points,
    spread over the view (the floor every method must beat, on every system).

    Parameters
    ----------
    system : str
    n_samples : int
    seed : int
    """

    name = "prior"
    input_kind = "positions"
    forecasts = True
    cost = 0
    inline = True
    figure_order = 7

    def __init__(self, *, system: str = "spring", n_samples: int = 256, seed: int = 0):
        self.system = system
        self.n_samples = n_samples
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        _system(self.system)
        check_positive_int(self.n_samples, "n_samples")

    def identify(self, obs: Observation) -> Posterior:
        t0 = time.perf_counter()
        system = _system(self.system)
        samples = system.sample_theta(check_positive_int(self.n_samples, "n_samples"),
                                      make_rng(self.seed, 0))
        mean = 0.5 * (system.prior_lo + system.prior_hi)
        std = (system.prior_hi - system.prior_lo) / np.sqrt(12.0)
        return Posterior(mean=mean, std=std, samples=samples,
                         extras={"n_simulations": 0, "wall_s": time.perf_counter() - t0,
                                 "check_reason": "the prior does not look at the observation"},
                         system=system.name)

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        system = _system(self.system)
        track = prepare_system(obs, system, 1)
        K = system.n_points
        last = np.empty((K, 2))
        for k in range(K):
            seen = np.flatnonzero(track.mask[:, k])
            last[k] = track.positions[seen[-1], k] if seen.size else np.nan
        x0, x1, y0, y1 = system.extent
        last = np.where(np.isfinite(last), last, [[0.5 * (x0 + x1), 0.5 * (y0 + y1)]])
        spread = np.array([x1 - x0, y1 - y0]) / np.sqrt(12.0)
        mean = np.repeat(last[None], horizon, axis=0)
        std = np.broadcast_to(spread, mean.shape).copy()
        if K == 1:
            mean, std = mean[:, 0], std[:, 0]
        return Forecast(mean=mean, std=std, extras={"n_simulations": 0})
