"""JAX twin of :mod:`sysid_bench.core.systems.spring`: the same simulator, jit-able and differentiable.

The same algorithm, step for step and operation for operation, as the numba kernel of
``spring.py`` (classical RK4, ``SUBSTEPS`` steps of ``h = dt / SUBSTEPS`` per frame,
``x'' = -w2 s - k3 s^3 - c v`` with ``s = x - L0``); ``SUBSTEPS`` is imported from there, so there
is one source of the physics. The system has no events, so frames are a plain ``lax.scan`` and
reverse-mode gradients in ``theta`` and ``state0`` are exact derivatives of the discrete
simulator.

Importing this module turns on ``jax_enable_x64`` (the simulator is float64, like the NumPy
one). Only this module imports JAX for the spring.
"""

from __future__ import annotations

from functools import partial

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from sysid_bench.core.systems.spring import SUBSTEPS  # noqa: E402

__all__ = ["simulate"]


def _acc(x, v, w2, k3, c, L0):
    s = x - L0
    return -w2 * s - k3 * (s * s * s) - c * v


def _frame(state, th, h):
    """Advance ``(x, v)`` by one frame interval: ``SUBSTEPS`` RK4 steps of length ``h``."""
    w2, k3, c, L0 = th[..., 0], th[..., 1], th[..., 2], th[..., 3]
    h2 = 0.5 * h
    h6 = h / 6.0

    def step(_, xv):
        x, v = xv
        a1 = _acc(x, v, w2, k3, c, L0)
        x2 = x + h2 * v
        v2 = v + h2 * a1
        a2 = _acc(x2, v2, w2, k3, c, L0)
        x3 = x + h2 * v2
        v3 = v + h2 * a2
        a3 = _acc(x3, v3, w2, k3, c, L0)
        x4 = x + h * v3
        v4 = v + h * a3
        a4 = _acc(x4, v4, w2, k3, c, L0)
        return x + h6 * (v + 2.0 * (v2 + v3) + v4), v + h6 * (a1 + 2.0 * (a2 + a3) + a4)

    # a loop, not unrolled: the same operations, and XLA compiles the gradient of one step
    # instead of SUBSTEPS copies (unrolled, grad took minutes to compile on a loaded machine)
    x, v = lax.fori_loop(0, SUBSTEPS, step, state)
    return (x, v), jnp.stack([x, v], axis=-1)


@partial(jax.jit, static_argnums=(2, 3))
def _simulate(theta, state0, n_frames, dt):
    h = dt / SUBSTEPS
    carry = (state0[..., 0], state0[..., 1])
    if theta.ndim == 2:  # (n_frames, P): theta[t] holds from frame t to t + 1
        _, traj = lax.scan(lambda c, th: _frame(c, th, h), carry, theta[: n_frames - 1])
    else:
        _, traj = lax.scan(lambda c, _: _frame(c, theta, h), carry, None, length=n_frames - 1)
    return jnp.concatenate([state0[None, :], traj], axis=0)


def simulate(theta, state0, n_frames: int = 200, dt: float = 0.05):
    """Simulate one trajectory (JAX).

    Parameters
    ----------
    theta : array_like, shape (4,) or (n_frames, 4)
        ``[w2, k3, c, L0]``, or one row per frame (row t holds from frame t to t + 1).
    state0 : array_like, shape (2,)
        ``[x0, v0]``.
    n_frames : int
        Frames returned, frame 0 included (static under ``jit``).
    dt : float
        Seconds between frames (static under ``jit``).

    Returns
    -------
    jax.Array, shape (n_frames, 2), float64
        States at the frame times; frame 0 equals ``state0``.

    Notes
    -----
    On concrete arrays the arguments are validated as ``Spring.simulate`` validates them
    (``ValueError`` naming the argument: shapes, the envelope, the step check); under
    ``jit``/``grad``/``vmap`` only the shapes are checked.
    """
    from sysid_bench.core.systems import get

    system = get("spring")
    n_frames, dt = system._check_frames_dt(n_frames, dt)
    th = jnp.asarray(theta, jnp.float64)
    s0 = jnp.asarray(state0, jnp.float64)
    if th.shape not in ((4,), (n_frames, 4)):
        raise ValueError(f"theta: expected shape (4,) or ({n_frames}, 4) for the spring system, "
                         f"got {th.shape}")
    if s0.shape != (2,):
        raise ValueError(f"state0: expected shape (2,) for the spring system, got {s0.shape}")
    if not any(isinstance(a, jax.core.Tracer) for a in (theta, state0)):
        # concrete input: the NumPy simulator's checks (envelope, state bounds, step size)
        th_np = system.check_theta(np.asarray(th).reshape((1,) + th.shape), n_frames)
        s0_np = system.check_state0(np.asarray(s0)[None])
        th3 = th_np if th_np.ndim == 3 else np.broadcast_to(th_np[:, None], (1, n_frames, 4))
        system._check_step(th3, s0_np, dt)
    return _simulate(th, s0, n_frames, dt)
