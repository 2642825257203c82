"""JAX twin of the collision system's simulator (:mod:`sysid_bench.core.systems.collision`).

The same exact event stepping, pass for pass: per frame, the earliest event time in closed form
among {puck-puck contact, wall 1, wall 2, stop 1, stop 2}, both pucks moved there exactly, that
one event applied (same order on ties), until the frame's time is used up. What differs is the
layout for XLA:

* frames are a ``lax.scan``; each frame makes a **fixed** number :data:`MAX_PASSES` of masked
  passes (a pass after the frame's time is used up moves nothing), so reverse-mode AD works. A
  trajectory that would need more passes in a frame is marked bad: its states are NaN from that
  frame on (so a sampler rejects the point); on concrete input :func:`simulate` raises
  ``RuntimeError`` instead. Over 100,000 trajectories from the design's initial states with
  parameters across the envelope (half of them at its low-restitution, large-ratio corners) no
  frame needed more than 5 passes; the longest instantaneous wall/puck/puck sequence over the
  envelope has 15 contacts (16 passes, see the NumPy module), so :data:`MAX_PASSES` = 24 leaves
  room for other events in the same frame;
* the NumPy kernel's no-event fast path is not taken: a frame without events is one pass whose
  event times all lie beyond the frame, which moves the pucks by the same formula;
* every division and square root that a ``jnp.where`` discards is taken of a safe value, so a
  branch not taken never sends NaN into a gradient.

Gradients are exact across events: event times are closed-form roots
(``t = 2 d / (s + sqrt(s^2 - 2 a d))``, ``|v| / mu``), differentiable in the state and in
``theta``, and the state after an event depends on them through the time as it should. A stop
sets the velocity to the constant 0 (its derivative is 0, as the physics says); a grazing contact
(``s^2 = 2 a d``) and a change in the order of events are true discontinuities.

Importing this module turns on ``jax_enable_x64``: the twin is float64 like the NumPy kernel.
"""

from __future__ import annotations

from functools import partial

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from sysid_bench.core.systems.collision import XL, XR, R  # noqa: E402

__all__ = ["simulate", "simulate_core", "MAX_PASSES"]

#: Masked passes per frame (see the module docstring).
MAX_PASSES = 24


def _sqrt0(a):
    """sqrt(a) for a > 0, else 0, with a finite gradient everywhere."""
    pos = a > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, a, 1.0)), 0.0)


def _div(num, den, ok):
    """num / den where ``ok``, else inf; ``den`` replaced by 1 where not ``ok``."""
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), jnp.inf)


def _event_times(x1, v1, x2, v2, mu):
    """As collision._event_times."""
    g = jnp.maximum(x2 - x1 - 2.0 * R, 0.0)
    s = v1 - v2
    c = mu * (jnp.sign(v1) - jnp.sign(v2))
    disc = s * s - 2.0 * c * g
    tp = _div(2.0 * g, s + _sqrt0(disc), (s > 0.0) & (disc >= 0.0))
    d1 = jnp.maximum(x1 - XL, 0.0)
    disc1 = v1 * v1 - 2.0 * mu * d1
    tw1 = _div(2.0 * d1, -v1 + _sqrt0(disc1), (v1 < 0.0) & (disc1 >= 0.0))
    d2 = jnp.maximum(XR - x2, 0.0)
    disc2 = v2 * v2 - 2.0 * mu * d2
    tw2 = _div(2.0 * d2, v2 + _sqrt0(disc2), (v2 > 0.0) & (disc2 >= 0.0))
    ts1 = _div(jnp.abs(v1), mu, (v1 != 0.0) & (mu > 0.0))
    ts2 = _div(jnp.abs(v2), mu, (v2 != 0.0) & (mu > 0.0))
    return tp, tw1, tw2, ts1, ts2


def _move(x, v, t, mu):
    """As collision._move."""
    sg = jnp.sign(v)
    sp = jnp.abs(v)
    return x + sg * t * (sp - 0.5 * mu * t), sg * jnp.maximum(sp - mu * t, 0.0)


def _pass(state, rem, th):
    """One masked pass of collision._advance_frame's loop."""
    x1, v1, x2, v2 = state
    lq, eb, mu, ew = th
    tp, tw1, tw2, ts1, ts2 = _event_times(x1, v1, x2, v2, mu)
    te = jnp.minimum(jnp.minimum(jnp.minimum(tp, tw1), jnp.minimum(tw2, ts1)), ts2)
    live = rem > 0.0
    ev = live & (te < rem)
    # how far this pass moves: to the event, to the frame's end, or nowhere (frame done)
    tt = jnp.where(ev, jnp.where(ev, te, 0.0), jnp.where(live, rem, 0.0))
    x1, v1 = _move(x1, v1, tt, mu)
    x2, v2 = _move(x2, v2, tt, mu)
    is_p = ev & (tp <= te)
    is_w1 = ev & ~is_p & (tw1 <= te)
    is_w2 = ev & ~is_p & ~is_w1 & (tw2 <= te)
    is_s1 = ev & ~is_p & ~is_w1 & ~is_w2 & (ts1 <= te)
    is_s2 = ev & ~is_p & ~is_w1 & ~is_w2 & ~is_s1
    m2 = 2.0**lq
    u1 = (v1 + m2 * v2 + m2 * eb * (v2 - v1)) / (1.0 + m2)
    u2 = (v1 + m2 * v2 + eb * (v1 - v2)) / (1.0 + m2)
    v1n = jnp.where(is_p, u1, jnp.where(is_w1, -ew * v1, jnp.where(is_s1, 0.0, v1)))
    v2n = jnp.where(is_p, u2, jnp.where(is_w2, -ew * v2, jnp.where(is_s2, 0.0, v2)))
    x1 = jnp.where(is_w1, XL, x1)
    x2 = jnp.where(is_w2, XR, x2)
    rem = jnp.where(ev, rem - jnp.where(ev, te, 0.0), 0.0)
    return (x1, v1n, x2, v2n), rem


