"""The bouncing ball: the suite's one source of physics (NumPy).

State ``[x, y, vx, vy]`` (m, m/s), parameters ``theta = [e, g, d, r]`` (see ``PRIOR``). The ball's
centre moves in the box ``[0, BOX_WIDTH] x [floor, floor + BOX_WIDTH]``:

* free flight with quadratic drag: ``ax = -d |v| vx``, ``ay = g - d |v| vy``;
* floor contact moving down: ``vy <- -e vy`` at the exact contact time;
* walls at ``x = 0`` and ``x = BOX_WIDTH`` reflect ``vx`` elastically at the exact contact time;
* rolling: a floor rebound slower than ``ROLL_SPEED`` leaves the ball on the floor with ``vy = 0``
  and ``ax = -r sign(vx)`` (no drag) until ``vx`` reaches 0, where it stops for good.

Integration is classical RK4 with ``SUBSTEPS`` steps per frame, vectorised over the batch. A step
that crosses a contact is cut at the contact: the contact time ``tau`` is the root of
``y(tau) = floor`` (or ``x(tau) = wall``) where ``y(tau)`` is itself one RK4 step of length ``tau``
from the start of the step, found by Newton's method to machine precision; the event is applied
there and the rest of the step integrated afresh. Contacts are therefore not snapped to frames or
steps. ``sysid_bench.physics_jax`` is the JAX twin of this module (same algorithm, tested equal).
"""

from __future__ import annotations

import numpy as np

from sysid_bench._validate import (
    as_float_array,
    check_positive_float,
    check_positive_int,
    check_seed,
)

__all__ = [
    "PARAMS",
    "PRIOR",
    "BOX_WIDTH",
    "DT",
    "N_FRAMES",
    "ROLL_SPEED",
    "SUBSTEPS",
    "STATE0_RANGES",
    "simulate",
    "sample_theta",
    "sample_state0",
    "normalise_theta",
    "denormalise_theta",
    "check_theta",
    "check_state0",
]

PARAMS: tuple[str, ...] = ("e", "g", "d", "r")
PRIOR: dict[str, tuple[float, float]] = {
    "e": (0.6, 1.0),
    "g": (-12.81, -6.81),
    "d": (0.0005, 0.05),
    "r": (0.0, 0.7),
}
BOX_WIDTH = 10.0  # m; the box is square: [0, 10] x [floor, floor + 10]
DT = 0.05  # s between frames
N_FRAMES = 200  # frames per video (10 s)
#: A floor rebound slower than this (m/s) starts rolling. At 0.25 m/s the hop would be 2-5 mm
#: high and last under one frame: invisible at any rendered size, and the cut-off stops the
#: Zeno cascade of ever smaller bounces.
ROLL_SPEED = 0.25
#: RK4 steps per frame interval (h = 12.5 ms at dt = 0.05); chosen so the simulator agrees with
#: a tight-tolerance event-driven solve_ivp reference to well under 1e-6 m (tests/test_physics.py).
SUBSTEPS = 3
#: The authors' ranges for initial states; velocities are drawn with a random sign.
STATE0_RANGES = {"x": (0.0, 10.0), "y": (6.0, 8.0), "vx": (4.0, 8.0), "vy": (3.0, 4.0)}

_LO = np.array([PRIOR[p][0] for p in PARAMS])
_HI = np.array([PRIOR[p][1] for p in PARAMS])
_NEWTON_ITERS = 1  # contact-time refinement from a parabolic guess (see _contact_time)
_MAX_STEPS = 64  # loop passes for one frame: SUBSTEPS steps plus one per contact


