"""JAX twin of :mod:`sysid_bench.core.physics`: the same simulator, jit-able and differentiable.

Same algorithm, step for step, as the NumPy simulator (and tested equal to it to 1e-9 m in
float64, ``tests/test_physics_jax.py``): classical RK4 with ``SUBSTEPS`` steps of
``h = dt / SUBSTEPS`` per frame; a ball with a contact in a frame is restarted at the start of
the plain step that holds its first contact, its contact time found by the same parabolic guess
plus ``_NEWTON_ITERS`` Newton step(s) on the RK4 step length, the contact applied there, then
steps of ``min(rem, h)`` until the frame's time is used up. The constants (``PARAMS``,
``BOX_WIDTH``, ``ROLL_SPEED``, ``SUBSTEPS``, ``_NEWTON_ITERS``) are imported from
``sysid_bench.core.physics``: there is one source of physics.

What differs is only how the work is laid out for XLA:

* the state is four real arrays ``x, y, vx, vy`` instead of two complex ones (the arithmetic is
  the same, operation for operation; ``|v|`` is ``sqrt(vx^2 + vy^2)`` instead of ``hypot``, a
  difference of at most one rounding);
* frames are a ``lax.scan`` and each frame makes a **fixed** number of masked passes after its
  plain steps (:data:`MAX_PASSES`), instead of a data-dependent loop, so reverse-mode AD works
  (no ``lax.while_loop`` on the differentiated path). A frame in which no ball has a contact
  skips the passes with ``lax.cond`` (under ``vmap`` the skip becomes a select, still correct);
  in a large batch the balls with a contact are gathered into a fraction of the lanes
  (:func:`_slots`) for the passes and scattered back, since only a few percent of balls have a
  contact in any one frame.
  A ball that would need more passes than that is marked bad: :func:`simulate` raises
  ``RuntimeError`` on concrete input, and returns NaN states for it from that frame on under a
  JAX transformation (so a sampler rejects the point instead of using a wrong trajectory);
* gradients are correct across contacts: the contact time's first guess is computed under
  ``stop_gradient`` and the final Newton step is differentiated, which makes the contact time
  carry the implicit-function derivative ``dtau/dtheta = -(df/dtheta) / (df/dtau)`` (up to a
  term proportional to the guess's residual, ~1e-6 m, i.e. relative error ~1e-7); the state
  after the contact then depends on ``theta`` through ``tau`` as it should. The switch to
  rolling (a rebound crossing ``ROLL_SPEED``) is a true discontinuity and has no useful gradient.

Importing this module turns on ``jax_enable_x64`` (``jax.config.update``): the simulator is
float64, like the NumPy one, and NumPyro's NUTS then runs in float64 too. Only this module and
``methods.nuts`` import JAX.
"""

from __future__ import annotations

from functools import partial

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from sysid_bench.core import physics  # noqa: E402
from sysid_bench.core._validate import as_float_array, check_positive_int  # noqa: E402
from sysid_bench.core.physics import (  # noqa: E402
    _NEWTON_ITERS,
    BOX_WIDTH,
    DT,
    N_FRAMES,
    PARAMS,
    ROLL_SPEED,
    SUBSTEPS,
)

__all__ = ["simulate", "simulate_core", "MAX_CONTACTS", "MAX_PASSES", "PARAMS"]

#: Contacts (floor, wall, start of rolling, stop) one ball may have in one frame. At the prior's
#: limits a ball can bounce twice on the floor within 50 ms just above ``ROLL_SPEED`` and meet a
#: wall in the same frame.
MAX_CONTACTS = 4
#: Masked passes per frame after the plain steps: a restarted ball needs at most one pass per
#: remaining plain step, one per contact, and one for a rounding-sized remainder of the frame.
#: Over 20,000 random balls and 20,000 adversarial ones (g = -12.81, e near 1, skimming the
#: floor at 15 m/s from wall to wall) no ball needed more than 6; a ball needing more is
#: reported (see ``simulate``), never silently wrong.
MAX_PASSES = SUBSTEPS + MAX_CONTACTS + 1


