"""Weak-form evidence: a system's damping read off the network's own track, blended into its
posterior (the ``weak_evidence`` stage, :mod:`methods.vid2param.stages`).

A system's network reads its stiffness-like parameters from the period (the pendulum's g, the
spring's w2) but its damping only slowly, though its track holds it (its keypoints are a few
hundredths of a pixel off the truth on its own render). The equation of motion is linear in
the damping given the state, so a least-squares fit reads it; second differences of the track
would drown it in noise (the noise's second difference is ``sqrt(6) sigma / dt^2``), so each
window of ``WINDOW + 1`` frames is weighed by a smooth test function ``phi`` (zero at both ends)
and summed by parts twice, which moves every derivative onto ``phi``::

    x'' = sum_j a_j f_j(x, x')   ->   sum_t phi''_t x_t = sum_j a_j sum_t phi_t f_j(x_t, x'_t)

(a damping term ``-c x'`` becomes ``+c sum_t phi'_t x_t``: no derivative of the track at all).
Every window ending at a frame is one row of a running least-squares problem; after each
frame its solution and covariance (``sigma^2 (Phi^T Phi)^-1``, ``sigma^2`` from the residuals,
times ``1 + gain (W + 1) C / (n - C)`` for the overlapping windows) give an estimate, blended
with the network's posterior by inverse variance with the estimate's variance ``(kappa sd)^2 +
tau^2`` (``kappa``, ``tau`` per parameter and ``gain`` fitted by Gaussian NLL on train-split
videos, the network frozen). The collision's friction comes from such windows, its wall
restitution from the bounces (:class:`CollisionForm`). What each reads: the model card,
"Session 31".

As the ball's drag evidence (:mod:`methods.vid2param.drag`) the blend is not fed back into the
recurrence: the network runs as trained.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["WINDOW", "WEAK_FORMS", "WeakForm", "PendulumWeakForm", "SpringWeakForm",
           "CollisionForm", "WeakStatistic", "CollisionStatistic", "blend", "fit_blend",
           "window_weights", "PRIOR_MEAN", "PRIOR_STD"]

#: Frames in a window, less one (16: 0.8 s at 20 frames/s; 8 left the pendulum's mu at 0.022,
#: 24 and 32 no better than 16 on the measurement in the module's docstring).
WINDOW = 16
#: A window counts once it has this many valid windows more than coefficients.
MIN_EXTRA = 3


def window_weights(window: int, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``phi = (1 - s^2)^4`` on ``s`` in [-1, 1] over ``window + 1`` samples and its central first
    and second differences over ``dt`` (``phi`` is 0 beyond the window), each times the
    quadrature weight ``dt``: three arrays of shape (window + 1,).

    The differences, not the analytic derivatives: summed by parts, ``sum phi''_t x_t`` is then
    exactly ``sum phi_t (x_{t+1} - 2 x_t + x_{t-1}) / dt^2`` (``phi`` is 0 at both ends), so a
    constant offset of the track contributes nothing (the analytic weights summed to -0.0065
    over 16 frames, which on the collision's 5 m positions outweighed the friction term)."""
    s = np.linspace(-1.0, 1.0, int(window) + 1)
    u = 1.0 - s * s
    phi = u**4
    pad = np.concatenate([[0.0], phi, [0.0]])
    dphi = (pad[2:] - pad[:-2]) / (2.0 * dt)
    ddphi = (pad[2:] - 2.0 * phi + pad[:-2]) / dt**2
    return phi * dt, dphi * dt, ddphi * dt


#: Compiled once per machine (numba's on-disk cache). A stream's push and a batch run the same
#: kernels frame by frame, so both give the same bits.
_njit = numba.njit(cache=True, nogil=True)

#: Kinds of the window kernel.
_PENDULUM, _SPRING = 0, 1


