"""The skeleton every simulation-based method (lsq, bo, emcee, nuts) is built on.

A :class:`SimulationMethod` implements one thing, ``_fit(obs) -> Fit``: its search or sampler,
returning a named :class:`Fit` (the posterior, the draws a forecast resamples with their initial
states and floors, the prepared track, the counting simulator and the clock) instead of a 3- to
7-tuple. ``identify`` and ``forecast`` are written once, here: ``identify`` is the fit's
posterior; ``forecast`` resamples ``n_forecast`` draws (by the fit's weights when it has them,
uniformly otherwise, from the seed's stream 1 so the forecast does not reuse the fit's draws)
and continues each draw's own trajectory past the last observed frame.

The counting simulator and the likelihood are the harness's (:mod:`sysid_bench.simulator`),
track preparation is :mod:`methods._tracks`, weighting and resampling :mod:`methods._weights`.
"""

from __future__ import annotations

import abc
import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from methods._tracks import Track, clip_state
from methods._weights import resample
from sysid_bench import physics
from sysid_bench._validate import check_positive_int
from sysid_bench.estimator import Check, Estimator, Forecast, Observation, Posterior
from sysid_bench.physics import PRIOR_STD
from sysid_bench.simulator import CountingSimulator

__all__ = ["SimulationMethod", "Fit", "forecast_by_simulation", "make_rng", "Stopwatch",
           "one_blas_thread", "model_check", "widen_failed", "widen_to_support", "check_prefixes",
           "uninformed", "widen_uninformed", "refine_fit", "state0_box",
           "state0_half"]

#: ``Check.note`` of a failed check whose intervals were widened
WIDENED_NOTE = ("intervals widened to at least the prior's: the model at the reported "
                "parameters does not explain the observation")