_TINY_W = 1e-12  # as physics._contact_time: keeps the Newton step finite at a grazing contact


# --------------------------------------------------------------------------------------------
# the pieces, on (n,) arrays; every expression mirrors physics.py operation for operation
def _speed(vx, vy):
    """|v| with a finite gradient at v = 0 (a stopped ball)."""
    s2 = vx * vx + vy * vy
    pos = s2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s2, 1.0)), 0.0)


def _acc(vx, vy, cx, cy, k):
    ks = k * _speed(vx, vy)
    return cx - ks * vx, cy - ks * vy


def _rk4(x, y, vx, vy, h, cx, cy, k):
    """One RK4 step of length ``h`` (scalar or (n,)); acceleration ``c - k |v| v``."""
    h2 = 0.5 * h
    a1x, a1y = _acc(vx, vy, cx, cy, k)
    v2x, v2y = vx + h2 * a1x, vy + h2 * a1y
    a2x, a2y = _acc(v2x, v2y, cx, cy, k)
    v3x, v3y = vx + h2 * a2x, vy + h2 * a2y
    a3x, a3y = _acc(v3x, v3y, cx, cy, k)
    v4x, v4y = vx + h * a3x, vy + h * a3y
    a4x, a4y = _acc(v4x, v4y, cx, cy, k)
    h6 = h / 6.0
    return (
        x + h6 * (vx + 2.0 * (v2x + v3x) + v4x),
        y + h6 * (vy + 2.0 * (v2y + v3y) + v4y),
        vx + h6 * (a1x + 2.0 * (a2x + a3x) + a4x),
        vy + h6 * (a1y + 2.0 * (a2y + a3y) + a4y),
    )


def _forces(roll, vx, g, d, r):
    """Constant acceleration (cx, cy) and drag k of each ball in its current mode.

    The NumPy simulator stores these and refreshes them after each contact; recomputing them from
    the state gives the same values, since a rolling ball's ``sign(vx)`` only changes at a
    contact (wall, stop).
    """
    cx = jnp.where(roll, -r * jnp.sign(vx), 0.0)
    cy = jnp.where(roll, 0.0, g)
    k = jnp.where(roll, 0.0, d)
    return cx, cy, k


def _events(vx, xn, yn, vxn, roll, cx, fl):
    """Balls that cross a wall or the floor, or stop rolling, by the end of a span."""
    hit = (xn < 0.0) | (xn > BOX_WIDTH)
    hit = hit | ((yn < fl) & ~roll)
    return hit | (roll & (cx != 0) & (vxn * vx <= 0))


def _contact_time(x, y, vx, vy, h, cx, cy, k, on_y, target):
    """Step length ``tau`` in [0, h] at which one RK4 step reaches ``target`` (any shape).

    The parabolic first guess is a constant as far as AD is concerned; the Newton step(s) after
    it carry the derivative, so ``dtau = -(df/dtheta) / (df/dtau)`` at the contact.
    """
    sg = lax.stop_gradient
    gx, gy, gvx, gvy, gcx, gcy, gk, gt = (sg(a) for a in (x, y, vx, vy, cx, cy, k, target))
    z0 = jnp.where(on_y, gy, gx) - gt
    a0x, a0y = _acc(gvx, gvy, gcx, gcy, gk)
    w0 = jnp.where(on_y, gvy, gvx)
    a0 = jnp.where(on_y, a0y, a0x)
    disc = jnp.maximum(w0 * w0 - 2.0 * a0 * z0, 0.0)
    q = -0.5 * (w0 + jnp.copysign(jnp.sqrt(disc), w0))
    nz = q != 0
    tau = jnp.where(nz, z0 / jnp.where(nz, q, 1.0), 0.0)
    tau = jnp.clip(tau, 0.0, sg(h))
    for _ in range(_NEWTON_ITERS):
        xt, yt, vxt, vyt = _rk4(x, y, vx, vy, tau, cx, cy, k)
        f = jnp.where(on_y, yt, xt) - target
        w = jnp.where(on_y, vyt, vxt)
        w = jnp.where(jnp.abs(w) < _TINY_W, jnp.copysign(_TINY_W, w), w)
        tau = jnp.clip(tau - f / w, 0.0, h)
    return tau