class WeakForm:
    """A system's equation of motion in weak form, linear in ``n_coef`` coefficients; its rows
    are made by the compiled kernel of its ``kind`` (:func:`_window_update`).

    Attributes
    ----------
    system : str
    n_coef : int
        Coefficients of the linear model (C).
    blends : dict
        ``{param: (coefficient index, factor)}``: the parameter is ``factor * coef``.
    """

    system = ""
    n_coef = 0
    kind = -1
    blends: dict = {}
    #: blended parameters whose posterior is the prior's until the track shows their evidence
    unseen_prior: tuple = ()
    #: the pendulum's angle span under which a window is left out; the spring's centre
    STILL_RAD = 0.0
    X_REF = 0.0

    def statistic(self, batch: int, window: int = WINDOW, dt: float = 0.05, gain: float = 1.0):
        """The running statistic of ``batch`` tracks (``update``, ``summary``); ``gain``
        scales the overlapping windows' variance factor ``1 + gain (W + 1) C / (n - C)``."""
        return WeakStatistic(self, batch, window, dt, gain)

    def track(self, track, window: int = WINDOW, dt: float = 0.05, gain: float = 1.0):
        """The estimates and variances after every frame of many tracks.

        Parameters
        ----------
        track : ndarray, shape (..., T, K, 2)
            The tracked points, metres.

        Returns
        -------
        est, var : ndarray, shape (..., T, J)
            The blended parameters (``blends`` order) in physical units and their variances
            from what the frames up to each one show (NaN and inf before enough), the stream's
            numbers frame by frame.
        """
        tr = np.asarray(track, dtype=np.float64)
        lead, T = tr.shape[:-3], tr.shape[-3]
        tr = tr.reshape(-1, T, *tr.shape[-2:])
        J = len(self.blends)
        st = self.statistic(tr.shape[0], window, dt, gain)
        est = np.empty((tr.shape[0], T, J))
        var = np.empty((tr.shape[0], T, J))
        for t in range(T):
            st.update(tr[:, t])
            est[:, t], var[:, t] = st.summary()
        return est.reshape(*lead, T, J), var.reshape(*lead, T, J)


class PendulumWeakForm(WeakForm):
    """``theta'' = k sin(theta) - b omega - mu sign(omega)``, ``k = g / L``; the angle about the
    pivot at the world's origin (the default scene the network was trained on), unwrapped
    frame by frame. Rows: ``sum phi'' theta = k sum phi sin(theta) + b sum phi' theta - mu sum
    phi sign(omega)`` (omega's sign from the central difference at the inner frames). Windows
    where the angle spans less than ``STILL_RAD`` are left out: a bob at rest (stuck by
    friction) has no ``sign(omega)``."""

    system = "pendulum"
    n_coef = 3
    kind = _PENDULUM
    blends = {"b": (1, 1.0), "mu": (2, 1.0)}
    STILL_RAD = 0.02


class SpringWeakForm(WeakForm):
    """``x'' = a0 + a1 x + a2 x^2 + a3 x^3 - c x'``: the Duffing spring's cubic in the stretch
    ``x - L0`` expanded about a fixed ``X_REF`` (L0 is unknown; the cubic's top coefficient is
    ``-k3`` about any centre). Rows: ``sum phi'' x = sum_j a_j sum phi x^j + c sum phi' x``."""

    system = "spring"
    n_coef = 5
    kind = _SPRING
    blends = {"k3": (3, -1.0), "c": (4, 1.0)}
    X_REF = 1.5  # the middle of L0's prior (m): keeps the powers of order 1


