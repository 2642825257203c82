"""Shared machinery of the classical baselines (lsq, bo, emcee, nuts, sindy).

One place for what must be identical across methods so that their numbers are comparable:

* :class:`CountingSimulator` wraps :func:`sysid_bench.physics.simulate` and counts simulations the
  way sbibm does: **one trajectory = one simulation**, whatever the batch size;
* :func:`gaussian_loglik` and :func:`mean_sq_error` score simulated positions against observed
  ones, skipping unseen (NaN) frames; the likelihood of emcee and nuts, the objective of lsq and bo;
* :func:`prepare` turns an :class:`~sysid_bench.estimator.Observation` into a :class:`Track`:
  validated positions, the floor (given, or estimated) and the initial state (given, or
  estimated by a local polynomial fit, with its standard error);
* :func:`segment_track` finds floor and wall contacts and the rolling phase from positions alone
  (SINDy fits between them; the state and floor estimates use them);
* :func:`forecast_by_simulation` turns posterior samples into a :class:`Forecast`.

Noise model (decided here, mirrored by ``methods.nuts`` in JAX): observed positions are the
simulated ones plus independent Gaussian noise of a **fixed** standard deviation ``sigma`` per
coordinate, a hyperparameter of every method (default :data:`DEFAULT_SIGMA` = 0.02 m). Not
inferred because clean positions (the paper's setting) have zero noise, where an inferred scale
collapses to 0 and the posterior to a spike no sampler can explore; 0.02 m is about 2.5 times the
RMS error of :func:`sysid_bench.tracking.track` on clean 28x28 renders (0.006-0.009 m), so tracked
input is not treated as more precise than it is. Pass a larger ``sigma`` for noisy video.

Unknown floor (``Observation.floor is None``): estimated from the floor contacts seen (the height
where the polynomial fits just before and just after a bounce meet), else from the rolling phase
(median height), else taken as the lowest position seen (no contact seen: the floor is at most
there, and it only matters for forecasting), with a standard error (``Track.floor_std``). lsq and
bo use the point estimate; emcee samples the floor as a nuisance around it (a fixed floor 1-2 cm
off biased g by several posterior widths on tracked video).

Unknown initial state (``Observation.state0 is None``): position and velocity at frame 0 from a
cubic (quadratic when short) least-squares fit to the first free-flight run (a quadratic in x
in the rolling phase), with standard errors from the fit under the noise level the track's own
second differences show (``Track.noise``; floored, since on clean tracks drag makes the
polynomial itself ~3e-3 m/s wrong). lsq samples initial states around it (as the paper's
real-video variant), emcee samples it as a nuisance parameter, bo keeps it fixed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from sysid_bench import physics
from sysid_bench.estimator import Forecast, Observation, observed_positions

__all__ = [
    "DEFAULT_SIGMA",
    "LO",
    "HI",
    "SPAN",
    "PRIOR_MEAN",
    "PRIOR_STD",
    "CountingSimulator",
    "gaussian_loglik",
    "mean_sq_error",
    "Track",
    "Segments",
    "Contact",
    "prepare",
    "segment_track",
    "floor_contacts",
    "local_state",
    "clip_state",
    "check_sigma",
    "tempered_weights",
    "resample",
    "forecast_by_simulation",
    "check_horizon",
    "make_rng",
    "Stopwatch",
    "one_blas_thread",
]

#: Default standard deviation (m) of the Gaussian position noise in the likelihood.
DEFAULT_SIGMA = 0.02

LO = np.array([physics.PRIOR[p][0] for p in physics.PARAMS])
HI = np.array([physics.PRIOR[p][1] for p in physics.PARAMS])
SPAN = HI - LO
PRIOR_MEAN = 0.5 * (LO + HI)
#: Standard deviation of the uniform prior: what "no information" honestly reports.
PRIOR_STD = SPAN / np.sqrt(12.0)

# Free-flight accelerations stay below these (m/s^2) over the whole prior: a_y = g - d|v|vy <= 0
# unless the ball falls faster than terminal speed, |a_x| = d|v||vx| <= 0.05 * 15 * 8 = 6.
# Half a contact impulse is at least 16|vy| (floor) or 20|vx| (wall) m/s^2 per frame at dt = 0.05.
_FLOOR_ACC = 3.0
_WALL_ACC = 8.0
# Floors on the standard errors of a fitted state: on clean tracks the fit's residuals are ~0
# but drag makes the polynomial model itself wrong by ~1e-3 m and ~3e-3 m/s.
_MIN_STATE_STD = np.array([1e-3, 1e-3, 5e-3, 5e-3])
_FLOOR_SE_ONE = 0.02  # m, floor from a single bounce: a few times a cubic fit's typical error
_FLOOR_SE_UNSEEN = 0.1  # m, no contact seen


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


def check_sigma(sigma) -> float:
    """``sigma`` as a float > 0, else ``ValueError`` naming it."""
    try:
        s = float(sigma)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"sigma: expected a positive number of metres, got {sigma!r}") from exc
    if not np.isfinite(s) or s <= 0:
        raise ValueError(f"sigma: expected a finite number of metres > 0, got {sigma!r}")
    return s


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


def check_horizon(horizon) -> int:
    """``horizon`` as an int >= 1, else ``ValueError`` naming it."""
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
        raise ValueError(f"horizon: expected an integer >= 1 (frames), got {horizon!r}")
    return int(horizon)


# ------------------------------------------------------------------------------------------
# simulation and likelihood
class CountingSimulator:
    """:func:`sysid_bench.physics.simulate` that counts trajectories (sbibm-style budget).

    Attributes
    ----------
    n_simulations : int
        Trajectories simulated so far; a batch of B counts B.
    """

    def __init__(self) -> None:
        self.n_simulations = 0

    def __call__(self, theta, state0, n_frames: int, dt: float, floor) -> np.ndarray:
        """Simulate; same arguments and result as ``physics.simulate``: (B, n_frames, 4)."""
        out = physics.simulate(theta, state0, n_frames=n_frames, dt=dt, floor=floor)
        self.n_simulations += int(out.shape[0])
        return out

    def positions(self, theta, state0, n_frames: int, dt: float, floor) -> np.ndarray:
        """Simulated positions only, shape (B, n_frames, 2)."""
        return self(theta, state0, n_frames, dt, floor)[..., :2]


def mean_sq_error(sim_pos: np.ndarray, obs_pos: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Mean squared position error over seen frames and both coordinates.

    Parameters
    ----------
    sim_pos : ndarray, shape (..., T, 2)
    obs_pos : ndarray, shape (T, 2)
        NaN where unseen (those rows must be False in ``mask``).
    mask : ndarray of bool, shape (T,)

    Returns
    -------
    ndarray, shape (...)
        m^2.
    """
    diff = np.where(mask[:, None], sim_pos - np.where(mask[:, None], obs_pos, 0.0), 0.0)
    return np.sum(diff * diff, axis=(-2, -1)) / (2.0 * np.count_nonzero(mask))