# --------------------------------------------------------------------------------------------
# validation
def check_theta(theta, n_frames: int | None = None, name: str = "theta") -> np.ndarray:
    """Validate parameters; returns float64 (B, 4) or (B, n_frames, 4).

    Raises ``ValueError`` for a wrong shape, NaN/inf, ``e`` outside [0, 1], ``g >= 0``,
    negative ``d`` or ``r``.
    """
    th = as_float_array(theta, name, ndim=(2, 3), last=len(PARAMS))
    if th.ndim == 3 and n_frames is not None and th.shape[1] != n_frames:
        raise ValueError(
            f"{name}: expected (B, n_frames={n_frames}, 4) for time-varying parameters, got shape {th.shape}"
        )
    e, g, d, r = (th[..., i] for i in range(4))
    if (e < 0).any() or (e > 1).any():
        raise ValueError(f"{name}: expected e in [0, 1], got values in [{e.min():g}, {e.max():g}]")
    if (g >= 0).any():
        raise ValueError(f"{name}: expected g < 0 (down), got max g = {g.max():g}")
    if (d < 0).any():
        raise ValueError(f"{name}: expected d >= 0, got min d = {d.min():g}")
    if (r < 0).any():
        raise ValueError(f"{name}: expected r >= 0, got min r = {r.min():g}")
    return th


def check_state0(state0, floor, name: str = "state0") -> np.ndarray:
    """Validate initial states (B, 4) against the box above ``floor`` (B,)."""
    s0 = as_float_array(state0, name, ndim=2, last=4)
    x, y = s0[:, 0], s0[:, 1]
    if (x < 0).any() or (x > BOX_WIDTH).any():
        raise ValueError(
            f"{name}: expected x in [0, {BOX_WIDTH:g}] (inside the box), got x in [{x.min():g}, {x.max():g}]"
        )
    rel = y - floor
    if (rel < 0).any() or (rel > BOX_WIDTH).any():
        raise ValueError(
            f"{name}: expected floor <= y <= floor + {BOX_WIDTH:g} (inside the box), "
            f"got y - floor in [{rel.min():g}, {rel.max():g}]"
        )
    return s0


def _check_floor(floor, batch: int) -> np.ndarray:
    fl = as_float_array(floor, "floor", ndim=(0, 1))
    if fl.ndim == 1 and fl.shape[0] != batch:
        raise ValueError(f"floor: expected a scalar or shape ({batch},), got shape {fl.shape}")
    return np.broadcast_to(fl, (batch,)).astype(np.float64)


# --------------------------------------------------------------------------------------------
# sampling helpers
def sample_theta(n: int, rng=None, subranges=None) -> np.ndarray:
    """Draw parameters uniformly from ``PRIOR``, optionally from chosen sub-ranges.

    Parameters
    ----------
    n : int
    rng : int, None or numpy.random.Generator
    subranges : sequence of int, optional
        Each parameter's range is cut into 10 equal sub-ranges numbered 0-9 from the low end;
        each draw picks one of these uniformly (independently per parameter), then a value
        uniformly within it. ``None`` draws from the whole range.

    Returns
    -------
    ndarray, shape (n, 4)
    """
    n = check_positive_int(n, "n")
    rng = check_seed(rng)
    if subranges is None:
        u = rng.random((n, len(PARAMS)))
    else:
        sub = np.asarray(subranges)
        if sub.ndim != 1 or sub.size == 0 or (sub < 0).any() or (sub > 9).any():
            raise ValueError(f"subranges: expected integers in 0..9, got {subranges!r}")
        k = rng.choice(sub, size=(n, len(PARAMS)))
        u = (k + rng.random((n, len(PARAMS)))) / 10.0
    return _LO + u * (_HI - _LO)


def sample_state0(n: int, rng=None, floor=0.0) -> np.ndarray:
    """Draw initial states from the authors' ranges (``STATE0_RANGES``), above ``floor``.

    Returns
    -------
    ndarray, shape (n, 4)
    """
    n = check_positive_int(n, "n")
    rng = check_seed(rng)
    fl = _check_floor(floor, n)
    lo = np.array([STATE0_RANGES[k][0] for k in ("x", "y", "vx", "vy")])
    hi = np.array([STATE0_RANGES[k][1] for k in ("x", "y", "vx", "vy")])
    s = lo + rng.random((n, 4)) * (hi - lo)
    s[:, 2:] *= rng.choice([-1.0, 1.0], size=(n, 2))
    s[:, 1] += fl
    return s


def normalise_theta(theta) -> np.ndarray:
    """Map parameters to [0, 1] by ``PRIOR`` (any leading shape, last axis 4)."""
    return (np.asarray(theta, dtype=np.float64) - _LO) / (_HI - _LO)