@_njit
def _window_update(kind, pts, t, buf, prev, A, bv, yy, n, phi, dphi, ddphi, still, x_ref):
    """Add frame ``t`` (0-based) of B tracks ``pts`` (B, K, 2) to the window forms' state:
    ``buf`` (B, W + 1) the series' last W + 1 values (oldest first), ``prev`` (B,) the last
    value, the normal equations ``A`` (B, C, C), ``bv`` (B, C), ``yy`` and ``n`` (B,)."""
    B, W1 = buf.shape
    C = A.shape[1]
    reg = np.empty(C)
    for b in range(B):
        if kind == _PENDULUM:
            v = math.atan2(pts[b, 0, 0], -pts[b, 0, 1])
            if t > 0:  # unwrapped: the nearest turn of the new angle to the last one
                v = prev[b] + (v - prev[b] + math.pi) % (2.0 * math.pi) - math.pi
        else:
            v = pts[b, 0, 0] - x_ref
        prev[b] = v
        for j in range(W1 - 1):
            buf[b, j] = buf[b, j + 1]
        buf[b, W1 - 1] = v
        if t + 1 < W1:
            continue
        w = buf[b]
        ok = True
        lhs = 0.0
        for j in range(W1):
            if not math.isfinite(w[j]):
                ok = False
            lhs += w[j] * ddphi[j]
        if not ok:
            continue
        if kind == _PENDULUM:
            lo, hi = w[0], w[0]
            s_sin, s_d, s_sg = 0.0, 0.0, 0.0
            for j in range(W1):
                lo, hi = min(lo, w[j]), max(hi, w[j])
                s_sin += math.sin(w[j]) * phi[j]
                s_d += w[j] * dphi[j]
            for j in range(1, W1 - 1):
                d = w[j + 1] - w[j - 1]
                s_sg += (1.0 if d > 0 else (-1.0 if d < 0 else 0.0)) * phi[j]
            if hi - lo <= still:
                continue
            reg[0], reg[1], reg[2] = s_sin, s_d, -s_sg
        else:
            s0, s1, s2, s3, s_d = 0.0, 0.0, 0.0, 0.0, 0.0
            for j in range(W1):
                x = w[j]
                x2 = x * x
                s0 += phi[j]
                s1 += x * phi[j]
                s2 += x2 * phi[j]
                s3 += x2 * x * phi[j]
                s_d += x * dphi[j]
            reg[0], reg[1], reg[2], reg[3], reg[4] = s0, s1, s2, s3, s_d
        for i in range(C):
            for k in range(C):
                A[b, i, k] += reg[i] * reg[k]
            bv[b, i] += reg[i] * lhs
        yy[b] += lhs * lhs
        n[b] += 1.0


@_njit
def _lu_solve(M, piv, rhs):
    """``M^-1 rhs`` from ``M``'s LU factors in place (``_lu``) and its pivots."""
    C = M.shape[0]
    x = rhs.copy()
    for i in range(C):
        x[i], x[piv[i]] = x[piv[i]], x[i]
        for k in range(i):
            x[i] -= M[i, k] * x[k]
    for i in range(C - 1, -1, -1):
        for k in range(i + 1, C):
            x[i] -= M[i, k] * x[k]
        x[i] /= M[i, i]
    return x


@_njit
def _lu(M, piv):
    """Doolittle LU of ``M`` (C, C) in place with partial pivoting; ``piv[i]``: the row swapped
    with row i at step i."""
    C = M.shape[0]
    for i in range(C):
        p = i
        for r in range(i + 1, C):
            if abs(M[r, i]) > abs(M[p, i]):
                p = r
        piv[i] = p
        if p != i:
            for k in range(C):
                M[i, k], M[p, k] = M[p, k], M[i, k]
        for r in range(i + 1, C):
            M[r, i] /= M[i, i]
            for k in range(i + 1, C):
                M[r, k] -= M[r, i] * M[i, k]


@_njit
def _window_summary(A, bv, yy, n, idx, fac, min_rows, window, gain, est, var):
    """Least-squares estimates of the coefficients ``idx`` times ``fac`` and their variances
    (``sigma^2 (A^-1)_ii``, ``sigma^2`` from the residuals) into ``est``, ``var`` (B, J); NaN
    and inf with fewer than ``min_rows`` rows. A relative ridge of 1e-10 of the diagonal keeps
    a window set that does not excite a term (a pendulum at rest, a small cubic) solvable."""
    B, C = bv.shape
    J = idx.shape[0]
    W1 = window + 1
    M = np.empty((C, C))
    piv = np.empty(C, dtype=np.int64)
    e = np.empty(C)
    for b in range(B):
        if n[b] < min_rows:
            for j in range(J):
                est[b, j] = np.nan
                var[b, j] = np.inf
            continue
        tr = 0.0
        for i in range(C):
            tr += A[b, i, i]
        for i in range(C):
            for k in range(C):
                M[i, k] = A[b, i, k]
            M[i, i] += 1e-10 * tr / C + 1e-300
        _lu(M, piv)
        coef = _lu_solve(M, piv, bv[b])
        rss = yy[b]
        for i in range(C):
            rss -= coef[i] * bv[b, i]
        s2 = max(rss, 0.0) / max(n[b] - C, 1.0)
        # overlapping windows: n rows hold about n / W independent ones, so few rows read
        # their residuals' variance small and the coefficients' too (kappa is fitted at the
        # lengths pooled; ``gain``, fitted with it, keeps the first frames' intervals from
        # being far too narrow)
        s2 *= 1.0 + gain * W1 * C / (n[b] - C)
        for j in range(J):
            for i in range(C):
                e[i] = 0.0
            e[idx[j]] = 1.0
            x = _lu_solve(M, piv, e)
            est[b, j] = coef[idx[j]] * fac[j]
            var[b, j] = s2 * x[idx[j]]


