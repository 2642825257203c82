"""The bouncing ball: the suite's one source of physics (NumPy).

State ``[x, y, vx, vy]`` (m, m/s), parameters ``theta = [e, g, d, r]`` (see ``PRIOR``). The ball's
centre moves in the box ``[0, BOX_WIDTH] x [floor, floor + BOX_WIDTH]``:

* free flight with quadratic drag: ``ax = -d |v| vx``, ``ay = g - d |v| vy``;
* floor contact moving down: ``vy <- -e vy`` at the exact contact time;
* walls at ``x = 0`` and ``x = BOX_WIDTH`` reflect ``vx`` elastically at the exact contact time;
* rolling: a floor rebound slower than ``ROLL_SPEED`` leaves the ball on the floor with ``vy = 0``
  and ``ax = -r sign(vx)`` (no drag) until ``vx`` reaches 0, where it stops for good.

The walls and the floor are the design's by default; ``simulate(..., floor=None)`` has no floor
(free fall) and ``walls=(left, right)`` moves the walls or ``walls=None`` removes them (free in
x): the scene of ``systems.get("ball").simulate(..., scene=BallScene(...))``. With the defaults
every number is as it was (the kernel takes the walls as arguments, compared the same way).

Integration is classical RK4 with ``SUBSTEPS`` steps per frame, one ball at a time in scalar code
compiled by numba (cached on disk after the first call of a machine). A step
that crosses a contact is cut at the contact: the contact time ``tau`` is the root of
``y(tau) = floor`` (or ``x(tau) = wall``) where ``y(tau)`` is itself one RK4 step of length ``tau``
from the start of the step, found by Newton's method to machine precision; the event is applied
there and the rest of the step integrated afresh. Contacts are therefore not snapped to frames or
steps. ``sysid_bench.core.physics_jax`` is the JAX twin of this module (same algorithm, tested equal).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sysid_bench.core._validate import (
    as_float_array,
    check_int_array,
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
    "ENVELOPE",
    "V_MAX",
    "DT_MAX",
    "FLOOR_MAX",
    "MAX_FRAMES",
    "DRAG_STEP",
    "CONTACTS_MAX",
    "simulate",
    "simulate_perturbed",
    "sample_theta",
    "sample_state0",
    "normalise_theta",
    "denormalise_theta",
    "check_theta",
    "check_state0",
    "PRIOR_LO",
    "PRIOR_HI",
    "PRIOR_SPAN",
    "PRIOR_MEAN",
    "PRIOR_STD",
    "check_dt",
    "check_step",
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

#: The inputs the model is meant for (and tested at every corner, tests/test_physics.py). Outside
#: them the integrator is not stable or the box is not resolved: RK4 at ``d = 1e6`` or
#: ``vx0 = 1e6`` overflows to NaN, ``g = -1e9`` or ``dt = 100`` packs hundreds of contacts into
#: one frame, a floor at 1e300 m leaves no bits for the 10 m box. ``simulate`` raises
#: ``ValueError`` naming the input instead. Parameters, closed ranges (``g`` must also be < 0):
#: ``e`` in [0, 1] (no energy gain at the floor); ``g`` down to -100 m/s^2 (~10 Earth g; PRIOR's
#: span is [-12.81, -6.81]); ``d`` up to 2 /m (40x PRIOR's top; a ping-pong ball is ~0.15);
#: ``r`` up to 100 m/s^2.
ENVELOPE: dict[str, tuple[float, float]] = {
    "e": (0.0, 1.0),
    "g": (-100.0, 0.0),
    "d": (0.0, 2.0),
    "r": (0.0, 100.0),
}
#: Largest initial velocity component, m/s (the authors' largest is 8).
V_MAX = 100.0
#: Longest frame interval, s (1 frame/s); within it, ``CONTACTS_MAX`` bounds dt with g and speed.
DT_MAX = 1.0
#: Most contacts one frame may hold: the kernel allows ``_MAX_STEPS`` (64) passes per frame, a
#: contact costs at most two, ``SUBSTEPS`` plain steps the rest. Estimated per ball as
#: ``1.25 dt |g| / (2 ROLL_SPEED)`` floor bounces (a rebound at ``ROLL_SPEED`` is the shortest
#: hop; 1.25 for drag shortening it) plus ``v_bound dt / BOX_WIDTH + 1`` wall hits. The design's
#: physics has ~3; |g| = 100 allows dt up to ~0.1 s, the prior's |g| up to ~0.8 s.
CONTACTS_MAX = 24
#: Largest floor height magnitude, m: keeps ~1e-13 m resolution inside the box.
FLOOR_MAX = 1000.0
#: Most frames one ``simulate`` call makes: 14 hours at 20 frames/s, 32 MB per ball. Beyond it
#: a typo (``10**9``) would be a ``MemoryError`` from NumPy instead of an error naming it.
MAX_FRAMES = 1_000_000
#: Largest drag per RK4 step, ``d * v_bound * dt / SUBSTEPS``, where
#: ``v_bound = sqrt(vx0^2 + vy0^2 + 2 |g| (y0 - floor))`` bounds the speed (energy never grows).
#: RK4 is stable for drag up to ~1.39 per step (eigenvalue 2 d |v|); 0.5 keeps a margin. The
#: design's physics is at ~0.015.
DRAG_STEP = 0.5

#: The design's walls, ``(0, BOX_WIDTH)``: ``simulate``'s default ``walls``.
_BOX = (0.0, BOX_WIDTH)
_LO = np.array([PRIOR[p][0] for p in PARAMS])
_HI = np.array([PRIOR[p][1] for p in PARAMS])
#: ``PRIOR`` as arrays in ``PARAMS`` order, defined here once: bounds, width, and the mean and
#: standard deviation of the uniform prior (what "no information" honestly reports).
PRIOR_LO = _LO.copy()
PRIOR_HI = _HI.copy()
PRIOR_SPAN = PRIOR_HI - PRIOR_LO
PRIOR_MEAN = (PRIOR_LO + PRIOR_HI) / 2
PRIOR_STD = PRIOR_SPAN / np.sqrt(12.0)
for _a in (PRIOR_LO, PRIOR_HI, PRIOR_SPAN, PRIOR_MEAN, PRIOR_STD):
    _a.setflags(write=False)
_NEWTON_ITERS = 1  # contact-time refinement from a parabolic guess (see _contact_time)
_MAX_STEPS = 64  # loop passes for one frame: SUBSTEPS steps plus one per contact
#: Compiled once per machine (numba's on-disk cache); error_model="numpy": 1/0 gives inf, not an
#: exception, as the arithmetic of the NumPy reference it replaced.
_njit = numba.njit(cache=True, nogil=True, error_model="numpy")


# --------------------------------------------------------------------------------------------
# validation
def check_theta(theta, n_frames: int | None = None, name: str = "theta") -> np.ndarray:
    """Validate parameters; returns float64 (B, 4) or (B, n_frames, 4).

    Raises ``ValueError`` for a wrong shape, NaN/inf, ``g >= 0`` or any parameter outside
    ``ENVELOPE``.
    """
    th = as_float_array(theta, name, ndim=(2, 3), last=len(PARAMS))
    if th.ndim == 3 and n_frames is not None and th.shape[1] != n_frames:
        raise ValueError(
            f"{name}: expected (B, n_frames={n_frames}, 4) for time-varying parameters, got shape {th.shape}"
        )
    if th.shape[0] == 0:  # an empty batch: nothing to check (simulate answers (0, T, 4))
        return th
    # one min and one max per parameter: cheap next to any simulation
    flat = th.reshape(-1, len(PARAMS))
    lo, hi = flat.min(axis=0), flat.max(axis=0)
    if hi[1] >= 0:
        raise ValueError(f"{name}: expected g < 0 (down), got max g = {hi[1]:g}")
    for i, p in enumerate(PARAMS):
        a, b = ENVELOPE[p]
        if lo[i] < a or hi[i] > b:
            what = {"d": "d >= 0 and ", "r": "r >= 0 and "}.get(p, "")
            raise ValueError(
                f"{name}: expected {what}{p} in [{a:g}, {b:g}] (physics.ENVELOPE), "
                f"got values in [{lo[i]:g}, {hi[i]:g}]"
            )
    return th


def check_state0(state0, floor, name: str = "state0", walls=_BOX) -> np.ndarray:
    """Validate initial states (B, 4): inside the box above ``floor`` (B,), speeds up to ``V_MAX``.

    With other ``walls`` (a validated ``(left, right)`` or None) or no floor (``floor`` all
    ``-inf``), x must lie between the walls (if any), y above the floor (if any), and both
    within ``FLOOR_MAX`` of the origin; the design's box keeps its own check below.
    """
    s0 = as_float_array(state0, name, ndim=2, last=4)
    x, y = s0[:, 0], s0[:, 1]
    vmax = float(np.abs(s0[:, 2:]).max(initial=0.0))
    if vmax > V_MAX:
        raise ValueError(
            f"{name}: expected |vx|, |vy| <= {V_MAX:g} m/s (physics.V_MAX), got {vmax:g}"
        )
    floor = np.broadcast_to(np.asarray(floor, dtype=np.float64), y.shape)
    if walls != _BOX or not np.isfinite(floor).all():
        _check_state0_scene(x, y, floor, walls, name)
        return s0
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


def _check_state0_scene(x, y, floor, walls, name) -> None:
    big = float(np.abs(np.concatenate([x, y])).max(initial=0.0))
    if big > FLOOR_MAX:
        raise ValueError(f"{name}: expected |x|, |y| <= {FLOOR_MAX:g} m (physics.FLOOR_MAX), got {big:g}")
    if walls is not None and ((x < walls[0]).any() or (x > walls[1]).any()):
        raise ValueError(
            f"{name}: expected x between the walls {tuple(walls)}, got x in [{x.min():g}, {x.max():g}]"
        )
    rel = y - floor
    if (rel < 0).any():
        raise ValueError(f"{name}: expected y >= floor (above the floor), got y - floor down to {rel.min():g}")


def _check_walls(walls):
    """``walls`` as a tuple ``(left, right)`` of floats, or None (no walls)."""
    if walls is None:
        return None
    w = as_float_array(walls, "walls", ndim=1)
    if w.shape != (2,) or not w[0] < w[1] or np.abs(w).max() > FLOOR_MAX:
        raise ValueError(f"walls: expected None or (left, right) metres with left < right, both "
                         f"within {FLOOR_MAX:g} m (physics.FLOOR_MAX), got {walls!r}")
    return (float(w[0]), float(w[1]))


def _check_floor(floor, batch: int) -> np.ndarray:
    fl = as_float_array(floor, "floor", ndim=(0, 1))
    if fl.ndim == 1 and fl.shape[0] != batch:
        raise ValueError(f"floor: expected a scalar or shape ({batch},), got shape {fl.shape}")
    big = float(np.abs(fl).max(initial=0.0))
    if big > FLOOR_MAX:
        raise ValueError(f"floor: expected |floor| <= {FLOOR_MAX:g} m (physics.FLOOR_MAX), got {big:g}")
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
        sub = check_int_array(subranges, "subranges", lo=0, hi=9)
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
    return (as_float_array(theta, "theta", last=len(PARAMS), allow_nan=True) - _LO) / (_HI - _LO)


def denormalise_theta(u) -> np.ndarray:
    """Inverse of ``normalise_theta``."""
    return _LO + as_float_array(u, "u", last=len(PARAMS), allow_nan=True) * (_HI - _LO)


# --------------------------------------------------------------------------------------------
# integration
#
# Compiled by numba (see _simulate_kernel): plain steps vectorised across balls, contacts one
# ball at a time in scalar code, so a contact costs a few dozen floating-point operations for
# the ball that has it instead of a fixed number of array passes over the whole batch (what the
# earlier vectorised NumPy version paid, since with thousands of balls some ball has a contact in
# nearly every frame). Balls are independent, so batch order and chunking change nothing.
# A ball's state is (x, y, vx, vy); its forces are a constant acceleration (cx, cy) (``(0, g)`` in
# flight, ``(-r sgn(vx), 0)`` while rolling) and a drag constant k (0 while rolling): the
# acceleration is ``c - k |v| v``.
@_njit
def _rk4(x, y, vx, vy, h, cx, cy, k):
    """One classical RK4 step of length ``h``; returns the new (x, y, vx, vy)."""
    h2 = 0.5 * h
    s = k * math.sqrt(vx * vx + vy * vy)
    a1x, a1y = cx - s * vx, cy - s * vy
    v2x, v2y = vx + h2 * a1x, vy + h2 * a1y
    s = k * math.sqrt(v2x * v2x + v2y * v2y)
    a2x, a2y = cx - s * v2x, cy - s * v2y
    v3x, v3y = vx + h2 * a2x, vy + h2 * a2y
    s = k * math.sqrt(v3x * v3x + v3y * v3y)
    a3x, a3y = cx - s * v3x, cy - s * v3y
    v4x, v4y = vx + h * a3x, vy + h * a3y
    s = k * math.sqrt(v4x * v4x + v4y * v4y)
    a4x, a4y = cx - s * v4x, cy - s * v4y
    h6 = h / 6.0
    return (
        x + h6 * (vx + 2.0 * (v2x + v3x) + v4x),
        y + h6 * (vy + 2.0 * (v2y + v3y) + v4y),
        vx + h6 * (a1x + 2.0 * (a2x + a3x) + a4x),
        vy + h6 * (a1y + 2.0 * (a2y + a3y) + a4y),
    )


@_njit
def _event(vx, xn, yn, vxn, roll, cx, fl, wl, wr):
    """Does a span from velocity ``vx`` to state (xn, yn, vxn) cross a wall or the floor, or stop
    a rolling ball? In flight vy never turns from down to up and vx never changes sign, and
    rolling is a constant deceleration, so a first contact stays visible at the end of a longer
    span."""
    if xn < wl or xn > wr:
        return True
    if roll:
        return cx != 0.0 and vxn * vx <= 0.0
    return yn < fl


@_njit
def _contact_time(x, y, vx, vy, h, cx, cy, k, on_y, target):
    """Step length ``tau`` in [0, h] with ``RK4(state, tau)`` reaching ``target``.

    ``on_y`` picks the coordinate (y for the floor, x for a wall). The first guess is the root of
    the constant-acceleration parabola from the step start (error ~h^3); Newton's method on the
    RK4 step itself, whose derivative with respect to the step length is the end velocity up to
    O(tau^4), then converges quadratically (``_NEWTON_ITERS`` steps reach ~1e-15 s).
    """
    s = k * math.sqrt(vx * vx + vy * vy)
    if on_y:
        z0, w0, a0 = y - target, vy, cy - s * vy
    else:
        z0, w0, a0 = x - target, vx, cx - s * vx
    # root of z0 + w0 t + a0 t^2 / 2 = 0 on the approach side, in the cancellation-free form
    disc = max(w0 * w0 - 2.0 * a0 * z0, 0.0)
    q = -0.5 * (w0 + math.copysign(math.sqrt(disc), w0))
    tau = z0 / q if q != 0.0 else 0.0
    tau = min(max(tau, 0.0), h)
    for _ in range(_NEWTON_ITERS):
        xt, yt, vxt, vyt = _rk4(x, y, vx, vy, tau, cx, cy, k)
        f = (yt if on_y else xt) - target
        w = vyt if on_y else vxt
        if abs(w) < 1e-12:
            w = math.copysign(1e-12, w)
        tau = min(max(tau - f / w, 0.0), h)
    return tau


@_njit
def _forces(roll, vx, g, d, r):
    """(cx, cy, k) of a ball in its current mode."""
    if roll:
        return -r * np.sign(vx), 0.0, 0.0
    return 0.0, g, d


@_njit
def _contact(x, y, vx, vy, xn, yn, hs, cx, cy, k, fl, roll, e, g, d, r, rem, spin, dwell, wl, wr):
    """Move a ball to its first contact within its step ``hs`` (which ends at (xn, yn)) and
    apply it. Returns the new state, rolling flag and the time ``tau`` consumed.

    ``spin`` and ``dwell`` are the perturbations of :func:`simulate_perturbed` (0 for the
    design's physics, where they change nothing: ``(1 - 0) * vx`` is ``vx`` exactly); ``rem``
    is the time left in the frame, which bounds a dwell. ``wl``, ``wr`` are the walls
    (``-inf``, ``inf`` for none: then no wall is ever flagged).
    """
    left = xn < wl
    wall = left or xn > wr
    down = yn < fl and not roll
    stop = roll and not wall  # a rolling ball flagged without a wall can only be stopping
    wall_x = wl if left else wr
    # A ball may reach the floor and a wall in one step: solve both, keep the earlier.
    t_floor = _contact_time(x, y, vx, vy, hs, cx, cy, k, True, fl) if down else np.inf
    t_wall = _contact_time(x, y, vx, vy, hs, cx, cy, k, False, wall_x) if wall else np.inf
    # Rolling is constant deceleration: the stopping time is exact.
    t_stop = abs(vx) / abs(cx) if stop else np.inf
    tau = min(min(t_floor, t_wall), min(t_stop, hs))
    x, y, vx, vy = _rk4(x, y, vx, vy, tau, cx, cy, k)
    # Apply the first contact (ties: all, so a corner hit reflects both axes).
    if t_floor <= tau:
        y = fl
        vy = -e * vy
        vx = (1.0 - spin) * vx
        if vy < ROLL_SPEED:
            vy = 0.0
            roll = True
        elif dwell > 0.0:
            # soft contact: the ball stays on the floor for `dwell`, sliding at vx
            slide = min(dwell, rem - tau)
            x = min(max(x + vx * slide, wl), wr)
            tau += slide
    if t_wall <= tau:
        x = wall_x
        vx = -vx
    if t_stop <= tau:
        vx = 0.0
    return x, y, vx, vy, roll, tau


@_njit
def _advance_frame(x, y, vx, vy, roll, fl, e, g, d, r, dt, spin, dwell, wl, wr):
    """Advance one ball by ``dt`` in ``SUBSTEPS`` RK4 steps, each contact at its exact time.

    The plain steps run first; from the start of the first step that holds a contact, the rest
    of the frame is integrated in steps of at most ``h``, cut at each contact.
    """
    h = dt / SUBSTEPS
    cx, cy, k = _forces(roll, vx, g, d, r)
    rem = 0.0
    for s in range(SUBSTEPS):
        xn, yn, vxn, vyn = _rk4(x, y, vx, vy, h, cx, cy, k)
        if _event(vx, xn, yn, vxn, roll, cx, fl, wl, wr):
            rem = dt - s * h
            break
        x, y, vx, vy = xn, yn, vxn, vyn
    if rem == 0.0:
        return x, y, vx, vy, roll
    for _ in range(_MAX_STEPS):
        hs = min(rem, h)
        xn, yn, vxn, vyn = _rk4(x, y, vx, vy, hs, cx, cy, k)
        if not _event(vx, xn, yn, vxn, roll, cx, fl, wl, wr):
            x, y, vx, vy = xn, yn, vxn, vyn
            rem = rem - hs
        else:
            x, y, vx, vy, roll, tau = _contact(
                x, y, vx, vy, xn, yn, hs, cx, cy, k, fl, roll, e, g, d, r, rem, spin, dwell, wl, wr
            )
            cx, cy, k = _forces(roll, vx, g, d, r)
            rem -= tau
        if not rem > 0.0:
            return x, y, vx, vy, roll
    raise RuntimeError("simulate: more contacts in one frame than expected")


@_njit
def _simulate_kernel(th, s0, fl, pert, dt, out, wl, wr):
    """Fill ``out`` (n_frames, 4, B) from ``s0`` (4, B); ``th`` is (1, 4, B) or (n_frames, 4, B);
    ``pert`` (2, B) is (spin, dwell) per ball, zeros for the design's physics; ``wl``, ``wr``
    the walls (0 and ``BOX_WIDTH`` in the design; ``-inf``, ``inf`` for none) and ``fl`` (B,)
    the floors (``-inf`` for none: the ball falls freely).

    Each frame runs in two passes over the balls. The first takes every ball's plain
    ``SUBSTEPS`` steps with no branches, so the compiler vectorises it across balls (SIMD), and
    flags the balls whose frame holds a contact; the second redoes just those from the frame
    start, one ball at a time, with each contact at its exact time (``_advance_frame``, ~6% of
    ball-frames). A flagged ball's result is the same as if it had taken the scalar path alone.
    ``SUBSTEPS`` must be a compile-time constant here: with a run-time step count the inner
    loop is not unrolled and the pass stays scalar (measured 4x slower).
    """
    varying = th.shape[0] > 1
    B = s0.shape[1]
    h = dt / SUBSTEPS
    X, Y, VX, VY = s0[0].copy(), s0[1].copy(), s0[2].copy(), s0[3].copy()
    R = np.zeros(B)  # 1.0 while rolling (a float keeps the first pass branch-free)
    flag = np.zeros(B)  # 1.0 where the frame holds a contact (float: a bool store stops SIMD)
    out[0] = s0
    for t in range(out.shape[0] - 1):
        i = t if varying else 0
        G, D, RR = th[i, 1], th[i, 2], th[i, 3]
        NX, NY, NVX, NVY = out[t + 1, 0], out[t + 1, 1], out[t + 1, 2], out[t + 1, 3]
        for b in range(B):
            x, y, vx, vy, rl = X[b], Y[b], VX[b], VY[b], R[b]
            # _forces without branches: rolling (rl = 1) or flying (rl = 0)
            sg = 1.0 if vx > 0.0 else (-1.0 if vx < 0.0 else 0.0)
            cx = rl * (-RR[b] * sg)
            cy = (1.0 - rl) * G[b]
            k = (1.0 - rl) * D[b]
            v0x = vx
            for _ in range(SUBSTEPS):
                x, y, vx, vy = _rk4(x, y, vx, vy, h, cx, cy, k)
            # _event over the whole frame (a first contact stays visible at its end)
            flag[b] = (
                (x < wl) | (x > wr) | ((rl == 0.0) & (y < fl[b]))
                | ((rl != 0.0) & (cx != 0.0) & (vx * v0x <= 0.0))
            )
            NX[b], NY[b], NVX[b], NVY[b] = x, y, vx, vy
        for b in range(B):
            if flag[b] != 0.0:
                x, y, vx, vy, rb = _advance_frame(
                    X[b], Y[b], VX[b], VY[b], R[b] != 0.0, fl[b],
                    th[i, 0, b], G[b], D[b], RR[b], dt, pert[0, b], pert[1, b], wl, wr,
                )
                NX[b], NY[b], NVX[b], NVY[b] = x, y, vx, vy
                R[b] = 1.0 if rb else 0.0
        X[:], Y[:], VX[:], VY[:] = NX, NY, NVX, NVY


#: Balls per kernel call: bounds the scratch copy of the (n_frames, 4, chunk) layout (~50 MB).
_CHUNK = 8192


def simulate(theta, state0, n_frames: int = N_FRAMES, dt: float = DT, floor=0.0, *,
             walls=_BOX) -> np.ndarray:
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
    floor : float, array_like of shape (B,), or None
        Floor height per ball; None: no floor (the ball falls freely).
    walls : (float, float) or None
        x of the left and right walls, m; None: no walls (free in x). The default is the
        design's box, ``(0, BOX_WIDTH)``; with it (and a floor) every number is as before.

    Returns
    -------
    ndarray, shape (B, n_frames, 4)
        States at ``t = 0, dt, ..., (n_frames - 1) dt``; frame 0 equals ``state0``.

    Raises
    ------
    ValueError
        Naming the argument, for inputs outside what the model is meant for: parameters outside
        ``ENVELOPE`` (or ``g >= 0``), an initial velocity component above ``V_MAX``, ``dt``
        above ``DT_MAX``, ``|floor|`` above ``FLOOR_MAX``, drag per integration step above
        ``DRAG_STEP``, more than ``CONTACTS_MAX`` possible contacts per frame; and, as a last
        guard, for any non-finite result.
    """
    th, s0, fl, n_frames, dt, walls = _check_inputs(theta, state0, n_frames, dt, floor, walls)
    out = _run(th, s0, fl, np.zeros((2, s0.shape[0])), n_frames, dt, walls)
    _check_finite(out, th, s0, fl, dt)
    return out


def check_dt(dt) -> float:
    """Validate a frame interval: a number in (0, ``DT_MAX``]."""
    dt = check_positive_float(dt, "dt")
    if dt > DT_MAX:
        raise ValueError(f"dt: expected at most {DT_MAX:g} s between frames (physics.DT_MAX), got {dt:g}")
    return dt


def check_step(th, s0, fl, dt, walls=_BOX, n_frames: int | None = None) -> None:
    """Raise unless every ball's frame is one the integrator resolves: drag per RK4 step at
    most ``DRAG_STEP`` and at most ``CONTACTS_MAX`` contacts per frame (see both).

    ``th`` (B, 4) or (B, T, 4), ``s0`` (B, 4), ``fl`` (B,), all validated; ``walls`` validated
    (None: no wall hits); a ball without a floor (``fl`` = ``-inf``) falls for ``n_frames``
    frames, which bounds its speed.
    """
    if not len(s0):
        return
    if th.ndim == 3:
        d, g = th[..., 2].max(axis=1), th[..., 1].min(axis=1)
    else:
        d, g = th[:, 2], th[:, 1]
    if np.isfinite(fl).all():
        drop = s0[:, 1] - fl
    else:  # no floor: the drop is bounded by the fall over the clip (drag only slows it)
        span = (n_frames if n_frames is not None else N_FRAMES) * dt
        drop = np.where(np.isfinite(fl), s0[:, 1] - fl,
                        np.abs(s0[:, 3]) * span + 0.5 * np.abs(g) * span**2)
    v = np.sqrt(s0[:, 2] ** 2 + s0[:, 3] ** 2 + 2.0 * np.abs(g) * drop)
    step = d * v * (dt / SUBSTEPS)
    worst = int(np.argmax(step))
    if step[worst] > DRAG_STEP:
        raise ValueError(
            f"theta, state0, dt: drag per integration step d * speed * dt / {SUBSTEPS} must be "
            f"<= {DRAG_STEP:g} (physics.DRAG_STEP) for the integrator to be stable; ball {worst} "
            f"has d = {d[worst]:g}, speed up to {v[worst]:g} m/s, dt = {dt:g}: {step[worst]:.3g}. "
            f"Use a smaller dt or d"
        )
    if walls == _BOX:
        hits = 1.25 * dt * np.abs(g) / (2.0 * ROLL_SPEED) + v * dt / BOX_WIDTH + 1.0
    else:
        bounces = np.where(np.isfinite(fl), 1.25 * dt * np.abs(g) / (2.0 * ROLL_SPEED), 0.0)
        hits = bounces + (0.0 if walls is None else v * dt / (walls[1] - walls[0]) + 1.0)
    worst = int(np.argmax(hits))
    if hits[worst] > CONTACTS_MAX:
        raise ValueError(
            f"theta, state0, dt: contacts per frame must stay <= {CONTACTS_MAX} "
            f"(physics.CONTACTS_MAX); ball {worst} with g = {g[worst]:g}, speed up to "
            f"{v[worst]:g} m/s and dt = {dt:g} may have {hits[worst]:.0f}. Use a smaller dt"
        )


def _check_finite(out, th, s0, fl, dt) -> None:
    """Raise naming the inputs of balls whose states are not finite (NaN stays NaN and inf
    turns NaN in later frames, so the last frame shows them: (B, 4) values to check, not all)."""
    last = out[:, -1]
    if np.isfinite(last).all():
        return
    bad = np.flatnonzero(~np.isfinite(last).all(axis=1))
    i = int(bad[0])
    raise ValueError(
        f"simulate: non-finite states for {bad.size} ball(s) {bad[:10].tolist()}; the first has "
        f"theta = {np.asarray(th[i]).reshape(-1, 4)[0].tolist()}, state0 = {s0[i].tolist()}, "
        f"floor = {float(fl[i]):g}, dt = {dt:g} (inputs outside what the model was tested for)"
    )


_ENV_LO = np.array([ENVELOPE[p][0] for p in PARAMS])
_ENV_HI = np.array([ENVELOPE[p][1] for p in PARAMS])
#: The fast check's margin on the step bounds: an input within it of a bound takes the full
#: checks, so rounding can never let the fast one pass what they would refuse.
_FAST_MARGIN = 1.0 - 1e-9


@_njit
def _inputs_ok(th, s0, fl, dt):
    """True when ``_check_inputs`` would accept these float64 arrays: ``th`` (B, Tt, 4),
    ``s0`` (B, 4), ``fl`` (B,), ``dt`` in (0, DT_MAX]. One pass, no error text (the full checks
    name what is wrong); NaN fails every comparison, so it takes the full checks too."""
    for b in range(s0.shape[0]):
        dmax, gmin = -np.inf, np.inf
        for t in range(th.shape[1]):
            for i in range(4):
                v = th[b, t, i]
                if not (v >= _ENV_LO[i] and v <= _ENV_HI[i]):
                    return False
            if not th[b, t, 1] < 0.0:
                return False
            dmax, gmin = max(dmax, th[b, t, 2]), min(gmin, th[b, t, 1])
        x, y, vx, vy, f = s0[b, 0], s0[b, 1], s0[b, 2], s0[b, 3], fl[b]
        if not (abs(vx) <= V_MAX and abs(vy) <= V_MAX and 0.0 <= x <= BOX_WIDTH
                and abs(f) <= FLOOR_MAX and 0.0 <= y - f <= BOX_WIDTH):
            return False
        v = np.sqrt(vx**2 + vy**2 + 2.0 * abs(gmin) * (y - f))
        if not dmax * v * (dt / SUBSTEPS) <= DRAG_STEP * _FAST_MARGIN:
            return False
        hits = 1.25 * dt * abs(gmin) / (2.0 * ROLL_SPEED) + v * dt / BOX_WIDTH + 1.0
        if not hits <= CONTACTS_MAX * _FAST_MARGIN:
            return False
    return True


def _fast_inputs(theta, state0, n_frames, dt, floor):
    """``_check_inputs``' result for the common well-formed call (float64 arrays, an int frame
    count, a float dt and floor) in one compiled pass; None for anything else, which then takes
    the full checks. The many small simulations of fits and checks paid ~110 us of checks for
    a ~10 us simulation."""
    if not (type(theta) is np.ndarray and type(state0) is np.ndarray
            and theta.dtype == np.float64 and state0.dtype == np.float64
            and type(n_frames) is int and 1 <= n_frames <= MAX_FRAMES
            and type(dt) in (float, np.float64) and 0.0 < dt <= DT_MAX
            and state0.ndim == 2 and state0.shape[1] == 4 and state0.shape[0] > 0):
        return None
    B = state0.shape[0]
    if theta.shape == (B, 4):
        th3 = theta[:, None, :]
    elif theta.shape == (B, n_frames, 4):
        th3 = theta
    else:
        return None
    if type(floor) in (float, int, np.float64):
        fl = np.full(B, float(floor))
    elif type(floor) is np.ndarray and floor.dtype == np.float64 and floor.shape in ((), (B,)):
        fl = np.broadcast_to(floor, (B,)).astype(np.float64)
    else:
        return None
    if not _inputs_ok(th3, state0, fl, float(dt)):
        return None
    return theta, state0, fl, n_frames, float(dt)


def _check_inputs(theta, state0, n_frames, dt, floor, walls=_BOX):
    """Validate ``simulate``'s arguments; returns (theta, state0, floor (B,), n_frames, dt,
    walls); a missing floor is ``-inf``, missing walls None."""
    if walls is _BOX or walls == _BOX:  # the design's box: the fast path as before
        fast = _fast_inputs(theta, state0, n_frames, dt, floor)
        if fast is not None:
            return fast + (_BOX,)
    return _check_inputs_full(theta, state0, n_frames, dt, floor, walls)


def _check_inputs_full(theta, state0, n_frames, dt, floor, walls=_BOX):
    """Every check of ``simulate``'s arguments, each raising with its own message."""
    n_frames = check_positive_int(n_frames, "n_frames")
    if n_frames > MAX_FRAMES:
        raise ValueError(f"n_frames: expected at most {MAX_FRAMES} frames per simulation "
                         f"(physics.MAX_FRAMES), got {n_frames}")
    dt = check_dt(dt)
    th = check_theta(theta, n_frames)
    s0 = as_float_array(state0, "state0", ndim=2, last=4)
    B = s0.shape[0]
    if th.shape[0] != B:
        raise ValueError(
            f"theta: expected {B} rows to match state0 (B={B}), got shape {th.shape}"
        )
    walls = _check_walls(walls)
    fl = np.full(B, -np.inf) if floor is None else _check_floor(floor, B)
    s0 = check_state0(s0, fl, walls=walls)
    check_step(th, s0, fl, dt, walls=walls, n_frames=n_frames)
    return th, s0, fl, n_frames, dt, walls


def _run(th, s0, fl, pert, n_frames, dt, walls=_BOX):
    """The kernel over chunks of balls; arguments validated, ``pert`` (2, B)."""
    wl, wr = (-np.inf, np.inf) if walls is None else (float(walls[0]), float(walls[1]))
    B = s0.shape[0]
    out = np.empty((B, n_frames, 4))
    for b0 in range(0, B, _CHUNK):
        b1 = min(B, b0 + _CHUNK)
        part = th[b0:b1] if th.ndim == 3 else th[b0:b1, None, :]
        scratch = np.empty((n_frames, 4, b1 - b0))  # contiguous: one compiled specialisation
        _simulate_kernel(np.ascontiguousarray(part.transpose(1, 2, 0)),
                         np.ascontiguousarray(s0[b0:b1].T), np.ascontiguousarray(fl[b0:b1]),
                         np.ascontiguousarray(pert[:, b0:b1]), dt, scratch, wl, wr)
        out[b0:b1] = scratch.transpose(2, 0, 1)
    return out


def simulate_perturbed(theta, state0, spin=0.0, dwell=0.0, n_frames: int = N_FRAMES,
                       dt: float = DT, floor=0.0, *, walls=_BOX) -> np.ndarray:
    """``simulate`` with two deviations real balls show and the design's physics does not.

    For robustness studies: methods identify with ``simulate``'s model, the videos come from
    this one. Both act at floor bounces; with both 0 the result equals ``simulate``'s exactly.

    Parameters
    ----------
    theta, state0, n_frames, dt, floor, walls
        As for :func:`simulate`.
    spin : float or array_like, shape (B,)
        Fraction of the horizontal speed lost at each floor bounce (spin and friction), in
        [0, 1).
    dwell : float or array_like, shape (B,)
        Seconds a bouncing ball stays on the floor, sliding at its horizontal speed, before it
        leaves (a soft contact), in [0, dt). A dwell is cut short at the end of a frame.

    Returns
    -------
    ndarray, shape (B, n_frames, 4)
    """
    th, s0, fl, n_frames, dt, walls = _check_inputs(theta, state0, n_frames, dt, floor, walls)
    B = s0.shape[0]
    pert = np.empty((2, B))
    for j, (name, val, hi) in enumerate((("spin", spin, 1.0), ("dwell", dwell, dt))):
        v = as_float_array(val, name, ndim=(0, 1))
        if v.ndim == 1 and v.shape[0] != B:
            raise ValueError(f"{name}: expected a scalar or shape ({B},), got shape {v.shape}")
        if (v < 0).any() or (v >= hi).any():
            raise ValueError(f"{name}: expected values in [0, {hi:g}), got [{v.min():g}, {v.max():g}]")
        pert[j] = v
    out = _run(th, s0, fl, pert, n_frames, dt, walls)
    _check_finite(out, th, s0, fl, dt)
    return out