def _contact_pass(state, rem, h, th, fl):
    """One masked pass of the contact loop of ``physics._advance_frame`` (+ ``_contact``) over all balls.

    Balls with ``rem <= 0`` are left as they are.
    """
    x, y, vx, vy, roll = state
    e, g, d, r = th
    cx, cy, k = _forces(roll, vx, g, d, r)
    live = rem > 0
    hs = jnp.minimum(rem, h)
    xn, yn, vxn, vyn = _rk4(x, y, vx, vy, hs, cx, cy, k)
    ev = _events(vx, xn, yn, vxn, roll, cx, fl)
    quiet = live & ~ev
    hit = live & ev

    left = xn < 0.0
    wall = left | (xn > BOX_WIDTH)
    down = (yn < fl) & ~roll
    stop = roll & (cx != 0) & ~wall
    # floor and wall contact times side by side (axis 0), the way physics solves "both"
    on_y = jnp.stack((jnp.ones_like(roll), jnp.zeros_like(roll)))
    target = jnp.stack((fl, jnp.where(left, 0.0, BOX_WIDTH)))
    t2 = _contact_time(x, y, vx, vy, hs, cx, cy, k, on_y, target)
    inf = jnp.inf
    t_floor = jnp.where(down, t2[0], inf)
    t_wall = jnp.where(wall, t2[1], inf)
    t_stop = jnp.where(stop, jnp.abs(vx) / jnp.where(stop, jnp.abs(cx), 1.0), inf)
    tau = jnp.minimum(jnp.minimum(t_floor, t_wall), jnp.minimum(t_stop, hs))
    xc, yc, vxc, vyc = _rk4(x, y, vx, vy, tau, cx, cy, k)

    do_floor = t_floor <= tau
    vy_out = -e * vyc
    slow = do_floor & (vy_out < ROLL_SPEED)
    yc = jnp.where(do_floor, fl, yc)
    vyc = jnp.where(do_floor, jnp.where(slow, 0.0, vy_out), vyc)
    do_wall = t_wall <= tau
    xc = jnp.where(do_wall, jnp.where(left, 0.0, BOX_WIDTH), xc)
    vxc = jnp.where(do_wall, -vxc, vxc)
    vxc = jnp.where(t_stop <= tau, 0.0, vxc)

    def pick(a_hit, a_quiet, a_old):
        return jnp.where(hit, a_hit, jnp.where(quiet, a_quiet, a_old))

    new = (
        pick(xc, xn, x),
        pick(yc, yn, y),
        pick(vxc, vxn, vx),
        pick(vyc, vyn, vy),
        roll | (hit & slow),
    )
    rem = jnp.where(quiet, rem - hs, jnp.where(hit, rem - tau, rem))
    return new, rem


