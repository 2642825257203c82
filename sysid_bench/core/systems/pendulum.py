"""A pendulum with viscous and Coulomb pivot friction: the suite's system that sticks.

Physics (``design.md``, section "Systems", fixed)
--------------------------------------------------
A bob on a massless rod of length ``L`` hangs from a pivot at world ``(0, 0)`` (x right, y up).
State ``[theta, omega]`` (rad, rad/s), ``theta`` from straight down, counter-clockwise positive;
the tracked point is the bob, ``(L sin theta, -L cos theta)`` (K = 1). While it moves::

    theta'' = (g / L) sin(theta) - b omega - mu sign(omega)

(``g < 0`` is down, so ``(g / L) sin(theta)`` is a restoring torque). When ``omega`` reaches 0
(an exact event) with ``G = (g / L) sin(theta)``: if ``|G| <= mu`` the bob stays there for good
(it sticks); otherwise it moves on with ``sign(omega)`` replaced by ``sign(G)`` (friction opposes
the impending motion) until ``omega`` leaves 0. A state with ``omega = 0`` -- a start with
``omega0 = 0``, a stuck bob at a frame start -- follows the same rule. The rule is evaluated with
the parameters of the current frame, so for constant parameters a stuck bob stays stuck for good,
and the state ``[theta, omega]`` alone says what happens next (no hidden mode flag).

Parameters, in this order (:attr:`Pendulum.params`):

======  ==========================================  ================
name    meaning                                     prior range
======  ==========================================  ================
``g``   gravity, m/s^2, negative = down             [-12.81, -6.81]
``L``   rod length, m                               [0.5, 2.0]
``b``   viscous pivot damping, 1/s                  [0.0, 0.5]
``mu``  Coulomb pivot friction, rad/s^2             [0.0, 0.5]
======  ==========================================  ================

Initial states: ``|theta0|`` in [0.5, 2.5] with a random sign, ``omega0`` in [-1, 1].

Numerics
--------
Classical RK4 on a fixed grid of ``n`` steps per frame interval, ``h = dt / n`` with
``n = max(SUBSTEPS, ceil(dt / H_MAX))`` (``H_MAX = 0.05 / SUBSTEPS``: at the design's ``dt = 0.05``
exactly ``SUBSTEPS`` steps; a longer frame interval gets more steps rather than a coarser,
possibly unstable, step). The kernel, compiled by numba, advances 64 trajectories ("lanes")
together: frames outer, steps, then lanes, so consecutive operations belong to independent
trajectories. Each step first takes the plain RK4 step of every lane in one branch-free loop that
the compiler vectorises: it calls no ``sin`` -- ``sin`` and ``cos`` of the angle are computed
exactly once a frame and carried through the frame's steps by angle addition,
``sin(theta + d) = sin(theta) cos(d) + cos(theta) sin(d)``, with Taylor series of ``sin(d)`` and
``cos(d)`` (to d^7 and d^8) for the small increments ``|d| <= _D_MAX`` (``d = h omega`` and
the like: at most ~0.07 rad in the prior). A lane whose step holds an event, that starts at rest
or whose increment is larger is redone from the step's start by the scalar step with events
described below (``sin`` of each stage angle). The two evaluations of ``sin`` agree to ~1e-15
(the trajectories moved by <= 2.6e-13 m on 2000 prior cases when the carried one came in). A
trajectory's result does not depend on its batch or lane, and a batch of
``_base.PARALLEL_MIN`` trajectories or more runs its chunks over numba's threads (bitwise the
same output).

Within a step the friction direction ``s`` is constant, so the right-hand side is smooth. A step
whose end has ``s * omega <= 0`` holds an event: its time ``tau`` is the root of
``omega(tau) = 0`` where ``omega(tau)`` is itself one RK4 step of length ``tau`` from the start of
the step, found by a quadratic first guess (Taylor series of ``omega`` to second order), then
:data:`_NEWTON_ITERS` Newton steps safeguarded by bisection inside the bracket ``[0, h]``, then
one last plain Newton step (the one the JAX twin differentiates); the derivative of the RK4 step
with respect to its length is the end acceleration up to O(tau^4), so Newton converges to machine
precision. The bob is moved there with ``omega = 0`` exactly, the stick rule applied, and the
rest of the step integrated afresh from rest with the new direction. Events are therefore not
snapped to frames or steps. Between two events ``omega`` keeps its sign for at least a half swing
(``pi / sqrt(|g| / L)``, >= 0.26 s in the envelope), far longer than a step, so an end-of-step
sign test cannot miss one and a step holds at most one.

``SUBSTEPS = 7`` was measured (``scripts/measure_system_speed.py --accuracy --substeps 6 7 8``):
at the prior's fastest corner (``g = -12.81``, ``L = 0.5``, ``b = mu = 0``, ``|theta0| = 2.5``,
``|omega0| = 1``, all four sign combinations; it swings to within ~0.3 rad of the top) the
largest bob position error over 200 frames at ``dt = 0.05`` against the event-driven
``solve_ivp`` reference (DOP853, ``rtol = atol = 1e-12``) is 9.8e-6 m with 4 steps, 2.9e-6 m
with 5, 1.05e-6 m with 6, 4.3e-7 m with 7, 1.9e-7 m with 8 and 4.5e-8 m with 10 (RK4's
``h^4``); with friction at that corner (``mu`` 0.2 or 0.5, events every half swing and a stick)
it is smaller, and on 100 random prior cases it is at most 5.7e-8 m with 7. 7 is the fewest
steps that keep a 2x margin under the design's 1e-6 m (``tests/test_system_pendulum.py`` checks
that corner at half the tolerance); it was 8 until the simulator had to run 2000 x 200 at
>= 1000x its reference loop. The JAX twin, :mod:`sysid_bench.core.systems.pendulum_jax`, takes the
same steps with the same operations, but for ``sin`` of every stage angle where the kernel's
plain steps carry it (see above): they agree to ~1e-13 m.

View
----
A 5 m square centred on the pivot, extent ``(-2.5, 2.5, -2.5, 2.5)``, on a 64 x 64 frame
(12.8 px/m). The bob is a white disc of radius :data:`BOB_RADIUS` = 0.12 m (1.54 px), drawn no
smaller than :data:`BOB_MIN_PX` = 1.5 px at any frame size; the rod a line of
:data:`ROD_WIDTH` metres (at least 1 px) at :data:`ROD_LEVEL` of white, composited under the bob
by maximum. Why 64 x 64: at 28 x 28 the design's 0.1 m bob is 0.56 px across in radius, so its
anti-aliased disc is a single grey pixel whose centroid moves in jumps -- and the rod, which has
the same order of brightness, cannot be told from it; a bob of 1.5 px radius spans ~3 x 3 pixels
brighter than anything the rod can reach, and its centroid follows it to a tenth of a pixel
(measured on 20 prior videos of 200 frames: 0.023 px RMS, 0.05 px worst on clean video; with
blur 0.5 and noise 8, 0.041 px RMS, 0.17 px worst).

The tracker uses only pixels brighter than :data:`_THRESHOLD` (above the rod's level plus
pixel noise), so the rod never pulls it: a first centroid of those pixels, then a second one
within a window around it (stray noise far away does not count). A frame gives NaN when too
little bright mass is near that centroid (dropped, black, occluded) or too much lies elsewhere
(all white, pure noise).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sysid_bench.core._validate import as_float_array, check_positive_int, check_seed
from sysid_bench.core.systems import _draw
from sysid_bench.core.systems._base import System, use_parallel
from sysid_bench.core.systems._scene import PendulumScene

__all__ = [
    "Pendulum",
    "SUBSTEPS",
    "H_MAX",
    "n_substeps",
    "BOB_RADIUS",
    "BOB_MIN_PX",
    "ROD_WIDTH",
    "ROD_LEVEL",
    "THETA0_RANGE",
    "OMEGA0_RANGE",
]

#: RK4 steps per frame interval at dt = 0.05 (see the module docstring for the measurement).
SUBSTEPS = 7
#: Longest RK4 step (s); a frame interval above 0.05 s gets more steps than SUBSTEPS.
H_MAX = 0.05 / SUBSTEPS
#: Bob radius (m) and its smallest drawn radius (px), see the module docstring.
BOB_RADIUS = 0.12
BOB_MIN_PX = 1.5
#: Rod width (m; drawn at least 1 px wide) and grey level (fraction of white).
ROD_WIDTH = 0.04
ROD_LEVEL = 0.3
#: Initial-state ranges (design): |theta0| (random sign) and omega0.
THETA0_RANGE = (0.5, 2.5)
OMEGA0_RANGE = (-1.0, 1.0)

#: Safeguarded Newton steps locating an event (from a guess already good to ~1e-7 s).
_NEWTON_ITERS = 4
#: |df/dtau| floor in the Newton step (a grazing event), as the ball's contact time.
_TINY_W = 1e-12

#: Tracker: pixels dimmer than this fraction of white are ignored (rod 0.3 plus ~5 sigma of
#: noise 8 grey levels).
_THRESHOLD = 0.5
#: Tracker: fraction of a whole clean bob's bright mass that must be found near the centroid.
_MIN_MASS = 0.35
#: Tracker: bright mass allowed away from the bob, in clean-bob masses.
_MAX_STRAY = 0.5

# state0_from_track: the first seen frames fitted (angle, quadratic in time) and the half-widths
# of the box around the estimate (measured on 2000 prior trajectories with 1 cm Gaussian noise:
# 99.9% quantiles of |error| 0.041 rad and 0.67 rad/s, largest 0.050 and 0.96; quantiles doubled,
# rounded up; 5 or 10 frames fitted gave larger errors)
_FIT_FRAMES = 7
_THETA_HALF = 0.1
_OMEGA_HALF = 1.4

_njit = numba.njit(cache=True, nogil=True, error_model="numpy")


def n_substeps(dt: float) -> int:
    """RK4 steps per frame interval ``dt``: ``max(SUBSTEPS, ceil(dt / H_MAX))``."""
    return max(SUBSTEPS, int(math.ceil(dt / H_MAX * (1.0 - 1e-12))))


# --------------------------------------------------------------------------------------------
# the kernel: scalar code per trajectory; ``k = g / L`` and ``c = mu * s`` with ``s`` the friction
# direction (+1, -1), so the acceleration is ``k sin(theta) - b omega - c``.
@_njit
def _acc(th, om, k, b, c):
    return k * math.sin(th) - b * om - c


@_njit
def _rk4(th, om, h, k, b, c):
    """One classical RK4 step of length ``h``; returns the new (theta, omega)."""
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


#: Largest angle increment ``|d|`` (rad) the plain step takes by angle addition; a step with a
#: larger one goes through :func:`_step`. The series of :func:`_sin_cos_small` stop at d^7 and
#: d^8: their first omitted terms, d^9/9! and d^10/10!, are under 2.8e-15 at ``|d| = 0.1`` and
#: under 1.2e-16 (rounding) at the prior's largest ``|d|``, ``h |omega| <= 0.0072 * 10`` at
#: dt = 0.05 (two terms more cost 8% of the kernel's time and changed no figure).
_D_MAX = 0.1
# Taylor coefficients of sin (d^3 .. d^7) and cos (d^2 .. d^8); products, not divisions
_S3, _S5, _S7 = -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0
_C2, _C4, _C6, _C8 = -0.5, 1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sin_cos_small(d):
    """sin(d) and cos(d) for |d| <= :data:`_D_MAX`, by their Taylor series."""
    q = d * d
    sn = d + d * q * (_S3 + q * (_S5 + q * _S7))
    cs = 1.0 + q * (_C2 + q * (_C4 + q * (_C6 + q * _C8)))
    return sn, cs


# inlined (numba IR), so the compiler sees the lanes' loop whole and vectorises it
@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _rk4_carried(th, om, S, C, h, k, b, c):
    """:func:`_rk4` given ``S, C = sin(th), cos(th)``, with no call of ``sin``: each later
    stage's ``sin(th + d)`` is ``S cos(d) + C sin(d)`` (angle addition with the small ``d`` of
    :func:`_sin_cos_small`), and so are the new angle's sine and cosine, carried to the next
    step. Returns the new (theta, omega, sin theta, cos theta) and the largest ``|d|`` (the
    result holds when it is at most :data:`_D_MAX`)."""
    h2 = 0.5 * h
    kS = k * S
    kC = k * C
    a1 = kS - b * om - c
    d2 = h2 * om
    o2 = om + h2 * a1
    sn, cs = _sin_cos_small(d2)
    a2 = (kS * cs + kC * sn) - b * o2 - c
    d3 = h2 * o2
    o3 = om + h2 * a2
    sn, cs = _sin_cos_small(d3)
    a3 = (kS * cs + kC * sn) - b * o3 - c
    d4 = h * o3
    o4 = om + h * a3
    sn, cs = _sin_cos_small(d4)
    a4 = (kS * cs + kC * sn) - b * o4 - c
    h6 = h / 6.0
    d5 = h6 * (om + 2.0 * (o2 + o3) + o4)
    sn, cs = _sin_cos_small(d5)
    small = (abs(d2) <= _D_MAX) & (abs(d3) <= _D_MAX) & (abs(d4) <= _D_MAX) & (abs(d5) <= _D_MAX)
    return (th + d5, om + h6 * (a1 + 2.0 * (a2 + a3) + a4), S * cs + C * sn, C * cs - S * sn,
            small)


@_njit
def _direction(th, om, k, mu):
    """Friction direction of a state: sign(omega), or at omega = 0 the stick rule: 0 (stuck)
    when ``|k sin(theta)| <= mu``, else sign(k sin(theta))."""
    if om > 0.0:
        return 1.0
    if om < 0.0:
        return -1.0
    G = k * math.sin(th)
    if abs(G) <= mu:
        return 0.0
    return 1.0 if G > 0.0 else -1.0


@_njit
def _event_time(th, om, h, k, b, c, s):
    """Length ``tau`` in [0, h] of the RK4 step from (th, om) whose omega is 0.

    ``s`` is sign(om) and the step of length ``h`` ends with ``s * omega <= 0``.
    """
    a0 = _acc(th, om, k, b, c)
    j0 = k * math.cos(th) * om - b * a0  # omega'' at the start
    # smallest positive root of om + a0 t + j0 t^2 / 2, in the cancellation-free form
    disc = max(a0 * a0 - 2.0 * j0 * om, 0.0)
    q = -0.5 * (a0 + math.copysign(math.sqrt(disc), a0))
    tau = om / q if q != 0.0 else 0.5 * h
    tau = min(max(tau, 0.0), h)
    lo, hi = 0.0, h
    for _ in range(_NEWTON_ITERS):
        tn, on = _rk4(th, om, tau, k, b, c)
        if s * on > 0.0:
            lo = tau
        else:
            hi = tau
        w = _acc(tn, on, k, b, c)
        if abs(w) < _TINY_W:
            w = math.copysign(_TINY_W, w)
        nxt = tau - on / w
        tau = nxt if lo <= nxt <= hi else 0.5 * (lo + hi)
    # the last plain Newton step (the one the JAX twin differentiates)
    tn, on = _rk4(th, om, tau, k, b, c)
    w = _acc(tn, on, k, b, c)
    if abs(w) < _TINY_W:
        w = math.copysign(_TINY_W, w)
    return min(max(tau - on / w, 0.0), h)


@_njit
def _step(th, om, h, k, b, mu):
    """One RK4 step of length ``h`` with its event; returns the new (theta, omega).

    At most two passes: the step, or the step up to its event and the rest of it from rest in
    the new direction. A second event in one step would need a half swing shorter than a step
    (>= 0.26 s against <= H_MAX in the envelope) and is not looked for.
    """
    s = _direction(th, om, k, mu)
    if s == 0.0:
        return th, om  # stuck
    c = mu * s
    tn, on = _rk4(th, om, h, k, b, c)
    if s * on > 0.0:
        return tn, on
    if om == 0.0:
        # started at rest and does not leave it: |G| exceeds mu by a rounding only
        return th, om
    tau = _event_time(th, om, h, k, b, c, s)
    te, _ = _rk4(th, om, tau, k, b, c)
    s2 = _direction(te, 0.0, k, mu)
    rem = h - tau
    if s2 == 0.0 or not rem > 0.0:
        return te, 0.0  # stuck at the event, or the event ends the step
    t2, o2 = _rk4(te, 0.0, rem, k, b, mu * s2)
    if s2 * o2 > 0.0:
        return t2, o2
    return te, 0.0  # at rest and does not leave it (as above)


@_njit
def _chunk(th, s0, dt, nsub, out, b0, b1):
    """Fill ``out[b0:b1]`` (n_frames, 2 each) from ``s0[b0:b1]``; ``th`` is (B, 1 or n_frames, 4).

    Frames outer, then the ``nsub`` steps, then the trajectories ("lanes"). Each step first
    takes the plain step of every lane in one branch-free loop that the compiler vectorises
    (:func:`_rk4_carried`: no call of ``sin``); a lane whose step holds an event, that is at
    rest, or whose angle increment exceeds :data:`_D_MAX` is then redone from the step's start
    by :func:`_step`. Lanes are independent: a trajectory's result does not depend on the chunk.
    """
    n = b1 - b0
    varying = th.shape[1] > 1
    h = dt / nsub
    st = np.empty((5, n))  # lanes' theta, omega, sin theta, cos theta, 1.0 = redo this step
    prev = np.empty((4, n))  # the step's start
    prm = np.empty((3, n))  # k = g / L, b, mu of the frame
    for j in range(n):
        st[0, j], st[1, j] = s0[b0 + j, 0], s0[b0 + j, 1]
        out[b0 + j, 0, 0], out[b0 + j, 0, 1] = st[0, j], st[1, j]
    for t in range(out.shape[1] - 1):
        f = t if varying else 0
        for j in range(n):
            prm[0, j] = th[b0 + j, f, 0] / th[b0 + j, f, 1]
            prm[1, j] = th[b0 + j, f, 2]
            prm[2, j] = th[b0 + j, f, 3]
            st[2, j] = math.sin(st[0, j])  # exact once a frame, then carried
            st[3, j] = math.cos(st[0, j])
        for _ in range(nsub):
            prev[:] = st[:4]
            for j in range(n):
                om = st[1, j]
                s = math.copysign(1.0, om)
                tn, on, sn, cn, small = _rk4_carried(st[0, j], om, st[2, j], st[3, j], h,
                                                     prm[0, j], prm[1, j], prm[2, j] * s)
                st[0, j], st[1, j], st[2, j], st[3, j] = tn, on, sn, cn
                st[4, j] = 0.0 if (s * on > 0.0) & (om != 0.0) & small else 1.0
            for j in range(n):
                if st[4, j] != 0.0:
                    # an event, at rest or fast: the step from its start with its event
                    a, w = _step(prev[0, j], prev[1, j], h, prm[0, j], prm[1, j], prm[2, j])
                    st[0, j], st[1, j] = a, w
                    st[2, j] = math.sin(a)
                    st[3, j] = math.cos(a)
        for j in range(n):
            out[b0 + j, t + 1, 0], out[b0 + j, t + 1, 1] = st[0, j], st[1, j]


#: Trajectories advanced together in the innermost loop (their states stay in L1 cache).
_LANES = 64


@_njit
def _kernel(th, s0, dt, nsub, out):
    """Fill ``out`` (B, n_frames, 2) from ``s0`` (B, 2), ``_LANES`` trajectories at a time."""
    B = s0.shape[0]
    for b0 in range(0, B, _LANES):
        _chunk(th, s0, dt, nsub, out, b0, min(B, b0 + _LANES))


@numba.njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _kernel_parallel(th, s0, dt, nsub, out):
    """:func:`_kernel` with the chunks spread over numba's threads (each trajectory's
    arithmetic is the same, so the output is bitwise the serial kernel's)."""
    B = s0.shape[0]
    for c in numba.prange((B + _LANES - 1) // _LANES):
        b0 = c * _LANES
        _chunk(th, s0, dt, nsub, out, b0, min(B, b0 + _LANES))


# --------------------------------------------------------------------------------------------
# the system
class Pendulum(System):
    """Pendulum with viscous and Coulomb pivot friction: parameters g, L, b, mu; state
    [theta, omega]; K = 1 (the bob). See the module docstring for physics, numerics and view."""

    name = "pendulum"
    params = ("g", "L", "b", "mu")
    prior = {"g": (-12.81, -6.81), "L": (0.5, 2.0), "b": (0.0, 0.5), "mu": (0.0, 0.5)}
    #: Accepted values: gravity from 0 to ~3 Earth g, rods from 0.2 m to 5 m (fastest small swing
    #: sqrt(30 / 0.2) = 12 rad/s, 0.09 rad per RK4 step of H_MAX), damping and friction up to 10x
    #: the prior's top.
    envelope = {"g": (-30.0, 0.0), "L": (0.2, 5.0), "b": (0.0, 5.0), "mu": (0.0, 5.0)}
    state = ("theta", "omega")
    state_bounds = {"theta": (-2 * np.pi, 2 * np.pi), "omega": (-50.0, 50.0)}
    n_points = 1
    #: experiment 3: gravity and friction may change during a clip; a rod does not change length
    changing_params = ("g", "b", "mu")
    #: experiment 4's simplified physics: viscous and Coulomb friction held in training
    simplified_params = ("b", "mu")
    extent = (-2.5, 2.5, -2.5, 2.5)
    size = (64, 64)
    noise_m = 0.01
    jax_twin = "sysid_bench.core.systems.pendulum_jax:simulate"
    scene_type = PendulumScene
    _theta_row_ok = True  # the kernel reads row 0 for every frame of a (B, 1, P) theta
    #: the smallest frames with room for the bob (drawn >= 1.5 px) and its swing
    min_size = (8, 8)

    # ------------------------------------------------------------------------------------------
    # physics
    def _simulate(self, theta, state0, n_frames, dt, scene=None):
        # the state is angular: the pivot moves the bob (observe), not the motion
        out = np.empty((state0.shape[0], n_frames, 2))
        kernel = _kernel_parallel if use_parallel(state0.shape[0]) else _kernel
        kernel(theta, state0, dt, n_substeps(dt), out)
        return out

    def sample_state0(self, n, rng=None):
        """Initial states (n, 2): ``|theta0|`` in [0.5, 2.5] with a random sign, ``omega0`` in
        [-1, 1] (drawn in that order from ``rng``)."""
        n = check_positive_int(n, "n")
        rng = check_seed(rng)
        mag = THETA0_RANGE[0] + rng.random(n) * (THETA0_RANGE[1] - THETA0_RANGE[0])
        sign = rng.choice([-1.0, 1.0], size=n)
        om = OMEGA0_RANGE[0] + rng.random(n) * (OMEGA0_RANGE[1] - OMEGA0_RANGE[0])
        return np.stack([mag * sign, om], axis=1)

    def reference(self, theta, state0, n_frames=200, dt=0.05):
        """Event-driven ``solve_ivp`` (DOP853, rtol = atol = 1e-12) of one trajectory.

        Each segment has a fixed friction direction ``s``; a terminal event ``s * omega = 0``
        (crossing downwards) ends it, the stick rule is applied at the event's state and the
        integration restarted from ``omega = 0``. A stuck bob keeps its angle to the end.

        Parameters
        ----------
        theta : ndarray, shape (4,)
        state0 : ndarray, shape (2,)
        n_frames : int
        dt : float

        Returns
        -------
        ndarray, shape (n_frames, 2)
        """
        from scipy.integrate import solve_ivp

        n_frames, dt = self._check_frames_dt(n_frames, dt)
        th = self.check_theta(np.asarray(theta, dtype=np.float64).reshape(1, -1))[0]
        s0 = self.check_state0(np.asarray(state0, dtype=np.float64).reshape(1, -1))[0]
        g, L, b, mu = (float(v) for v in th)
        k = g / L
        times = np.arange(n_frames) * dt
        out = np.empty((n_frames, 2))
        t0, y0, filled = 0.0, s0.copy(), 0
        while filled < n_frames:
            s = _direction(y0[0], y0[1], k, mu)
            if s == 0.0:
                out[filled:] = (y0[0], 0.0)
                break

            def rhs(t, y, s=s):
                return (y[1], k * math.sin(y[0]) - b * y[1] - mu * s)

            def turn(t, y, s=s):
                return s * y[1]

            turn.terminal = True
            turn.direction = -1.0
            sol = solve_ivp(rhs, (t0, times[-1]), y0, method="DOP853", rtol=1e-12, atol=1e-12,
                            events=turn, dense_output=True)
            if not sol.success:
                raise RuntimeError(f"pendulum reference: solve_ivp failed: {sol.message}")
            t1 = sol.t[-1]
            upto = filled + int(np.searchsorted(times[filled:], t1, side="right"))
            if upto > filled:
                out[filled:upto] = sol.sol(times[filled:upto]).T
            filled = upto
            if sol.status != 1:
                break
            t0 = float(sol.t_events[0][0])
            y0 = np.array([sol.y_events[0][0][0], 0.0])
        return out

    # ------------------------------------------------------------------------------------------
    # camera
    def _observe(self, states, theta, scene=None):
        L = theta[:, None, 1] if theta.ndim == 2 else theta[:, : states.shape[1], 1]
        out = np.empty(states.shape[:2] + (1, 2))
        out[..., 0, 0] = L * np.sin(states[..., 0])
        out[..., 0, 1] = -L * np.cos(states[..., 0])
        if scene is not None and scene.pivot != (0.0, 0.0):  # the default adds nothing (bit for bit)
            out[..., 0, :] += np.asarray(scene.pivot)
        return out

    def jax_observe(self, states, theta):
        """The bob in JAX for NUTS (``methods.nuts``): states (T, 2), theta (4,) ->
        (T, 1, 2); the same map as :meth:`_observe`, which NumPy's in-place writes keep from
        tracing."""
        import jax.numpy as jnp

        L = theta[1]
        return jnp.stack([L * jnp.sin(states[:, 0]), -L * jnp.cos(states[:, 0])], axis=-1)[:, None]

    @staticmethod
    def _sizes(view: _draw.View) -> tuple[float, float]:
        """Bob radius and rod width in pixels for a view."""
        ppm = min(view.px_per_m)
        return max(BOB_RADIUS * ppm, BOB_MIN_PX), max(ROD_WIDTH * ppm, 1.0)

    def _render(self, points, states, theta, size, **nuisance):
        opts = _draw.check_nuisance(nuisance)
        view = _draw.View(self.extent, size)
        r_px, w_px = self._sizes(view)
        sub = _draw.blur_positions(points, opts["dt"], opts["blur"])[..., 0, :]  # (B, T, S, 2)
        pix = view.to_pixels(sub)
        pivot = np.broadcast_to(view.to_pixels(np.zeros(2)), pix.shape[2:])
        b, t = pix.shape[:2]
        img = np.empty((b, t) + tuple(size), dtype=np.float32)
        for i in range(b):  # one video at a time: the drawing holds (T, H, W) arrays only
            bob = _draw.draw_discs(pix[i], r_px, size)
            rod = _draw.draw_segments(np.broadcast_to(pivot, pix[i].shape), pix[i], w_px, size)
            img[i] = np.maximum(np.float32(ROD_LEVEL) * rod, bob)
        return _draw.finish(img * np.float32(255.0), occlusion=opts["occlusion"],
                            drop=opts["drop"], noise=opts["noise"], seed=opts["seed"])

    def _track(self, frames):
        t, h, w = frames.shape
        view = _draw.View(self.extent, (h, w))
        r_px, _ = self._sizes(view)
        img = frames.astype(np.float32) / np.float32(255.0)
        wgt = np.clip(img - np.float32(_THRESHOLD), 0.0, None)
        jc = np.arange(w, dtype=np.float32) + np.float32(0.5)
        ic = np.arange(h, dtype=np.float32) + np.float32(0.5)
        # a clean bob's bright mass: the disc's area times (1 - threshold), roughly
        disc = np.float32(np.pi * r_px**2 * (1.0 - _THRESHOLD))
        mass = wgt.sum(axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            c = (wgt.sum(axis=1) @ jc) / mass
            r = (wgt.sum(axis=2) @ ic) / mass
            # second pass within a window around the first centroid (room for a blur streak)
            win = np.float32(r_px + 4.0) ** 2
            near = ((jc[None, None, :] - c[:, None, None]) ** 2
                    + (ic[None, :, None] - r[:, None, None]) ** 2) <= win
            wn = np.where(near, wgt, np.float32(0.0))
            m_near = wn.sum(axis=(1, 2))
            c = (wn.sum(axis=1) @ jc) / m_near
            r = (wn.sum(axis=2) @ ic) / m_near
        seen = (m_near >= _MIN_MASS * disc) & (mass - m_near <= _MAX_STRAY * disc)
        out = view.to_metres(np.stack([c, r], axis=-1).astype(np.float64))
        out[~seen] = np.nan
        return out[:, None, :]

    def state0_from_track(self, positions, dt=0.05):
        """A rough initial state from a noisy track: the bob's angle ``atan2(x, -y)`` over the
        first seen frames, unwrapped, fitted by a quadratic in time.

        Parameters
        ----------
        positions : ndarray, shape (T, K, 2) or (T, 2)
            Observed bob positions in metres, NaN where unseen (noise of about 1 cm).
        dt : float

        Returns
        -------
        state0 : ndarray, shape (2,)
            ``[theta0, omega0]``: the fit and its slope at frame 0, inside :attr:`state_bounds`.
        scale : ndarray, shape (2,)
            Half-widths (:data:`_THETA_HALF` rad, :data:`_OMEGA_HALF` rad/s) that held the truth
            in every one of 2000 prior trajectories with 1 cm noise; wider when fewer than four
            of the first frames are seen.
        """
        pos = as_float_array(positions, "positions", ndim=(2, 3), allow_nan=True)
        if pos.ndim == 2:
            pos = pos[:, None, :]
        if pos.shape[1:] != (self.n_points, 2):
            raise ValueError(
                f"positions: expected (T, {self.n_points}, 2) for the {self.name} system, got "
                f"shape {pos.shape}"
            )
        _, dt = self._check_frames_dt(1, dt)
        ok = np.isfinite(pos[:, 0]).all(axis=1)
        seen = np.flatnonzero(ok)
        if seen.size == 0:
            raise ValueError(f"positions: expected at least one seen frame, got {ok.size} NaN")
        idx = seen[:_FIT_FRAMES]
        ang = np.unwrap(np.arctan2(pos[idx, 0, 0], -pos[idx, 0, 1]))
        deg = min(2, idx.size - 1)
        if deg == 0:
            th0, om0 = float(ang[0]), 0.0
        else:
            coef = np.polynomial.polynomial.polyfit(idx * dt, ang, deg)
            th0, om0 = float(coef[0]), float(coef[1])
        lo = np.array([self.state_bounds[q][0] for q in self.state])
        hi = np.array([self.state_bounds[q][1] for q in self.state])
        est = np.clip(np.array([th0, om0]), lo, hi)
        scale = np.array([_THETA_HALF, _OMEGA_HALF])
        if idx.size < 4 or idx[-1] > 2 * _FIT_FRAMES:  # few or late frames: a wider box
            scale = np.array([0.5, 4.0])
        return est, scale