class WeakStatistic:
    """The running weak-form fit of B tracks, one frame at a time (compiled).

    Parameters
    ----------
    form : WeakForm
    batch : int
    window : int
    dt : float
        Seconds per frame.
    """

    def __init__(self, form: WeakForm, batch: int, window: int = WINDOW, dt: float = 0.05,
                 gain: float = 1.0):
        B, C = int(batch), form.n_coef
        self.form, self.window, self.gain = form, int(window), float(gain)
        self.w = window_weights(self.window, dt)
        self.buf = np.full((B, self.window + 1), np.nan)
        self.prev = np.zeros(B)
        self.t = 0
        self.A = np.zeros((B, C, C))
        self.bv = np.zeros((B, C))
        self.yy = np.zeros(B)
        self.n = np.zeros(B)
        self.idx = np.array([i for i, _ in form.blends.values()], dtype=np.int64)
        self.fac = np.array([f for _, f in form.blends.values()], dtype=np.float64)
        self.est = np.empty((B, len(self.idx)))
        self.var = np.empty((B, len(self.idx)))

    def update(self, pts) -> None:
        """Add each track's newest points ``pts`` (B, K, 2) m."""
        f = self.form
        _window_update(f.kind, np.ascontiguousarray(pts, dtype=np.float64), self.t, self.buf,
                       self.prev, self.A, self.bv, self.yy, self.n, *self.w, f.STILL_RAD,
                       f.X_REF)
        self.t += 1

    def summary(self) -> tuple[np.ndarray, np.ndarray]:
        """The blended parameters' estimates and variances (B, J) so far (new arrays)."""
        _window_summary(self.A, self.bv, self.yy, self.n, self.idx, self.fac,
                        self.form.n_coef + MIN_EXTRA, self.window, self.gain, self.est,
                        self.var)
        return self.est.copy(), self.var.copy()


class CollisionForm(WeakForm):
    """The collision's friction and wall restitution, read where the track shows each alone.

    * ``mu``: between contacts each puck decelerates by ``mu`` against its velocity, so a window
      of ``WINDOW + 1`` frames in which a puck moves one way (every step over ``U_MIN``), both
      pucks at least ``MARGIN`` from the walls and from each other, is a weak-form row
      ``sum phi'' x = -mu sign(v) sum phi`` (two rows per window, one per puck).
    * ``ew``: a wall bounce (a puck moving towards its wall for ``K`` steps, two steps, then
      away for ``K`` steps, within ``MARGIN`` of the wall, the other puck away) gives the speeds
      in and out from straight lines through the ``K + 1`` frames on each side, taken to the
      contact (where each line meets the wall; kept where both lines put it a quarter step or
      more inside the two middle steps, so neither line holds a frame from the contact's other
      side) with the deceleration read by then; ``ew`` is the least-squares
      ratio of the speeds out to in over the bounces, its variance the lines' slope noise.

    Walls and puck size are the default scene's (the network's view).
    """

    system = "collision"
    blends = {"mu": (0, 1.0), "ew": (1, 1.0)}
    # before a wall bounce nothing shows ew, and the network reads it at guessing level (0.096
    # normalised MSE after 200 test frames, the uniform prior's 0.083): the prior until one
    unseen_prior = ("ew",)
    MARGIN = 0.5  # m: a frame's travel at 10 m/s, so no contact falls between two frames
    U_MIN = 0.01  # m per frame: 0.2 m/s, ~4x a step's noise on the network's track
    K = 4

    def statistic(self, batch: int, window: int = WINDOW, dt: float = 0.05, gain: float = 1.0):
        return CollisionStatistic(self, batch, window, dt, gain)