def _slots(n: int) -> int:
    """Lanes for the contact passes of a batch of ``n`` balls (static): all of them for small
    batches, an eighth (at least 64) for large ones, where a frame's contacts are a few percent."""
    return n if n <= 128 else max(64, n // 8)


def _frame(carry, th, *, dt, fl, max_passes):
    """Advance every ball by one frame (``physics._advance_frame``, batched with masks)."""
    x, y, vx, vy, roll, bad = carry
    e, g, d, r = th
    h = dt / SUBSTEPS
    cx, cy, k = _forces(roll, vx, g, d, r)
    steps = [(x, y, vx, vy)]
    for _ in range(SUBSTEPS):
        steps.append(_rk4(*steps[-1], h, cx, cy, k))
    end = steps[-1]
    hit = _events(vx, end[0], end[1], end[2], roll, cx, fl)

    def resolve(_):
        # restart each ball with a contact at the start of the plain step holding its first one
        first = jnp.full(x.shape, SUBSTEPS - 1)
        for s in range(SUBSTEPS - 2, -1, -1):
            (_, _, va, _), (xb, yb, vb, _) = steps[s], steps[s + 1]
            first = jnp.where(_events(va, xb, yb, vb, roll, cx, fl), s, first)
        start = list(steps[0])
        for s in range(1, SUBSTEPS):
            start = [jnp.where(first == s, a, b) for a, b in zip(steps[s], start)]
        st = tuple(jnp.where(hit, a, b) for a, b in zip(start, end)) + (roll,)
        rem = jnp.where(hit, dt - first.astype(x.dtype) * h, 0.0)

        def passes(st, rem, th, fl):
            def one_pass(c, _):
                st, rem = c
                out = lax.cond(
                    jnp.any(rem > 0),
                    lambda c: _contact_pass(c[0], c[1], h, th, fl),
                    lambda c: c,
                    (st, rem),
                )
                return out, None

            (st, rem), _ = lax.scan(one_pass, (st, rem), None, length=max_passes)
            return st, rem

        def full(_):
            return passes(st, rem, th, fl)

        n = x.shape[0]
        slots = _slots(n)
        if slots == n:
            st_out, rem_out = full(None)
        else:
            # Few balls have a contact in a frame: gather them into `slots` lanes, run the passes
            # there and scatter back (the full width only when more balls than lanes hit).
            def compact(_):
                idx = jnp.nonzero(hit, size=slots, fill_value=n)[0]  # n = no ball (dropped)

                def take(a):
                    return a.at[idx].get(mode="fill", fill_value=0)

                sub_st, sub_rem = passes(
                    tuple(take(a) for a in st), take(rem), tuple(take(a) for a in th), take(fl)
                )
                out = tuple(a.at[idx].set(b, mode="drop") for a, b in zip(st, sub_st))
                return out, rem.at[idx].set(sub_rem, mode="drop")

            st_out, rem_out = lax.cond(jnp.sum(hit) <= slots, compact, full, None)
        return st_out, rem_out > 0

    def plain(_):
        return end + (roll,), jnp.zeros_like(roll)

    (x, y, vx, vy, roll), unresolved = lax.cond(jnp.any(hit), resolve, plain, None)
    bad = bad | unresolved
    out = jnp.where(bad[:, None], jnp.nan, jnp.stack((x, y, vx, vy), axis=-1))
    return (x, y, vx, vy, roll, bad), out


@partial(jax.jit, static_argnames=("n_frames", "dt", "max_passes"))
def simulate_core(
    theta, state0, floor, n_frames: int = N_FRAMES, dt: float = DT, max_passes: int = MAX_PASSES
):
    """Unchecked simulation, the traceable core of :func:`simulate`.

    Parameters
    ----------
    theta : array, shape (B, 4) or (B, n_frames, 4)
    state0 : array, shape (B, 4)
    floor : array, shape (B,)
    n_frames : int (static)
    dt : float (static)
    max_passes : int (static)
        Masked passes per frame after the plain steps (see :data:`MAX_PASSES`).

    Returns
    -------
    states : array, shape (B, n_frames, 4)
    bad : array of bool, shape (B,)
        Balls that needed more than ``MAX_PASSES`` passes in some frame; their states are NaN
        from that frame on.
    """
    theta = jnp.asarray(theta, jnp.float64)
    state0 = jnp.asarray(state0, jnp.float64)
    fl = jnp.broadcast_to(jnp.asarray(floor, jnp.float64), state0.shape[:1])
    B = state0.shape[0]
    carry = (state0[:, 0], state0[:, 1], state0[:, 2], state0[:, 3], jnp.zeros(B, bool), jnp.zeros(B, bool))
    step = partial(_frame, dt=float(dt), fl=fl, max_passes=int(max_passes))
    if theta.ndim == 3:
        xs = jnp.moveaxis(theta[:, : n_frames - 1], 1, 0)  # (n_frames - 1, B, 4)
        body = lambda c, t: step(c, tuple(t[:, i] for i in range(4)))  # noqa: E731
        carry, traj = lax.scan(body, carry, xs)
    else:
        th = tuple(theta[:, i] for i in range(4))
        carry, traj = lax.scan(lambda c, _: step(c, th), carry, None, length=n_frames - 1)
    traj = jnp.moveaxis(traj, 0, 1)  # (B, n_frames - 1, 4)
    states = jnp.concatenate((state0[:, None, :], traj), axis=1)
    return states, carry[5]


def _is_traced(*args) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in args)


