"""The generic points likelihood: what a simulation method composes on a system other than the ball.

Every method is one class (``methods.get(name, system=S)``); on the ball it runs the ball's own
machinery (:mod:`methods._simulation`, :mod:`methods._tracks`), on any other registered system
(:mod:`sysid_bench.core.systems`) it composes the parts below, which need nothing but the
:class:`~sysid_bench.core.systems.System` interface (so a system a user registers gets them too):

* :class:`PointsTrack`: the observation as the methods see it: the K tracked points (T, K, 2)
  (tracked from the frames with the system's own ``track`` when only frames are given), which
  points were seen, and the initial state: ``Observation.state0`` when known, else the
  system's ``state0_from_track`` estimate and the box around it (intersected with the system's
  ``state_bounds``) inside which it is searched or sampled;
* :class:`PointsSimulator`: ``system.simulate`` then ``system.observe``, counting one
  simulation per trajectory as :class:`sysid_bench.core.simulator.CountingSimulator` does;
* :class:`Problem`: the likelihood. Observed points are the simulated ones plus independent
  Gaussian noise of a fixed ``sigma`` per coordinate (default :func:`default_sigma`, the
  system's ``noise_m`` and a fifth more for tracking error); unseen points contribute nothing;
  the prior is uniform on the prior box and on the initial-state box. Coordinates ``u`` in the
  unit cube: the P parameters mapped by the prior, then (when unknown) the S state variables
  mapped by their box;
* :func:`search` (cross-entropy rounds of batched simulations) and :func:`refine`
  (``scipy.optimize.least_squares`` from the best points, Jacobians by forward differences in one
  simulated batch) with the Laplace covariance at the optimum: the start of lsq, emcee and nuts
  on the systems;
* :class:`Points`: the part a method holds for one system (its track, problem, posterior and
  forecast), and :class:`SimulationOnSystems`, the base of the simulation methods that picks the
  ball's machinery or :class:`Points` by the ``system`` hyperparameter.

What each method does with them is in its own module (``_fit_points`` of :mod:`methods.lsq`,
:mod:`methods.bo`, :mod:`methods.ensemble`, :mod:`methods.nuts`).

Forecasts are (H, 2) for a system with one tracked point and (H, K, 2) for K > 1.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from methods._simulation import SimulationMethod, Stopwatch, make_rng, one_blas_thread
from methods._weights import resample
from sysid_bench.core._validate import check_positive_int
from sysid_bench.core.estimator import Check, Forecast, Observation, Posterior
from sysid_bench.core.footage import check_knowledge
from sysid_bench.core.simulator import DEFAULT_SIGMA, SimulationBudgetExceeded, check_sigma

__all__ = [
    "PointsTrack", "PointsSimulator", "Problem", "PointsFit", "Points",
    "SimulationOnSystems", "default_sigma", "prepare_points", "search", "refine", "draw_inside",
    "uninformed_params", "answer_prior", "forecast_points", "system_of", "check_system_param",
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
    from sysid_bench.core import systems

    return systems.get(name)


# ------------------------------------------------------------------------------------------
# the observation
@dataclass
class PointsTrack:
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
    scene : Scene or None
        The observation's scene when it is not the system's default (a camera's track, its
        ends and objects at their true sizes); None: the default, simulated as it always was.
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
    scene: object = None

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


def prepare_points(obs: Observation, system, min_seen: int = 3) -> PointsTrack:
    """The :class:`PointsTrack` of ``obs`` (positions as given, else ``system.track(frames)``).

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
    # a scene other than the default (a camera's) is simulated as the observation holds it
    scene = obs.scene if obs.scene is not None and obs.scene != system.default_scene else None
    bounds = system.state_bounds if scene is None else system.state_bounds_for(scene)
    blo = np.array([bounds.get(q, (-np.inf, np.inf))[0] for q in system.state])
    bhi = np.array([bounds.get(q, (-np.inf, np.inf))[1] for q in system.state])
    if obs.state0 is not None:
        s0 = np.asarray(obs.state0, dtype=np.float64)
        return PointsTrack(system, pos, mask, float(obs.dt), s0, True, s0.copy(), s0.copy(), kind,
                           scene)
    est, half = system.state0_from_track(pos, float(obs.dt))
    est, half = np.asarray(est, dtype=np.float64), np.abs(np.asarray(half, dtype=np.float64))
    lo = np.maximum(est - half, blo)
    hi = np.minimum(est + half, bhi)
    hi = np.maximum(hi, lo + 1e-9)  # an estimate on a bound still leaves a box
    est = np.clip(est, lo, hi)
    return PointsTrack(system, pos, mask, float(obs.dt), est, False, lo, hi, kind, scene)


