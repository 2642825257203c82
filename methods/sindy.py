"""``sindy``: sparse regression (pysindy) on the free-flight pieces of the track, plus contacts.

One smooth ODE cannot pass through a bounce, so the track is first split where contacts are
(:func:`methods._tracks.segment_track`: second-difference impulses mark floor and wall hits, a
still, lowest stretch marks rolling). Then:

* ``g`` and ``d``: pysindy fits the velocities ``(vx, vy)`` of all free-flight segments together
  (a list of trajectories) with STLSQ on a library ``[1, |v| vx, |v| vy]`` -- a bias and the two
  quadratic drag terms. The physics says ``vx' = -d |v| vx`` and ``vy' = g - d |v| vy``, so ``g``
  is the bias of the ``vy`` equation and ``d`` the drag coefficient, read from both equations
  and combined with weights ``sum(feature^2)`` (the joint least-squares value). Velocities and
  accelerations come from pysindy's differentiation of positions (4th-order finite differences,
  or Savitzky-Golay smoothed ones for noisy tracks with ``smoothing_window``). A segment whose
  heights do not curve as a ball in flight does (:func:`free_flight`: the ball sliding on the
  floor at a wobbling tracked height) is left out: it reads ``g ~ 0``.
* ``e``: at each floor bounce, the ratio of vertical velocities after and before, where fits of
  the flights on either side (up to 15 frames each) meet, with its standard error propagated
  from the fits (:func:`bounce_ratios`); pooled by inverse variance, a ratio far from the others
  dropped (:func:`pool_ratios`).
* ``r``: the deceleration of ``x`` in the rolling phase (quadratic fit per rolling run, between
  wall contacts). Not seen (no rolling yet) -> the prior, with the prior's std.

Standard errors: ``g``/``d`` from the regression (residual variance times ``(Theta^T Theta)^-1``
on the identified support, inflated by ``sqrt(3)`` because finite-difference accelerations of
neighbouring frames share positions and are not independent), and never below the
delete-one-block jackknife over blocks of one stencil's frames within the segments (three blocks
or more; :func:`_segment_jackknife`): errors that a segment's frames share (its smoothing, its
ends) show only there. ``e`` from the pool (scaled up by the ratios' scatter when they disagree
beyond their errors); ``r`` from the fit. Estimates are clipped into the prior box (so they can
be simulated); a clipped estimate's std grows by the distance it was moved (up to the prior's
std), so an estimate the data pushed out of the box is not reported as a confident one at the
edge. A parameter the track does not inform reports the prior mean and std.

Outliers: before anything else, a seen position further from the running median of its
neighbours (5 seen frames) than any real ball could be -- the largest speed times the frames
between them, plus 0.1 m -- is marked unseen (``extras["n_outliers"]``). The largest speed is
the larger of the prior's bound (|v0| <= 8.9 m/s falling 10 m at |g| = 12.81: 18.3 m/s) and
twice the track's upper-quartile frame-to-frame speed. One 1000 m outlier used to move the
floor estimate to -1000 m and give a confident, wrong posterior (issue 14).

Forecast: the identified hybrid model is :func:`sysid_bench.core.physics.simulate` run from the state
estimated at the last seen frame, for ``n_forecast`` draws of parameters and state from their
standard errors.

Model check (``Posterior.check``, :func:`methods._simulation.check_posterior`): the posterior
mean simulated with our physics from the start that fits it best (the tracked start refitted by
least squares with the parameters held) against the seen positions, judged against the
harness's tracking noise ``DEFAULT_SIGMA``; when it misses, a parameter vector inside the 90%
intervals with its own start may pass instead. Read from derivatives, the mean rarely
reproduces a whole clip within 2 cm (on the report's 20 clean test videos its 200-frame
trajectory missed by 0.76 m RMS median); where the intervals are wide enough to hold a fit the
check passes inside them, elsewhere it fails and the intervals are widened to what the data
supports (:func:`methods._simulation.widen_to_support`: to hold the best fit found, or to the
prior's when even that fit fails).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from methods._simulation import (
    Stopwatch,
    check_posterior,
    forecast_by_simulation,
    make_rng,
    one_blas_thread,
)
from methods._tracks import clip_state, prepare, segment_track
from sysid_bench.core._validate import check_number, check_positive_int
from sysid_bench.core.estimator import (
    Estimator,
    Forecast,
    Observation,
    Posterior,
    observed_positions,
)
from sysid_bench.core.physics import PRIOR_HI as HI
from sysid_bench.core.physics import PRIOR_LO as LO
from sysid_bench.core.physics import PRIOR_MEAN, PRIOR_STD
from sysid_bench.core.simulator import DEFAULT_SIGMA, CountingSimulator

__all__ = ["SINDy", "bounce_ratios", "free_flight", "pool_ratios", "reject_outliers"]

_FEATURES = ("1", "|v|vx", "|v|vy")
_CLEAN_NOISE = 1e-3  # m; below this a track is "clean" and needs no smoothing
_TUNED_DT = 0.05  # s; the default windows were chosen on 20 frames/s tracks


def _window_at(w: int, dt: float) -> int:
    """A default smoothing window of ``w`` frames at 20 frames/s held as the same span of time
    at a faster capture's ``dt`` (odd; never narrower): 9 frames at 60 frames/s would smooth a
    third of the time, and a second derivative's noise grows as 1/dt^2 (a 60 fps pendulum, 1 cm
    noise: g -11.5 +- 1.7 with 11 frames, -9.78 +- 0.28 with 31; truth -9.74). Unchanged at
    20 frames/s and slower."""
    if not w or dt >= _TUNED_DT:
        return w
    return max(w, int(round(w * _TUNED_DT / dt)) // 2 * 2 + 1)
_CORR_INFLATION = np.sqrt(3.0)  # FD accelerations of adjacent frames share positions


#: Speed no ball from the prior can exceed, m/s: |v0| <= sqrt(8^2 + 4^2), then a 10 m fall at
#: the prior's largest |g| (energy never grows).
_PRIOR_SPEED = float(np.sqrt(8.0**2 + 4.0**2 + 2.0 * 12.81 * 10.0))
_OUTLIER_SLACK = 0.1  # m: tracking noise and the ball's radius of error on top of the motion


def reject_outliers(positions: np.ndarray, dt: float) -> np.ndarray:
    """Boolean mask (T,) of seen positions no real ball could be at: outliers.

    Each seen position is compared with the per-coordinate median of the window of 5 seen
    frames around it (fewer at the ends). The median is one of the window's positions, so on a
    real track it is within ``v_max * dt * k`` of the centre, ``k`` the most frames between the
    centre and the window's members; a larger distance (plus ``_OUTLIER_SLACK``) marks an outlier.
    Two neighbouring outliers in a window of 5 still leave the median on the track.

    Parameters
    ----------
    positions : ndarray, shape (T, 2)
        Metres, NaN = unseen.
    dt : float

    Returns
    -------
    ndarray, shape (T,), bool
    """
    out = np.zeros(len(positions), bool)
    idx = np.flatnonzero(np.isfinite(positions).all(axis=1))
    n = idx.size
    if n < 3:
        return out
    p = positions[idx]
    step = np.linalg.norm(np.diff(p, axis=0), axis=1) / (np.diff(idx) * dt)
    v_max = max(_PRIOR_SPEED, 2.0 * float(np.quantile(step, 0.75)))
    j = np.arange(n)
    lo = np.clip(j - 2, 0, max(n - 5, 0))  # windows of 5 (3 or 4 at short tracks), shifted at ends
    hi = np.minimum(lo + 5, n)
    for a in range(n):
        w = slice(lo[a], hi[a])
        med = np.median(p[w], axis=0)
        reach = v_max * dt * float(np.abs(idx[w] - idx[a]).max()) + _OUTLIER_SLACK
        out[idx[a]] = float(np.linalg.norm(p[a] - med)) > reach
    return out


#: frames of each flight fitted on either side of a bounce: a whole short hop, or the 15 frames
#: nearest the contact (on 30 tracked 28x28 training videos, seed 777: the ratios' error RMS
#: 0.108 against 0.77 from cubics on 5 frames, and their standard errors held 94% of the
#: truths at +/- 1.645)
_BOUNCE_FRAMES = 15
#: on a clean track (noise under 1 mm) the 5 frames nearest the contact, cubics: longer fits
#: there show drag's bias (-0.005 in e at 15 frames) and no noise to average away
_CLEAN_BOUNCE_FRAMES = 5
_OUTLIER_Z = 3.0  # a bounce ratio this many robust scatters off the median is dropped
_MIN_RATIO_SE = 2e-3


#: a run of "flight" frames whose height curves less than a quarter of the weakest gravity in
#: the prior (by 3 of its standard errors) is the ball sliding or rolling on the floor at a
#: tracked height that wobbles: on the report's test videos such runs read g ~ 0 and pulled the
#: pooled g toward 0 by up to 3.6 of its standard errors after 200 frames
_FLIGHT_CURVATURE = HI[1] / 4.0


def free_flight(runs, positions: np.ndarray, dt: float, noise: float) -> list[tuple[int, int]]:
    """The runs ``[(start, stop), ...]`` whose heights curve as a ball in flight does.

    A parabola fitted to each run's heights gives ``y'' = 2a`` and its standard error
    (residual scatter at least ``noise``); a run is kept unless ``2a`` lies above
    :data:`_FLIGHT_CURVATURE` by more than 3 standard errors (short, noisy runs are kept).
    """
    kept = []
    for a, b in runs:
        t = np.arange(a, b) * dt
        coef, cov = _side_fit(t - t.mean(), positions[a:b, 1], noise, deg=2)
        se = 2.0 * float(np.sqrt(cov[0, 0]))  # of y'' = 2a
        if 2.0 * float(coef[0]) - 3.0 * se <= _FLIGHT_CURVATURE:
            kept.append((a, b))
    return kept


def _side_fit(t: np.ndarray, y: np.ndarray, noise: float, deg: int):
    """Polynomial fit of heights ``y(t)``: coefficients (highest first) and their covariance,
    the residual variance (at least ``noise`` squared) times ``(X^T X)^-1``. (Least squares on
    the Vandermonde matrix, as the bounce fits were measured with; ``_tracks._polyfit`` is
    ``np.polyfit`` and moves the checks' searches in the last digits.)"""
    X = np.vander(t, deg + 1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ coef
    s2 = max(float(resid @ resid) / max(len(t) - deg - 1, 1), noise**2)
    return coef, s2 * np.linalg.pinv(X.T @ X)


def _contact_ratio(ca: np.ndarray, cb: np.ndarray, lo: float, hi: float) -> float:
    """``-v_out / v_in`` where the curves before (``ca``) and after (``cb``) meet in
    ``[lo, hi]`` (the meeting nearest its centre); NaN when they do not meet there or the
    velocities are not a fall and a rise."""
    roots = np.roots(np.polysub(ca, cb))
    roots = roots[np.abs(roots.imag) < 1e-9].real
    roots = roots[(roots >= lo - 1e-9) & (roots <= hi + 1e-9)]
    if roots.size == 0:
        return float("nan")
    tc = float(roots[np.argmin(np.abs(roots - 0.5 * (lo + hi)))])
    v_in = float(np.polyval(np.polyder(ca), tc))
    v_out = float(np.polyval(np.polyder(cb), tc))
    return -v_out / v_in if v_in < 0.0 < v_out else float("nan")


def bounce_ratios(positions: np.ndarray, dt: float, seg, noise: float,
                  k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertical velocity ratio at every floor bounce seen, and its standard error.

    Each pair of consecutive free-flight runs (``seg.flight_all``, 3 frames or more, that
    :func:`free_flight` keeps) at most 3 frames apart with a floor hit between them is one bounce. The heights of up to ``k`` frames
    on each side are fitted (:func:`_side_fit`), the contact is where the two curves meet in
    the gap, the ratio is ``-v_out / v_in`` there. The standard error propagates both fits'
    covariances through the whole computation, the contact time included (a numerical Jacobian
    of the ratio in the coefficients). Fits over whole hops, not the few frames at the contact,
    are what make this usable on video: 5-frame cubics gave ratios from 0.1 to 4.6.

    Parameters
    ----------
    positions : ndarray, shape (T, 2)
    dt : float
    seg : methods._tracks.Segments
    noise : float
        The track's position noise (m): the least residual scatter assumed.
    k : int, optional
        Frames fitted on each side; default 15, or 5 on a clean track (``noise`` < 1 mm).

    Returns
    -------
    ratios, se : ndarray, shape (n_bounces,)
    """
    ratios, ses = [], []
    runs = free_flight(seg.flight_all, positions, dt, noise)
    clean = noise < _CLEAN_NOISE
    if k is None:
        k = _CLEAN_BOUNCE_FRAMES if clean else _BOUNCE_FRAMES
    cubic_from = 5 if clean else 8
    for (a0, a1), (b0, b1) in zip(runs[:-1], runs[1:]):
        if b0 - a1 > 3 or not seg.floor_hit[max(a1 - 1, 0): b0 + 1].any():
            continue
        ia = np.arange(max(a0, a1 - k), a1)
        ib = np.arange(b0, min(b1, b0 + k))
        tm = 0.5 * (a1 - 1 + b0) * dt  # centred times: conditioning
        # a cubic takes up drag's curvature where there are frames enough for it
        ca, cov_a = _side_fit(ia * dt - tm, positions[ia, 1], noise, 3 if len(ia) >= cubic_from else 2)
        cb, cov_b = _side_fit(ib * dt - tm, positions[ib, 1], noise, 3 if len(ib) >= cubic_from else 2)
        lo, hi = (a1 - 1) * dt - tm, b0 * dt - tm
        r0 = _contact_ratio(ca, cb, lo, hi)
        if not np.isfinite(r0):
            continue
        var = 0.0
        for side, (c, cov) in enumerate(((ca, cov_a), (cb, cov_b))):
            jac = np.zeros(len(c))
            for j in range(len(c)):
                h = 1e-6 * max(1.0, abs(float(c[j])))
                cp = c.copy()
                cp[j] += h
                r = _contact_ratio(cp, cb, lo, hi) if side == 0 else _contact_ratio(ca, cp, lo, hi)
                jac[j] = (r - r0) / h if np.isfinite(r) else 0.0
            var += float(jac @ cov @ jac)
        ratios.append(r0)
        ses.append(max(float(np.sqrt(var)), _MIN_RATIO_SE))
    return np.asarray(ratios, dtype=np.float64), np.asarray(ses, dtype=np.float64)


def pool_ratios(ratios: np.ndarray, se: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Inverse-variance pool of bounce ratios: ``(mean, std, used)``.

    With three ratios or more, one further from their median than :data:`_OUTLIER_Z` standard
    errors, scaled by the ratios' own robust scatter (so a track whose every ratio scatters
    loses none), is dropped (a bounce in a corner, a hop mistaken for two). The pooled std is
    scaled up by ``sqrt(chi2 / dof)`` when the used ratios scatter more than their standard
    errors say (never down).

    Parameters
    ----------
    ratios, se : ndarray, shape (n,)

    Returns
    -------
    mean, std : float
    used : ndarray, shape (n,), bool
    """
    r = np.asarray(ratios, dtype=np.float64)
    se = np.asarray(se, dtype=np.float64)
    used = np.ones(r.size, bool)
    if r.size >= 3:
        z = np.abs(r - np.median(r)) / se
        used = z <= _OUTLIER_Z * max(1.4826 * float(np.median(z)), 1.0)
    w = 1.0 / se[used] ** 2
    m = float(np.sum(w * r[used]) / np.sum(w))
    n = int(used.sum())
    phi = float(np.sum(w * (r[used] - m) ** 2)) / (n - 1) if n >= 2 else 1.0
    return m, float(np.sqrt(max(phi, 1.0) / np.sum(w))), used


def _drag_x(a, b):
    return a * np.sqrt(a * a + b * b)


def _drag_y(a, b):
    return b * np.sqrt(a * a + b * b)


def _g_d(coef: np.ndarray, theta: np.ndarray) -> tuple[float, float]:
    """``(g, d)`` from the SINDy coefficients (2, 3): ``g`` the bias of ``vy'``, ``d`` the two
    drag coefficients combined with weights ``sum(feature^2)`` (the joint least-squares value;
    NaN when no flight frame moves)."""
    sxx = float(theta[:, 1] @ theta[:, 1])
    syy = float(theta[:, 2] @ theta[:, 2])
    d = -(coef[0, 1] * sxx + coef[1, 2] * syy) / (sxx + syy) if sxx + syy > 0 else float("nan")
    return float(coef[1, 0]), float(d)


def _blocks(lengths: list[int], size: int) -> list[int]:
    """Split segments of ``lengths`` frames into consecutive blocks of about ``size`` frames
    (at least one per segment; none straddles two): the jackknife's units."""
    out = []
    for n in lengths:
        k = max(n // max(size, 1), 1)
        out.extend(np.diff(np.linspace(0, n, k + 1).round().astype(int)).tolist())
    return out


def _segment_jackknife(coef: np.ndarray, theta: np.ndarray, acc: np.ndarray,
                       lengths: list[int]) -> np.ndarray | None:
    """Delete-one-block jackknife std ``(2,)`` of ``(g, d)``: the least squares on the
    identified support refitted without each block of frames in turn (:func:`_blocks`: within
    segments). ``None`` under 3 blocks (two leave-one-out values say next to nothing about a
    spread).

    Parameters
    ----------
    coef : ndarray, shape (2, 3)
        The fit on every segment (its zeros: the support).
    theta : ndarray, shape (N, 3)
        Library features of every flight frame, segments one after another.
    acc : ndarray, shape (N, 2)
    lengths : list of int
        Frames of each block, in order (summing to N).
    """
    S = len(lengths)
    if S < 3:
        return None
    edges = np.concatenate([[0], np.cumsum(lengths)])
    vals = []
    for j in range(S):
        keep = np.ones(len(theta), bool)
        keep[edges[j]:edges[j + 1]] = False
        c = np.zeros_like(coef)
        for k in range(2):
            active = np.flatnonzero(coef[k] != 0)
            if active.size:
                c[k, active] = np.linalg.lstsq(theta[keep][:, active], acc[keep, k], rcond=None)[0]
        vals.append(_g_d(c, theta[keep]))
    vals = np.asarray(vals)
    if not np.all(np.isfinite(vals)):
        return None
    return np.sqrt((S - 1) / S * np.sum((vals - vals.mean(axis=0)) ** 2, axis=0))


class SINDy(Estimator):
    """Hybrid SINDy: pysindy on free flight, velocity ratios at bounces, rolling deceleration
    (the ball); on another system, the system's feature library
    (:class:`methods._sindy_libraries.SINDyPoints`: the pendulum and the spring; n/a on the
    collision, whose parameters act only at contacts).

    Parameters
    ----------
    system : str
        ``"ball"`` or a system with a library (``systems``).
    threshold : float, optional
        STLSQ sparsity threshold on the coefficients (physical units; must stay below the
        smallest drag constant, 5e-4, or drag is thresholded away). None: 1e-4 on the ball, 0
        elsewhere (plain least squares: the libraries are minimal).
    smoothing_window : int, optional
        0 for plain 4th-order finite differences (clean positions); an odd number >= 5 for
        Savitzky-Golay (cubic) smoothed differences over that many frames (noisy positions);
        ``None`` picks 0 when the track's own noise estimate is below 1 mm, else 9 (on 20
        tracked 28x28 test videos: normalised MSE on e, g, d 0.096 with 0, 0.040 with 7,
        0.033 with 9, 0.038 with 11). Another system: None (the library's, 15) or an odd
        number >= 7 (order 4 Savitzky-Golay). None's windows are frames at 20 frames/s: a
        faster capture's window spans the same time (27 frames at 60 frames/s for 9).
    min_segment : int
        The ball only: shortest free-flight segment used, in frames.
    n_forecast : int
        Draws of parameters and last state simulated by ``forecast``.
    seed : int
        Seeds the forecast draws.
    """

    name = "sindy"
    #: why ``known``/``prior`` are refused (``methods.get``; issue 38 §4)
    knowledge_refused = (
        "its sparse regression fits a library's coefficients, not the parameters themselves, so a held value or a range has no place in it")
    input_kind = "positions"
    min_frames = 3
    forecasts = True
    cost = 4
    online_cost = True  # a row of the online-cost table (re-identifies every prefix)
    #: the ball and the systems with a feature library (methods._sindy_libraries.LIBRARIES)
    systems = ("ball", "pendulum", "spring")
    #: Systems with the hybrid library of this module (free flight between contacts, the
    #: contacts' ratios: the ball's floor and walls); the others in ``systems`` have a feature
    #: library in :mod:`methods._sindy_libraries`.
    own_library = ("ball",)
    #: ``threshold`` when None, by system (default 0: the libraries' coefficients are
    #: physical constants, none to prune); the ball's 1e-4 sits below its smallest drag, 5e-4.
    default_threshold = {"ball": 1e-4}

    def __init__(
        self,
        *,
        system: str = "ball",
        threshold: float | None = None,
        smoothing_window: int | None = None,
        min_segment: int = 5,
        n_forecast: int = 32,
        seed: int = 0,
    ):
        self.system = system
        self.threshold = threshold
        self.smoothing_window = smoothing_window
        self.min_segment = min_segment
        self.n_forecast = n_forecast
        self.seed = seed

    @classmethod
    def na_reason(cls, system: str) -> str:
        """Why sindy is n/a on ``system`` (not among ``systems``): said by ``methods.get``."""
        from methods._sindy_libraries import na_reason

        return na_reason(system)

    def _threshold(self):
        """``threshold``, None read as this system's default (1e-4 on the ball, else 0)."""
        if self.threshold is None:
            return self.default_threshold.get(self.system, 0.0)
        return self.threshold

    def _points(self):
        """The part for a system other than the ball (its feature library)."""
        from methods._sindy_libraries import SINDyPoints

        return SINDyPoints(system=self.system, threshold=self._threshold(),
                           smoothing_window=self.smoothing_window, n_forecast=self.n_forecast,
                           seed=self.seed)

    def _points_at(self, obs: Observation):
        """:meth:`_points` with the library's default window held in seconds at ``obs.dt``
        (:func:`_window_at`; the given one, or the same part, at 20 frames/s and slower)."""
        part = self._points()
        if self.smoothing_window is None and float(obs.dt) < _TUNED_DT:
            from methods._sindy_libraries import LIBRARIES

            w = _window_at(LIBRARIES[self.system].window, float(obs.dt))
            w = min(w, max(LIBRARIES[self.system].window, (obs.n_frames - 3) // 2 * 2 + 1))
            part.smoothing_window = w
        return part

    def _validate(self) -> None:
        super()._validate()
        from methods._points import check_system_param

        check_system_param(self)
        check_number(self._threshold(), "threshold", lo=0.0)
        w = self.smoothing_window
        if self.system not in self.own_library:
            if w is not None and (isinstance(w, bool) or not isinstance(w, (int, np.integer))
                                  or w < 7 or w % 2 == 0):
                raise ValueError(f"smoothing_window: expected None or an odd integer >= 7 on the "
                                 f"{self.system} system, got {w!r}")
            w = None
        if w is not None and (isinstance(w, bool) or not isinstance(w, (int, np.integer)) or w < 0
                              or (w and (w < 5 or w % 2 == 0))):
            raise ValueError(f"smoothing_window: expected None, 0 or an odd integer >= 5, got {w!r}")
        check_positive_int(self.min_segment, "min_segment", minimum=3)
        check_positive_int(self.n_forecast, "n_forecast")

    def _differentiator(self, noise: float, dt: float = _TUNED_DT):
        import pysindy as ps

        w = self.smoothing_window
        if w is None:
            w = 0 if noise < _CLEAN_NOISE else _window_at(9, float(dt))
        if isinstance(w, bool) or not isinstance(w, (int, np.integer)) or w < 0 or (w and (w < 5 or w % 2 == 0)):
            raise ValueError(f"smoothing_window: expected 0 or an odd integer >= 5, got {w!r}")
        if w == 0:
            # 4th order: on 20 clean test tracks the drag constant's bias fell from -3e-4 (order 2,
            # ~10 posterior std) to 1e-6
            return ps.FiniteDifference(order=4), 5
        return ps.SmoothedFiniteDifference(smoother_kws={"window_length": int(w), "polyorder": 3}), int(w)

    def _fit(self, obs: Observation):
        import pysindy as ps

        clock = Stopwatch()
        thr = float(self._threshold())
        if not np.isfinite(thr) or thr < 0:
            raise ValueError(f"threshold: expected a number >= 0, got {self.threshold!r}")
        min_seg = check_positive_int(self.min_segment, "min_segment", minimum=3)
        if not isinstance(obs, Observation):
            raise ValueError(f"obs: expected a sysid_bench.core.estimator.Observation, got {type(obs).__name__}")
        kind = "positions" if obs.positions is not None else "frames"
        pos = np.array(observed_positions(obs, min_seen=3), dtype=np.float64)  # tracks frames once
        bad = reject_outliers(pos, float(obs.dt))
        pos[bad] = np.nan
        track = prepare(dataclasses.replace(obs, frames=None, positions=pos))
        track.input_kind = kind
        diff, stencil = self._differentiator(track.noise, track.dt)
        dt = track.dt
        seg = segment_track(track.positions, dt, min_len=max(min_seg, stencil), floor=track.floor)
        mean = PRIOR_MEAN.copy()
        std = PRIOR_STD.copy()
        informed = np.zeros(4, bool)
        extras: dict = {"n_segments": len(seg.flight), "n_bounces": 0, "n_rolling": len(seg.rolling)}

        # g, d: SINDy on the velocities of every free-flight segment
        flights = free_flight(seg.flight, track.positions, dt, track.noise)
        extras["n_not_flight"] = len(seg.flight) - len(flights)
        if flights:
            vel = [np.asarray(diff(track.positions[a:b], np.arange(a, b) * dt)) for a, b in flights]
            lib = ps.CustomLibrary(
                library_functions=[_drag_x, _drag_y],
                function_names=[lambda a, b: f"|v|{a}", lambda a, b: f"|v|{b}"],
                include_bias=True,
            )
            model = ps.SINDy(
                optimizer=ps.STLSQ(threshold=thr),
                feature_library=lib,
                differentiation_method=diff,
            )
            with one_blas_thread():
                model.fit(vel, t=dt, feature_names=["vx", "vy"])
            coef = np.asarray(model.coefficients())  # rows vx', vy'; columns _FEATURES
            V = np.concatenate(vel)
            A = np.concatenate([np.asarray(diff(v, np.arange(len(v)) * dt)) for v in vel])
            theta = np.column_stack([np.ones(len(V)), _drag_x(V[:, 0], V[:, 1]), _drag_y(V[:, 0], V[:, 1])])
            lengths = [len(v) for v in vel]
            cov = []
            for k in range(2):
                active = np.flatnonzero(coef[k] != 0)
                resid = A[:, k] - theta @ coef[k]
                dof = max(len(V) - active.size, 1)
                s2 = float(resid @ resid) / dof
                c = np.zeros((3, 3))
                if active.size:
                    c[np.ix_(active, active)] = s2 * np.linalg.pinv(theta[:, active].T @ theta[:, active])
                cov.append(c * _CORR_INFLATION**2)
            mean[1], d = _g_d(coef, theta)
            std[1] = np.sqrt(cov[1][0, 0])
            if np.isfinite(d):  # some flight frame moves: the drag features weigh d
                sxx = float(theta[:, 1] @ theta[:, 1])
                syy = float(theta[:, 2] @ theta[:, 2])
                mean[2] = d
                std[2] = np.sqrt(cov[0][1, 1] * sxx**2 + cov[1][2, 2] * syy**2) / (sxx + syy)
            # the frames of one segment share its smoothing and its bounces' errors; segments
            # are what is independent: never claim less than their jackknife spread
            jk = _segment_jackknife(coef, theta, A, _blocks(lengths, stencil))
            if jk is not None:
                std[1:3] = np.maximum(std[1:3], jk)
                extras["jackknife_std"] = jk.tolist()
            informed[1:3] = True
            extras["coefficients"] = coef.tolist()
            extras["features"] = list(_FEATURES)
            extras["equations"] = model.equations()
            # the bias of vy' is g only if some segment has enough vertical motion to see it
            extras["n_flight_frames"] = int(len(V))

        # e: velocity ratios at floor bounces, each with its standard error, pooled
        ratios, ratio_se = bounce_ratios(track.positions, dt, seg, track.noise)
        if ratios.size:
            mean[0], std[0], used = pool_ratios(ratios, ratio_se)
            informed[0] = True
            extras["n_bounces"] = int(used.sum())
            extras["bounce_ratios"] = ratios.tolist()
            extras["bounce_ratio_se"] = ratio_se.tolist()
            extras["bounce_ratios_used"] = used.tolist()

        # r: rolling deceleration
        r_est, r_w = [], []
        for a, b in seg.rolling:
            if b - a < 4:
                continue
            t = np.arange(a, b) * dt
            tm = t.mean()
            c, cv = np.polyfit(t - tm, track.positions[a:b, 0], 2, cov="unscaled")
            resid = track.positions[a:b, 0] - np.polyval(c, t - tm)
            s2 = max(float(resid @ resid) / max(b - a - 3, 1), track.noise**2)
            vx = c[1]
            if abs(vx) < 1e-6:
                continue
            r_est.append(-2.0 * c[0] * np.sign(vx))
            r_w.append(1.0 / (4.0 * s2 * cv[0, 0]))
        if r_est:
            w = np.asarray(r_w)
            mean[3] = float(np.sum(w * np.asarray(r_est)) / w.sum())
            std[3] = float(1.0 / np.sqrt(w.sum()))
            informed[3] = True

        clipped = (mean < LO) | (mean > HI)
        moved = np.abs(np.clip(mean, LO, HI) - mean)
        mean = np.clip(mean, LO, HI)
        # a clip is evidence against the fit: at least as unsure as the distance moved
        std = np.where(informed, np.maximum(std, np.minimum(moved, PRIOR_STD)), PRIOR_STD)
        extras.update(
            {
                "n_simulations": 0,
                "wall_s": clock(),
                "informed": informed.tolist(),
                "clipped": clipped.tolist(),
                "n_outliers": int(bad.sum()),
                **track.describe(),
            }
        )
        return Posterior(mean=mean, std=std, samples=None, extras=extras), track, clock

    def identify(self, obs: Observation) -> Posterior:
        """Parameters read from the SINDy coefficients, bounces and rolling.

        Returns
        -------
        Posterior
            mean/std (4,), no samples; ``extras`` has the SINDy ``coefficients`` (2, 3) over
            ``features``, the ``equations``, ``bounce_ratios``, which parameters the track
            ``informed`` and which were ``clipped`` into the prior box; ``check`` the model
            check (see the module), ``extras["check_simulations"]`` its simulations. Another
            system: mean/std (P,) from the library's coefficients.
        """
        if self.system not in self.own_library:
            return self._points_at(obs).identify(obs)
        post, track, _ = self._fit(obs)
        sim = CountingSimulator()
        post = check_posterior(post, sim, track, track.state0, track.floor, DEFAULT_SIGMA,
                               fit_state0=True, seed=track.n_frames)
        post.extras["check_simulations"] = sim.n_simulations
        return post

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Run the identified hybrid model (the simulator) from the last seen frame.

        Returns
        -------
        Forecast
            mean/std (horizon, 2); samples (n_forecast, horizon, 2). Another system: the
            identified model run on from the last frame's estimated state, (H, 2) or (H, K, 2).
        """
        if self.system not in self.own_library:
            return self._points_at(obs).forecast(obs, horizon)
        m = check_positive_int(self.n_forecast, "n_forecast")
        post, track, clock = self._fit(obs)
        rng = make_rng(self.seed, 1)
        theta = np.clip(post.mean + post.std * rng.standard_normal((m, 4)), LO, HI)
        state, state_std = track.end_state()
        states = clip_state(state + state_std * rng.standard_normal((m, 4)), track.floor)
        last_seen = int(np.flatnonzero(track.mask)[-1])
        sim = CountingSimulator()
        return forecast_by_simulation(
            sim, theta, states, track.floor, track.dt, horizon,
            skip=track.n_frames - 1 - last_seen, clock=clock, extras={"posterior_extras": post.extras},
        )
