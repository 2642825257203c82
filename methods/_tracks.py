"""Track segmentation and state estimation for the position-based methods.

:func:`prepare` turns an :class:`~sysid_bench.core.estimator.Observation` into a :class:`Track`:
validated positions, the floor (given, or estimated) and the initial state (given, or estimated
by a local polynomial fit, with its standard error). :func:`segment_track` finds floor and wall
contacts and the rolling phase from positions alone (SINDy fits between them; the state and
floor estimates use them).

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

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from sysid_bench.core import physics
from sysid_bench.core.estimator import BOX_MARGIN, Observation, observed_positions

__all__ = ["Track", "Segments", "Contact", "prepare", "start_before_contact", "segment_track",
           "floor_contacts",
           "local_state", "clip_state"]

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
    # the top a hair inside: an interception run saw lsq refused by check_state0 with y - floor
    # = 10.000000000000002 after this clip (not reproduced with plain floors since)
    s[..., 1] = np.clip(s[..., 1], fl, fl + physics.BOX_WIDTH * (1 - 1e-12))
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
    state0_refit : bool
        The estimated start was refitted on the frames before an early contact
        (:func:`start_before_contact`).
    box : ThetaBox, optional
        The parameter box the fit and its model check search and sample
        (:class:`methods._simulation.ThetaBox`: the user's ranges and held values); None: the
        prior, ``PRIOR``.
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
    state0_refit: bool = False
    box: object = None

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


def floor_estimate(y: np.ndarray, seg: Segments, noise: float) -> tuple[float, float]:
    """The floor's height and its standard error, m, from a track's heights ``y`` (T,) and its
    segments (contacts first, then rolling frames, else only a bound: the lowest point)."""
    lowest = float(np.nanmin(y))
    if seg.contacts:
        h = np.array([c.height for c in seg.contacts])
        floor = float(np.median(h))
        spread = float(np.std(h, ddof=1)) / np.sqrt(h.size) if h.size >= 2 else _FLOOR_SE_ONE
        floor_std = max(spread, noise, _MIN_STATE_STD[1])
    elif seg.on_floor.any():
        yf = y[seg.on_floor]
        floor = float(np.median(yf))
        floor_std = max(float(np.std(yf)) / np.sqrt(yf.size), noise, _MIN_STATE_STD[1])
    else:  # no contact seen: the floor is at most the lowest point; how far below, unknown
        floor, floor_std = lowest, _FLOOR_SE_UNSEEN
    return min(floor, lowest), floor_std  # every seen centre is above the floor


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
        raise ValueError(f"obs: expected a sysid_bench.core.estimator.Observation, got {type(obs).__name__}")
    pos = observed_positions(obs, min_seen=3)
    mask = np.isfinite(pos).all(axis=1)
    dt = float(obs.dt)
    seg = segment_track(pos, dt, floor=obs.floor)
    noise = max(float(seg.acc_noise.max()) * dt**2 / np.sqrt(6.0), 1e-4)
    if obs.floor is not None:
        floor, floor_std, floor_known = float(obs.floor), 0.0, True
    else:
        floor_known = False
        floor, floor_std = floor_estimate(pos[:, 1], seg, noise)
        if not seg.on_floor.any():
            # the rolling test used the lowest point as floor level; redo it with the estimate
            seg = segment_track(pos, dt, floor=floor)
    if obs.state0 is not None:
        s0 = obs.state0
        m = BOX_MARGIN  # within it: tracking-sized error, moved onto the edge by clip_state
        if not (-m <= s0[0] <= physics.BOX_WIDTH + m and floor - m <= s0[1] <= floor + physics.BOX_WIDTH + m):
            raise ValueError(
                f"state0: expected a position within {m:g} m of the box x in [0, {physics.BOX_WIDTH:g}], "
                f"y in [{floor:g}, {floor + physics.BOX_WIDTH:g}], got ({s0[0]:g}, {s0[1]:g})"
            )
        s0 = clip_state(s0, floor)
        s0_std, known = np.zeros(4), True
    else:
        s0, s0_std = _end_state(pos, dt, seg, "start", floor, noise)
        s0, known = clip_state(s0, floor), False
    track = Track(
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
    # an estimated start extrapolated back across an early contact lies in a mirrored basin
    return start_before_contact(track)


#: free flight departs from a constant velocity plus the prior's mean gravity by at most about
#: this much (m/s^2): the prior's g is within 3 of its mean, drag adds up to ~6 (``_tracks``)
_FREE_ACC = 9.0


def start_before_contact(track: Track) -> Track:
    """``track`` with its initial-state estimate refitted on the frames before the first
    contact, when :func:`prepare`'s first estimate extrapolated it back across one.

    The first estimate fits the first free-flight run of at least 3 frames. When a contact comes
    earlier (a wall bounce in frame 2 of test case 0 of the default scale), that fit describes
    the ball *after* the contact, extrapolated to frame 0 as if there were none: in that case
    x0 = 10 m and vx0 = -6.4 m/s for a ball at 9.2 m moving right at +6.4 m/s, its standard
    errors (1 cm, 0.07 m/s) 77 and 170 times smaller than its error. A sampler started there (or
    whose prior on the start is a box of standard errors around it) settles in the mirrored
    basin and reports a narrow, wrong posterior. The seen frames before the first contact
    observe the start directly (those before the first frame flagged, and that frame too when
    the next is flagged: the contact lies between them): with 3 or more, ``local_state``'s
    polynomial fit; with 2, the line through them with the prior's mean gravity added back to
    the vertical velocity and velocity errors of at least half of ``_FREE_ACC`` times their
    time apart (the rest of gravity and drag). With fewer than 2 such frames, or no contact
    before the fitted run, or a known start, ``track`` is returned as it is.

    Parameters
    ----------
    track : Track

    Returns
    -------
    Track
        ``track``, or a copy with ``state0`` and ``state0_std`` (4,) replaced and
        ``state0_refit`` True. :func:`prepare` applies it, so every method gets the refit start.
    """
    if track.state0_known:
        return track
    seg = track.segments
    flags = np.flatnonzero(seg.floor_hit | seg.wall_hit)
    starts = [a for a, _ in seg.flight_all] + [a for a, _ in seg.rolling]
    if flags.size == 0 or not starts or seg.stopped[0] or flags[0] > min(starts):
        return track
    # a contact's impulse shows in the second differences of the frames either side of it:
    # the first two frames flagged bracket it, and the first of them is still before it
    f = int(flags[0])
    if f + 1 < track.n_frames and (seg.floor_hit[f + 1] or seg.wall_hit[f + 1]):
        f += 1
    early = np.flatnonzero(track.mask[:f])
    if early.size < 2:
        return track
    state, std = local_state(track.positions, track.dt, early, 0.0, track.noise,
                             floor=track.floor)
    if early.size == 2:
        span = float(early[1] - early[0]) * track.dt
        state[3] -= 0.5 * physics.PRIOR_MEAN[1] * span
        std[2:] = np.maximum(std[2:], 0.5 * _FREE_ACC * span)
    return dataclasses.replace(track, state0=clip_state(state, track.floor), state0_std=std,
                               state0_refit=True)