# ------------------------------------------------------------------------------------------
# the simulator and the likelihood
class PointsSimulator:
    """``system.simulate`` and ``system.observe``, one simulation counted per trajectory.

    Parameters
    ----------
    system : System
    max_simulations : int, optional
        Budget; a batch that would exceed it raises ``SimulationBudgetExceeded``.
    scene : Scene, optional
        Simulated and observed in this scene (None: the system's default, as before).
        :class:`Problem` sets it from its track's.
    """

    def __init__(self, system, max_simulations: int | None = None, scene=None) -> None:
        self.system = system
        self.max_simulations = max_simulations
        self.n_simulations = 0
        self.scene = scene

    def _scene(self) -> dict:
        """The ``scene`` keyword of simulate/observe: none for the default scene (the calls
        are then exactly the ones made before scenes were held)."""
        return {} if self.scene is None else {"scene": self.scene}

    def __call__(self, theta, state0, n_frames: int, dt: float) -> np.ndarray:
        """States (B, n_frames, S) of theta (B, P) from state0 (B, S)."""
        b = int(np.shape(theta)[0])
        if self.max_simulations is not None and self.n_simulations + b > self.max_simulations:
            raise SimulationBudgetExceeded(
                f"max_simulations: a batch of {b} would exceed the budget of "
                f"{self.max_simulations} simulations ({self.n_simulations} used)"
            )
        out = self.system.simulate(theta, state0, n_frames=n_frames, dt=dt, **self._scene())
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
        out[rows] = self.system.observe(st, theta[rows], **self._scene())


