"""JAX twin of :mod:`sysid_bench.systems.pendulum`: the same simulator, jit-able and differentiable.

Same algorithm, step for step and operation for operation, as the NumPy kernel (tested equal to
it to 1e-9 m in float64): RK4 on ``n_substeps(dt)`` steps per frame; a step whose end has
``s * omega <= 0`` is redone in passes -- the event time by the same quadratic guess, safeguarded
Newton steps and last Newton step, the stick rule, the rest of the step with the new direction.
The constants (``SUBSTEPS``, ``_NEWTON_ITERS``, ``_MAX_PASSES``, ``_TINY_W``) come from
:mod:`sysid_bench.systems.pendulum`: there is one source of physics.

How it is laid out for XLA:

* one trajectory (NUTS vmaps/jits it); frames are a ``lax.scan``. Each frame first takes its
  plain steps; only a frame in which ``omega`` is 0 at the start or changes sign at a step end is
  redone step by step with events (``lax.cond``; under ``vmap`` the branch becomes a select and
  is still correct). A step makes a **fixed** number of passes (:data:`_MAX_PASSES`), each
  skipped by ``lax.cond`` when it has nothing to do, instead of a data-dependent loop, so
  reverse-mode AD works. A trajectory that would need more passes is marked bad: ``simulate``
  raises ``RuntimeError`` on concrete input and gives NaN states from that frame on under a JAX
  transformation (a sampler then rejects the point);
* gradients are correct across events: the event time's guess and safeguarded Newton steps are
  computed under ``stop_gradient`` and the last Newton step is differentiated, so ``tau`` carries
  the implicit-function derivative ``-(d omega / d p) / (d omega / d tau)`` and the state after the
  event depends on the parameters through it. Sticking (``|G| <= mu``) is a true switch and has
  no useful gradient across it.

Importing this module turns on ``jax_enable_x64`` (``jax.config.update``), as
:mod:`sysid_bench.physics_jax` does.
"""

from __future__ import annotations

from functools import partial

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from sysid_bench.systems.pendulum import (  # noqa: E402
    _MAX_PASSES,
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
    lo, hi = jnp.zeros_like(gh), gh
    for _ in range(_NEWTON_ITERS):
        tn, on = _rk4(gth, gom, tau, gk, gb, gc)
        before = gs * on > 0.0
        lo = jnp.where(before, tau, lo)
        hi = jnp.where(before, hi, tau)
        w = _guard(_acc(tn, on, gk, gb, gc))
        nxt = tau - on / w
        tau = jnp.where((lo <= nxt) & (nxt <= hi), nxt, 0.5 * (lo + hi))
    tn, on = _rk4(th, om, tau, k, b, c)
    w = _guard(_acc(tn, on, k, b, c))
    return jnp.minimum(jnp.maximum(tau - on / w, 0.0), h)


def _pass(st, k, b, mu):
    """One pass of the loop in ``pendulum._step``: integrate the rest ``rem`` of the step, or up
    to its first event and apply it. A pass with ``rem <= 0`` changes nothing."""
    th, om, s, rem = st
    live = rem > 0.0
    c = mu * s
    tn, on = _rk4(th, om, rem, k, b, c)
    quiet = s * on > 0.0

    def event(_):
        tau = _event_time(th, om, rem, k, b, c, s)
        te, _w = _rk4(th, om, tau, k, b, c)
        s_new = _direction(te, 0.0, k, mu)
        left = rem - tau
        left = jnp.where((s_new == 0.0) | ~(left > 0.0), 0.0, left)
        # a pass that started at rest and does not leave it: stays (as the NumPy kernel)
        at_rest = om == 0.0
        return (jnp.where(at_rest, th, te), jnp.zeros_like(om), jnp.where(at_rest, s, s_new),
                jnp.where(at_rest, 0.0, left))

    def plain(_):
        return tn, on, s, jnp.zeros_like(rem)

    new = lax.cond(live & ~quiet, event, plain, None)
    return tuple(jnp.where(live, a, b_) for a, b_ in zip(new, st))


def _step(th, om, h, k, b, mu):
    """One RK4 step with its events (``pendulum._step``); returns (theta, omega, unresolved)."""
    s = _direction(th, om, k, mu)
    st = (th, om, s, jnp.where(s == 0.0, 0.0, h))
    st = _pass(st, k, b, mu)

    def more(x, _):
        return lax.cond(x[3] > 0.0, lambda y: _pass(y, k, b, mu), lambda y: y, x), None

    st, _ = lax.scan(more, st, None, length=_MAX_PASSES - 1)  # traced once, not unrolled
    return st[0], st[1], st[3] > 0.0


def _frame(carry, p, *, h, nsub):
    th, om, bad = carry
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
        def one(c, _):
            x, y, u = _step(c[0], c[1], h, k, b, mu)
            return (x, y, c[2] | u), None

        out, _ = lax.scan(one, (th, om, jnp.zeros((), bool)), None, length=nsub)
        return out

    def plain(_):
        return a, w, jnp.zeros((), bool)

    a, w, unres = lax.cond(crossed, resolve, plain, None)
    bad = bad | unres
    out = jnp.where(bad, jnp.nan, jnp.stack((a, w)))
    return (a, w, bad), out


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
    states : array, shape (n_frames, 2)
    bad : array of bool, shape ()
        True when some step needed more than ``_MAX_PASSES`` passes; states are NaN from there.
    """
    theta = jnp.asarray(theta, jnp.float64)
    state0 = jnp.asarray(state0, jnp.float64)
    nsub = n_substeps(float(dt))
    step = partial(_frame, h=float(dt) / nsub, nsub=nsub)
    carry = (state0[0], state0[1], jnp.zeros((), bool))
    if theta.ndim == 2:
        carry, traj = lax.scan(step, carry, theta[: n_frames - 1])
    else:
        carry, traj = lax.scan(lambda c, _: step(c, theta), carry, None, length=n_frames - 1)
    return jnp.concatenate((state0[None], traj), axis=0), carry[2]


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
    (``ValueError`` naming the argument) and a step needing more than ``_MAX_PASSES`` passes
    raises ``RuntimeError``. Inside ``jit``/``grad``/``vmap`` values cannot be inspected: the
    arguments are only shape-checked and such a trajectory is NaN from that frame on.
    """
    system = Pendulum()
    n_frames, dt = system._check_frames_dt(n_frames, dt)
    traced = any(isinstance(a, jax.core.Tracer) for a in (theta, state0))
    if not traced:
        th = np.asarray(theta)
        th = system.check_theta(th[None], n_frames if th.ndim == 2 else None)[0]
        s0 = system.check_state0(np.asarray(state0)[None])[0]
        states, bad = simulate_core(th, s0, n_frames=n_frames, dt=dt)
        if bool(bad):
            raise RuntimeError(
                f"pendulum_jax: more than {_MAX_PASSES - 1} events in one RK4 step "
                f"(theta = {th.tolist()}, state0 = {s0.tolist()})"
            )
        return states
    theta, state0 = jnp.asarray(theta), jnp.asarray(state0)
    if theta.ndim not in (1, 2) or theta.shape[-1] != 4 or state0.shape != (2,):
        raise ValueError(
            f"theta, state0: expected (4,) or (n_frames, 4) and (2,), got {theta.shape} and "
            f"{state0.shape}"
        )
    return simulate_core(theta, state0, n_frames=n_frames, dt=dt)[0]