def one_blas_thread():
    """Context limiting BLAS to one thread (``threadpoolctl``).

    The baselines' matrices are tiny (GP kernels of 20 points, a 120 x 140 Hankel matrix, 4-8
    column Jacobians); on the shared 2-core machine OpenBLAS threads contending for the cores
    made them 6-20x slower (bo 19 s -> 3 s, dmd 1.3 s -> 0.06 s per call).
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


class Stopwatch:
    """Wall-clock seconds since construction (``perf_counter``)."""

    def __init__(self) -> None:
        self._t0 = time.perf_counter()

    def __call__(self) -> float:
        return time.perf_counter() - self._t0


def make_rng(seed, stream: int = 0) -> np.random.Generator:
    """Generator for one purpose (``stream``) of a method, fixed by its ``seed``.

    An int (or None) seed gives ``default_rng([seed, stream])`` so that, e.g., a forecast's
    resampling does not reuse the identification's draws; a Generator is used as it is.
    """
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, bool) or not (seed is None or isinstance(seed, (int, np.integer))):
        raise ValueError(f"seed: expected an int, None or numpy.random.Generator, got {seed!r}")
    return np.random.default_rng(None if seed is None else [int(seed), stream])


def forecast_by_simulation(
    sim: CountingSimulator,
    theta: np.ndarray,
    state: np.ndarray,
    floor: float,
    dt: float,
    horizon: int,
    skip: int = 0,
    clock: Stopwatch | None = None,
    extras: dict | None = None,
) -> Forecast:
    """Forecast positions by simulating posterior samples.

    Simulates ``skip + horizon + 1`` frames from ``state`` and returns the last ``horizon``:
    with ``state`` the initial states and ``skip = T - 1`` this continues each sample's own
    trajectory past the last observed frame; with ``state`` the estimated state at the last
    observed frame and ``skip = 0`` it continues from there.

    Parameters
    ----------
    sim : CountingSimulator
    theta : ndarray, shape (S, 4)
    state : ndarray, shape (S, 4)
    floor : float or ndarray, shape (S,)
    dt : float
    horizon : int
    skip : int
    clock : Stopwatch, optional
        Started when the forecast's work began; ``extras["wall_s"]`` reads it at the end.
    extras : dict, optional
        More entries for ``Forecast.extras``.

    Returns
    -------
    Forecast
        mean/std (horizon, 2), samples (S, horizon, 2); ``extras`` holds ``n_simulations`` (all
        of ``sim``'s, the identification's included) and ``wall_s``.
    """
    traj = sim.positions(theta, clip_state(state, floor), skip + horizon + 1, dt, floor)
    samples = traj[:, skip + 1 :]
    ex = dict(extras or {})
    ex["n_simulations"] = sim.n_simulations
    if clock is not None:
        ex["wall_s"] = clock()
    return Forecast(mean=samples.mean(axis=0), std=samples.std(axis=0), samples=samples, extras=ex)


def check_prefixes(posts: list, obs: Observation, lengths, noise_m: float,
                   window: int | None = None) -> list:
    """Model checks of posteriors after each of ``lengths`` frames of ``obs`` (any method).

    For a method that does not fit trajectories itself (Vid2Param): the observation is tracked
    once (:func:`sysid_bench.estimator.observed_positions`: the harness's tracker on frames),
    and each posterior mean is simulated with our physics from the start that fits it best
    (:func:`model_check` with ``fit_state0``) over its prefix, judged against ``noise_m``.
    A prefix with fewer than 3 seen frames fails ("nothing observed" / too few). ``window``:
    only the last ``window`` frames of each prefix are checked (parameters that change over
    time: one constant ``theta`` explains one stretch, not the whole video).

    Returns
    -------
    list of Posterior
        ``posts`` with ``check`` set, widened where it failed (:func:`widen_failed`).
    """
    from methods._tracks import prepare
    from sysid_bench.estimator import observed_positions

    try:
        pos = observed_positions(obs, min_seen=0)
    except ValueError:
        pos = None
    out = []
    for n, post in zip(lengths, posts):
        sim = CountingSimulator()
        try:
            if pos is None:
                raise ValueError("nothing tracked")
            start = 0 if window is None else max(int(n) - int(window), 0)
            track = prepare(dataclasses.replace(obs, frames=None, positions=pos[start: int(n)],
                                                state0=None))
            info: dict = {}
            check = model_check(sim, post.mean, track.state0, track.floor, track, noise_m,
                                fit_state0=True, info=info)
            if check.ok:
                flat = uninformed(sim, post.mean, info["state0"], track.floor, track, noise_m)
                post = widen_uninformed(post, flat, seed=int(n))
            post = widen_to_support(post, check, sim, track, info["state0"], track.floor)
        except ValueError as exc:
            check = Check(float("nan"), float(noise_m), False, 0, f"no track to check: {exc}")
            post = widen_failed(post, check)
        post.extras["check_simulations"] = sim.n_simulations
        out.append(post)
    return out


#: a parameter is uninformed when moving it across its whole prior range changes the
#: trajectory's sum of squared residuals by less than this many noise variances (~1 nat at 2)
UNINFORMED_CHI2 = 4.0


def uninformed(sim: CountingSimulator, theta, state0, floor: float, track: Track,
               noise_m: float) -> np.ndarray:
    """Which parameters (4,) bool the track cannot inform at ``theta`` from ``state0``.

    Each parameter is set to its prior's low and high end (the others held) and the two
    trajectories compared over the seen frames: when their squared distance summed over the
    seen coordinates is below ``UNINFORMED_CHI2`` noise variances, no data this track could
    hold tells the ends apart (a ball at rest says nothing of e, g or d; a clip without rolling
    nothing of r), so no interval narrower than the prior's is supported. 8 simulations. A
    still track (every seen position within 2 noise of their median) informs none.
    """
    seen = track.positions[track.mask]
    if len(seen) and np.max(np.abs(seen - np.median(seen, axis=0))) <= 2.0 * float(noise_m):
        # a still track: its start explains it whatever the parameters (a sampler's start a
        # hair above the floor would make e look informed by bounces nobody saw)
        return np.ones(4, dtype=bool)
    th = np.repeat(np.asarray(theta, dtype=np.float64)[None], 8, axis=0)
    for k in range(4):
        th[2 * k, k], th[2 * k + 1, k] = physics.PRIOR_LO[k], physics.PRIOR_HI[k]
    s0 = clip_state(np.repeat(np.asarray(state0, dtype=np.float64)[None], 8, axis=0), floor)
    pos = sim.positions(th, s0, track.n_frames, track.dt, float(floor))[:, track.mask]
    d2 = np.sum((pos[0::2] - pos[1::2]) ** 2, axis=(1, 2))
    return d2 < UNINFORMED_CHI2 * float(noise_m) ** 2


def widen_uninformed(post: Posterior, flat: np.ndarray, seed: int = 0) -> Posterior:
    """``post`` with the parameters ``flat`` (4,) bool at least as wide as the prior: std at
    least the prior's, and their sample columns (if any) redrawn from the uniform prior
    (seeded), so intervals and quantiles say the data did not inform them."""
    flat = np.asarray(flat, dtype=bool)
    if not flat.any():
        return post
    std = np.where(flat, np.maximum(post.std, PRIOR_STD), post.std)
    samples = post.samples
    if samples is not None:
        samples = np.array(samples, dtype=np.float64, copy=True)
        u = np.random.default_rng([seed, 29]).random((len(samples), 4))
        prior = physics.PRIOR_LO + u * physics.PRIOR_SPAN
        samples[:, flat] = prior[:, flat]
    extras = {**post.extras, "uninformed": [p for p, f in zip(physics.PARAMS, flat) if f]}
    return Posterior(mean=np.asarray(post.mean), std=std, samples=samples, extras=extras,
                     check=post.check, system=post.system)


def widen_failed(post: Posterior, check: Check) -> Posterior:
    """``post`` with ``check``; when the check fails, spread at least the prior's.

    A failed check means the model, at the parameters the method reports, does not explain the
    observation (a hovering ball, random points, physics that is not ours): the mean is kept,
    the standard deviation becomes at least the prior's (``PRIOR_STD``) and the samples (if
    any) are replaced by as many uniform prior draws (seeded), so every interval
    (``Posterior.interval``) holds at least the central 90% of the prior box. ``extras["check_failed"]`` says so.
    """
    if check.ok:
        post.check = check  # in place: a subclass's lazy samples stay lazy
        return post
    check = dataclasses.replace(check, note=check.note or WIDENED_NOTE)
    prior_std = np.broadcast_to(PRIOR_STD, np.shape(post.std))
    extras = {**post.extras, "check_failed": True}
    samples = post.samples
    if samples is not None:
        # as many draws from the uniform prior (seeded): intervals and quantiles the prior's
        samples = physics.sample_theta(len(samples), np.random.default_rng([29, len(samples)]))
    return Posterior(mean=np.asarray(post.mean), std=np.maximum(post.std, prior_std),
                     samples=samples, extras=extras, check=check, system=post.system)


#: simulations the search for what the data supports may use (:func:`widen_to_support`)
SUPPORT_SIMS = 450
#: the checks' least-squares tolerance (:func:`refine_fit`'s ``tol``)
CHECK_TOL = 1e-4


def widen_to_support(post: Posterior, check: Check, sim: CountingSimulator, track: Track,
                     state0: np.ndarray, floor: float) -> Posterior:
    """``post`` with ``check``; when it fails, intervals widened to what the data supports.

    A failed check says the posterior mean does not reproduce the track. Whether the model can
    reproduce it at all is asked by a local least-squares fit from the posterior mean (and
    ``state0``; the start is fitted too unless known), :func:`refine_fit`, at most
    :data:`SUPPORT_SIMS` simulations. If that best fit passes the same check, the data support
    the model near the method's answer: each parameter's std grows to at least its distance
    from the best fit (so the 90% interval holds the best fit), the samples are stretched
    about the mean by the same factors, and ``check.note`` says so (the verdict stays failed,
    with the posterior mean's RMS). If even the best fit fails, the model does not explain the
    observation and the spread becomes at least the prior's (:func:`widen_failed`).
    """
    if check.ok:
        post.check = check
        return post
    if track.state0_known:
        lo_s = hi_s = None
        s0 = track.state0
    else:
        lo_s, hi_s = state0_box(track)
        s0 = np.clip(np.asarray(state0, dtype=np.float64), lo_s, hi_s)
    try:
        best, s0_best, rms = refine_fit(sim, track, np.clip(post.mean, physics.PRIOR_LO,
                                                             physics.PRIOR_HI),
                                        s0, lo_s, hi_s, SUPPORT_SIMS, tol=CHECK_TOL)
    except ValueError:
        return widen_failed(post, check)
    if not model_check(sim, best, s0_best, floor, track, check.noise_m).ok:
        return widen_failed(post, check)
    std = np.maximum(post.std, np.abs(best - post.mean))
    samples = post.samples
    if samples is not None:
        samples = np.asarray(samples, dtype=np.float64)
        ratio = np.where(post.std > 0, std / np.where(post.std > 0, post.std, 1.0), 1.0)
        samples = post.mean + (samples - post.mean) * ratio
        samples = np.clip(samples, physics.PRIOR_LO, physics.PRIOR_HI)
    note = (f"the posterior mean misses the track by {check.rms_m:.3g} m RMS; intervals "
            f"widened to hold the best fit found from it ({rms:.3g} m RMS)")
    check = dataclasses.replace(check, note=note)
    extras = {**post.extras, "check_failed": True, "support_fit": best.tolist(),
              "support_rms_m": rms}
    return Posterior(mean=np.asarray(post.mean), std=std, samples=samples, extras=extras,
                     check=check, system=post.system)


# Half-widths of the initial-state box, in standard errors of the estimate, and at least these
# (m, m, m/s, m/s): around the tracked start, as the paper's real-video variant.
_STATE_BOX_SE = 3.0
_STATE_BOX_MIN = np.array([0.01, 0.01, 0.05, 0.05])
#: simulations a model check may spend fitting the initial state (``model_check(fit_state0=)``)
CHECK_STATE_SIMS = 200


def state0_half(track: Track) -> np.ndarray:
    """Half-widths (4,) of the box around an estimated initial state that lsq searches: 3
    standard errors of the estimate, at least 1 cm and 5 cm/s."""
    return np.maximum(_STATE_BOX_SE * track.state0_std, _STATE_BOX_MIN)


def state0_box(track: Track) -> tuple[np.ndarray, np.ndarray]:
    """The box ``(lo, hi)`` (4,) each, :func:`state0_half` around the estimated initial state,
    inside the room (:func:`clip_state`)."""
    half = state0_half(track)
    return (clip_state(track.state0 - half, track.floor),
            clip_state(track.state0 + half, track.floor))


def model_check(sim: CountingSimulator, theta: np.ndarray, state0: np.ndarray, floor: float,
                track: Track, noise_m: float, fit_state0: bool = False,
                info: dict | None = None) -> Check:
    """:class:`Check` of the trajectory of ``theta`` (4,) from ``state0`` (4,) over ``track``.

    Simulates that one trajectory (counted by ``sim``) and judges its residual RMS over the
    seen frames against ``noise_m`` (:meth:`Check.from_residuals`). ``fit_state0``: for a
    method that holds an estimated initial state fixed (bo, sindy), the start is first fitted
    by least squares with ``theta`` held (:func:`refine_fit`, at most
    :data:`CHECK_STATE_SIMS` simulations, inside :func:`state0_box`): the check then asks
    whether the posterior-mean parameters explain the track, not whether a finite-difference
    start does (from the tracked start, 200 frames of a clean video drift by metres).
    ``info``: a dict that receives the start used (``"state0"``).
    """
    if fit_state0 and not track.state0_known:
        lo, hi = state0_box(track)
        _, state0, _ = refine_fit(sim, track, theta, state0, lo, hi, CHECK_STATE_SIMS,
                                  fit_theta=False, tol=CHECK_TOL)
    if info is not None:
        info["state0"] = np.asarray(state0, dtype=np.float64)
    traj = sim.positions(np.asarray(theta, dtype=np.float64)[None],
                         clip_state(np.asarray(state0, dtype=np.float64)[None], floor),
                         track.n_frames, track.dt, float(floor))[0]
    m = track.mask[:, None]
    resid = np.where(m, traj - np.where(m, track.positions, 0.0), np.nan)
    return Check.from_residuals(resid, float(noise_m))


def refine_fit(sim: CountingSimulator, track: Track, theta0, s00, lo_s, hi_s, max_sims: int,
               fit_theta: bool = True, tol: float = 1e-8):
    """Local least squares from ``theta0`` (4,), ``s00`` (4,); returns ``(theta, state0, rms)``.

    Coordinates: the parameters mapped to [0, 1] by the prior (held at ``theta0`` when
    ``fit_theta`` is False), then (when ``lo_s`` is not None) the initial state mapped to [0, 1]
    by its box ``[lo_s, hi_s]`` (held at ``s00`` otherwise). Residuals are the seen coordinates'
    errors (m); the Jacobian is forward differences, one batch of D + 1 simulations per
    evaluation, at most ``max_sims`` simulations in all (counted by ``sim``). ``tol``: the
    optimiser's ``ftol``/``xtol`` (the checks use 1e-4: they need the RMS to a few percent of the
    noise, not the optimum to 8 digits, and it cut their cost ~3x). Never returns a worse fit
    than the start; ``rms`` is the returned fit's residual RMS (m).
    """
    from scipy.optimize import least_squares

    free = lo_s is not None
    if not (free or fit_theta):
        raise ValueError("fit_theta: expected True when the initial state is held (no box)")
    theta0 = np.asarray(theta0, dtype=np.float64)
    s00 = np.asarray(s00, dtype=np.float64)
    nt = 4 if fit_theta else 0
    D = nt + (4 if free else 0)
    mask = track.mask
    obs = track.positions[mask].ravel()
    span_s = (hi_s - lo_s) if free else None

    def unpack(U):
        if fit_theta:
            th = physics.denormalise_theta(np.clip(U[:, :4], 0.0, 1.0))
        else:
            th = np.broadcast_to(theta0, (len(U), 4))
        if free:
            s0 = clip_state(lo_s + np.clip(U[:, nt:], 0.0, 1.0) * span_s, track.floor)
        else:
            s0 = np.broadcast_to(s00, (len(U), 4))
        return th, s0

    def resid(U):
        th, s0 = unpack(U)
        pos = sim.positions(th, s0, track.n_frames, track.dt, track.floor)
        return pos[:, mask].reshape(len(U), -1) - obs

    x0 = np.empty(D)
    if fit_theta:
        x0[:4] = physics.normalise_theta(theta0[None])[0]
    if free:
        x0[nt:] = np.where(span_s > 0, (s00 - lo_s) / np.where(span_s > 0, span_s, 1.0), 0.5)
    x0 = np.clip(x0, 0.0, 1.0)
    h = 1e-6
    cache = {}

    def fun(x):
        key = x.tobytes()
        if key not in cache:
            # the point and its D forward steps in one batch (stepping inwards at a bound)
            steps = np.where(x + h <= 1.0, h, -h)
            U = np.vstack([x, x + np.diag(steps)])
            r = resid(U)
            cache.clear()
            cache[key] = (r[0], ((r[1:] - r[0]) / steps[:, None]).T)
        return cache[key][0]

    def jac(x):
        fun(x)
        return cache[x.tobytes()][1]

    r0 = fun(x0)
    with one_blas_thread():
        res = least_squares(fun, x0, jac=jac, bounds=(0.0, 1.0), method="trf",
                            max_nfev=max(max_sims // (D + 1), 1), x_scale="jac",
                            ftol=tol, xtol=tol)
    x = res.x if np.sum(res.fun**2) < np.sum(r0**2) else x0
    th, s0 = unpack(x[None])
    rms = float(np.sqrt(np.mean(fun(x) ** 2)))
    return th[0], s0[0], rms



@dataclass
class Fit:
    """What a simulation-based method's fit found.

    Attributes
    ----------
    posterior : Posterior
    theta : ndarray, shape (N, 4)
        Draws a forecast resamples from (physical units).
    state0 : ndarray, shape (N, 4)
        Their initial states.
    floor : float or ndarray, shape (N,)
        The floor (one for all, or per draw when the method samples it).
    track : Track
    sim : CountingSimulator
        The simulator the fit used (a forecast's simulations add to its count).
    clock : Stopwatch
        Started when the fit began (a forecast's ``wall_s`` includes the fit).
    weights : ndarray, shape (N,), optional
        Normalised weights of the draws; None when they are equally weighted samples.
    state0_point : ndarray, shape (4,), optional
        The initial state that belongs to the reported point estimate ``posterior.mean``
        (lsq, bo: the best fit's own; samplers: the mean of the draws' initial states). The
        model check simulates the posterior mean from it. None: ``state0``'s (weighted) mean.
    floor_point : float, optional
        The floor of that trajectory; None: ``floor``'s (weighted) mean.
    noise_m : float, optional
        The observation noise the method assumed (its ``sigma``); None: ``self.sigma``.
    check_fits_state0 : bool
        The method held an estimated initial state fixed: the check fits the start first
        (:func:`model_check`'s ``fit_state0``).
    """

    posterior: Posterior
    theta: np.ndarray
    state0: np.ndarray
    floor: float | np.ndarray
    track: Track
    sim: CountingSimulator
    clock: Stopwatch
    weights: np.ndarray | None = None
    state0_point: np.ndarray | None = None
    floor_point: float | None = None
    noise_m: float | None = None
    check_fits_state0: bool = False

    def checked(self, noise_m: float) -> Posterior:
        """The posterior with its model check (:func:`model_check`, :func:`widen_to_support`;
        parameters the track cannot inform widened to the prior, :func:`uninformed`);
        the check's simulations are in ``extras["check_simulations"]``, not in
        ``n_simulations``."""
        w = self.weights
        s0 = self.state0_point
        if s0 is None:
            s0 = np.average(np.asarray(self.state0), axis=0, weights=w)
        fl = self.floor_point
        if fl is None:
            fl = float(np.average(self.floor, weights=w)) if np.ndim(self.floor) else self.floor
        noise = noise_m if self.noise_m is None else self.noise_m
        # the check's own simulations are counted apart: n_simulations stays the method's
        sim = CountingSimulator()
        info: dict = {}
        check = model_check(sim, self.posterior.mean, s0, float(fl), self.track, noise,
                            fit_state0=self.check_fits_state0, info=info)
        post = self.posterior
        if check.ok:
            # a track that cannot inform a parameter (a ball at rest: e, g, d) supports no
            # interval narrower than the prior's, however the sampler or search ended up
            flat = uninformed(sim, post.mean, info["state0"], float(fl), self.track, noise)
            post = widen_uninformed(post, flat, seed=self.track.n_frames)
        post = widen_to_support(post, check, sim, self.track, info["state0"], float(fl))
        post.extras["check_simulations"] = sim.n_simulations
        return post


class SimulationMethod(Estimator):
    """Base of the simulation-based methods: implement ``_fit``; ``identify``/``forecast`` follow.

    Subclasses take an ``n_forecast`` hyperparameter (draws simulated by ``forecast``) and a
    ``seed``.
    """

    input_kind = "positions"
    min_frames = 3  # fewer seen frames cannot fix a state and parameters (``_tracks.prepare``)
    forecasts = True

    @abc.abstractmethod
    def _fit(self, obs: Observation) -> Fit:
        """Search or sample; everything ``identify`` and ``forecast`` need."""

    def identify(self, obs: Observation) -> Posterior:
        """Posterior over ``(e, g, d, r)`` given all frames of ``obs`` (see the class), with its
        model check: the posterior mean simulated from its own initial state
        (``Fit.state0_point``) against the seen positions, judged against the noise the method
        assumed (``sigma``); a failed check widens the intervals (:func:`widen_failed`)."""
        return self._fit(obs).checked(float(self.sigma))

    def _forecast_state0(self, fit: Fit, idx: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Initial states of the forecast's draws ``idx``: by default the draws' own."""
        return fit.state0[idx]

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Positions of the ``horizon`` frames after ``obs``: ``n_forecast`` draws of the fit
        (with their initial states and floors) continued past the last frame.

        Returns
        -------
        Forecast
            mean/std (horizon, 2); samples (n_forecast, horizon, 2); ``extras`` holds
            ``n_simulations`` (the fit's included), ``wall_s`` and ``posterior_extras``.
        """
        m = check_positive_int(self.n_forecast, "n_forecast")
        fit = self._fit(obs)
        # a stream independent of the fit's draws, still fixed by the seed
        rng = make_rng(self.seed, 1)
        if fit.weights is not None:
            idx = resample(fit.weights, m, rng)
        else:
            idx = rng.choice(len(fit.theta), size=m, replace=len(fit.theta) < m)
        state0 = self._forecast_state0(fit, idx, rng)
        floor = fit.floor[idx] if np.ndim(fit.floor) else fit.floor
        return forecast_by_simulation(
            fit.sim, fit.theta[idx], state0, floor, fit.track.dt, horizon,
            skip=fit.track.n_frames - 1, clock=fit.clock,
            extras={"posterior_extras": fit.posterior.extras},
        )