@_njit
def _line(p, s0, n):
    """Least-squares line through ``p[s0:s0 + n]`` at times ``s0..s0 + n - 1``: intercept,
    slope, residual sum of squares."""
    sm, pm = 0.0, 0.0
    for j in range(n):
        sm += s0 + j
        pm += p[s0 + j]
    sm /= n
    pm /= n
    sxx, sxy = 0.0, 0.0
    for j in range(n):
        d = s0 + j - sm
        sxx += d * d
        sxy += d * (p[s0 + j] - pm)
    v = sxy / sxx
    a = pm - v * sm
    rss = 0.0
    for j in range(n):
        r = p[s0 + j] - a - v * (s0 + j)
        rss += r * r
    return a, v, rss


@_njit
def _collision_update(pts, t, buf, f, bsum, cool, phi, ddphi, margin, u_min, K, R, XL, XR):
    """Add frame ``t`` of B two-puck tracks ``pts`` (B, 2, 2): ``buf`` (B, L, 2) the last L
    centres, ``f`` (B, 4) the friction rows' sums (reg^2, reg lhs, lhs^2, rows), ``bsum`` (B, 8)
    the bounces' sums (``CollisionStatistic.summary``), ``cool`` (B, 2) frames before a puck's
    next bounce may count."""
    B, L, _ = buf.shape
    W1 = phi.shape[0]
    n_b = 2 * K + 3
    sum_phi = 0.0
    for j in range(W1):
        sum_phi += phi[j]
    p = np.empty(n_b)
    for b in range(B):
        for j in range(L - 1):
            buf[b, j, 0] = buf[b, j + 1, 0]
            buf[b, j, 1] = buf[b, j + 1, 1]
        buf[b, L - 1, 0] = pts[b, 0, 0]
        buf[b, L - 1, 1] = pts[b, 1, 0]
        for i in range(2):
            cool[b, i] = max(cool[b, i] - 1.0, 0.0)
        if t + 1 >= W1:  # friction rows of the window of the last W1 frames
            j0 = L - W1
            free = True
            for j in range(j0, L):
                x1, x2 = buf[b, j, 0], buf[b, j, 1]
                if not (math.isfinite(x1) and math.isfinite(x2) and x1 > XL + margin
                        and x2 < XR - margin and x2 - x1 > 2.0 * R + margin):
                    free = False
            if free:
                for i in range(2):
                    sg = 1.0 if buf[b, j0 + 1, i] > buf[b, j0, i] else -1.0
                    moving = True
                    lhs = 0.0
                    for j in range(W1):
                        if j > 0 and (buf[b, j0 + j, i] - buf[b, j0 + j - 1, i]) * sg <= u_min:
                            moving = False
                        lhs += buf[b, j0 + j, i] * ddphi[j]
                    if moving:
                        reg = -sg * sum_phi
                        f[b, 0] += reg * reg
                        f[b, 1] += reg * lhs
                        f[b, 2] += lhs * lhs
                        f[b, 3] += 1.0
        if t + 1 < n_b:
            continue
        j0 = L - n_b
        far = True
        for j in range(j0, L):
            x1, x2 = buf[b, j, 0], buf[b, j, 1]
            if not (math.isfinite(x1) and math.isfinite(x2) and x2 - x1 > 2.0 * R + margin):
                far = False
        if not far:
            continue
        for i in range(2):
            if cool[b, i] > 0:
                continue
            wall = XL if i == 0 else XR
            toward = -1.0 if i == 0 else 1.0
            near = False
            for j in range(n_b):
                p[j] = buf[b, j0 + j, i]
                if abs(p[j] - wall) < margin:
                    near = True
            if not near:
                continue
            ok = True
            for j in range(n_b - 1):
                u = (p[j + 1] - p[j]) * toward  # > 0: towards the wall
                if j < K and not u > u_min:
                    ok = False
                if j > K + 1 and not u < -u_min:
                    ok = False
            if not ok:
                continue
            a1, v1, r1 = _line(p, 0, K + 1)
            a2, v2, r2 = _line(p, K + 2, K + 1)
            c1 = (wall - a1) / v1
            c2 = (wall - a2) / v2
            # the contact a quarter step or more inside the two middle steps: every contact
            # time is so placed at one of two alignments, and neither line then holds a frame
            # from its other side
            if not (K + 0.25 < c1 < K + 1.75 and K + 0.25 < c2 < K + 1.75):
                continue
            sc = 0.5 * (c1 + c2)
            # a line's slope is the speed at its middle frame: the contact is d_in frames later
            # (slower by dec d_in) and d_out frames before the line out's middle; dec is
            # applied in summary, with the friction read by then
            s1, s2 = abs(v1), abs(v2)
            d_in, d_out = sc - K / 2.0, (K + 2.0 + K / 2.0) - sc
            sxx = 0.0
            for j in range(K + 1):
                sxx += (j - K / 2.0) ** 2
            sv2 = (r1 + r2) / (2.0 * (K + 1) - 4.0) / sxx
            cols = (s1 * s2, s1 * d_out - s2 * d_in, d_in * d_out, s1 * s1, s1 * d_in,
                    d_in * d_in, sv2)
            good = True
            for c in cols:
                if not math.isfinite(c):
                    good = False
            if not good:
                continue
            for k in range(7):
                bsum[b, k] += cols[k]
            bsum[b, 7] += 1.0
            cool[b, i] = 2.0 * K + 1.0


