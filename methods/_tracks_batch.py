""":func:`~methods._tracks.prepare` for many observations at once, bitwise the same Tracks.

``prepare`` costs ~8 ms a video, nearly all of it NumPy's per-call overhead on tiny arrays: the
segmentation's masks and robust scales, and ~17 polynomial fits a video (``floor_contacts``'
cubics either side of each bounce and their roots, the start's fit). :func:`prepare_batch` does
the same arithmetic for all tracks of a length at once: the masks on (B, T) arrays, every fit
of a size in one stacked least-squares call and every contact's roots in one stacked eigenvalue
call. The per-video functions in :mod:`methods._tracks` are left as they are (lsq, bo, emcee,
nuts and sindy use them); the batched path gives bitwise the same :class:`Track` for every
observation (``tests/test_tracks_batch.py`` compares all fields on the test split), because each
step repeats the per-video one's floating-point operations in the same order:

- NumPy's medians (the mean of the middle one or two of the finite values sorted) and its
  sums over the same contiguous axis;
- ``np.polyfit``: the same Vandermonde matrix scaled by its column norms, and the same LAPACK
  least-squares driver (``gelsd``) per fit -- NumPy's ``lstsq`` gufunc called on a stack of
  equal-sized fits (``np.linalg.lstsq`` refuses stacks; the gufunc it calls does not), the
  covariance from the same ``np.dot`` and a stacked ``inv``;
- ``np.roots``: the same companion matrix, a stacked ``eigvals`` (the same ``geev`` per
  matrix); ``np.polyval`` and ``np.polyder`` as the same Horner steps and products.

Where the stacked gufunc is missing (another NumPy) or a fit is degenerate, that fit falls back
to ``np.polyfit`` itself.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from methods._tracks import (
    _FLOOR_ACC,
    _MIN_STATE_STD,
    _WALL_ACC,
    Contact,
    Segments,
    Track,
    clip_state,
    floor_estimate,
    local_state,
    start_before_contact,
)
from sysid_bench.core.estimator import Observation, observed_positions

try:  # the gufunc np.linalg.lstsq calls; it takes stacks of equal-sized problems
    from numpy.linalg import _umath_linalg as _ulinalg

    _LSTSQ = _ulinalg.lstsq
except (ImportError, AttributeError):  # pragma: no cover - another NumPy: per-fit np.polyfit
    _LSTSQ = None

__all__ = ["prepare_batch"]


# ------------------------------------------------------------------------------------------
# numpy's small routines, row by row over stacks, in the same floating-point order
def _polyfit_rows(x: np.ndarray, y: np.ndarray, deg: int, cov: bool = False):
    """``np.polyfit(x[i], y[i], deg)`` for every row ``i`` (bitwise), from one stacked call.

    Parameters
    ----------
    x, y : ndarray, shape (N, n)
    deg : int
    cov : bool
        Also return ``cov="unscaled"``'s covariance.

    Returns
    -------
    coef : ndarray, shape (N, deg + 1)
        Highest power first.
    cov : ndarray, shape (N, deg + 1, deg + 1)
        Only with ``cov``.
    """
    x = np.asarray(x, dtype=np.float64) + 0.0
    y = np.asarray(y, dtype=np.float64) + 0.0
    n_rows, n = x.shape
    order = deg + 1
    if _LSTSQ is None or n_rows == 0 or n < order:
        return _polyfit_loop(x, y, deg, cov)
    rcond = n * np.finfo(np.float64).eps
    lhs = np.empty((n_rows, n, order))
    tmp = lhs[:, :, ::-1]  # np.vander: ones, then running products of x
    tmp[:, :, 0] = 1
    if order > 1:
        tmp[:, :, 1:] = x[:, :, None]
        np.multiply.accumulate(tmp[:, :, 1:], out=tmp[:, :, 1:], axis=2)
    scale = np.sqrt((lhs * lhs).sum(axis=1))  # (N, order): np.polyfit's column norms
    lhs /= scale[:, None, :]
    try:
        with np.errstate(invalid="raise", over="ignore", divide="ignore", under="ignore"):
            c, _, rank, _ = _LSTSQ(lhs, y[:, :, None], rcond, signature="ddd->ddid")
    except (FloatingPointError, np.linalg.LinAlgError):  # a degenerate fit: one at a time
        return _polyfit_loop(x, y, deg, cov)
    if np.any(rank != order):
        warnings.warn("Polyfit may be poorly conditioned", np.exceptions.RankWarning, stacklevel=2)
    coef = c[:, :, 0] / scale
    if not cov:
        return coef
    gram = np.stack([np.dot(a.T, a) for a in lhs])  # np.polyfit's own product, matrix by matrix
    vbase = np.linalg.inv(gram)
    vbase /= scale[:, :, None] * scale[:, None, :]
    return coef, vbase


def _polyfit_loop(x, y, deg, cov):
    """:func:`_polyfit_rows` one ``np.polyfit`` at a time."""
    if not cov:
        return np.array([np.polyfit(a, b, deg) for a, b in zip(x, y)]).reshape(len(x), deg + 1)
    fits = [np.polyfit(a, b, deg, cov="unscaled") for a, b in zip(x, y)]
    return (np.array([f[0] for f in fits]).reshape(len(x), deg + 1),
            np.array([f[1] for f in fits]).reshape(len(x), deg + 1, deg + 1))


def _polyval_rows(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``np.polyval(p[i], x[i])`` for every row (Horner's steps as NumPy takes them).

    ``p`` (N, d + 1), ``x`` (N,) or (N, n)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.zeros_like(x)
    pe = p if x.ndim == 1 else p[:, None, :]
    for j in range(p.shape[1]):
        y = y * x + pe[..., j]
    return y


def _polyder_rows(p: np.ndarray) -> np.ndarray:
    """``np.polyder(p[i])`` for every row: ``p[:-1] * [d, ..., 1]``."""
    n = p.shape[1] - 1
    return p[:, :-1] * np.arange(n, 0, -1)


def _roots_rows(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.roots(p[i])`` for every row (the companion matrices' stacked ``eigvals``).

    Returns
    -------
    roots : ndarray, shape (N, d), complex
        Row ``i``'s roots first, in ``np.roots``' order; NaN after them (fewer roots where
        ``p[i]`` has leading zeros).
    count : ndarray of int, shape (N,)
    """
    n_rows, N = p.shape
    out = np.full((n_rows, max(N - 1, 0)), np.nan, dtype=complex)
    count = np.zeros(n_rows, dtype=int)
    plain = (p[:, 0] != 0) & (p[:, -1] != 0)  # no leading or trailing zeros to strip
    if N > 1 and plain.any():
        rows = np.flatnonzero(plain)
        A = np.zeros((rows.size, N - 1, N - 1))
        A[:, np.arange(1, N - 1), np.arange(N - 2)] = 1.0
        A[:, 0, :] = -p[rows, 1:] / p[rows, :1]
        out[rows] = np.linalg.eigvals(A)
        count[rows] = N - 1
    for i in np.flatnonzero(~plain):
        r = np.roots(p[i])
        out[i, : r.size], count[i] = r, r.size
    return out, count


