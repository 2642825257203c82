"""Model checks of many videos' posteriors at once (``Vid2Param.identify_batch``, issue 39).

:func:`methods._simulation.check_prefixes` checks one video at a time: its fits are
``scipy.optimize.least_squares`` runs of 4-8 free quantities, each evaluation a batch of 5-9
simulations, and ~90% of a check's time was the optimiser's own overhead, not simulation
(~170 ms a video on 2 cores). :func:`check_batch` runs the same checks for a whole batch of
videos in lock step: every fit is a bounded Levenberg-Marquardt iteration vectorised over the
videos (a batched linear solve), and each iteration is one simulator call for all of them (the
point and its forward-difference steps). The videos are tracked by one
:func:`~sysid_bench.core.tracking.track_batch` and prepared by one
:func:`~methods._tracks_batch.prepare_batch` (bitwise ``prepare``'s Tracks). The steps of a
check are those of :func:`~methods._simulation.check_posterior` for the first prefix of a
video (no warm start):

1. the posterior mean from its start fitted inside :func:`~methods._simulation.state0_box`
   (``theta`` held, at most :data:`~methods._simulation.CHECK_STATE_SIMS` simulations);
2. where that fails, the region check: ``theta`` inside the 90% box and the start refitted,
   by continuation over :data:`~methods._simulation.REGION_STAGES` of the track;
3. passed: parameters the track cannot inform widened to the prior
   (:func:`~methods._simulation.uninformed`); failed: the best fit from the region's, over the
   whole prior box (:func:`~methods._simulation.widen_to_support`'s fit), and the intervals
   widened to hold it when it passes, to the prior otherwise.

A fit stops when it converges (relative decrease of the sum of squares or step below
:data:`~methods._simulation.CHECK_TOL`) or when its budget is spent (:data:`STOP_ON_PASS`: also
as soon as it passes; off, so that ``Check.rms_m`` is the fit's optimum as the per-video path
reports it: 141 simulations a video against 116 with it, 543 per video). The optimiser is not
scipy's trust-region reflective method, so a fit may end at another point of the same basin:
verdicts agree on the test split but not bitwise on every video (measured in the tests and
``docs/vid2param-speed.md``). Videos whose track cannot be checked (too few seen frames) or
whose start is known take the sequential path, which says why.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numba
import numpy as np

from methods._simulation import (
    CHECK_STATE_SIMS,
    CHECK_TOL,
    MEAN_NOTE,
    REGION_NOTE,
    REGION_SIMS,
    REGION_STAGES,
    SUPPORT_SIMS,
    UNINFORMED_CHI2,
    check_prefixes,
    region_box,
    state0_box,
    widen_failed,
    widen_uninformed,
)
from methods._tracks import Track, clip_state
from methods._tracks_batch import prepare_batch
from sysid_bench.core import physics
from sysid_bench.core.estimator import Check, Observation, Posterior
from sysid_bench.core.physics import BOX_WIDTH
from sysid_bench.core.simulator import CountingSimulator

__all__ = ["check_batch"]

#: forward-difference step of the fits' Jacobians, in [0, 1] box coordinates (as refine_fit's)
_H = 1e-6
#: Levenberg-Marquardt damping: start, shrink on an accepted step, grow on a rejected one, and
#: give up above the largest (the step has become a vanishing gradient step)
_LAM0, _LAM_DOWN, _LAM_UP, _LAM_MAX = 1e-3, 3.0, 4.0, 1e8


#: stop a fit as soon as its trajectory passes (the verdict cannot change after that); False
#: runs each fit to convergence, so ``Check.rms_m`` is the fit's own optimum, as the per-video
#: path reports it
STOP_ON_PASS = False


@lru_cache(maxsize=4096)
def _bound(n: int) -> float:
    return Check.bound(n)


class _Fits:
    """A bounded least-squares problem per video over the first ``m`` frames of each track.

    Coordinates (per video, in [lb, ub] within [0, 1]): the parameters mapped by the prior
    (when ``theta_fixed`` is None), then the initial state mapped by its box ``[lo_s, hi_s]``,
    exactly as :func:`methods._simulation.refine_fit` maps them.
    """

    def __init__(self, sim: CountingSimulator, tracks: list[Track], m: int,
                 theta_fixed: np.ndarray | None, theta_box, lo_s: np.ndarray, hi_s: np.ndarray,
                 counts: np.ndarray, idx: np.ndarray):
        self.sim, self.m, self.counts, self.idx = sim, m, counts, idx
        self.dt = tracks[0].dt
        self.floor = np.array([t.floor for t in tracks])
        mask = np.stack([t.mask[:m] for t in tracks])  # (N, m)
        pos = np.stack([t.positions[:m] for t in tracks])
        self.w = np.repeat(mask[:, :, None], 2, axis=2).reshape(len(tracks), -1).astype(float)
        self.obs = np.where(mask[:, :, None], np.nan_to_num(pos), 0.0).reshape(len(tracks), -1)
        self.theta_fixed = theta_fixed
        self.nt = 0 if theta_fixed is not None else 4
        self.D = self.nt + 4
        self.lo_s, self.span_s = lo_s, hi_s - lo_s
        n = len(tracks)
        self.lb, self.ub = np.zeros((n, self.D)), np.ones((n, self.D))
        if theta_fixed is None and theta_box is not None:
            lb = np.clip(physics.normalise_theta(np.asarray(theta_box[0], np.float64)), 0.0, 1.0)
            ub = np.clip(physics.normalise_theta(np.asarray(theta_box[1], np.float64)), 0.0, 1.0)
            lb = np.minimum(lb, ub)
            point = ub - lb < 1e-9
            lb = np.where(point, np.minimum(lb, 1.0 - 1e-9), lb)
            ub = np.where(point, lb + 1e-9, ub)
            self.lb[:, :4], self.ub[:, :4] = lb, ub

    def to_x(self, theta: np.ndarray | None, s0: np.ndarray) -> np.ndarray:
        x = np.empty((len(s0), self.D))
        if self.nt:
            x[:, :4] = physics.normalise_theta(theta)
        span = self.span_s
        x[:, self.nt:] = np.where(span > 0, (s0 - self.lo_s) / np.where(span > 0, span, 1.0), 0.5)
        return np.clip(x, self.lb, self.ub)

    def unpack(self, U: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``U`` (R, K, D) for the videos ``rows`` (R,): theta, state0 (R, K, 4) each."""
        if self.nt:
            th = physics.denormalise_theta(
                np.clip(U[..., :4], self.lb[rows, None, :4], self.ub[rows, None, :4]))
        else:
            th = np.broadcast_to(self.theta_fixed[rows, None], U.shape[:2] + (4,))
        s0 = clip_state(self.lo_s[rows, None] + np.clip(U[..., self.nt:], 0.0, 1.0)
                        * self.span_s[rows, None], self.floor[rows, None])
        return th, s0

    def resid(self, U: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Residuals (R, K, 2m) of the points ``U`` (R, K, D), zero where unseen (one simulator
        call for all of them)."""
        R, K = U.shape[:2]
        th, s0 = self.unpack(U, rows)
        fl = np.repeat(self.floor[rows], K)
        pos = self.sim.positions(th.reshape(R * K, 4), s0.reshape(R * K, 4), self.m, self.dt, fl)
        self.counts[self.idx[rows]] += K  # the rows' videos are distinct
        return (pos.reshape(R, K, -1) - self.obs[rows, None]) * self.w[rows, None]

    def jac(self, x: np.ndarray, r: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Forward-difference Jacobians (R, 2m, D) at ``x`` (R, D) whose residuals are ``r``
        (R, 2m), stepping inwards at a bound (D simulations a video)."""
        steps = np.where(x + _H <= self.ub[rows], _H, -_H)
        U = x[:, None] + steps[:, :, None] * np.eye(self.D)
        rs = self.resid(U, rows)
        return np.swapaxes((rs - r[:, None]) / steps[:, :, None], 1, 2)

    def solve(self, x0: np.ndarray, max_sims: int, stop_rms: np.ndarray | None = None,
              tol: float = CHECK_TOL) -> np.ndarray:
        """Bounded Levenberg-Marquardt from ``x0`` (N, D), every video in lock step; returns
        the best point found (never worse than the start).

        A trial step costs one simulation, its Jacobian (only when the step is taken) D more.
        Coordinates on a bound whose descent direction points out of the box are held for the
        step (a projected step would stall there). Each video stops when it converges
        (relative decrease of the sum of squares, or a step, below ``tol``), when its
        simulations reach ``max_sims``, or, with ``stop_rms`` (N,), as soon as its sum of
        squares is at most ``n_seen * stop_rms^2`` (its fit passes).
        """
        n = len(x0)
        x = np.clip(np.asarray(x0, dtype=np.float64), self.lb, self.ub)
        rows = np.arange(n)
        r = self.resid(x[:, None], rows)[:, 0]
        sims = np.full(n, 1)
        sse = np.einsum("ij,ij->i", r, r)
        n_res = self.w.sum(axis=1)
        stop_sse = (None if stop_rms is None or not STOP_ON_PASS
                    else n_res * np.asarray(stop_rms) ** 2)
        active = sims + self.D < max_sims
        if stop_sse is not None:
            active &= ~(sse <= stop_sse)
        J = np.zeros((n, r.shape[1], self.D))
        if active.any():
            a = np.flatnonzero(active)
            J[a] = self.jac(x[a], r[a], a)
            sims[a] += self.D
        lam = np.full(n, _LAM0)
        eye = np.eye(self.D)
        while active.any():
            a = np.flatnonzero(active)
            xa = x[a]
            A, g = _normal_equations(J, r, a)
            held = (((xa <= self.lb[a]) & (g > 0)) | ((xa >= self.ub[a]) & (g < 0)))
            keep = ~held
            A = A * keep[:, :, None] * keep[:, None, :] + held[:, :, None] * eye
            g = np.where(held, 0.0, g)
            diag = np.maximum(np.einsum("ikk->ik", A), 1e-12)
            M = A + lam[a, None, None] * diag[:, :, None] * eye
            step = -_solve(M, g)
            xn = np.clip(xa + step, self.lb[a], self.ub[a])
            rn = self.resid(xn[:, None], a)[:, 0]
            sims[a] += 1
            ssen = np.einsum("ij,ij->i", rn, rn)
            ok = ssen < sse[a]
            moved = np.linalg.norm(xn - xa, axis=1)
            conv = ok & ((sse[a] - ssen <= tol * sse[a])
                         | (moved <= tol * (tol + np.linalg.norm(xa, axis=1))))
            acc = a[ok]
            x[acc], r[acc], sse[acc] = xn[ok], rn[ok], ssen[ok]
            lam[acc] = np.maximum(lam[acc] / _LAM_DOWN, 1e-12)
            lam[a[~ok]] *= _LAM_UP
            done = conv | (sims[a] + self.D >= max_sims) | (lam[a] > _LAM_MAX) | (moved == 0.0)
            if stop_sse is not None:
                done |= sse[a] <= stop_sse[a]
            active[a[done]] = False
            more = acc[active[acc]]  # taken steps that go on: their Jacobians
            if more.size:
                J[more] = self.jac(x[more], r[more], more)
                sims[more] += self.D
        return x


@numba.njit(cache=True, nogil=True)
def _normal_equations(J: np.ndarray, r: np.ndarray, rows: np.ndarray):
    """``J^T J`` and ``J^T r`` of the videos ``rows`` (R,): (R, D, D) and (R, D).

    ``J`` (N, K, D) and ``r`` (N, K) as :meth:`_Fits.solve` keeps them. Bitwise
    ``np.einsum("irk,irl->ikl", J[rows], J[rows])`` and ``np.einsum("irk,ir->ik", ...)``: einsum
    adds the products one residual after another from zero, and so does this loop (each
    product rounded, no fused multiply-add: numba's default); ``J^T J`` is symmetric, so only
    its upper half is summed. It was ~20 % of the fits' time as einsum (one pass per output
    over the gathered ``J[rows]``), most of it not the arithmetic.
    """
    n, K, D = rows.shape[0], J.shape[1], J.shape[2]
    A = np.zeros((n, D, D))
    g = np.zeros((n, D))
    for j in range(n):
        i = rows[j]
        for q in range(K):
            rq = r[i, q]
            for k in range(D):
                jk = J[i, q, k]
                g[j, k] += jk * rq
                for m in range(k, D):
                    A[j, k, m] += jk * J[i, q, m]
        for k in range(D):
            for m in range(k):
                A[j, k, m] = A[j, m, k]
    return A, g


def _solve(M: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``M^-1 g`` for a batch of damped normal matrices (least squares where singular)."""
    try:
        return np.linalg.solve(M, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.stack([np.linalg.lstsq(Mi, gi, rcond=None)[0] for Mi, gi in zip(M, g)])


def _judge_all(sim: CountingSimulator, theta, s0, tracks: list[Track], noise_m: float,
               counts: np.ndarray, idx: np.ndarray) -> list[Check]:
    """The :class:`Check` of each video's one trajectory (one simulator call for all)."""
    fl = np.array([t.floor for t in tracks])
    T = tracks[0].n_frames
    pos = sim.positions(np.asarray(theta, np.float64), clip_state(np.asarray(s0, np.float64), fl),
                        T, tracks[0].dt, fl)
    counts[idx] += 1
    out = []
    noise = float(noise_m)
    for p, t in zip(pos, tracks):
        # Check.from_residuals's verdict, its chi-square bound cached by residual count
        r = (p - np.where(t.mask[:, None], t.positions, 0.0))[t.mask].ravel()
        if r.size == 0:
            out.append(Check.from_residuals(r, noise))
            continue
        rms = float(np.sqrt(np.mean(r * r)))
        out.append(Check(rms, noise, bool(rms <= _bound(r.size) * noise), int(r.size)))
    return out


def _uninformed_all(sim: CountingSimulator, theta: np.ndarray, s0: np.ndarray,
                    tracks: list[Track], noise_m: float, counts: np.ndarray,
                    idx: np.ndarray) -> np.ndarray:
    """:func:`~methods._simulation.uninformed` of each video (N, 4) bool, one simulator call
    (8 trajectories a video that is not still)."""
    n = len(tracks)
    flat = np.zeros((n, 4), dtype=bool)
    moving = []
    for i, t in enumerate(tracks):
        seen = t.positions[t.mask]
        if len(seen) and np.max(np.abs(seen - np.median(seen, axis=0))) <= 2.0 * float(noise_m):
            flat[i] = True  # a still track informs nothing
        else:
            moving.append(i)
    if not moving:
        return flat
    mv = np.array(moving)
    counts[idx[mv]] += 8
    th = np.repeat(theta[mv], 8, axis=0).reshape(len(mv), 8, 4)
    for k in range(4):
        th[:, 2 * k, k], th[:, 2 * k + 1, k] = physics.PRIOR_LO[k], physics.PRIOR_HI[k]
    fl = np.array([tracks[i].floor for i in mv])
    st = clip_state(np.repeat(s0[mv], 8, axis=0).reshape(len(mv), 8, 4), fl[:, None])
    T = tracks[0].n_frames
    pos = sim.positions(th.reshape(-1, 4), st.reshape(-1, 4), T, tracks[0].dt,
                        np.repeat(fl, 8)).reshape(len(mv), 8, T, 2)
    for j, i in enumerate(mv):
        p = pos[j][:, tracks[i].mask]
        d2 = np.sum((p[0::2] - p[1::2]) ** 2, axis=(1, 2))
        flat[i] = d2 < UNINFORMED_CHI2 * float(noise_m) ** 2
    return flat


def _pass_rms(tracks: list[Track], noise_m: float) -> np.ndarray:
    """The largest passing RMS (m) of each track's seen coordinates."""
    return np.array([_bound(2 * int(t.mask.sum())) * float(noise_m) for t in tracks])


def check_batch(posts: list[Posterior], frames: np.ndarray, noise_m: float,
                window: int | None = None, dt: float | None = None) -> list[Posterior]:
    """Model checks of the posteriors of whole videos, all at once (see the module).

    Parameters
    ----------
    posts : list of Posterior, length N
        Each video's posterior after all its frames.
    frames : ndarray, shape (N, T, H, W)
        The videos (tracked here with :func:`sysid_bench.core.tracking.track_batch`).
    noise_m : float
        The observation noise (m) the checks judge against.
    window : int, optional
        Only the last ``window`` frames are checked (as :func:`check_prefixes`'s).
    dt : float, optional
        Seconds between frames; None: the :class:`Observation` default.

    Returns
    -------
    list of Posterior, length N
        ``posts`` with ``check`` set, widened where it failed, as
        :func:`~methods._simulation.check_prefixes` on each video's full length would;
        ``extras["check_simulations"]`` counts each video's simulations.
    """
    from sysid_bench.core.tracking import track_batch

    fr = np.asarray(frames)
    n = len(posts)
    if n == 0:
        return []
    if fr.ndim != 4 or fr.shape[0] != n:
        raise ValueError(f"frames: expected shape ({n}, T, H, W) (one video per posterior), "
                         f"got {fr.shape}")
    T = fr.shape[1]
    obs_kw = {} if dt is None else {"dt": float(dt)}
    start = 0 if window is None else max(T - int(window), 0)
    pos = track_batch(fr, 0.0)
    pos[..., 0] = np.clip(pos[..., 0], 0.0, BOX_WIDTH)  # as observed_positions
    out: list[Posterior | None] = [None] * n
    tracks, idx = [], []
    # every video's prepare at once (bitwise the per-video Tracks; None where it would raise)
    prepared = prepare_batch([Observation(positions=pos[i, start:], **obs_kw) for i in range(n)])
    for i, track in enumerate(prepared):
        if track is None or track.state0_known:
            # nothing to fit here (or a known start): the sequential path says why
            out[i] = check_prefixes([posts[i]], Observation(frames=fr[i], **obs_kw), [T],
                                    noise_m, window)[0]
            continue
        tracks.append(track)
        idx.append(i)
    if tracks:
        for i, post in zip(idx, _check_tracks([posts[i] for i in idx], tracks, noise_m, T)):
            out[i] = post
    return out


def _check_tracks(posts: list[Posterior], tracks: list[Track], noise_m: float,
                  seed: int) -> list[Posterior]:
    """:func:`check_batch`'s checks of tracks of equal length with estimated starts."""
    sim = CountingSimulator()
    n = len(tracks)
    counts = np.zeros(n, dtype=int)
    every = np.arange(n)
    mean = np.array([np.asarray(p.mean, np.float64) for p in posts])
    boxes = [state0_box(t) for t in tracks]
    lo_s = np.array([b[0] for b in boxes])
    hi_s = np.array([b[1] for b in boxes])
    s0 = np.clip(np.array([t.state0 for t in tracks]), lo_s, hi_s)
    T = tracks[0].n_frames
    pass_rms = _pass_rms(tracks, noise_m)

    # 1. the posterior mean, its start fitted (theta held)
    f = _Fits(sim, tracks, T, mean, None, lo_s, hi_s, counts, every)
    x = f.solve(f.to_x(None, s0), CHECK_STATE_SIMS, stop_rms=pass_rms)
    s0 = f.unpack(x[:, None], every)[1][:, 0]
    mean_chk = _judge_all(sim, mean, s0, tracks, noise_m, counts, every)
    ok = np.array([c.ok for c in mean_chk])
    theta = mean.copy()
    final = list(mean_chk)
    notes = [MEAN_NOTE if c.ok else "" for c in mean_chk]

    # 2. the region check where the mean fails: theta inside the 90% box, the start refitted,
    # by continuation over longer parts of the track
    fail = np.flatnonzero(~ok)
    region_th, region_s0, region_chk = {}, {}, {}
    if fail.size:
        rb = [region_box(posts[i]) for i in fail]
        lo_t, hi_t = np.array([b[0] for b in rb]), np.array([b[1] for b in rb])
        th_r = np.clip(mean[fail], lo_t, hi_t)
        s0_r = s0[fail]
        sub = [tracks[i] for i in fail]
        for frac in REGION_STAGES:
            m = max(int(np.ceil(frac * T)), min(T, 3))
            use = np.array([t.mask[:m].sum() >= 3 for t in sub])
            if not use.any():
                continue
            rows = np.flatnonzero(use)
            f = _Fits(sim, [sub[j] for j in rows], m, None, (lo_t[rows], hi_t[rows]),
                      lo_s[fail[rows]], hi_s[fail[rows]], counts, fail[rows])
            stop = pass_rms[fail[rows]] if m >= T else None
            x = f.solve(f.to_x(th_r[rows], s0_r[rows]), REGION_SIMS, stop_rms=stop)
            th_new, s0_new = f.unpack(x[:, None], np.arange(len(rows)))
            th_r[rows], s0_r[rows] = th_new[:, 0], s0_new[:, 0]
        chk = _judge_all(sim, th_r, s0_r, sub, noise_m, counts, fail)
        for j, i in enumerate(fail):
            region_th[i], region_s0[i], region_chk[i] = th_r[j], s0_r[j], chk[j]
            p = posts[i]
            p.extras["region_box"] = [lo_t[j].tolist(), hi_t[j].tolist()]
            p.extras["region_rms_m"] = chk[j].rms_m
            p.extras["mean_rms_m"] = mean_chk[i].rms_m
            if chk[j].ok:
                ok[i] = True
                theta[i], s0[i] = th_r[j], s0_r[j]
                final[i] = chk[j]
                notes[i] = (f"{REGION_NOTE}: the posterior mean misses the track by "
                            f"{mean_chk[i].rms_m:.3g} m RMS, a parameter vector inside the "
                            f"interval explains it ({chk[j].rms_m:.3g} m RMS)")

    # 3a. passed: what the track cannot inform is widened to the prior
    out: list[Posterior | None] = [None] * n
    good = np.flatnonzero(ok)
    flats = _uninformed_all(sim, theta[good], s0[good], [tracks[i] for i in good], noise_m,
                            counts, good)
    for i, flat in zip(good, flats):
        post = widen_uninformed(posts[i], flat, seed=seed)
        post.check = dataclasses.replace(final[i], note=notes[i])
        out[i] = post
    # 3b. failed: the best fit over the prior box from the region's, judged as the mean was
    bad = np.flatnonzero(~ok)
    if bad.size:
        sub = [tracks[i] for i in bad]
        th0 = np.clip(np.array([region_th[i] for i in bad]), physics.PRIOR_LO, physics.PRIOR_HI)
        s00 = np.clip(np.array([region_s0[i] for i in bad]), lo_s[bad], hi_s[bad])
        f = _Fits(sim, sub, T, None, None, lo_s[bad], hi_s[bad], counts, bad)
        x = f.solve(f.to_x(th0, s00), SUPPORT_SIMS, stop_rms=pass_rms[bad])
        th_b, s0_b = (a[:, 0] for a in f.unpack(x[:, None], np.arange(len(bad))))
        chk_b = _judge_all(sim, th_b, s0_b, sub, noise_m, counts, bad)
        for j, i in enumerate(bad):
            check, post = mean_chk[i], posts[i]
            if not chk_b[j].ok:
                out[i] = widen_failed(post, check)
                continue
            best, rms = th_b[j], chk_b[j].rms_m
            std = np.maximum(post.std, np.abs(best - post.mean))
            samples = post.samples
            if samples is not None:
                samples = np.asarray(samples, dtype=np.float64)
                ratio = np.where(post.std > 0, std / np.where(post.std > 0, post.std, 1.0), 1.0)
                samples = np.clip(post.mean + (samples - post.mean) * ratio,
                                  physics.PRIOR_LO, physics.PRIOR_HI)
            note = (f"the posterior mean misses the track by {check.rms_m:.3g} m RMS; "
                    f"intervals widened to hold the best fit found from it ({rms:.3g} m RMS)")
            extras = {**post.extras, "check_failed": True, "support_fit": best.tolist(),
                      "support_rms_m": rms}
            out[i] = Posterior(mean=np.asarray(post.mean), std=std, samples=samples,
                               extras=extras, check=dataclasses.replace(check, note=note),
                               system=post.system)
    for i, post in enumerate(out):
        post.extras["check_simulations"] = int(counts[i])
    return out
