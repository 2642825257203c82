"""JAX twin of :mod:`sysid_bench.core.systems.pendulum`: the same simulator, jit-able and differentiable.

Same algorithm, step for step and operation for operation, as the NumPy kernel (tested equal to
it to 1e-9 m in float64; they differ by ~1e-13 m, since the kernel's plain steps carry ``sin`` of
the angle by angle addition where this twin calls ``sin`` at every stage): RK4 on ``n_substeps(dt)`` steps per frame; a step whose end has
``s * omega <= 0`` is cut at its event -- the time by the same quadratic guess, safeguarded
Newton steps and last Newton step, the stick rule, the rest of the step from rest in the new
direction. The constants (``SUBSTEPS``, ``_NEWTON_ITERS``, ``_TINY_W``) come from
:mod:`sysid_bench.core.systems.pendulum`: there is one source of physics.

How it is laid out for XLA:

* one trajectory (NUTS vmaps/jits it); frames are a ``lax.scan``. Each frame first takes its
  plain steps; only a frame in which ``omega`` is 0 at the start or changes sign at a step end is
  redone step by step with events (one ``lax.cond`` per frame; under ``vmap`` it becomes a
  select and is still correct). Those steps are branch-free: the plain step, the event time,
  the state at the event and the rest of the step from rest are all computed and the outcome
  selected by the NumPy kernel's conditions, so there is no data-dependent loop and reverse-mode
  AD is possible (the passes as nested conditionals made the gradient's compile take minutes).
  Known gap: reverse-mode gradients are correct (they match central finite differences of the
  NumPy simulator to ~1e-10) but slow -- on the loaded 2-core machine ``jax.grad`` of a 10-frame
  loss compiled in ~50 s and ran in ~2 min, against milliseconds for the forward pass; the cause
  (XLA's code for the differentiated scan -> cond -> scan nest) was not found in time;
* gradients are correct across events: the event time's guess and safeguarded Newton steps are
  computed under ``stop_gradient`` and the last Newton step is differentiated, so ``tau`` carries
  the implicit-function derivative ``-(d omega / d p) / (d omega / d tau)`` and the state after the
  event depends on the parameters through it. Sticking (``|G| <= mu``) is a true switch and has
  no useful gradient across it.

Importing this module turns on ``jax_enable_x64`` (``jax.config.update``), as
:mod:`sysid_bench.core.physics_jax` does.
"""

from __future__ import annotations

from functools import partial

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from sysid_bench.core.systems.pendulum import (  # noqa: E402
    _NEWTON_ITERS,
    _TINY_W,
    Pendulum,
    n_substeps,
)

__all__ = ["simulate", "simulate_core"]


# --------------------------------------------------------------------------------------------
# the pieces, on scalars; every expression mirrors pendulum.py operation for operation
def _acc(th, om, k, b, c):
    return k * jnp.sin(th) - b * om - c


def _rk4(th, om, h, k, b, c):
    h2 = 0.5 * h
    a1 = _acc(th, om, k, b, c)
    o2 = om + h2 * a1
    a2 = _acc(th + h2 * om, o2, k, b, c)
    o3 = om + h2 * a2
    a3 = _acc(th + h2 * o2, o3, k, b, c)
    o4 = om + h * a3
    a4 = _acc(th + h * o3, o4, k, b, c)
    h6 = h / 6.0
    return th + h6 * (om + 2.0 * (o2 + o3) + o4), om + h6 * (a1 + 2.0 * (a2 + a3) + a4)


def _direction(th, om, k, mu):
    G = k * jnp.sin(th)
    rule = jnp.where(jnp.abs(G) <= mu, 0.0, jnp.where(G > 0.0, 1.0, -1.0))
    return jnp.where(om > 0.0, 1.0, jnp.where(om < 0.0, -1.0, rule))


def _guard(w):
    return jnp.where(jnp.abs(w) < _TINY_W, jnp.copysign(_TINY_W, w), w)


def _event_time(th, om, h, k, b, c, s):
    """As ``pendulum._event_time``; the guess and the safeguarded steps carry no gradient, the
    last Newton step does."""
    sg = lax.stop_gradient
    gth, gom, gh, gk, gb, gc, gs = (sg(a) for a in (th, om, h, k, b, c, s))
    a0 = _acc(gth, gom, gk, gb, gc)
    j0 = gk * jnp.cos(gth) * gom - gb * a0
    disc = jnp.maximum(a0 * a0 - 2.0 * j0 * gom, 0.0)
    q = -0.5 * (a0 + jnp.copysign(jnp.sqrt(disc), a0))
    nz = q != 0.0
    tau = jnp.where(nz, gom / jnp.where(nz, q, 1.0), 0.5 * gh)
    tau = jnp.minimum(jnp.maximum(tau, 0.0), gh)

    def newton(_, x):
        tau, lo, hi = x
        tn, on = _rk4(gth, gom, tau, gk, gb, gc)
        before = gs * on > 0.0
        lo = jnp.where(before, tau, lo)
        hi = jnp.where(before, hi, tau)
        w = _guard(_acc(tn, on, gk, gb, gc))
        nxt = tau - on / w
        return jnp.where((lo <= nxt) & (nxt <= hi), nxt, 0.5 * (lo + hi)), lo, hi

    # a loop, not unrolled: it carries no gradient and keeps the compiled program small
    tau, _, _ = lax.fori_loop(0, _NEWTON_ITERS, newton, (tau, jnp.zeros_like(gh), gh))
    tn, on = _rk4(th, om, tau, k, b, c)
    w = _guard(_acc(tn, on, k, b, c))
    return jnp.minimum(jnp.maximum(tau - on / w, 0.0), h)