def sq_error(pts: np.ndarray, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sum of squared errors (...) of points (..., T, K, 2) over the seen (T, K) coordinates."""
    m = mask[..., None]
    diff = np.where(m, pts - np.where(m, obs, 0.0), 0.0)
    return np.sum(diff * diff, axis=(-3, -2, -1))


class Problem:
    """Likelihood and prior of one track, in unit coordinates ``u`` (D,) = (P [+ S],).

    Parameters
    ----------
    track : PointsTrack
    sigma : float
        Noise standard deviation (m) per coordinate.
    sim : PointsSimulator
    known : dict of str -> float, optional
        Parameters held fixed (as :func:`sysid_bench.core.footage.parse_known` returns): their unit
        coordinate maps to the value whatever it is (span 0), so every sample holds it exactly.
    prior : dict of str -> (float, float), optional
        Ranges replacing the system's prior for the named parameters (as
        :func:`sysid_bench.core.footage.parse_prior` validates them).

    Notes
    -----
    A first step of issue 38 §4: no method passes ``known``/``prior`` here yet; without them
    the ranges are the system's own, bit for bit as before.
    """

    def __init__(self, track: PointsTrack, sigma: float, sim: PointsSimulator,
                 known: dict | None = None, prior: dict | None = None):
        sys_ = track.system
        self.track, self.sigma, self.sim, self.system = track, float(sigma), sim, sys_
        if track.scene is not None and sim.scene is None:  # the observation's world
            sim.scene = track.scene
        self.P, self.S = sys_.n_params, sys_.n_state
        self.free = not track.state0_known
        self.ndim = self.P + (self.S if self.free else 0)
        self.plo, self.pspan = sys_.prior_lo, sys_.prior_hi - sys_.prior_lo
        self.known = {str(k): float(v) for k, v in (known or {}).items()}
        for name, rng in {**(prior or {}), **{k: (v, v) for k, v in self.known.items()}}.items():
            if name not in sys_.params:
                raise ValueError(f"known/prior: expected parameters of {sys_.name} "
                                 f"{tuple(sys_.params)}, got {name!r}")
            i = list(sys_.params).index(name)
            lo, hi = float(rng[0]), float(rng[1])
            self.plo[i], self.pspan[i] = lo, hi - lo
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

    def point_residuals(self, theta: np.ndarray, state0: np.ndarray) -> np.ndarray:
        """Residuals (T, K, 2), metres, of the trajectory of theta (P,) from state0 (S,) over
        every frame of the track; NaN where unseen."""
        pts = self.sim.points(theta[None], state0[None], self.track.n_frames, self.track.dt)[0]
        return np.where(self.track.mask[..., None], pts - self.track.positions, np.nan)

    def check(self, theta: np.ndarray, state0: np.ndarray, note: str = "",
              res: np.ndarray | None = None) -> Check:
        """:class:`Check` of the trajectory of theta (P,) from state0 (S,) (all frames);
        ``res``: its :meth:`point_residuals` when already simulated."""
        if res is None:
            res = self.point_residuals(theta, state0)
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


def residual_tau(res: np.ndarray, c: float = 5.0) -> float:
    """Integrated autocorrelation time (frames) of fit residuals.

    The normalised autocorrelation is averaged over the coordinates (each series with its
    unseen frames left out, so a gap joins its two sides), then summed with Sokal's window
    (the first lag ``M >= c * tau``). White residuals give ~1; a tracker's error that drifts
    over ``n`` frames gives ~``n``.

    Parameters
    ----------
    res : ndarray, shape (T, ...)
        Residuals over time, NaN where unseen.
    """
    r = np.asarray(res, dtype=np.float64).reshape(len(res), -1)
    acf, n_ser = None, 0
    for j in range(r.shape[1]):
        x = r[np.isfinite(r[:, j]), j]
        if x.size < 8:
            continue
        x = x - x.mean()
        v = float(x @ x)
        if v <= 0:
            continue
        n = x.size
        f = np.fft.rfft(x, 2 * n)
        a = np.fft.irfft(f * np.conj(f))[:n] / v
        L = min(len(acf), n) if acf is not None else n
        acf = a[:L] if acf is None else acf[:L] + a[:L]
        n_ser += 1
    if acf is None:
        return 1.0
    acf = acf / n_ser
    taus = 2.0 * np.cumsum(acf) - 1.0
    m = np.arange(len(taus))
    win = np.flatnonzero(m >= c * taus)
    tau = float(taus[win[0]] if win.size else taus[-1])
    return max(tau, 1.0)


def noise_inflation(prob: Problem, theta: np.ndarray | None = None,
                    state0: np.ndarray | None = None,
                    res: np.ndarray | None = None) -> tuple[float, dict]:
    """How much a white-noise likelihood with ``prob.sigma`` understates the spread a track
    supports: ``max(1, rms * sqrt(tau) / sigma)`` at ``theta``, ``state0``.

    A sampler whose likelihood takes every coordinate as independent noise of ``sigma`` reads
    ``n`` frames as ``n`` independent looks. A camera's track errs by more than ``sigma`` (rms)
    and in runs of frames (its residuals' autocorrelation time ``tau``, :func:`residual_tau`):
    the data hold about ``n / tau`` looks of noise ``rms``, so every posterior spread is
    ``rms * sqrt(tau) / sigma`` times too narrow. A fit within ``sigma / sqrt(tau)`` (a
    rendered track) is left as it is (factor 1).

    Parameters
    ----------
    prob : Problem
    theta, state0 : ndarray, shapes (P,), (S,)
        Where to measure; not needed when ``res`` is given.
    res : ndarray, shape (T, K, 2), optional
        ``prob.point_residuals(theta, state0)`` when the caller has them (its model check
        simulated that trajectory already).

    Returns
    -------
    factor : float
    info : dict
        ``residual_rms_m``, ``residual_tau``, ``noise_inflation``.
    """
    if res is None:
        res = prob.point_residuals(np.asarray(theta, dtype=np.float64),
                                   np.ascontiguousarray(np.asarray(state0, dtype=np.float64)))
    return residual_inflation(res, prob.sigma)


def residual_inflation(res: np.ndarray, sigma: float) -> tuple[float, dict]:
    """:func:`noise_inflation`'s factor from residuals ``res`` (T, ...) (NaN where unseen) and
    the likelihood's noise ``sigma`` (m): ``max(1, rms * sqrt(tau) / sigma)``, and its record
    (``residual_rms_m``, ``residual_tau``, ``noise_inflation``; empty with factor 1 when no
    residual is finite). The ball's samplers call it on their own tracks."""
    ok = np.isfinite(res)
    if not ok.any():
        return 1.0, {}
    rms = float(np.sqrt(np.mean(res[ok] ** 2)))
    tau = residual_tau(res)
    k = max(1.0, rms * np.sqrt(tau) / sigma)
    return float(k), {"residual_rms_m": rms, "residual_tau": tau, "noise_inflation": float(k)}


def inflate_in_box(samples: np.ndarray, mean: np.ndarray, std: np.ndarray, k: float, lo,
                   span):
    """Samples (N, P) spread ``k`` times wider about ``mean`` and clipped into the box
    ``[lo, lo + span]`` ((P,) each), ``std`` (P,) times ``k`` up to the box's uniform std.
    ``k <= 1``: both returned as they are (the same objects)."""
    if k <= 1.0:
        return samples, std
    out = np.clip(mean + k * (samples - mean), lo, lo + span)
    return out, np.minimum(k * np.asarray(std, dtype=np.float64), span / np.sqrt(12.0))


def inflate(prob: Problem, samples: np.ndarray, std: np.ndarray, k: float):
    """:func:`inflate_in_box` about the samples' mean, in the prior's box."""
    if k <= 1.0:
        return samples, std
    return inflate_in_box(samples, samples.mean(axis=0), std, k, prob.plo, prob.pspan)


def uninformed_params(prob: Problem, cov: np.ndarray) -> np.ndarray:
    """Which of the problem's P parameters (P,) bool the track does not inform: their Laplace
    variance ``cov`` (unit coordinates, from :func:`refine`, before any widening) at the
    uniform prior's, 1/12 (a held parameter, span 0, is the user's value, not uninformed)."""
    return (np.diag(cov)[:prob.P] >= (1.0 / 12.0) * (1.0 - 1e-9)) & (prob.pspan > 0)


def answer_prior(prob: Problem, flat: np.ndarray, mean: np.ndarray, std: np.ndarray,
                 draws: np.ndarray, rng: np.random.Generator) -> None:
    """The prior's answer, in place, for the parameters ``flat`` (P,) bool: mean the range's
    centre, std its uniform spread, the draws (n, P) uniform over it (``rng``). Where the track
    does not inform a parameter the optimiser leaves it anywhere, an end of its range as often
    as not, and that point moves with the frame rate or the start."""
    if flat.any():
        mean[flat] = prob.plo[flat] + 0.5 * prob.pspan[flat]
        draws[:, flat] = prob.plo[flat] + prob.pspan[flat] * rng.random(
            (len(draws), int(flat.sum())))
        std[flat] = prob.pspan[flat] / np.sqrt(12.0)


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
# the part a method composes for one system
@dataclass
class PointsFit:
    """What a fit found: the posterior, draws a forecast resamples (with their initial states)
    and their weights (None: equally weighted samples), the problem and the clock."""

    posterior: Posterior
    theta: np.ndarray
    state0: np.ndarray
    weights: np.ndarray | None
    prob: Problem
    clock: Stopwatch


def system_of(name):
    """The registered system ``name`` (``ValueError`` listing the known ones)."""
    return _system(name)


class Points:
    """The generic points likelihood on one system, as a method composes it.

    Parameters
    ----------
    system : System
    sigma : float
        Noise (m) of the likelihood per coordinate.
    min_frames : int
        Fewest frames with a seen point the method accepts.
    seed : int
        The method's seed (the prior draws of a widened posterior).
    """

    def __init__(self, system, sigma: float, min_frames: int = 3, seed: int = 0,
                 known: dict | None = None, prior: dict | None = None) -> None:
        self.system = system
        self.sigma = float(sigma)
        self.min_frames = int(min_frames)
        self.seed = seed
        self.known, self.prior = dict(known or {}), dict(prior or {})

    def track(self, obs: Observation) -> PointsTrack:
        """The :class:`PointsTrack` of ``obs``."""
        return prepare_points(obs, self.system, self.min_frames)

    def problem(self, obs: Observation) -> Problem:
        """The likelihood of ``obs`` with a fresh simulation counter."""
        return Problem(self.track(obs), self.sigma, PointsSimulator(self.system),
                       self.known, self.prior)

    def posterior(self, prob: Problem, mean, std, samples, extras, check) -> Posterior:
        """The posterior; where its model check failed, widened to the prior (the track is not
        explained by the mean's trajectory, so no interval narrower than the prior's is claimed:
        the mean stays, ``std`` becomes at least the prior's, the samples are prior draws, and
        ``check.note`` and ``extras["widened"]`` say so). The prior is the problem's: the
        user's ranges where given, a known parameter held (the mean and every sample its
        value, std 0); ``extras["known"]``/``extras["prior"]`` record them when given."""
        if check is not None and not check.ok:
            # the problem's ranges: the system's own unless the user gave some (span 0: held)
            lo, span = prob.plo, prob.pspan
            rng = np.random.default_rng([int(self.seed or 0), len(samples)])
            samples = lo + span * rng.random((len(samples), len(lo)))
            std = np.maximum(np.asarray(std, dtype=float), span / np.sqrt(12.0))
            note = "intervals widened to the prior: the model does not explain the track"
            check = dataclasses.replace(check, note=f"{check.note}; {note}" if check.note else note)
            extras = {**extras, "widened": "prior"}
        if prob.known or self.prior:
            held = [prob.system.params.index(k) for k in prob.known]
            mean, std = np.array(mean, dtype=float), np.array(std, dtype=float)
            mean[held] = [prob.known[k] for k in prob.known]  # not a sum's rounding of it
            std[held] = 0.0
            samples = np.array(samples, dtype=float)
            samples[:, held] = [prob.known[k] for k in prob.known]
            extras = {**extras, "known": dict(prob.known),
                      "prior": {k: [float(a), float(b)] for k, (a, b) in self.prior.items()}}
        return Posterior(mean=mean, std=std, samples=samples, extras=extras, check=check,
                         system=prob.system.name)

    def forecast(self, fit: PointsFit, n_forecast: int, horizon: int) -> Forecast:
        """Points of the ``horizon`` frames after the fitted observation: ``n_forecast`` draws of
        the fit (with their initial states) continued past the last frame; (H, 2), or
        (H, K, 2) for K > 1."""
        m = check_positive_int(n_forecast, "n_forecast")
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


class SimulationOnSystems(SimulationMethod):
    """Base of the simulation methods, one class on every system.

    A subclass takes a ``system`` hyperparameter (a registered name, default ``"ball"``) and
    ``sigma`` (None: the system's default noise), implements ``_fit`` (the ball, with
    :mod:`methods._simulation`) and ``_fit_points(obs, part)`` (any other system, with the
    :class:`Points` part built here); ``identify`` and ``forecast`` pick the one for
    ``system`` by :attr:`own_machinery`. ``per_system_defaults`` maps a hyperparameter whose
    None means a default that differs between the two to ``(own machinery's, the others')``.
    """

    systems = "any"
    per_system_defaults: dict = {}
    #: The systems fitted with the method's own machinery (``_fit``: :mod:`methods._simulation`
    #: and :mod:`methods._tracks`, written for the ball's hybrid physics, its floor and its
    #: tracker) rather than the generic :class:`Points`; every other system, a user's included,
    #: gets :class:`Points`. Data, not a branch on a name (issue 37).
    own_machinery: tuple[str, ...] = ("ball",)

    def _validate(self) -> None:
        super()._validate()
        check_system_param(self)
        if self.sigma is not None:
            check_sigma(self.sigma)
        check_positive_int(self.n_forecast, "n_forecast")
        self._knowledge()

    def _knowledge(self) -> tuple[dict, dict]:
        """``known``/``prior`` (absent or None: nothing) checked on the system, as
        :func:`sysid_bench.core.footage.parse_known`/``parse_prior`` check the command line's.

        Returns
        -------
        known : dict of str -> float
        prior : dict of str -> (float, float)
        """
        known, prior = getattr(self, "known", None), getattr(self, "prior", None)
        if not known and not prior:
            return {}, {}
        return check_knowledge(_system(self.system), known, prior)

    def _prepare(self, obs: Observation):
        """The own machinery's :class:`methods._tracks.Track` of ``obs``
        (:func:`methods._tracks.prepare`), carrying the user's knowledge as its ``box``
        (:class:`methods._simulation.ThetaBox`; None without any, so every figure without
        knowledge is the one it was)."""
        from methods._simulation import ThetaBox
        from methods._tracks import prepare

        track = prepare(obs)
        known, prior = self._knowledge()
        if known or prior:
            track = dataclasses.replace(track, box=ThetaBox.of(known, prior))
        return track

    def _box(self, track):
        """The parameter box of ``track`` (the user's, else the prior's)."""
        from methods._simulation import box_of

        return box_of(track)

    def _own_machinery(self) -> bool:
        return self.system in self.own_machinery

    def _hp(self, name: str):
        """Hyperparameter ``name``, its None read as this system's default."""
        v = getattr(self, name)
        if v is None and name in self.per_system_defaults:
            ball, other = self.per_system_defaults[name]
            return ball if self._own_machinery() else other
        return v

    def _sigma(self) -> float:
        """The likelihood's noise (m): ``sigma``, else the ball's ``DEFAULT_SIGMA`` or the
        system's :func:`default_sigma`."""
        if self.sigma is not None:
            return check_sigma(self.sigma)
        return DEFAULT_SIGMA if self._own_machinery() else default_sigma(_system(self.system))

    def _points(self) -> Points:
        known, prior = self._knowledge()
        return Points(_system(self.system), self._sigma(), self.min_frames, self.seed,
                      known, prior)

    def _fit_points(self, obs: Observation, part: Points) -> PointsFit:  # pragma: no cover
        raise NotImplementedError

    def identify(self, obs: Observation) -> Posterior:
        """Posterior over the system's parameters (``system.params`` order), with its model
        check (the ball: see :meth:`SimulationMethod.identify`)."""
        if self._own_machinery():
            return self._fit(obs).checked(self._sigma())
        return self._fit_points(obs, self._points()).posterior

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Positions (the ball, (H, 2)) or points ((H, 2), or (H, K, 2) for K > 1) of the
        ``horizon`` frames after ``obs``: ``n_forecast`` draws of the fit continued."""
        if self._own_machinery():
            return super().forecast(obs, horizon)
        part = self._points()
        return part.forecast(self._fit_points(obs, part), self.n_forecast, horizon)


def check_system_param(est) -> None:
    """``est.system``: a registered name among the systems the class declares."""
    name = est.system
    if not isinstance(name, str):
        raise ValueError(f"system: expected a registered system name (str), got {name!r}")
    _system(name)  # ValueError listing the known systems
    declared = type(est).systems
    if declared != "any" and name not in declared:
        raise ValueError(f"system: expected one of {', '.join(declared)} ({est.name} runs on "
                         f"those), got {name!r}")