def gaussian_loglik(sim_pos: np.ndarray, obs_pos: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Log-likelihood of observed positions: independent N(sim, sigma^2) per seen coordinate.

    The one likelihood of emcee and nuts (nuts mirrors this in JAX). Frames with
    ``mask == False`` (unseen) contribute nothing.

    Parameters
    ----------
    sim_pos : ndarray, shape (..., T, 2)
        Simulated positions (m).
    obs_pos : ndarray, shape (T, 2)
        Observed positions (m), NaN allowed where ``mask`` is False.
    mask : ndarray of bool, shape (T,)
    sigma : float
        Noise standard deviation (m).

    Returns
    -------
    ndarray, shape (...)
    """
    n = 2.0 * np.count_nonzero(mask)
    diff = np.where(mask[:, None], sim_pos - np.where(mask[:, None], obs_pos, 0.0), 0.0)
    sse = np.sum(diff * diff, axis=(-2, -1))
    return -0.5 * sse / sigma**2 - n * np.log(sigma) - 0.5 * n * np.log(2.0 * np.pi)


# ------------------------------------------------------------------------------------------
# segmentation of a track into free flight, contacts and rolling
@dataclass
class Contact:
    """A floor bounce located between two free-flight segments.

    ``t`` (s from frame 0), ``height`` (m, the floor there), ``v_in`` < 0 < ``v_out`` (m/s, the
    vertical velocities just before and after), ``ratio`` = ``-v_out / v_in``.
    """

    t: float
    height: float
    v_in: float
    v_out: float

    @property
    def ratio(self) -> float:
        return -self.v_out / self.v_in


@dataclass
class Segments:
    """Where a track is in free flight, where it bounces and where it rolls.

    Attributes
    ----------
    flight : list of (start, stop)
        Frame ranges ``[start, stop)`` of free flight with no contact inside, all frames seen,
        at least ``min_len`` frames long.
    flight_all : list of (start, stop)
        The same down to 3 frames (enough for a local state estimate at the track's ends).
    rolling : list of (start, stop)
        Frame ranges on the floor and still moving, split at wall contacts.
    stopped : ndarray of bool, shape (T,)
        Frames where the ball lies still on the floor.
    on_floor : ndarray of bool, shape (T,)
        Rolling or stopped.
    floor_hit, wall_hit : ndarray of bool, shape (T,)
        Frames whose second difference carries a contact impulse.
    acc_noise : ndarray, shape (2,)
        Robust scale (m/s^2) of second-difference noise per axis.
    """

    flight: list[tuple[int, int]]
    flight_all: list[tuple[int, int]]
    rolling: list[tuple[int, int]]
    stopped: np.ndarray
    on_floor: np.ndarray
    floor_hit: np.ndarray
    wall_hit: np.ndarray
    acc_noise: np.ndarray
    contacts: list[Contact] = field(default_factory=list)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` ranges of consecutive True values."""
    m = np.concatenate(([False], np.asarray(mask, bool), [False])).astype(np.int8)
    edges = np.flatnonzero(np.diff(m))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _robust_scale(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if x.size < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def segment_track(positions: np.ndarray, dt: float, *, min_len: int = 5, floor: float | None = None) -> Segments:
    """Split a track at floor and wall contacts and find its rolling phase.

    A contact inside a frame interval puts an impulse into the second differences of the two
    frames around it; at least one of them carries half of it, far above any free-flight
    acceleration (see ``_FLOOR_ACC``/``_WALL_ACC``), so dropping every flagged frame leaves
    segments that each lie on one side of every contact.

    Parameters
    ----------
    positions : ndarray, shape (T, 2)
        Metres, NaN where unseen.
    dt : float
    min_len : int
        Shortest free-flight segment kept (frames).
    floor : float, optional
        Known floor height; else the lowest position seen stands in for finding the rolling phase.

    Returns
    -------
    Segments
    """
    pos = np.asarray(positions, dtype=np.float64)
    T = pos.shape[0]
    seen = np.isfinite(pos).all(axis=1)
    acc = np.full((T, 2), np.nan)
    if T >= 3:
        acc[1:-1] = (pos[2:] - 2.0 * pos[1:-1] + pos[:-2]) / dt**2
    # Contacts are sparse spikes: the median of frame-to-frame changes ignores them.
    noise = np.array([_robust_scale(np.diff(acc[:, k])) / np.sqrt(2.0) for k in range(2)])
    floor_hit = np.nan_to_num(acc[:, 1], nan=0.0) > _FLOOR_ACC + 5.0 * noise[1]
    wall_hit = np.abs(np.nan_to_num(acc[:, 0], nan=0.0)) > _WALL_ACC + 5.0 * noise[0]

    # Rolling / stopped: near the floor level and vertically still on both sides.
    pos_noise = noise * dt**2 / np.sqrt(6.0)  # second difference of white noise has sd sqrt(6) s
    tol = max(0.01, 5.0 * float(pos_noise.max()))
    y = pos[:, 1]
    level = float(np.nanmin(y)) if floor is None else float(floor)
    dy = np.abs(np.diff(y))
    still_y = np.zeros(T, bool)
    if T >= 2:
        ok = np.nan_to_num(dy, nan=np.inf) < tol
        still_y[1:-1] = ok[:-1] & ok[1:]
        still_y[0] = ok[0]
        still_y[-1] = ok[-1]
    on_floor = seen & still_y & (np.abs(y - level) < tol)
    dx = np.abs(np.diff(pos[:, 0]))
    still_x = np.zeros(T, bool)
    if T >= 2:
        okx = np.nan_to_num(dx, nan=np.inf) < tol * 0.2
        still_x[1:-1] = okx[:-1] & okx[1:]
        still_x[0] = okx[0]
        still_x[-1] = okx[-1]
    stopped = on_floor & still_x
    # keep only floor runs of >= 3 frames: a single still frame is a bounce apex near the floor
    keep = np.zeros(T, bool)
    for a, b in _runs(on_floor):
        if b - a >= 3:
            keep[a:b] = True
    on_floor &= keep
    stopped &= keep
    moving_roll = on_floor & ~stopped & ~wall_hit
    rolling = [(a, b) for a, b in _runs(moving_roll) if b - a >= 3]

    flight_mask = seen & ~on_floor & ~floor_hit & ~wall_hit
    flight_all = [(a, b) for a, b in _runs(flight_mask) if b - a >= 3]
    seg = Segments(
        flight=[(a, b) for a, b in flight_all if b - a >= min_len],
        flight_all=flight_all,
        rolling=rolling,
        stopped=stopped,
        on_floor=on_floor,
        floor_hit=floor_hit,
        wall_hit=wall_hit,
        acc_noise=noise,
    )
    seg.contacts = floor_contacts(pos, dt, seg)
    return seg


def _polyfit(t: np.ndarray, z: np.ndarray, deg: int):
    """Polynomial fit of z(t) (t already shifted to the evaluation time); returns coefficients
    (highest power first), their unscaled covariance and the residual RMS."""
    coef, cov = np.polyfit(t, z, deg, cov="unscaled")
    resid = z - np.polyval(coef, t)
    dof = max(len(t) - deg - 1, 1)
    rms = float(np.sqrt(np.sum(resid**2) / dof))
    return coef, cov, rms


def floor_contacts(positions: np.ndarray, dt: float, seg: Segments, k: int = 5) -> list[Contact]:
    """Floor bounces between consecutive free-flight segments.

    Fits cubics (quadratics when a side has fewer than 5 frames) to the last ``k`` frames before
    and the first ``k`` after a short gap flagged as a floor hit, and takes the contact where the
    two curves meet inside the gap. (On clean tracks the cubic gets the velocity ratio within
    ~0.002 of ``e``; a quadratic is biased low by ~0.007 through drag.)

    Returns
    -------
    list of Contact
    """
    out: list[Contact] = []
    pos = positions
    for (a0, a1), (b0, b1) in zip(seg.flight[:-1], seg.flight[1:]):
        if b0 - a1 > 3 or not seg.floor_hit[max(a1 - 1, 0) : b0 + 1].any():
            continue
        ia = np.arange(max(a0, a1 - k), a1)
        ib = np.arange(b0, min(b1, b0 + k))
        if len(ia) < 3 or len(ib) < 3:
            continue
        deg = 3 if min(len(ia), len(ib)) >= 5 else 2
        tm = 0.5 * (a1 - 1 + b0) * dt  # centre the times for conditioning
        ca = np.polyfit(ia * dt - tm, pos[ia, 1], deg)
        cb = np.polyfit(ib * dt - tm, pos[ib, 1], deg)
        roots = np.roots(ca - cb)
        roots = roots[np.abs(roots.imag) < 1e-12].real
        lo, hi = (a1 - 1) * dt - tm, b0 * dt - tm
        roots = roots[(roots >= lo - 1e-9) & (roots <= hi + 1e-9)]
        if roots.size == 0:
            continue
        tc = float(roots[np.argmin(np.abs(roots))])
        v_in = float(np.polyval(np.polyder(ca), tc))
        v_out = float(np.polyval(np.polyder(cb), tc))
        if v_in < 0 < v_out:
            out.append(Contact(t=tc + tm, height=float(np.polyval(ca, tc)), v_in=v_in, v_out=v_out))
    return out


def local_state(positions, dt, frames, t_eval, sigma, *, rolling=False, floor=0.0):
    """State ``[x, y, vx, vy]`` at time ``t_eval`` (s) from a polynomial fit to some frames.

    Cubic with >= 6 frames, quadratic with fewer (linear in x and flat y while rolling). The
    standard error assumes independent position noise of ``max(sigma, residual RMS)``.

    Parameters
    ----------
    positions : ndarray, shape (T, 2)
    dt : float
    frames : ndarray of int
        Frames to fit (seen, one side of every contact).
    t_eval : float
    sigma : float
    rolling : bool
        The frames are on the floor: ``y = floor``, ``vy = 0`` and x is fitted by a quadratic.
    floor : float

    Returns
    -------
    state, std : ndarray, shape (4,)
    """
    t = frames * dt - t_eval
    state = np.empty(4)
    std = np.empty(4)
    for k in (0, 1):
        if rolling and k == 1:
            state[1], state[3] = floor, 0.0
            std[1], std[3] = sigma, sigma / (max(len(frames), 2) * dt)
            continue
        deg = 2 if rolling or len(frames) < 6 else 3
        deg = min(deg, len(frames) - 1)
        coef, cov, rms = _polyfit(t, positions[frames, k], deg)
        s = max(sigma, rms)
        state[k], state[k + 2] = coef[-1], coef[-2]
        std[k], std[k + 2] = s * np.sqrt(cov[-1, -1]), s * np.sqrt(cov[-2, -2])
    return state, np.maximum(std, _MIN_STATE_STD)


def clip_state(state: np.ndarray, floor) -> np.ndarray:
    """Move states (..., 4) inside the box, speeds within ``physics.V_MAX``, so the simulator
    accepts them (a track's outlier can make a finite-difference velocity absurd)."""
    s = np.array(state, dtype=np.float64, copy=True)
    fl = np.asarray(floor, dtype=np.float64)
    s[..., 0] = np.clip(s[..., 0], 0.0, physics.BOX_WIDTH)
    s[..., 1] = np.clip(s[..., 1], fl, fl + physics.BOX_WIDTH)
    s[..., 2:] = np.clip(s[..., 2:], -physics.V_MAX, physics.V_MAX)
    return s


def _end_state(pos, dt, seg: Segments, which: str, floor: float, noise: float):
    """Estimated ``(state, std)`` at frame 0 (``which="start"``) or at the last seen frame.

    Fits the free-flight run or rolling run nearest that end; ``noise`` is the position noise
    (m) assumed for the standard errors. When contacts may lie between the fitted frames and the
    end, the standard errors are inflated tenfold.
    """
    seen = np.flatnonzero(np.isfinite(pos).all(axis=1))
    first = which == "start"
    target = 0 if first else int(seen[-1])
    t_eval = target * dt
    if seg.stopped[target]:
        return np.array([pos[target, 0], floor, 0.0, 0.0]), np.array([noise, noise, 1e-3, 1e-3])
    pieces = [(a, b, False) for a, b in seg.flight_all] + [(a, b, True) for a, b in seg.rolling]
    if pieces:
        a, b, rolling = min(pieces, key=lambda p: p[0]) if first else max(pieces, key=lambda p: p[1])
        frames = np.arange(a, min(b, a + 10)) if first else np.arange(max(a, b - 10), b)
        state, std = local_state(pos, dt, frames, t_eval, noise, rolling=rolling, floor=floor)
        gap = slice(target, a + 1) if first else slice(b - 1, target + 1)
        if (seg.floor_hit[gap] | seg.wall_hit[gap]).any() or (~np.isfinite(pos[gap]).all(axis=1)).any():
            std = std * 10.0
        return state, std
    # no clean run (very short, or a contact every few frames): the seen frames nearest the end
    frames = seen[:4] if first else seen[-4:]
    state, std = local_state(pos, dt, frames, t_eval, noise)
    return state, std * 10.0


# ------------------------------------------------------------------------------------------
# a validated, prepared observation
@dataclass
class Track:
    """Positions ready for a simulation-based method.

    Attributes
    ----------
    positions : ndarray, shape (T, 2)
        Metres, NaN where unseen.
    mask : ndarray of bool, shape (T,)
        Seen frames.
    dt : float
    floor : float
    floor_known : bool
    floor_std : float
        Standard error of an estimated floor (0 when known): the spread of the contact heights
        over the square root of their number, at least the track's noise and 1 mm; 0.02 m from
        a single bounce; 0.1 m when no contact was seen.
    state0 : ndarray, shape (4,)
        Known or estimated initial state.
    state0_std : ndarray, shape (4,)
        Standard error of the estimate; zeros when known.
    state0_known : bool
    segments : Segments
    input_kind : str
        ``"positions"`` or ``"frames"`` (tracked).
    noise : float
        Position noise (m) estimated from the track itself (robust scale of second
        differences), floored at 1e-4; used for the standard errors of estimated states.
    """

    positions: np.ndarray
    mask: np.ndarray
    dt: float
    floor: float
    floor_known: bool
    floor_std: float
    state0: np.ndarray
    state0_std: np.ndarray
    state0_known: bool
    segments: Segments
    input_kind: str
    noise: float

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_seen(self) -> int:
        return int(self.mask.sum())

    def end_state(self):
        """Estimated ``(state, std)`` at the last seen frame, from the track alone."""
        return _end_state(self.positions, self.dt, self.segments, "end", self.floor, self.noise)

    def describe(self) -> dict:
        """Entries for ``Posterior.extras``."""
        return {
            "input": self.input_kind,
            "floor": self.floor,
            "floor_known": self.floor_known,
            "floor_std": self.floor_std,
            "state0_known": self.state0_known,
            "n_frames": self.n_frames,
            "n_seen": self.n_seen,
        }


def prepare(obs: Observation) -> Track:
    """Validate an observation and estimate what it does not give (floor, initial state).

    Parameters
    ----------
    obs : Observation

    Returns
    -------
    Track

    Raises
    ------
    ValueError
        ``obs`` not an Observation; fewer than 3 seen frames; positions outside the box;
        ``state0`` outside the box.
    """
    if not isinstance(obs, Observation):
        raise ValueError(f"obs: expected a sysid_bench.estimator.Observation, got {type(obs).__name__}")
    pos = observed_positions(obs, min_seen=3)
    mask = np.isfinite(pos).all(axis=1)
    dt = float(obs.dt)
    seg = segment_track(pos, dt, floor=obs.floor)
    noise = max(float(seg.acc_noise.max()) * dt**2 / np.sqrt(6.0), 1e-4)
    if obs.floor is not None:
        floor, floor_std, floor_known = float(obs.floor), 0.0, True
    else:
        floor_known = False
        lowest = float(np.nanmin(pos[:, 1]))
        if seg.contacts:
            h = np.array([c.height for c in seg.contacts])
            floor = float(np.median(h))
            spread = float(np.std(h, ddof=1)) / np.sqrt(h.size) if h.size >= 2 else _FLOOR_SE_ONE
            floor_std = max(spread, noise, _MIN_STATE_STD[1])
        elif seg.on_floor.any():
            y = pos[seg.on_floor, 1]
            floor = float(np.median(y))
            floor_std = max(float(np.std(y)) / np.sqrt(y.size), noise, _MIN_STATE_STD[1])
        else:  # no contact seen: the floor is at most the lowest point; how far below, unknown
            floor, floor_std = lowest, _FLOOR_SE_UNSEEN
        floor = min(floor, lowest)  # every seen centre is above the floor
        if not seg.on_floor.any():
            # the rolling test used the lowest point as floor level; redo it with the estimate
            seg = segment_track(pos, dt, floor=floor)
    if obs.state0 is not None:
        s0 = obs.state0
        if not (0.0 <= s0[0] <= physics.BOX_WIDTH and floor - 1e-9 <= s0[1] <= floor + physics.BOX_WIDTH):
            raise ValueError(
                f"state0: expected a position inside the box x in [0, {physics.BOX_WIDTH:g}], "
                f"y in [{floor:g}, {floor + physics.BOX_WIDTH:g}], got ({s0[0]:g}, {s0[1]:g})"
            )
        s0 = clip_state(s0, floor)
        s0_std, known = np.zeros(4), True
    else:
        s0, s0_std = _end_state(pos, dt, seg, "start", floor, noise)
        s0, known = clip_state(s0, floor), False
    return Track(
        positions=pos,
        mask=mask,
        dt=dt,
        floor=floor,
        floor_known=floor_known,
        floor_std=floor_std,
        state0=s0,
        state0_std=s0_std,
        state0_known=known,
        segments=seg,
        input_kind="positions" if obs.positions is not None else "frames",
        noise=noise,
    )


# ------------------------------------------------------------------------------------------
# weights, resampling, forecasting
def tempered_weights(loglik: np.ndarray, min_ess: float) -> tuple[np.ndarray, float, float]:
    """Normalised importance weights ``exp(beta * loglik)`` with the largest ``beta`` in (0, 1]
    whose effective sample size is at least ``min_ess``.

    A batch of prior draws rarely holds more than one draw inside a sharp likelihood peak; the
    untempered weights then put all mass on one draw and the spread collapses to 0. Tempering
    widens the weights to the resolution the draws actually have, so the reported spread is
    honest about the search rather than about the (unexplored) peak.

    Parameters
    ----------
    loglik : ndarray, shape (N,)
    min_ess : float

    Returns
    -------
    weights : ndarray, shape (N,)
    beta : float
    ess : float
    """
    ll = np.asarray(loglik, dtype=np.float64)
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    target = min(float(min_ess), float(np.isfinite(ll).sum()))

    def weights(beta):
        z = beta * (ll - ll.max())
        w = np.exp(z)
        w /= w.sum()
        return w, 1.0 / np.sum(w * w)

    w, ess = weights(1.0)
    if ess >= target:
        return w, 1.0, float(ess)
    lo, hi = 0.0, 1.0  # ESS(beta) falls as beta grows
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        _, e = weights(mid)
        if e >= target:
            lo = mid
        else:
            hi = mid
    w, ess = weights(lo)
    return w, lo, float(ess)


def resample(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` draws by systematic resampling of ``weights`` (N,)."""
    c = np.cumsum(weights)
    c[-1] = 1.0
    u = (rng.random() + np.arange(n)) / n
    return np.searchsorted(c, u)


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