def _step(th, om, h, k, b, mu):
    """One RK4 step with its event (``pendulum._step``), branch-free: both passes and the event
    time are always computed and the outcome selected, as the NumPy kernel's branches would."""
    s = _direction(th, om, k, mu)
    c = mu * s
    tn, on = _rk4(th, om, h, k, b, c)
    quiet = s * on > 0.0
    tau = _event_time(th, om, h, k, b, c, s)
    te, _w = _rk4(th, om, tau, k, b, c)
    s2 = _direction(te, jnp.zeros_like(om), k, mu)
    rem = h - tau
    t2, o2 = _rk4(te, jnp.zeros_like(om), rem, k, b, mu * s2)
    moves = (s2 != 0.0) & (rem > 0.0) & (s2 * o2 > 0.0)
    # stuck, or at rest and not leaving it: unchanged; else the plain step, or the event and
    # (when it moves on) the rest of the step
    keep = (s == 0.0) | (~quiet & (om == 0.0))
    th_ev = jnp.where(moves, t2, te)
    om_ev = jnp.where(moves, o2, 0.0)
    th_out = jnp.where(keep, th, jnp.where(quiet, tn, th_ev))
    om_out = jnp.where(keep, om, jnp.where(quiet, on, om_ev))
    return th_out, om_out


def _frame(carry, p, *, h, nsub):
    th, om = carry
    g, L, b, mu = p[0], p[1], p[2], p[3]
    k = g / L
    # the plain steps (the NumPy kernel's path when no step holds an event)
    s = jnp.sign(om)
    c = mu * s
    a, w = th, om
    crossed = om == 0.0
    for _ in range(nsub):
        a, w = _rk4(a, w, h, k, b, c)
        crossed = crossed | ~(s * w > 0.0)

    def resolve(_):
        def one(x, _):
            return _step(x[0], x[1], h, k, b, mu), None

        out, _ = lax.scan(one, (th, om), None, length=nsub)
        return out

    def plain(_):
        return a, w

    a, w = lax.cond(crossed, resolve, plain, None)
    return (a, w), jnp.stack((a, w))


@partial(jax.jit, static_argnames=("n_frames", "dt"))
def simulate_core(theta, state0, n_frames: int = 200, dt: float = 0.05):
    """Unchecked simulation of one trajectory, the traceable core of :func:`simulate`.

    Parameters
    ----------
    theta : array, shape (4,) or (n_frames, 4)
        ``[g, L, b, mu]``, constant or per frame (row t holds from frame t to t+1).
    state0 : array, shape (2,)
    n_frames : int (static)
    dt : float (static)

    Returns
    -------
    array, shape (n_frames, 2)
    """
    theta = jnp.asarray(theta, jnp.float64)
    state0 = jnp.asarray(state0, jnp.float64)
    nsub = n_substeps(float(dt))
    step = partial(_frame, h=float(dt) / nsub, nsub=nsub)
    carry = (state0[0], state0[1])
    if theta.ndim == 2:
        _, traj = lax.scan(step, carry, theta[: n_frames - 1])
    else:
        _, traj = lax.scan(lambda c, _: step(c, theta), carry, None, length=n_frames - 1)
    return jnp.concatenate((state0[None], traj), axis=0)


def simulate(theta, state0, n_frames: int = 200, dt: float = 0.05):
    """Simulate one pendulum (JAX); the same physics as ``Pendulum.simulate``.

    Parameters
    ----------
    theta : array_like, shape (4,) or (n_frames, 4)
        ``[g, L, b, mu]``, or one row per frame (row t holds from frame t to t+1).
    state0 : array_like, shape (2,)
        ``[theta0, omega0]``.
    n_frames : int
        Frames to return, frame 0 included (static under ``jit``).
    dt : float
        Seconds between frames (static under ``jit``).

    Returns
    -------
    jax.Array, shape (n_frames, 2), float64

    Notes
    -----
    On concrete arrays the arguments are validated as ``Pendulum.simulate`` validates them
    (``ValueError`` naming the argument). Inside ``jit``/``grad``/``vmap`` values cannot be
    inspected: the arguments are only shape-checked.
    """
    system = Pendulum()
    n_frames, dt = system._check_frames_dt(n_frames, dt)
    traced = any(isinstance(a, jax.core.Tracer) for a in (theta, state0))
    if not traced:
        th = np.asarray(theta)
        th = system.check_theta(th[None], n_frames if th.ndim == 2 else None)[0]
        s0 = system.check_state0(np.asarray(state0)[None])[0]
        return simulate_core(th, s0, n_frames=n_frames, dt=dt)
    theta, state0 = jnp.asarray(theta), jnp.asarray(state0)
    if theta.ndim not in (1, 2) or theta.shape[-1] != 4 or state0.shape != (2,):
        raise ValueError(
            f"theta, state0: expected (4,) or (n_frames, 4) and (2,), got {theta.shape} and "
            f"{state0.shape}"
        )
    return simulate_core(theta, state0, n_frames=n_frames, dt=dt)