def _sorted_median(s: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Median of the first ``count`` (N,) values of each sorted row of ``s`` (N, n), as
    ``np.median`` computes it (the middle value, or the mean of the middle two)."""
    lo = np.maximum((count - 1) // 2, 0)
    hi = np.maximum(count // 2, 0)
    r = np.arange(len(s))
    a, b = s[r, lo], s[r, hi]
    return np.where(count % 2 == 1, a, (a + b) / 2.0)


def _robust_scale_rows(x: np.ndarray) -> np.ndarray:
    """``methods._tracks._robust_scale`` of every row of ``x`` (N, n) (NaN: left out)."""
    x = np.where(np.isfinite(x), x, np.nan)
    count = np.isfinite(x).sum(axis=1)
    med = _sorted_median(np.sort(x, axis=1), count)  # NaN sort last
    dev = np.abs(x - med[:, None])
    mad = _sorted_median(np.sort(dev, axis=1), count)
    return np.where(count < 3, 0.0, 1.4826 * mad)


def _runs_rows(mask: np.ndarray):
    """``[start, stop)`` of the runs of True in each row of ``mask`` (B, T): row, start, stop
    (each (R,), in row-major order)."""
    B, T = mask.shape
    m = np.zeros((B, T + 2), dtype=np.int8)
    m[:, 1:-1] = mask
    d = np.diff(m, axis=1)
    rb, start = np.nonzero(d == 1)
    _, stop = np.nonzero(d == -1)
    return rb, start, stop


def _runs_lists(rb, start, stop, B: int, min_len: int) -> list[list[tuple[int, int]]]:
    keep = stop - start >= min_len
    out: list[list[tuple[int, int]]] = [[] for _ in range(B)]
    for b, a, e in zip(rb[keep].tolist(), start[keep].tolist(), stop[keep].tolist()):
        out[b].append((a, e))
    return out


# ------------------------------------------------------------------------------------------
# segment_track over (B, T, 2)
def _segment_rows(pos: np.ndarray, dt: float, level_floor: np.ndarray, *, min_len: int = 5,
                  k: int = 5) -> list[Segments]:
    """:func:`methods._tracks.segment_track` of each track of ``pos`` (B, T, 2) (T >= 3), with
    ``floor`` the entry of ``level_floor`` (B,), NaN where None; its contacts as
    :func:`~methods._tracks.floor_contacts` with ``k``."""
    B, T = pos.shape[:2]
    seen = np.isfinite(pos).all(axis=2)
    acc = np.full((B, T, 2), np.nan)
    acc[:, 1:-1] = (pos[:, 2:] - 2.0 * pos[:, 1:-1] + pos[:, :-2]) / dt**2
    dacc = np.diff(acc, axis=1)  # (B, T-1, 2)
    noise = np.stack([_robust_scale_rows(dacc[:, :, j]) / np.sqrt(2.0) for j in range(2)],
                     axis=1)  # (B, 2)
    floor_hit = np.nan_to_num(acc[:, :, 1], nan=0.0) > (_FLOOR_ACC + 5.0 * noise[:, 1])[:, None]
    wall_hit = (np.abs(np.nan_to_num(acc[:, :, 0], nan=0.0))
                > (_WALL_ACC + 5.0 * noise[:, 0])[:, None])

    pos_noise = noise * dt**2 / np.sqrt(6.0)
    tol = np.maximum(0.01, 5.0 * pos_noise.max(axis=1))[:, None]  # (B, 1)
    y = pos[:, :, 1]
    known = np.isfinite(level_floor)
    level = np.where(known, level_floor, np.nanmin(np.where(known[:, None], 0.0, y), axis=1))

    def still(d, lim):
        ok = np.nan_to_num(d, nan=np.inf) < lim
        s = np.zeros((B, T), bool)
        s[:, 1:-1] = ok[:, :-1] & ok[:, 1:]
        s[:, 0], s[:, -1] = ok[:, 0], ok[:, -1]
        return s

    on_floor = seen & still(np.abs(np.diff(y, axis=1)), tol) & (np.abs(y - level[:, None]) < tol)
    stopped = on_floor & still(np.abs(np.diff(pos[:, :, 0], axis=1)), tol * 0.2)
    # floor runs of >= 3 frames only (as segment_track)
    rb, a, b = _runs_rows(on_floor)
    long = b - a >= 3
    mark = np.zeros((B, T + 1), dtype=np.int64)
    np.add.at(mark, (rb[long], a[long]), 1)
    np.add.at(mark, (rb[long], b[long]), -1)
    keep = np.cumsum(mark, axis=1)[:, :T] > 0
    on_floor &= keep
    stopped &= keep
    rolling = _runs_lists(*_runs_rows(on_floor & ~stopped & ~wall_hit), B, 3)
    flight_mask = seen & ~on_floor & ~floor_hit & ~wall_hit
    fb, fa, fe = _runs_rows(flight_mask)
    flight_all = _runs_lists(fb, fa, fe, B, 3)
    flight = _runs_lists(fb, fa, fe, B, max(min_len, 3))
    segs = [Segments(flight=flight[i], flight_all=flight_all[i], rolling=rolling[i],
                     stopped=stopped[i], on_floor=on_floor[i], floor_hit=floor_hit[i],
                     wall_hit=wall_hit[i], acc_noise=noise[i]) for i in range(B)]
    for i, c in _contacts_rows(pos, dt, flight, floor_hit, k).items():
        segs[i].contacts = c
    return segs


def _contacts_rows(pos, dt, flight, floor_hit, k):
    """:func:`methods._tracks.floor_contacts` of every track at once: {row: contacts}."""
    pairs = [(i, a0, a1, b0, b1) for i, fl in enumerate(flight)
             for (a0, a1), (b0, b1) in zip(fl[:-1], fl[1:])]
    out: dict[int, list[Contact]] = {}
    if not pairs:
        return out
    row, a0, a1, b0, b1 = np.array(pairs).T
    # a floor hit in frames [max(a1 - 1, 0), b0] (a cumulative count per track)
    hits = np.zeros((floor_hit.shape[0], floor_hit.shape[1] + 1), dtype=np.int64)
    np.cumsum(floor_hit, axis=1, out=hits[:, 1:])
    lo_f = np.maximum(a1 - 1, 0)
    hi_f = np.minimum(b0 + 1, floor_hit.shape[1])
    hit = hits[row, np.maximum(hi_f, lo_f)] > hits[row, lo_f]
    na = a1 - np.maximum(a0, a1 - k)
    nb = np.minimum(b1, b0 + k) - b0
    cand = (b0 - a1 <= 3) & hit & (na >= 3) & (nb >= 3)
    found = []  # (index of the pair, Contact)
    for sa, sb in sorted(set(zip(na[cand].tolist(), nb[cand].tolist()))):
        g = np.flatnonzero(cand & (na == sa) & (nb == sb))
        deg = 3 if min(sa, sb) >= 5 else 2
        tm = 0.5 * (a1[g] - 1 + b0[g]) * dt  # centre the times, as floor_contacts
        ia = a1[g, None] - sa + np.arange(sa)  # np.arange(max(a0, a1 - k), a1)
        ib = b0[g, None] + np.arange(sb)
        ca = _polyfit_rows(ia * dt - tm[:, None], pos[row[g, None], ia, 1], deg)
        cb = _polyfit_rows(ib * dt - tm[:, None], pos[row[g, None], ib, 1], deg)
        lo, hi = (a1[g] - 1) * dt - tm, b0[g] * dt - tm
        roots, _ = _roots_rows(ca - cb)
        real = roots.real
        ok = ((np.abs(roots.imag) < 1e-12) & (real >= lo[:, None] - 1e-9)
              & (real <= hi[:, None] + 1e-9))
        # the first of the real roots inside the gap nearest the gap's centre, as np.argmin's
        j = np.argmin(np.where(ok, np.abs(real), np.inf), axis=1)
        has = np.flatnonzero(ok.any(axis=1))
        if not has.size:
            continue
        t = real[has, j[has]]
        v_in = _polyval_rows(_polyder_rows(ca[has]), t)
        v_out = _polyval_rows(_polyder_rows(cb[has]), t)
        height = _polyval_rows(ca[has], t)
        for n, ti, tmi, vi, vo, h in zip(g[has].tolist(), t.tolist(), tm[has].tolist(),
                                         v_in.tolist(), v_out.tolist(), height.tolist()):
            if vi < 0 < vo:
                found.append((n, Contact(t=ti + tmi, height=h, v_in=vi, v_out=vo)))
    for n, contact in sorted(found, key=lambda f: f[0]):  # each track's bounces in order
        out.setdefault(int(row[n]), []).append(contact)
    return out


# ------------------------------------------------------------------------------------------
# the estimated starts (_end_state "start") of many tracks
def _local_states(pos: np.ndarray, dt: float, jobs: list[tuple]) -> list[tuple]:
    """:func:`methods._tracks.local_state` for many fits: ``jobs`` (row, frames, t_eval,
    sigma, rolling, floor) with ``pos`` (B, T, 2) -> list of (state, std)."""
    out: list[tuple | None] = [None] * len(jobs)
    groups: dict[tuple[int, bool], list[int]] = {}
    for n, (_, frames, _, _, rolling, _) in enumerate(jobs):
        groups.setdefault((len(frames), bool(rolling)), []).append(n)
    for (nf, rolling), members in groups.items():
        deg = min(2 if rolling or nf < 6 else 3, nf - 1)
        if deg < 1:  # one frame: the per-video function says what it does
            for n in members:
                r, frames, t_eval, sigma, rl, fl = jobs[n]
                out[n] = local_state(pos[r], dt, frames, t_eval, sigma, rolling=rl, floor=fl)
            continue
        rows = np.array([jobs[n][0] for n in members])
        frames = np.array([jobs[n][1] for n in members])
        t_eval = np.array([jobs[n][2] for n in members], dtype=np.float64)
        sigma = np.array([jobs[n][3] for n in members], dtype=np.float64)
        t = frames * dt - t_eval[:, None]
        state = np.empty((len(members), 4))
        std = np.empty((len(members), 4))
        for kk in (0, 1):
            if rolling and kk == 1:
                state[:, 1] = [jobs[n][5] for n in members]
                state[:, 3] = 0.0
                std[:, 1] = sigma
                std[:, 3] = sigma / (max(nf, 2) * dt)
                continue
            z = pos[rows[:, None], frames, kk]
            coef, cov = _polyfit_rows(t, z, deg, cov=True)
            resid = z - _polyval_rows(coef, t)
            dof = max(nf - deg - 1, 1)
            rms = np.sqrt(np.sum(resid**2, axis=1) / dof)
            s = np.maximum(sigma, rms)
            state[:, kk], state[:, kk + 2] = coef[:, -1], coef[:, -2]
            std[:, kk] = s * np.sqrt(cov[:, -1, -1])
            std[:, kk + 2] = s * np.sqrt(cov[:, -2, -2])
        std = np.maximum(std, _MIN_STATE_STD)
        for j, n in enumerate(members):
            out[n] = (state[j], std[j])
    return out


def _start_states(pos, dt, segs, floors, noises):
    """``methods._tracks._end_state(..., "start", ...)`` of every track: list of (state, std)."""
    out: list[tuple | None] = [None] * len(segs)
    jobs, info = [], []
    for i, seg in enumerate(segs):
        p = pos[i]
        if seg.stopped[0]:
            nz = noises[i]
            out[i] = (np.array([p[0, 0], floors[i], 0.0, 0.0]), np.array([nz, nz, 1e-3, 1e-3]))
            continue
        pieces = ([(a, b, False) for a, b in seg.flight_all]
                  + [(a, b, True) for a, b in seg.rolling])
        if pieces:
            a, b, rolling = min(pieces, key=lambda q: q[0])
            frames = np.arange(a, min(b, a + 10))
            jobs.append((i, frames, 0.0, noises[i], rolling, floors[i]))
            gap = slice(0, a + 1)
            inflate = bool((seg.floor_hit[gap] | seg.wall_hit[gap]).any()
                           or (~np.isfinite(p[gap]).all(axis=1)).any())
        else:  # no clean run: the first seen frames
            frames = np.flatnonzero(np.isfinite(p).all(axis=1))[:4]
            jobs.append((i, frames, 0.0, noises[i], False, 0.0))
            inflate = True
        info.append((i, inflate))
    for (i, inflate), (state, std) in zip(info, _local_states(pos, dt, jobs)):
        out[i] = (state, std * 10.0 if inflate else std)
    return out


# ------------------------------------------------------------------------------------------
def prepare_batch(observations: Sequence[Observation]) -> list[Track | None]:
    """:func:`methods._tracks.prepare` of many observations, bitwise the same Tracks.

    Tracks of the same length and ``dt`` are segmented, their contacts found and their starts
    estimated together (see the module).

    Parameters
    ----------
    observations : sequence of Observation, length N
        The ball's, with positions or frames (frames are tracked one video at a time, as
        ``prepare`` does; :func:`sysid_bench.core.tracking.track_batch` them first to batch that too).

    Returns
    -------
    list of Track or None, length N
        ``prepare(observations[i])``, or None where that raises ``ValueError`` (fewer than 3
        seen frames; ``state0`` outside the box).

    Raises
    ------
    ValueError
        An entry is not an :class:`~sysid_bench.core.estimator.Observation`.
    """
    obs = list(observations)
    for i, o in enumerate(obs):
        if not isinstance(o, Observation):
            raise ValueError(f"observations[{i}]: expected a sysid_bench.core.estimator.Observation, "
                             f"got {type(o).__name__}")
    out: list[Track | None] = [None] * len(obs)
    groups: dict[tuple[int, float], list[tuple[int, np.ndarray]]] = {}
    for i, o in enumerate(obs):
        try:
            pos = observed_positions(o, min_seen=3)
        except ValueError:
            continue
        groups.setdefault((pos.shape[0], float(o.dt)), []).append((i, pos))
    for (_, dt), members in groups.items():
        idx = [i for i, _ in members]
        for i, track in zip(idx, _prepare_group([obs[i] for i in idx],
                                                np.stack([p for _, p in members]), dt)):
            out[i] = track
    return out


def _prepare_group(obs: list[Observation], pos: np.ndarray, dt: float) -> list[Track | None]:
    """:func:`prepare_batch` of observations whose positions ``pos`` (B, T, 2) share ``dt``."""
    B = len(obs)
    given = np.array([np.nan if o.floor is None else float(o.floor) for o in obs])
    segs = _segment_rows(pos, dt, given)
    noises, floors, floor_std, floor_known = [], [], [], []
    redo = []
    for i, (o, seg) in enumerate(zip(obs, segs)):
        noise = max(float(seg.acc_noise.max()) * dt**2 / np.sqrt(6.0), 1e-4)
        noises.append(noise)
        if o.floor is not None:
            floors.append(float(o.floor))
            floor_std.append(0.0)
            floor_known.append(True)
            continue
        floor_known.append(False)
        floor, fs = floor_estimate(pos[i, :, 1], seg, noise)
        floors.append(floor)
        floor_std.append(fs)
        if not seg.on_floor.any():
            redo.append(i)
    if redo:  # the rolling test redone at the estimated floor (as prepare)
        for i, seg in zip(redo, _segment_rows(pos[redo], dt, np.array([floors[i] for i in redo]))):
            segs[i] = seg
    out: list[Track | None] = [None] * B
    estimate = [i for i in range(B) if obs[i].state0 is None]
    starts = dict(zip(estimate, _start_states(pos[estimate], dt, [segs[i] for i in estimate],
                                              [floors[i] for i in estimate],
                                              [noises[i] for i in estimate])))
    from sysid_bench.core import physics
    from sysid_bench.core.estimator import BOX_MARGIN

    for i, o in enumerate(obs):
        floor = floors[i]
        if o.state0 is not None:
            s0 = o.state0
            m = BOX_MARGIN
            if not (-m <= s0[0] <= physics.BOX_WIDTH + m
                    and floor - m <= s0[1] <= floor + physics.BOX_WIDTH + m):
                continue  # prepare raises ValueError
            s0, s0_std, known = clip_state(s0, floor), np.zeros(4), True
        else:
            s0, s0_std = starts[i]
            s0, known = clip_state(s0, floor), False
        track = Track(positions=pos[i].copy(), mask=np.isfinite(pos[i]).all(axis=1), dt=dt,
                      floor=floor, floor_known=floor_known[i], floor_std=floor_std[i],
                      state0=s0, state0_std=s0_std, state0_known=known, segments=segs[i],
                      input_kind="positions" if o.positions is not None else "frames",
                      noise=noises[i])
        out[i] = start_before_contact(track)
    return out
