"""The skeleton every simulation-based method (lsq, bo, emcee, nuts) is built on.

A :class:`SimulationMethod` implements one thing, ``_fit(obs) -> Fit``: its search or sampler,
returning a named :class:`Fit` (the posterior, the draws a forecast resamples with their initial
states and floors, the prepared track, the counting simulator and the clock) instead of a 3- to
7-tuple. ``identify`` and ``forecast`` are written once, here: ``identify`` is the fit's
posterior; ``forecast`` resamples ``n_forecast`` draws (by the fit's weights when it has them,
uniformly otherwise, from the seed's stream 1 so the forecast does not reuse the fit's draws)
and continues each draw's own trajectory past the last observed frame.

The counting simulator and the likelihood are the harness's (:mod:`sysid_bench.core.simulator`),
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
from sysid_bench.core import physics
from sysid_bench.core._validate import check_positive_int
from sysid_bench.core.estimator import Check, Estimator, Forecast, Observation, Posterior
from sysid_bench.core.physics import PRIOR_STD
from sysid_bench.core.simulator import CountingSimulator

__all__ = ["SimulationMethod", "Fit", "ThetaBox", "PRIOR_BOX", "box_of", "forecast_by_simulation", "make_rng", "Stopwatch",
           "one_blas_thread", "model_check", "region_box", "region_check",
           "check_posterior", "widen_failed", "widen_to_support", "check_prefixes",
           "uninformed", "widen_uninformed", "refine_fit", "state0_box",
           "state0_half", "widen_by_discrepancy", "residual_tau"]

@dataclass(frozen=True)
class ThetaBox:
    """The ball's parameter box a fit searches and samples and its check judges in: the prior
    (``PRIOR``), with the user's ranges replacing it per parameter and held values as boxes of
    width 0 (issue 38 §4; the generic path's :class:`methods._points.Problem` does the same).

    Attributes
    ----------
    lo, hi : ndarray, shape (4,)
        Physical units, ``PARAMS`` order; ``lo == hi`` for a held parameter.
    known : dict of str -> float
    prior : dict of str -> (float, float)
    """

    lo: np.ndarray
    hi: np.ndarray
    known: dict
    prior: dict

    @classmethod
    def of(cls, known: dict | None = None, prior: dict | None = None) -> ThetaBox:
        """The box of checked ``known``/``prior`` (:func:`sysid_bench.core.footage.check_knowledge`)."""
        lo, hi = physics.PRIOR_LO.copy(), physics.PRIOR_HI.copy()
        known, prior = dict(known or {}), dict(prior or {})
        for name, (a, b) in {**prior, **{k: (v, v) for k, v in known.items()}}.items():
            i = physics.PARAMS.index(name)
            lo[i], hi[i] = float(a), float(b)
        return cls(lo, hi, known, prior)

    @property
    def span(self) -> np.ndarray:
        return self.hi - self.lo

    @property
    def std(self) -> np.ndarray:
        """The uniform box's standard deviations (4,) (0 where held)."""
        return self.span / np.sqrt(12.0)

    @property
    def held(self) -> np.ndarray:
        """(4,) bool: the parameters held at a known value."""
        return np.array([p in self.known for p in physics.PARAMS])

    def normalise(self, theta) -> np.ndarray:
        """Parameters (..., 4) to [0, 1] by the box (a held one to 0)."""
        span = self.span
        return (np.asarray(theta, dtype=np.float64) - self.lo) / np.where(span > 0, span, 1.0)

    def denormalise(self, u) -> np.ndarray:
        """Inverse of :meth:`normalise` (a held parameter is its value whatever ``u``)."""
        return self.lo + np.asarray(u, dtype=np.float64) * self.span

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` uniform draws (n, 4) (held columns exactly their values)."""
        return self.hold_samples(self.denormalise(rng.random((n, 4))))

    def hold_samples(self, samples: np.ndarray) -> np.ndarray:
        """``samples`` (N, 4) with the held columns set to their values (not ``lo + u * 0``'s
        rounding)."""
        for k, v in self.known.items():
            samples[:, physics.PARAMS.index(k)] = v
        return samples

    def hold(self, post: Posterior) -> Posterior:
        """``post`` with the held parameters exact (mean and every sample the value, std 0)
        and ``extras["known"]``/``extras["prior"]`` saying what was held."""
        mean, std = np.array(post.mean, dtype=float), np.array(post.std, dtype=float)
        held = [physics.PARAMS.index(k) for k in self.known]
        mean[held] = [self.known[k] for k in self.known]
        std[held] = 0.0
        samples = post.samples
        if samples is not None:
            samples = self.hold_samples(np.array(samples, dtype=float))
        extras = {**post.extras, "known": dict(self.known),
                  "prior": {k: [float(a), float(b)] for k, (a, b) in self.prior.items()}}
        return Posterior(mean=mean, std=std, samples=samples, extras=extras, check=post.check,
                         system=post.system)


#: the box of a track without the user's knowledge: the prior
PRIOR_BOX = ThetaBox(physics.PRIOR_LO, physics.PRIOR_HI, {}, {})


def box_of(track) -> ThetaBox:
    """The parameter box of ``track`` (its ``box``, else the prior's)."""
    box = getattr(track, "box", None)
    return PRIOR_BOX if box is None else box


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
    once (:func:`sysid_bench.core.estimator.observed_positions`: the harness's tracker on frames),
    and each posterior is checked with our physics over its prefix (:func:`check_posterior`
    with ``fit_state0``: the mean from the start that fits it best, else a parameter vector
    inside its 90% interval), judged against ``noise_m``. A prefix with fewer than 3 seen
    frames fails ("nothing observed" / too few). ``window``: only the last ``window`` frames
    of each prefix are checked (parameters that change over time: one constant ``theta``
    explains one stretch, not the whole video).

    Cost: consecutive prefixes differ by a frame, so each prefix starts from the previous one's
    judged trajectory (its start, moved on by the frames the window moved): that start is
    judged as it is first and the start's least-squares fit runs only when it fails; the
    previous prefix's parameters are tried first in the region check. The searches from such
    a warm start get :data:`WARM_SIMS` simulations when the prefix is at most
    :data:`SEARCH_GROWTH` times the previous one, their full budget when it grew more.

    Returns
    -------
    list of Posterior
        ``posts`` with ``check`` set, widened where it failed (:func:`widen_to_support`).
    """
    from methods._tracks import prepare
    from sysid_bench.core.estimator import observed_positions

    try:
        pos = observed_positions(obs, min_seen=0)
    except ValueError:
        pos = None
    out = []
    prev: dict | None = None  # the last prefix's window start, floor and fits (warm starts)
    for n, post in zip(lengths, posts):
        sim = CountingSimulator()
        try:
            if pos is None:
                raise ValueError("nothing tracked")
            start = 0 if window is None else max(int(n) - int(window), 0)
            track = prepare(dataclasses.replace(obs, frames=None, positions=pos[start: int(n)],
                                                state0=None))
            kw: dict = {"try_start": False, "search": True}
            s0 = track.state0
            if prev is not None and start >= prev["start"]:
                k, fl = start - prev["start"], prev["floor"]
                s0 = _moved(sim, (prev["theta"], prev["state0"]), k, track.dt, fl)[1]
                # a warm start is near the answer only for a prefix a little longer than the
                # last: from 50 frames to 200 the 90-simulation warm searches missed fits that
                # a full search finds (3 of vid2param's 6 failures on the report's test videos)
                near = int(n) <= SEARCH_GROWTH * prev["n"]
                kw.update(try_start=near, witness=_moved(sim, prev["region"], k, track.dt, fl),
                          support_start=_moved(sim, prev["support"], k, track.dt, fl))
                # nested prefixes: a trajectory's squared residuals over these frames are at
                # least those over the frames before; when the smallest sum found there,
                # spread over these residuals, still exceeds the bound, nothing found there
                # passes here. The searches are local, so this is trusted only until the
                # track has grown by SEARCH_GROWTH since the last search (then searched again)
                n_res = 2 * track.n_seen
                if (k == 0 and not prev["ok"] and np.isfinite(prev["best_sse"]) and n_res > 0
                        and n_res < SEARCH_GROWTH * prev["searched_n"]):
                    bound = Check.bound(n_res) * float(noise_m)
                    kw["search"] = bool(prev["best_sse"] / n_res <= bound ** 2)
            info: dict = {}
            post = check_posterior(post, sim, track, s0, track.floor, noise_m, fit_state0=True,
                                   seed=int(n), info=info, **kw)
            searched_n = 2 * track.n_seen
            if not kw["search"]:  # the bound found before still holds, and its fits
                info.update(best_sse=prev["best_sse"], region=prev["region"],
                            support=prev["support"])
                searched_n = prev["searched_n"]
            if info.get("support") is None and prev is not None and prev["support"] is not None:
                # the last best fit found stays the start of the next support search: a prefix
                # passed inside its box leaves none, and a later failure searching from the
                # box's edge with the warm budget missed fits it held (the README's clip:
                # from 110 frames on, widened to the prior though a fit explains the track)
                info["support"] = _moved(sim, prev["support"], start - prev["start"],
                                         track.dt, prev["floor"])
            prev = {"start": start, "n": int(n), "floor": float(track.floor), "ok": bool(post.check.ok),
                    "searched_n": searched_n, **info}
        except ValueError as exc:
            check = Check(float("nan"), float(noise_m), False, 0, f"no track to check: {exc}")
            post = widen_failed(post, check)
        post.extras["check_simulations"] = sim.n_simulations
        out.append(post)
    return out


#: :func:`check_prefixes` searches a failing chain of prefixes again once the track has
#: grown by this factor since its last search (whatever the bound from that search says)
SEARCH_GROWTH = 1.25


def _moved(sim: CountingSimulator, fit, k: int, dt: float, floor: float):
    """``fit = (theta, state0)`` with its start moved on by ``k`` frames (None stays None)."""
    if fit is None or k == 0:
        return fit
    th, s0 = fit
    s = sim(np.asarray(th, dtype=np.float64)[None],
            clip_state(np.asarray(s0, dtype=np.float64)[None], floor), k + 1, dt, floor)
    return th, s[0, -1]


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
        return ~box_of(track).held
    box = box_of(track)
    th = np.repeat(np.asarray(theta, dtype=np.float64)[None], 8, axis=0)
    for k in range(4):
        th[2 * k, k], th[2 * k + 1, k] = box.lo[k], box.hi[k]
    s0 = clip_state(np.repeat(np.asarray(state0, dtype=np.float64)[None], 8, axis=0), floor)
    pos = sim.positions(th, s0, track.n_frames, track.dt, float(floor))[:, track.mask]
    d2 = np.sum((pos[0::2] - pos[1::2]) ** 2, axis=(1, 2))
    # a held parameter is the user's value, not the track's to inform
    return (d2 < UNINFORMED_CHI2 * float(noise_m) ** 2) & ~box.held


def widen_uninformed(post: Posterior, flat: np.ndarray, seed: int = 0,
                     box: ThetaBox | None = None) -> Posterior:
    """``post`` with the parameters ``flat`` (4,) bool at least as wide as the prior: std at
    least the prior's, and their sample columns (if any) redrawn from the uniform prior
    (seeded), so intervals and quantiles say the data did not inform them."""
    flat = np.asarray(flat, dtype=bool)
    if not flat.any():
        return post
    box = PRIOR_BOX if box is None else box
    std = np.where(flat, np.maximum(post.std, box.std), post.std)
    samples = post.samples
    if samples is not None:
        samples = np.array(samples, dtype=np.float64, copy=True)
        u = np.random.default_rng([seed, 29]).random((len(samples), 4))
        prior = box.lo + u * box.span
        samples[:, flat] = prior[:, flat]
    extras = {**post.extras, "uninformed": [p for p, f in zip(physics.PARAMS, flat) if f]}
    return Posterior(mean=np.asarray(post.mean), std=std, samples=samples, extras=extras,
                     check=post.check, system=post.system)


def widen_failed(post: Posterior, check: Check, box: ThetaBox | None = None) -> Posterior:
    """``post`` with ``check``; when the check fails, spread at least the prior's.

    A failed check means the model, at the parameters the method reports, does not explain the
    observation (a hovering ball, random points, physics that is not ours): the mean is kept,
    the standard deviation becomes at least the prior's (``PRIOR_STD``) and the samples (if
    any) are replaced by as many uniform prior draws (seeded), so every interval
    (``Posterior.interval``) holds at least the central 90% of the prior box. ``extras["check_failed"]`` says so.
    ``box``: the prior with the user's ranges and held values (:class:`ThetaBox`; None: the
    prior's).
    """
    if check.ok:
        post.check = check  # in place: a subclass's lazy samples stay lazy
        return post
    check = dataclasses.replace(check, note=check.note or WIDENED_NOTE)
    box = PRIOR_BOX if box is None else box
    prior_std = np.broadcast_to(box.std, np.shape(post.std))
    extras = {**post.extras, "check_failed": True}
    samples = post.samples
    if samples is not None:
        # as many draws from the uniform prior (seeded): intervals and quantiles the prior's
        samples = box.sample(len(samples), np.random.default_rng([29, len(samples)]))
    return Posterior(mean=np.asarray(post.mean), std=np.maximum(post.std, prior_std),
                     samples=samples, extras=extras, check=check, system=post.system)


#: the model explains a track only roughly when its best fit's residual RMS is at most this share
#: of the track's own spread (the RMS of the seen positions about their mean); beyond it (random
#: points, a ball hovering mid-air) the misfit is the track and nothing is left to measure
DISCREPANCY_MAX_SHARE = 0.1


#: how :func:`widen_to_support` widens when even the best fit fails: None, to the prior
#: (:func:`widen_failed`, the default); else the ``reading`` of :func:`widen_by_discrepancy`.
#: Off by default: on physics that is not ours the best fit's e and d are biased by more than
#: any reading of its residuals says (docs/reliability.md, "Widening by a measured model
#: discrepancy")
DISCREPANCY_READING: str | None = None


def residual_tau(resid: np.ndarray) -> float:
    """Integrated autocorrelation time (frames, >= 1) of a best fit's residuals.

    ``resid`` (T, 2), metres, NaN where unseen: per coordinate, the seen residuals in frame
    order, their autocorrelation about zero (a constant offset is a perfectly correlated misfit,
    not noise) ``c_k = sum r_t r_{t+k} / sum r_t^2``, and ``tau = 1 + 2 sum_k c_k`` summed while
    ``c_k`` stays positive (the initial positive sequence: the noisy tail adds only noise);
    the coordinates' taus weighted by their sums of squares. White noise gives ~1; a misfit
    that drifts over ``m`` frames gives ~``m``. Never more than the seen frames.
    """
    resid = np.asarray(resid, dtype=np.float64)
    if resid.ndim != 2 or resid.shape[1] != 2:
        raise ValueError(f"resid: expected shape (T, 2), got {resid.shape}")
    taus, weights = [], []
    for j in range(2):
        r = resid[:, j]
        r = r[np.isfinite(r)]
        ss = float(np.sum(r * r))
        if r.size < 2 or ss <= 0.0:
            continue
        tau = 1.0
        for k in range(1, r.size):
            c = float(np.dot(r[:-k], r[k:])) / ss
            if c <= 0.0:
                break
            tau += 2.0 * c
        taus.append(min(tau, float(r.size)))
        weights.append(ss)
    if not taus:
        return 1.0
    return float(max(np.average(taus, weights=weights), 1.0))


def _discrepancy_std(sim: CountingSimulator, track: Track, best: np.ndarray, state0: np.ndarray,
                     noise_eff: float) -> np.ndarray:
    """Marginal std (4,) of the parameters at the best fit with ``noise_eff`` as the noise:
    Laplace, ``(J^T J / noise_eff^2 + P)^-1`` with ``J`` the seen positions' forward-difference
    Jacobian in the parameters and (unless known) the initial state (one batch of 5 or 9
    simulations, stepping inwards at the prior's bounds) and ``P`` the prior's precision
    (``1 / PRIOR_STD^2``; for the start, that of its box, :func:`state0_half`)."""
    best = np.asarray(best, dtype=np.float64)
    s0 = np.asarray(state0, dtype=np.float64)
    free = not track.state0_known
    h_t = 1e-6 * physics.PRIOR_SPAN
    h_t = np.where(best + h_t <= physics.PRIOR_HI, h_t, -h_t)
    th = np.repeat(best[None], 5 + 4 * free, axis=0)
    st = np.repeat(s0[None], len(th), axis=0)
    th[1:5] += np.diag(h_t)
    steps = list(h_t)
    prec = list(1.0 / PRIOR_STD ** 2)
    if free:
        half = state0_half(track)
        h_s = 1e-6 * half
        st[5:] += np.diag(h_s)
        steps += list(h_s)
        prec += list(1.0 / half ** 2)
    pos = sim.positions(th, clip_state(st, track.floor), track.n_frames, track.dt,
                        float(track.floor))[:, track.mask].reshape(len(th), -1)
    J = ((pos[1:] - pos[0]) / np.asarray(steps)[:, None]).T
    A = J.T @ J / float(noise_eff) ** 2 + np.diag(prec)
    cov = np.linalg.pinv(A)
    return np.sqrt(np.clip(np.diag(cov)[:4], 0.0, None))


def widen_by_discrepancy(post: Posterior, check: Check, sim: CountingSimulator, track: Track,
                         best: np.ndarray, state0: np.ndarray, seed: int = 0,
                         reading: str = "tau") -> Posterior:
    """``post`` widened by the model discrepancy its best fit measures, when the check fails
    even at the best fit; the prior (:func:`widen_failed`) where nothing can be measured.

    The best fit ``best`` (4,) from ``state0`` (4,) (:func:`refine_fit`) is simulated (counted
    by ``sim``) and its residuals over the seen frames measured: their RMS ``rho`` and their
    integrated autocorrelation time ``tau`` (:func:`residual_tau`). Read as noise, the misfit
    has the variance ``rho^2`` and only ``n / tau`` of the ``n`` residuals are independent, so
    it weighs as white noise of ``noise_eff = rho * sqrt(tau)`` would. ``reading`` says how the
    spread follows from it: ``"tau"``, the Laplace posterior at the best fit with that noise
    (:func:`_discrepancy_std`: its Jacobian, the start marginalised, the prior's precision
    added); ``"worst"``, the same with ``tau = n`` (``noise_eff = rho * sqrt(n)``: the shift
    of the linearised fit under a misfit of the measured size in its worst shape: one std
    is where the linearised sum of squares doubles); ``"scale"``, the
    method's own std times ``noise_eff / sigma``. Each parameter's std becomes the largest of
    the method's own, that spread and its distance from the best fit
    (its interval holds the best fit, as :func:`widen_to_support`'s), at most the prior's
    (``PRIOR_STD``). The samples (if any) are stretched about the mean by the same factors
    (clipped to the prior box, and further where their 90% interval still missed the best
    fit); a parameter whose std reached the prior's, or that the best fit cannot inform
    beyond ``noise_eff`` (:func:`uninformed`, 8 simulations), gets the prior (uniform draws,
    seeded by ``seed``). The verdict stays failed; ``check.note`` says what was measured and
    ``extras["discrepancy"]`` holds ``rms_m`` (rho), ``tau``, ``noise_m`` (noise_eff),
    ``factor`` (noise_eff over the assumed noise ``check.noise_m``), ``reading``,
    ``spread_std`` (4,, the spread the reading gave) and
    ``prior`` (the parameters given the prior).

    Falls back to the prior (:func:`widen_failed`) when the model explains nothing of the
    track: ``rho`` above :data:`DISCREPANCY_MAX_SHARE` of the track's spread (random points,
    a ball hovering mid-air), fewer than 3 seen frames, or a still track.
    """
    if reading not in ("tau", "worst", "scale"):
        raise ValueError(f"reading: expected 'tau', 'worst' or 'scale', got {reading!r}")
    best = np.asarray(best, dtype=np.float64)
    resid = _residuals(sim, best, state0, track.floor, track)
    m = track.mask
    seen = track.positions[m]
    r = resid[m].ravel()
    sigma = float(check.noise_m)
    if seen.shape[0] < 3 or not np.all(np.isfinite(r)) or not sigma > 0:
        return widen_failed(post, check)
    rho = float(np.sqrt(np.mean(r * r)))
    spread = float(np.sqrt(np.mean(np.var(seen, axis=0))))
    if not rho <= DISCREPANCY_MAX_SHARE * spread:
        return widen_failed(post, check)
    tau = residual_tau(resid)
    noise_eff = max(rho, sigma) * float(np.sqrt(r.size if reading == "worst" else tau))
    mean = np.asarray(post.mean, dtype=np.float64)
    old = np.asarray(post.std, dtype=np.float64)
    if reading == "scale":
        lap = old * (noise_eff / sigma)
    else:
        lap = _discrepancy_std(sim, track, best, state0, noise_eff)
    std = np.minimum(np.maximum(np.maximum(old, lap), np.abs(best - mean)), PRIOR_STD)
    flat = (std >= PRIOR_STD) | uninformed(sim, best, state0, track.floor, track, noise_eff)
    std = np.where(flat, PRIOR_STD, std)
    samples = post.samples
    if samples is not None:
        samples = np.asarray(samples, dtype=np.float64)
        ratio = np.where(old > 0, std / np.where(old > 0, old, 1.0), 1.0)
        samples = mean + (samples - mean) * ratio
        # a parameter the method gave no spread: Gaussian draws of the new std (seeded)
        point = (old <= 0) & (std > 0)
        if point.any():
            z = np.random.default_rng([seed, 37]).standard_normal((len(samples), 4))
            samples[:, point] = (mean + z * std)[:, point]
        samples = np.clip(samples, physics.PRIOR_LO, physics.PRIOR_HI)
        # the interval read from the samples holds the best fit too (a skewed cloud may not)
        lo, hi = np.quantile(samples, [0.05, 0.95], axis=0)
        for j in np.flatnonzero(((best < lo) | (best > hi)) & ~flat):
            side = lo[j] if best[j] < lo[j] else hi[j]
            if side != mean[j]:
                f = 1.05 * abs(best[j] - mean[j]) / abs(side - mean[j])
                samples[:, j] = np.clip(mean[j] + (samples[:, j] - mean[j]) * f,
                                        physics.PRIOR_LO[j], physics.PRIOR_HI[j])
        if flat.any():
            u = np.random.default_rng([seed, 31]).random((len(samples), 4))
            prior = physics.PRIOR_LO + u * physics.PRIOR_SPAN
            samples[:, flat] = prior[:, flat]
    k = noise_eff / sigma
    note = (f"the posterior mean misses the track by {check.rms_m:.3g} m RMS and the best fit "
            f"by {rho:.3g} m, correlated over {tau:.3g} frames: intervals widened as for "
            f"white noise of {noise_eff:.3g} m ({k:.3g} x the {sigma:.3g} m assumed), to hold "
            f"the best fit, at most the prior's")
    check = dataclasses.replace(check, note=note)
    extras = {**post.extras, "check_failed": True, "support_fit": best.tolist(),
              "discrepancy": {"rms_m": rho, "tau": tau, "noise_m": noise_eff, "factor": k,
                              "reading": reading, "spread_std": lap.tolist(),
                              "prior": [p for p, f in zip(physics.PARAMS, flat) if f]}}
    return Posterior(mean=mean, std=std, samples=samples, extras=extras, check=check,
                     system=post.system)


#: simulations the search for what the data supports may use (:func:`widen_to_support`)
SUPPORT_SIMS = 450
#: the checks' least-squares tolerance (:func:`refine_fit`'s ``tol``)
CHECK_TOL = 1e-4


def widen_to_support(post: Posterior, check: Check, sim: CountingSimulator, track: Track,
                     state0: np.ndarray, floor: float, start=None,
                     info: dict | None = None, max_sims: int = SUPPORT_SIMS,
                     seed: int = 0) -> Posterior:
    """``post`` with ``check``; when it fails, intervals widened to what the data supports.

    A failed check says the posterior mean does not reproduce the track. Whether the model can
    reproduce it at all is asked by a local least-squares fit from the posterior mean (and
    ``state0``; the start is fitted too unless known), :func:`refine_fit`, at most
    ``max_sims`` (:data:`SUPPORT_SIMS`) simulations. If that best fit passes the same check, the data support
    the model near the method's answer: each parameter's std grows to at least its distance
    from the best fit (so the 90% interval holds the best fit), the samples are stretched
    about the mean by the same factors, and ``check.note`` says so (the verdict stays failed,
    with the posterior mean's RMS). If even the best fit fails, the model does not explain the
    observation and the spread becomes at least the prior's (:func:`widen_failed`); with
    :data:`DISCREPANCY_READING` set, the intervals are instead widened by the discrepancy the
    best fit measures (:func:`widen_by_discrepancy`, seeded by ``seed``; off by default: on
    the perturbed cases it held too few truths, docs/reliability.md). ``start``:
    ``(theta, state0)`` to fit from instead (the region check's best fit inside the 90% box).
    ``info`` receives the best fit's ``"theta"``, ``"state0"`` and ``"rms"`` (when it ran).
    """
    if check.ok:
        post.check = check
        return post
    theta0 = post.mean
    if start is not None:
        theta0, state0 = start
    if track.state0_known:
        lo_s = hi_s = None
        s0 = track.state0
    else:
        lo_s, hi_s = state0_box(track)
        s0 = np.clip(np.asarray(state0, dtype=np.float64), lo_s, hi_s)
    box = box_of(track)
    try:
        best, s0_best, rms = refine_fit(sim, track, np.clip(theta0, box.lo, box.hi),
                                        s0, lo_s, hi_s, max_sims, tol=CHECK_TOL)
    except ValueError:
        return widen_failed(post, check, box)
    if info is not None:
        info.update(theta=best, state0=s0_best, rms=rms)
    # judged on the floor the fit used
    if not model_check(sim, best, s0_best, track.floor, track, check.noise_m).ok:
        if DISCREPANCY_READING is None:
            return widen_failed(post, check, box)
        return widen_by_discrepancy(post, check, sim, track, best, s0_best, seed=seed,
                                    reading=DISCREPANCY_READING)
    std = np.maximum(post.std, np.abs(best - post.mean))
    samples = post.samples
    if samples is not None:
        samples = np.asarray(samples, dtype=np.float64)
        ratio = np.where(post.std > 0, std / np.where(post.std > 0, post.std, 1.0), 1.0)
        samples = post.mean + (samples - post.mean) * ratio
        samples = np.clip(samples, box.lo, box.hi)
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


def _residuals(sim: CountingSimulator, theta, state0, floor: float, track: Track) -> np.ndarray:
    """Residuals (T, 2) of the one trajectory of ``theta`` (4,) from ``state0`` (4,) against
    ``track``'s positions, NaN where unseen (1 simulation, counted by ``sim``)."""
    traj = sim.positions(np.asarray(theta, dtype=np.float64)[None],
                         clip_state(np.asarray(state0, dtype=np.float64)[None], floor),
                         track.n_frames, track.dt, float(floor))[0]
    return track_residuals(traj, track)


def track_residuals(traj: np.ndarray, track: Track) -> np.ndarray:
    """Residuals (T, 2) of a simulated trajectory ``traj`` (T, 2) against ``track``'s
    positions, NaN where unseen."""
    m = track.mask[:, None]
    return np.where(m, traj - np.where(m, track.positions, 0.0), np.nan)


def _judge(sim: CountingSimulator, theta, state0, floor: float, track: Track,
           noise_m: float) -> Check:
    """:class:`Check` of the one trajectory of ``theta`` (4,) from ``state0`` (4,) (1 simulation)."""
    return Check.from_residuals(_residuals(sim, theta, state0, floor, track), float(noise_m))


def model_check(sim: CountingSimulator, theta: np.ndarray, state0: np.ndarray, floor: float,
                track: Track, noise_m: float, fit_state0: bool = False,
                info: dict | None = None, try_start: bool = False,
                max_sims: int = CHECK_STATE_SIMS) -> Check:
    """:class:`Check` of the trajectory of ``theta`` (4,) from ``state0`` (4,) over ``track``.

    Simulates that one trajectory (counted by ``sim``) and judges its residual RMS over the
    seen frames against ``noise_m`` (:meth:`Check.from_residuals`). ``fit_state0``: for a
    method that holds an estimated initial state fixed (bo, sindy), the start is first fitted
    by least squares with ``theta`` held (:func:`refine_fit`, at most
    ``max_sims`` (:data:`CHECK_STATE_SIMS`) simulations, inside :func:`state0_box`): the check
    then asks
    whether the posterior-mean parameters explain the track, not whether a finite-difference
    start does (from the tracked start, 200 frames of a clean video drift by metres).
    ``try_start``: ``state0`` is a warm start (the fitted start of the previous prefix, which
    differs by a frame): it is judged as it is first and the fit is skipped when it passes.
    ``info``: a dict that receives the start used (``"state0"``).
    """
    if fit_state0 and not track.state0_known:
        lo, hi = state0_box(track)
        state0 = np.clip(np.asarray(state0, dtype=np.float64), lo, hi)
        if try_start:
            check = _judge(sim, theta, state0, floor, track, noise_m)
            if check.ok:
                if info is not None:
                    info["state0"] = state0
                return check
        _, state0, _ = refine_fit(sim, track, theta, state0, lo, hi, max_sims,
                                  fit_theta=False, tol=CHECK_TOL)
    if info is not None:
        info["state0"] = np.asarray(state0, dtype=np.float64)
    return _judge(sim, theta, state0, floor, track, noise_m)


#: ``Check.note`` of a failed check that did not search (:func:`check_prefixes`)
UNSEARCHED_NOTE = ("intervals widened to at least the prior's: no fit found explained the "
                   "frames before these, so none can explain these (not searched again)")
#: the posterior's central interval the region check searches (:func:`region_box`)
REGION_LEVEL = 0.9
#: simulations the region check's bounded refit may use (a batch of 9 per step: the four
#: parameters and the four initial-state coordinates free)
REGION_SIMS = 180
#: the budget of each search (the start's, the region's, the support's) that starts warm, from
#: the previous prefix's fits (:func:`check_prefixes`): a frame more moves the optimum little
WARM_SIMS = 90
#: the parts of the track the region refit fits in turn (continuation)
REGION_STAGES = (0.25, 0.5, 1.0)
#: ``Check.note`` of a check passed by the posterior mean's own trajectory
MEAN_NOTE = "passes at the posterior mean"
#: ``Check.note`` (its start) of a check passed by a parameter vector inside the 90% interval
REGION_NOTE = "passes inside the 90% interval"


def region_box(post: Posterior, level: float = REGION_LEVEL,
               box: ThetaBox | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The posterior's central ``level`` box ``(lo, hi)``, (4,) each, inside the prior box.

    Per parameter, the interval a user reads (:meth:`Posterior.interval`): the samples'
    ``(1 - level) / 2`` and ``(1 + level) / 2`` quantiles when there are samples, else
    ``mean -/+ z std`` (1.645 std at 90%); an infinite or NaN side is the prior's bound.
    """
    b = PRIOR_BOX if box is None else box
    lo, hi = post.interval(level)
    lo = np.clip(np.where(np.isnan(lo), b.lo, lo), b.lo, b.hi)
    hi = np.clip(np.where(np.isnan(hi), b.hi, hi), b.lo, b.hi)
    return np.minimum(lo, hi), np.maximum(lo, hi)


def region_check(sim: CountingSimulator, post: Posterior, track: Track, state0: np.ndarray,
                 noise_m: float, witness=None, info: dict | None = None,
                 max_sims: int = REGION_SIMS) -> Check:
    """Does a parameter vector inside the posterior's 90% box explain the track?

    A bounded least-squares refit (:func:`refine_fit`): ``theta`` inside :func:`region_box`,
    the initial state free in :func:`state0_box` (held when known), from the posterior mean
    (clipped into the box) and ``state0``, by continuation (the first quarter of the track,
    then half, then all of it, :data:`REGION_STAGES`, at most ``max_sims`` simulations
    each: a long track's bounces make the landscape rough far from the optimum). The fit's
    trajectory is judged against ``noise_m`` as the mean's is (on ``track.floor``).
    ``witness``: ``(theta, state0)`` fitted to a neighbouring prefix (one frame shorter): it is
    judged first (clipped into the box; 1 simulation), and when it fails the refit starts from
    it on the whole track in one stage. ``info`` receives the judged ``"theta"`` and
    ``"state0"``.

    A wide posterior whose mean drifts off the track across bounces passes when its interval
    holds parameters that fit; a narrow one off the truth cannot move far enough and fails.
    """
    lo_t, hi_t = region_box(post, box=box_of(track))
    theta = np.clip(np.asarray(post.mean, dtype=np.float64), lo_t, hi_t)
    s0 = np.asarray(state0, dtype=np.float64)
    stages = REGION_STAGES
    if witness is not None:
        theta = np.clip(np.asarray(witness[0], dtype=np.float64), lo_t, hi_t)
        s0 = np.asarray(witness[1], dtype=np.float64)
        stages = (1.0,)
    if track.state0_known:
        lo_s = hi_s = None
        s0 = track.state0
    else:
        lo_s, hi_s = state0_box(track)
        s0 = np.clip(s0, lo_s, hi_s)
    if witness is not None:
        check = _judge(sim, theta, s0, track.floor, track, noise_m)
        if check.ok:
            if info is not None:
                info.update(theta=theta, state0=s0)
            return check
    for frac in stages:
        m = max(int(np.ceil(frac * track.n_frames)), min(track.n_frames, 3))
        part = track if m >= track.n_frames else dataclasses.replace(
            track, positions=track.positions[:m], mask=track.mask[:m])
        if part.mask.sum() < 3:
            continue
        theta, s0, _ = refine_fit(sim, part, theta, s0, lo_s, hi_s, max_sims, tol=CHECK_TOL,
                                  theta_box=(lo_t, hi_t))
    if info is not None:
        info.update(theta=theta, state0=s0)
    return _judge(sim, theta, s0, track.floor, track, noise_m)


def check_posterior(post: Posterior, sim: CountingSimulator, track: Track, state0: np.ndarray,
                    floor: float, noise_m: float, *, fit_state0: bool = False, seed: int = 0,
                    try_start: bool = False, witness=None, support_start=None,
                    search: bool = True, info: dict | None = None) -> Posterior:
    """``post`` with its model check, a check of the posterior rather than of one point.

    1. The posterior mean's trajectory from ``state0`` (fitted first with ``fit_state0``,
       judged from ``state0`` as it is first with ``try_start``; :func:`model_check`).
    2. If it fails, :func:`region_check` (from ``witness`` when given): a parameter vector
       inside the 90% interval box, with its own fitted start. Either passing passes;
       ``Check.note`` says which (:data:`MEAN_NOTE`, :data:`REGION_NOTE`) and ``Check.rms_m``
       is the RMS of the trajectory that passed.
    3. Passed: parameters the track cannot inform at the passing trajectory are widened to the
       prior (:func:`uninformed`, :func:`widen_uninformed` with ``seed``). Failed: the intervals
       are widened to what the data supports (:func:`widen_to_support`, from ``support_start``
       or the region's best fit); the verdict stays failed with the posterior mean's RMS.

    ``try_start`` (a warm start from the previous prefix) also limits each search to
    :data:`WARM_SIMS` simulations. ``search=False`` (:func:`check_prefixes`, when the prefix
    before was explained by nothing
    it searched): the mean is judged from ``state0`` only (1 simulation) and a failure widens
    to the prior (:func:`widen_failed`) without searching. All simulations are counted by
    ``sim``. ``info`` receives, for the next prefix: the judged ``"theta"`` and ``"state0"``,
    the region's and the support's fits (``"region"``, ``"support"``: ``(theta, state0)`` or
    None) and ``"best_sse"``, the smallest sum of squared residuals (m^2) found (NaN if none).
    """
    info = {} if info is None else info
    m_info: dict = {}
    budget = {} if not try_start else {"max_sims": WARM_SIMS}
    check = model_check(sim, post.mean, state0, floor, track, noise_m,
                        fit_state0=fit_state0 and search, info=m_info, try_start=try_start,
                        **budget)
    theta, s0, fl = np.asarray(post.mean, dtype=np.float64), m_info["state0"], float(floor)
    info.update(region=None, support=None, best_sse=check.rms_m ** 2 * check.n)
    if check.ok:
        check = dataclasses.replace(check, note=MEAN_NOTE)
    elif search:
        r_info: dict = {}
        region = region_check(sim, post, track, s0, noise_m, witness=witness, info=r_info,
                              **budget)
        info["region"] = (r_info["theta"], r_info["state0"])
        info["best_sse"] = min(info["best_sse"], region.rms_m ** 2 * region.n)
        post.extras["region_box"] = [b.tolist() for b in region_box(post, box=box_of(track))]
        post.extras["region_rms_m"] = region.rms_m
        post.extras["mean_rms_m"] = check.rms_m
        if region.ok:
            note = (f"{REGION_NOTE}: the posterior mean misses the track by {check.rms_m:.3g} m "
                    f"RMS, a parameter vector inside the interval explains it "
                    f"({region.rms_m:.3g} m RMS)")
            check = dataclasses.replace(region, note=note)
            theta, s0, fl = r_info["theta"], r_info["state0"], float(track.floor)
    info.update(theta=theta, state0=s0)
    if check.ok:
        # a track that cannot inform a parameter (a ball at rest: e, g, d) supports no
        # interval narrower than the prior's, however the method ended up
        flat = uninformed(sim, theta, s0, fl, track, noise_m)
        post = widen_uninformed(post, flat, seed=seed, box=box_of(track))
        post.check = check  # in place: a subclass's lazy samples stay lazy
        return post
    if not search:
        return widen_failed(post, dataclasses.replace(check, note=UNSEARCHED_NOTE), box_of(track))
    s_info: dict = {}
    post = widen_to_support(post, check, sim, track, s0, fl,
                            start=support_start or info["region"], info=s_info, seed=seed,
                            **budget)
    if s_info:
        info["support"] = (s_info["theta"], s_info["state0"])
        info["best_sse"] = min(info["best_sse"], s_info["rms"] ** 2 * check.n)
    return post


def refine_fit(sim: CountingSimulator, track: Track, theta0, s00, lo_s, hi_s, max_sims: int,
               fit_theta: bool = True, tol: float = 1e-8, theta_box=None):
    """Local least squares from ``theta0`` (4,), ``s00`` (4,); returns ``(theta, state0, rms)``.

    Coordinates: the parameters mapped to [0, 1] by the prior (held at ``theta0`` when
    ``fit_theta`` is False; kept inside ``theta_box = (lo, hi)``, (4,) each in physical units
    within the prior, when given: the region check's box), then (when ``lo_s`` is not None) the
    initial state mapped to [0, 1] by its box ``[lo_s, hi_s]`` (held at ``s00`` otherwise).
    Residuals are the seen coordinates'
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
    box = box_of(track)
    theta0 = np.asarray(theta0, dtype=np.float64)
    s00 = np.asarray(s00, dtype=np.float64)
    # the parameters fitted: all four but the held ones (the user's known values)
    free_t = np.flatnonzero(~box.held) if fit_theta else np.empty(0, dtype=int)
    if fit_theta and box.held.any():
        theta0 = box.hold_samples(theta0[None].copy())[0]
        if free_t.size == 0 and not free:  # everything held: nothing to fit
            return theta0, s00, float(np.sqrt(np.mean(
                (sim.positions(theta0[None], s00[None], track.n_frames, track.dt, track.floor)
                 [0, track.mask] - track.positions[track.mask]) ** 2)))
        fit_theta = free_t.size > 0
    nt = free_t.size
    D = nt + (4 if free else 0)
    mask = track.mask
    obs = track.positions[mask].ravel()
    span_s = (hi_s - lo_s) if free else None
    # bounds in the optimiser's coordinates: [0, 1] but the theta box's (never empty: a
    # zero-width side is opened by 1e-9 so the optimiser's strict bounds hold)
    lb, ub = np.zeros(D), np.ones(D)
    if fit_theta and theta_box is not None:
        lb[:nt] = np.clip(box.normalise(np.asarray(theta_box[0], np.float64))[free_t], 0.0, 1.0)
        ub[:nt] = np.clip(box.normalise(np.asarray(theta_box[1], np.float64))[free_t], 0.0, 1.0)
        lb[:nt] = np.minimum(lb[:nt], ub[:nt])
        point = ub[:nt] - lb[:nt] < 1e-9
        lb[:nt] = np.where(point, np.minimum(lb[:nt], 1.0 - 1e-9), lb[:nt])
        ub[:nt] = np.where(point, lb[:nt] + 1e-9, ub[:nt])
    u_held = box.normalise(theta0)  # the held parameters' unit coordinates (their values)

    def unpack(U):
        if fit_theta:
            uu = np.repeat(u_held[None], len(U), axis=0)
            uu[:, free_t] = np.clip(U[:, :nt], lb[:nt], ub[:nt])
            th = box.hold_samples(box.denormalise(uu)) if box.known else box.denormalise(uu)
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
        x0[:nt] = box.normalise(theta0)[free_t]
    if free:
        x0[nt:] = np.where(span_s > 0, (s00 - lo_s) / np.where(span_s > 0, span_s, 1.0), 0.5)
    x0 = np.clip(x0, lb, ub)
    h = 1e-6
    cache = {}

    def fun(x):
        key = x.tobytes()
        if key not in cache:
            # the point and its D forward steps in one batch (stepping inwards at a bound)
            steps = np.where(x + h <= ub, h, -h)
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
        res = least_squares(fun, x0, jac=jac, bounds=(lb, ub), method="trf",
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
        """The posterior with its model check (:func:`check_posterior`: the mean, else a
        parameter vector inside the 90% interval; failed: :func:`widen_to_support`;
        parameters the track cannot inform widened to the prior, :func:`uninformed`);
        the check's simulations are in ``extras["check_simulations"]``, not in
        ``n_simulations``. With the user's knowledge (``track.box``) the check judges the
        trajectories of the held values and searches and widens inside the user's ranges; the
        held parameters come back exact (:meth:`ThetaBox.hold`)."""
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
        post = check_posterior(self.posterior, sim, self.track, s0, float(fl), noise,
                               fit_state0=self.check_fits_state0, seed=self.track.n_frames)
        post.extras["check_simulations"] = sim.n_simulations
        if self.track.box is not None:  # the user's held values exact, whatever the widening
            post = self.track.box.hold(post)
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