def denormalise_theta(u) -> np.ndarray:
    """Inverse of ``normalise_theta``."""
    return _LO + np.asarray(u, dtype=np.float64) * (_HI - _LO)


# --------------------------------------------------------------------------------------------
# integration
#
# Positions and velocities are complex numbers (x + iy, vx + i vy): the drag acceleration
# -d |v| v is then three array operations, which halves the NumPy calls of every RK4 stage.
def _rk4(p, v, h, c, k):
    """One classical RK4 step of length ``h`` (scalar or per ball).

    p, v : (n,) complex position and velocity; c : (n,) complex constant acceleration
    (``i g`` in flight, ``-r sgn(vx)`` while rolling); k : (n,) drag constant (0 while rolling).
    The acceleration is ``c - k |v| v``.
    """
    h2 = 0.5 * h
    a1 = c - k * np.abs(v) * v
    v2 = v + h2 * a1
    a2 = c - k * np.abs(v2) * v2
    v3 = v + h2 * a2
    a3 = c - k * np.abs(v3) * v3
    v4 = v + h * a3
    a4 = c - k * np.abs(v4) * v4
    h6 = h / 6.0
    return p + h6 * (v + 2.0 * (v2 + v3) + v4), v + h6 * (a1 + 2.0 * (a2 + a3) + a4)


def _acc(v, c, k):
    return c - k * np.abs(v) * v


def _contact_time(p, v, h, c, k, on_y, target):
    """Step length ``tau`` in [0, h] with ``RK4(p, v, tau)`` reaching ``target``.

    ``on_y`` (n,) bool picks the coordinate (y for the floor, x for a wall). The first guess is
    the root of the constant-acceleration parabola from the step start (error ~h^3); Newton's
    method on the RK4 step itself, whose derivative with respect to the step length is the
    end velocity up to O(tau^4), then converges quadratically: two iterations reach ~1e-15 s.
    """
    z0 = np.where(on_y, p.imag, p.real) - target
    a0c = _acc(v, c, k)
    w0 = np.where(on_y, v.imag, v.real)
    a0 = np.where(on_y, a0c.imag, a0c.real)
    # root of z0 + w0 t + a0 t^2 / 2 = 0 on the approach side, in the cancellation-free form
    disc = np.maximum(w0 * w0 - 2.0 * a0 * z0, 0.0)
    q = -0.5 * (w0 + np.copysign(np.sqrt(disc), w0))
    tau = np.where(q != 0, z0 / np.where(q != 0, q, 1.0), 0.0)
    tau = np.clip(tau, 0.0, h)
    for _ in range(_NEWTON_ITERS):
        pt, vt = _rk4(p, v, tau, c, k)
        f = np.where(on_y, pt.imag, pt.real) - target
        w = np.where(on_y, vt.imag, vt.real)
        w = np.where(np.abs(w) < 1e-12, np.copysign(1e-12, w), w)
        tau = np.clip(tau - f / w, 0.0, h)
    return tau