@_njit
def _collision_summary(f, bsum, dt, min_rows, window, gain, est, var):
    """``mu`` (m/s^2) and ``ew`` and their variances into ``est``, ``var`` (B, 2)."""
    B = f.shape[0]
    for b in range(B):
        fa, fb, fyy, fn = f[b, 0], f[b, 1], f[b, 2], f[b, 3]
        mu = np.nan
        if fn >= min_rows and fa > 0:
            mu = fb / fa
            s2 = max(fyy - mu * fb, 0.0) / max(fn - 1.0, 1.0)
            s2 *= 1.0 + gain * (window + 1.0) / (fn - 1.0)  # overlapping windows (as above)
            est[b, 0], var[b, 0] = mu, s2 / fa
        else:
            est[b, 0], var[b, 0] = np.nan, np.inf
        pq, pd, dd, qq, qd, d2, sv2, bn = (bsum[b, 0], bsum[b, 1], bsum[b, 2], bsum[b, 3],
                                            bsum[b, 4], bsum[b, 5], bsum[b, 6], bsum[b, 7])
        # the speeds at the contacts, friction taken off with what is read now (0 before)
        dec = max(mu, 0.0) * dt * dt if math.isfinite(mu) else 0.0
        num = pq + dec * pd - dec * dec * dd  # sum vin vout
        den = qq - 2.0 * dec * qd + dec * dec * d2  # sum vin^2
        if bn >= 1 and den > 0:
            ew = num / den
            est[b, 1], var[b, 1] = ew, (sv2 / bn) * (1.0 + ew * ew) / den
        else:
            est[b, 1], var[b, 1] = np.nan, np.inf


class CollisionStatistic:
    """:class:`CollisionForm`'s running statistic of B tracks (``update``, ``summary``)."""

    def __init__(self, form: CollisionForm, batch: int, window: int = WINDOW, dt: float = 0.05,
                 gain: float = 1.0):
        from sysid_bench.core.systems.collision import XL, XR, R

        B = int(batch)
        self.form, self.window, self.dt, self.gain = form, int(window), float(dt), float(gain)
        self.w = window_weights(self.window, dt)
        self.geometry = (float(R), float(XL), float(XR))
        self.buf = np.full((B, max(self.window + 1, 2 * form.K + 3), 2), np.nan)
        self.t = 0
        self.f = np.zeros((B, 4))
        # the bounces' sums: speeds in and out and their friction terms (summary), the lines'
        # slope variance, the count
        self.b = np.zeros((B, 8))
        self.cool = np.zeros((B, 2))
        self.est = np.empty((B, 2))
        self.var = np.empty((B, 2))

    def update(self, pts) -> None:
        """Add each track's newest points ``pts`` (B, 2, 2) m."""
        f = self.form
        phi, _, ddphi = self.w
        _collision_update(np.ascontiguousarray(pts, dtype=np.float64), self.t, self.buf, self.f,
                          self.b, self.cool, phi, ddphi, f.MARGIN, f.U_MIN, f.K, *self.geometry)
        self.t += 1

    def summary(self) -> tuple[np.ndarray, np.ndarray]:
        """``mu`` (m/s^2) and ``ew`` and their variances (B, 2); NaN and inf before any row."""
        _collision_summary(self.f, self.b, self.dt, 1 + MIN_EXTRA, self.window, self.gain,
                           self.est, self.var)
        return self.est.copy(), self.var.copy()