def _frame(carry, th, *, dt, max_passes):
    state, bad = carry
    # the first pass ends most frames (no event); the others run only when one is needed
    state, rem = _pass(state, jnp.asarray(dt, jnp.float64), th)

    def more(c):
        def body(c, _):
            return _pass(c[0], c[1], th), None

        return lax.scan(body, c, None, length=max_passes - 1)[0]

    state, rem = lax.cond(rem > 0.0, more, lambda c: c, (state, rem))
    bad = bad | (rem > 0.0)
    out = jnp.where(bad, jnp.nan, jnp.stack(state))
    return (state, bad), out


@partial(jax.jit, static_argnames=("n_frames", "dt", "max_passes"))
def simulate_core(theta, state0, n_frames: int = 200, dt: float = 0.05,
                  max_passes: int = MAX_PASSES):
    """Unchecked, traceable simulation of one trajectory.

    Parameters
    ----------
    theta : array, shape (4,) or (n_frames, 4)
        ``[lq, eb, mu, ew]``; a row ``theta[t]`` holds from frame t to t+1.
    state0 : array, shape (4,)
    n_frames, dt, max_passes : static

    Returns
    -------
    states : array, shape (n_frames, 4)
        NaN from the first frame that needed more than ``max_passes`` passes.
    bad : bool array, shape ()
    """
    theta = jnp.asarray(theta, jnp.float64)
    state0 = jnp.asarray(state0, jnp.float64)
    carry = (tuple(state0[i] for i in range(4)), jnp.asarray(False))
    step = partial(_frame, dt=float(dt), max_passes=int(max_passes))
    if theta.ndim == 2:
        carry, traj = lax.scan(lambda c, t: step(c, tuple(t[i] for i in range(4))), carry,
                               theta[: n_frames - 1])
    else:
        th = tuple(theta[i] for i in range(4))
        carry, traj = lax.scan(lambda c, _: step(c, th), carry, None, length=n_frames - 1)
    return jnp.concatenate((state0[None], traj), axis=0), carry[1]


def _is_traced(*args) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in args)


def simulate(theta, state0, n_frames: int = 200, dt: float = 0.05):
    """Simulate one collision trajectory (JAX); the NumPy simulator's contract for B = 1.

    Parameters
    ----------
    theta : array_like, shape (4,) or (n_frames, 4)
        ``[lq, eb, mu, ew]``, constant or per frame.
    state0 : array_like, shape (4,)
        ``[x1, v1, x2, v2]``.
    n_frames : int
        Frames to return, frame 0 included (static under ``jit``).
    dt : float
        Seconds between frames (static under ``jit``).

    Returns
    -------
    jax.Array, shape (n_frames, 4), float64

    Notes
    -----
    On concrete arrays the arguments are validated as ``systems.get("collision").simulate``
    does (``ValueError`` naming the argument) and a trajectory needing more than
    :data:`MAX_PASSES` passes in a frame raises ``RuntimeError``. Under ``jit``/``grad``/
    ``vmap`` only shapes are checked and such a trajectory's states are NaN from that frame on.
    """
    from sysid_bench.core.systems import get

    system = get("collision")
    n_frames, dt = system._check_frames_dt(n_frames, dt)
    if not _is_traced(theta, state0):
        th = np.asarray(theta, dtype=np.float64)
        if th.ndim not in (1, 2):
            raise ValueError(f"theta: expected (4,) or (n_frames, 4) for the collision system, "
                             f"got shape {th.shape}")
        system.check_theta(th[None], n_frames if th.ndim == 2 else None)
        s0 = system.check_state0(np.asarray(state0, dtype=np.float64)[None])[0]
        states, bad = simulate_core(th, s0, n_frames=n_frames, dt=dt)
        if bool(bad):
            raise RuntimeError(f"simulate: more than {MAX_PASSES} passes needed in one frame "
                               f"(theta={th.tolist()})")
        return states
    theta, state0 = jnp.asarray(theta), jnp.asarray(state0)
    if theta.ndim not in (1, 2) or theta.shape[-1] != 4 or state0.shape != (4,):
        raise ValueError(f"theta, state0: expected (4,) or (n_frames, 4) and (4,), got "
                         f"{theta.shape} and {state0.shape}")
    return simulate_core(theta, state0, n_frames=n_frames, dt=dt)[0]