class _Balls:
    """Mutable batch state for ``simulate``: complex p, v, rolling flags and their forces."""

    def __init__(self, s0, floor):
        self.p = s0[:, 0] + 1j * s0[:, 1]
        self.v = s0[:, 2] + 1j * s0[:, 3]
        self.floor = floor
        self.rolling = np.zeros(len(floor), dtype=bool)
        self.any_rolling = False

    def set_params(self, e, g, d, r):
        self.e, self.g, self.d, self.r = e, g, d, r
        self._forces(slice(None))

    def _forces(self, j):
        """Effective constant acceleration and drag of balls ``j`` in their current mode."""
        if not self.any_rolling:
            if isinstance(j, slice):
                self.c, self.k = 1j * self.g, self.d.copy()
            else:
                self.c[j], self.k[j] = 1j * self.g[j], self.d[j]
            return
        if isinstance(j, slice):
            j = np.arange(self.p.size)
        roll = self.rolling[j]
        self.c[j] = np.where(roll, -self.r[j] * np.sign(self.v[j].real), 1j * self.g[j])
        self.k[j] = np.where(roll, 0.0, self.d[j])

    def _events(self, p, v, pn, vn, roll, c, fl):
        """Which balls cross the floor or a wall, or stop rolling, between (p, v) and (pn, vn).

        In flight vy never turns from down to up and vx never changes sign, and rolling is a
        constant deceleration, so a first contact stays visible at the end of a longer span.
        """
        hit = pn.real < 0.0
        hit |= pn.real > BOX_WIDTH
        hit |= (pn.imag < fl) & ~roll
        if self.any_rolling:
            hit |= roll & (c.real != 0) & (vn.real * v.real <= 0)
        return hit

    def advance_frame(self, dt, n_sub):
        """Advance every ball by ``dt`` in ``n_sub`` RK4 steps, each contact at its exact time.

        All balls take the plain steps first; the few with a contact in this frame are then
        redone from the frame start on their own, one contact at a time.
        """
        h = dt / n_sub
        steps = [(self.p, self.v)]
        for _ in range(n_sub):
            steps.append(_rk4(*steps[-1], h, self.c, self.k))
        p, v = steps[-1]
        hit = self._events(self.p, self.v, p, v, self.rolling, self.c, self.floor)
        if not hit.any():
            self.p, self.v = p, v
            return
        j = np.flatnonzero(hit)
        # Restart each of these balls at the start of the plain step holding its first contact.
        roll, c, fl = self.rolling[j], self.c[j], self.floor[j]
        first = np.full(j.size, n_sub - 1)
        for s in range(n_sub - 2, -1, -1):
            (pa, va), (pb, vb) = steps[s], steps[s + 1]
            inside = self._events(pa[j], va[j], pb[j], vb[j], roll, c, fl)
            first = np.where(inside, s, first)
        p0, v0 = steps[0][0][j], steps[0][1][j]
        for s in range(1, n_sub):
            at = first == s
            if at.any():
                p0[at], v0[at] = steps[s][0][j[at]], steps[s][1][j[at]]
        self.p, self.v = p, v
        self.p[j], self.v[j] = p0, v0
        self._resolve(j, dt - first * h, h)

    def _resolve(self, j, rem, h):
        """Integrate balls ``j`` over their remaining times ``rem`` in steps of at most ``h``.

        The subset is fixed for the whole frame (finished balls take zero-length steps, which
        RK4 leaves exactly unchanged): fewer NumPy calls than shrinking it every pass.
        """
        p, v, c, k = self.p[j], self.v[j], self.c[j], self.k[j]
        fl, roll = self.floor[j], self.rolling[j]
        e, g, d, r = self.e[j], self.g[j], self.d[j], self.r[j]
        for _ in range(_MAX_STEPS):
            hs = np.minimum(rem, h)
            pn, vn = _rk4(p, v, hs, c, k)
            hit = self._events(p, v, pn, vn, roll, c, fl)
            if not hit.any():
                p, v = pn, vn
                rem = rem - hs
                if not (rem > 0).any():
                    break
                continue
            quiet = ~hit
            p = np.where(quiet, pn, p)
            v = np.where(quiet, vn, v)
            rem = rem - np.where(quiet, hs, 0.0)
            i = np.flatnonzero(hit)
            pi, vi, ci, ki, rolli, tau = _contact(
                p[i], v[i], pn[i], hs[i], c[i], k[i], fl[i], roll[i], e[i], g[i], d[i], r[i]
            )
            p[i], v[i], c[i], k[i], roll[i] = pi, vi, ci, ki, rolli
            rem[i] -= tau
            if rolli.any():
                self.any_rolling = True
            if not (rem > 0).any():
                break
        else:
            raise RuntimeError("simulate: more contacts in one frame than expected")
        self.p[j], self.v[j], self.c[j], self.k[j], self.rolling[j] = p, v, c, k, roll