#: The systems with a weak form, by name.
WEAK_FORMS: dict[str, WeakForm] = {f.system: f for f in (PendulumWeakForm(), SpringWeakForm(),
                                                         CollisionForm())}


#: The uniform prior's normalised mean and std: a parameter only its evidence shows, before any.
PRIOR_MEAN, PRIOR_STD = 0.5, 1.0 / math.sqrt(12.0)


def blend(mu, sd, est, var, lo, width, kappa, tau, unseen_prior=False):
    """The network's normalised posterior ``mu``, ``sd`` (..., J) combined with the weak-form
    estimates ``est`` and variances ``var`` (..., J, physical units) by inverse variance, the
    estimate's variance ``(kappa sd_est)^2 + tau^2`` (normalised). Where there is no estimate
    yet the network's posterior is kept, or, for the parameters ``unseen_prior`` (bool, (J,))
    marks (the collision's ew before a wall bounce: the network reads it at guessing level), the
    uniform prior's mean and std."""
    u = (est - lo) / width
    # a floor far below any fitted tau: residuals that vanish in float64 give no infinite weight
    v = np.maximum(kappa**2 * var / width**2 + tau**2, 1e-12)
    have = np.isfinite(u) & np.isfinite(v)
    wn = 1.0 / (sd * sd)
    wl = 1.0 / np.where(have, v, 1.0)
    m = (wn * mu + wl * np.where(have, u, 0.0)) / (wn + wl)
    prior = ~have & np.asarray(unseen_prior, dtype=bool)
    m_out = np.where(have, m, np.where(prior, PRIOR_MEAN, mu))
    s_out = np.where(have, 1.0 / np.sqrt(wn + wl), np.where(prior, PRIOR_STD, sd))
    return m_out, s_out


#: The variance factor's gains tried (``WeakForm.statistic``): 0 leaves the residuals' variance
#: as it is, 1 counts about one independent row per window length.
GAINS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
#: The blend's search grid: ``kappa`` (a factor on the least-squares std, whose windows overlap
#: and whose residuals are not white) and ``tau`` (a floor, normalised: the fit's own bias).
KAPPAS = np.exp(np.linspace(np.log(0.3), np.log(30.0), 25))
TAUS = np.array([0.0, 0.001, 0.003, 0.01, 0.02, 0.05, 0.1])


def fit_blend(mu, sd, est, var, truth, lo, width, frames=(50, 100, 150, 200),
              unseen_prior=False):
    """``kappa``, ``tau`` of one parameter minimising the blended posterior's Gaussian NLL of
    the truths over the frames ``frames`` (1-based counts) of N videos.

    Parameters
    ----------
    mu, sd : ndarray, shape (N, T)
        The network's normalised posterior of the parameter.
    est, var : ndarray, shape (N, T)
    truth : ndarray, shape (N,)
        Normalised.

    Returns
    -------
    kappa, tau, nll : float
    """
    T = mu.shape[1]
    sel = [int(f) - 1 for f in frames if 0 < int(f) <= T] or [T - 1]
    m, s, e, v = (np.asarray(a)[:, sel] for a in (mu, sd, est, var))
    y = np.asarray(truth)[:, None]
    best = (1.0, 0.0, np.inf)
    for k in KAPPAS:
        for t in TAUS:
            bm, bs = blend(m, s, e, v, lo, width, k, t, unseen_prior)
            nll = float(np.mean(np.log(bs) + 0.5 * ((bm - y) / bs) ** 2))
            if nll < best[2]:
                best = (float(k), float(t), nll)
    return best