def simulate(theta, state0, n_frames: int = N_FRAMES, dt: float = DT, floor=0.0):
    """Simulate a batch of bouncing balls (JAX); same contract as ``physics.simulate``.

    Parameters
    ----------
    theta : array_like, shape (B, 4) or (B, n_frames, 4)
        ``[e, g, d, r]`` per ball, or per ball and frame (``theta[:, t]`` holds from frame ``t``
        to ``t + 1``; the last row is unused).
    state0 : array_like, shape (B, 4)
        ``[x, y, vx, vy]`` at frame 0, inside the box.
    n_frames : int
        Frames to return, frame 0 included (static under ``jit``).
    dt : float
        Seconds between frames (static under ``jit``).
    floor : float or array_like, shape (B,)

    Returns
    -------
    jax.Array, shape (B, n_frames, 4), float64
        States at the frame times; frame 0 equals ``state0``.

    Notes
    -----
    On concrete arrays the arguments are validated like ``physics.simulate`` (``ValueError``,
    the same envelope: ``physics.ENVELOPE``, ``V_MAX``, ``DT_MAX``, ``FLOOR_MAX``, ``DRAG_STEP``, ``CONTACTS_MAX``) and
    a ball needing more than ``MAX_PASSES`` passes in one frame raises ``RuntimeError``. Inside
    ``jit``/``grad``/``vmap`` values cannot be inspected: arguments are only shape-checked and
    such a ball's states are NaN from that frame on.
    """
    n_frames = check_positive_int(n_frames, "n_frames")
    dt = physics.check_dt(dt)  # static even under jit: bounded as in physics.simulate
    if not _is_traced(theta, state0, floor):
        th = physics.check_theta(np.asarray(theta), n_frames)
        s0 = as_float_array(np.asarray(state0), "state0", ndim=2, last=4)
        if th.shape[0] != s0.shape[0]:
            raise ValueError(
                f"theta: expected {s0.shape[0]} rows to match state0 (B={s0.shape[0]}), got shape {th.shape}"
            )
        fl = physics._check_floor(np.asarray(floor), s0.shape[0])
        s0 = physics.check_state0(s0, fl)
        physics.check_step(th, s0, fl, dt)
        states, bad = simulate_core(th, s0, fl, n_frames=n_frames, dt=dt, max_passes=MAX_PASSES)
        if bool(jnp.any(bad)):
            raise RuntimeError(
                f"simulate: more than {MAX_CONTACTS} contacts in one frame for balls "
                f"{np.flatnonzero(np.asarray(bad)).tolist()}"
            )
        physics._check_finite(np.asarray(states[:, -1:]), th, s0, fl, dt)
        return states
    theta, state0 = jnp.asarray(theta), jnp.asarray(state0)
    if theta.ndim not in (2, 3) or theta.shape[-1] != len(PARAMS) or state0.shape[-1] != 4:
        raise ValueError(
            f"theta, state0: expected (B, 4) or (B, n_frames, 4) and (B, 4), got {theta.shape} and {state0.shape}"
        )
    return simulate_core(theta, state0, floor, n_frames=n_frames, dt=dt, max_passes=MAX_PASSES)[0]