def _contact(p, v, pn, hs, c, k, fl, roll, e, g, d, r):
    """Move balls to their first contact within their step ``hs`` and apply it.

    Returns the new ``p, v``, forces ``c, k``, rolling flags and the time ``tau`` consumed.
    """
    n = p.size
    left = pn.real < 0.0
    wall = left | (pn.real > BOX_WIDTH)
    down = (pn.imag < fl) & ~roll
    stop = roll & ~wall  # rolling balls flagged without a wall can only be stopping
    # A ball may reach the floor and a wall in one step: solve both, keep the earlier.
    both = np.flatnonzero(down & wall)
    wall_x = np.where(left, 0.0, BOX_WIDTH)
    cand = np.concatenate((np.flatnonzero(down | wall), both))
    on_y = np.concatenate((down[cand[: cand.size - both.size]], np.zeros(both.size, bool)))
    t_floor = np.full(n, np.inf)
    t_wall = np.full(n, np.inf)
    if cand.size:
        target = np.where(on_y, fl[cand], wall_x[cand])
        t = _contact_time(p[cand], v[cand], hs[cand], c[cand], k[cand], on_y, target)
        t_floor[cand[on_y]] = t[on_y]
        t_wall[cand[~on_y]] = t[~on_y]
    # Rolling is constant deceleration: the stopping time is exact.
    t_stop = np.where(stop, np.abs(v.real) / np.where(stop, np.abs(c.real), 1.0), np.inf)
    tau = np.minimum(np.minimum(t_floor, t_wall), np.minimum(t_stop, hs))
    pc, vc = _rk4(p, v, tau, c, k)
    x, y, vx, vy = pc.real, pc.imag, vc.real, vc.imag

    # Apply the first contact (ties: all, so a corner hit reflects both axes).
    do_floor = t_floor <= tau
    vy_out = -e * vy
    slow = do_floor & (vy_out < ROLL_SPEED)
    y = np.where(do_floor, fl, y)
    vy = np.where(do_floor, np.where(slow, 0.0, vy_out), vy)
    roll = roll | slow
    do_wall = t_wall <= tau
    x = np.where(do_wall, wall_x, x)
    vx = np.where(do_wall, -vx, vx)
    vx = np.where(t_stop <= tau, 0.0, vx)
    c = np.where(roll, -r * np.sign(vx), 1j * g)
    k = np.where(roll, 0.0, d)
    return x + 1j * y, vx + 1j * vy, c, k, roll, tau


def simulate(theta, state0, n_frames: int = N_FRAMES, dt: float = DT, floor=0.0) -> np.ndarray:
    """Simulate a batch of bouncing balls and return their states at the frame times.

    Parameters
    ----------
    theta : array_like, shape (B, 4) or (B, n_frames, 4)
        ``[e, g, d, r]`` per ball, or per ball and frame, where ``theta[:, t]`` holds from frame
        ``t`` to frame ``t + 1`` (the last row is unused).
    state0 : array_like, shape (B, 4)
        ``[x, y, vx, vy]`` at frame 0, inside the box.
    n_frames : int
        Frames to return, frame 0 included.
    dt : float
        Seconds between frames.
    floor : float or array_like, shape (B,)
        Floor height per ball.

    Returns
    -------
    ndarray, shape (B, n_frames, 4)
        States at ``t = 0, dt, ..., (n_frames - 1) dt``; frame 0 equals ``state0``.
    """
    n_frames = check_positive_int(n_frames, "n_frames")
    dt = check_positive_float(dt, "dt")
    th = check_theta(theta, n_frames)
    s0 = as_float_array(state0, "state0", ndim=2, last=4)
    B = s0.shape[0]
    if th.shape[0] != B:
        raise ValueError(
            f"theta: expected {B} rows to match state0 (B={B}), got shape {th.shape}"
        )
    fl = _check_floor(floor, B)
    s0 = check_state0(s0, fl)

    out = np.empty((B, n_frames, 4))
    out[:, 0] = s0
    balls = _Balls(s0, fl)
    varying = th.ndim == 3
    if not varying:
        balls.set_params(*(th[:, i].copy() for i in range(4)))
    for t in range(n_frames - 1):
        if varying:
            balls.set_params(*(th[:, t, i].copy() for i in range(4)))
        balls.advance_frame(dt, SUBSTEPS)
        out[:, t + 1, 0] = balls.p.real
        out[:, t + 1, 1] = balls.p.imag
        out[:, t + 1, 2] = balls.v.real
        out[:, t + 1, 3] = balls.v.imag
    return out
