"""A block on a Duffing spring: the suite's system that is linear to first order.

Physics (``design.md``, section "Systems", fixed)
--------------------------------------------------
A block slides on a horizontal, frictionless track, tied to a wall at ``x = 0`` by a spring with
a cubic (Duffing) term and slowed by viscous damping. State ``[x, v]`` (m, m/s) of the block's
centre; with the spring's stretch ``s = x - L0``::

    x'' = -w2 s - k3 s^3 - c v

Parameters, in this order (:attr:`Spring.params`):

======  ==========================================  ============
name    meaning                                     prior range
======  ==========================================  ============
``w2``  linear stiffness over mass k/m, 1/s^2       [4, 25]
``k3``  cubic stiffness over mass, 1/(m^2 s^2)      [0, 20]
``c``   viscous damping, 1/s                        [0, 0.6]
``L0``  rest position of the block's centre, m      [1, 2]
======  ==========================================  ============

There are no events. The tracked point is ``(x, 0)`` (K = 1). Initial states: ``x0 = L0 + s0``
with ``|s0|`` in [0.2, 0.6] and a random sign, ``v0`` in [-0.5, 0.5].

Why this system is in the suite
-------------------------------
The cubic term is mostly a correction: its force relative to the linear one at the initial
stretch, ``k3 s0^2 / w2``, has a median of 0.10 over the prior and its 90% quantile is 0.35
(the extreme corner, ``20 x 0.36 / 4``, reaches 1.8), and damping only shrinks it. So the motion
is close to a damped linear oscillator about ``L0``: a sum of two decaying complex exponentials
plus a constant. That is exactly the model class of dynamic mode decomposition (DMD, linear in the
delay-embedded state) and a polynomial library of SINDy holds the true right-hand side
(``1, x, v, x^2, x^3`` span ``-w2 s - k3 s^3 - c v``) -- the methods that lose on the ball's
bounces should be at home here, and the report shows whether they are. ``k3`` is identifiable
only through how the motion changes with amplitude (frequency, harmonics), and weakly when the
stretch is small;
``L0`` is the centre of the oscillation, well determined by any method.

Numerics
--------
Classical RK4 with :data:`SUBSTEPS` steps per frame interval, compiled by numba: frames outer,
then the steps, then 256 trajectories at a time in a branch-free innermost loop that the compiler
vectorises (one trajectory's steps in a row are a latency-bound chain of dependent
multiplications: this order made the kernel ~4x faster, bitwise the same); a batch of
``_base.PARALLEL_MIN`` or more runs its chunks over numba's threads (bitwise the same).
``SUBSTEPS = 10`` was measured: at the
prior's stiffest corner (``w2 = 25``, ``k3 = 20``, ``c = 0``, ``|s0| = 0.6``, ``|v0| = 0.5``) the
largest position error over 200 frames at ``dt = 0.05`` against ``solve_ivp`` (DOP853, tolerances
1e-13) is 5.7e-7 m with 8 steps and 2.3e-7 m with 10 (RK4's error falls as ``h^4``), so 10 keeps
a 4x margin under the design's 1e-6 m. :mod:`sysid_bench.core.systems.spring_jax` is the JAX twin
(same steps, same operations).

Validity. ``simulate`` raises ``ValueError`` (naming the arguments) when the RK4 step is too
coarse for a trajectory's stiffness or damping: ``h * max(w_eff, c) > STEP_MAX`` with
``w_eff^2 = w2 + 3 k3 A^2`` at the amplitude ``A`` the initial energy allows (the largest of
``w2``, ``k3``, ``c`` over the frames for time-varying parameters). Anywhere in the envelope and
the state bounds this holds at ``dt <= 0.06``, so it only refuses coarse frame intervals. The
model has no wall contact (the design: no events): a start far from ``L0`` that would carry the
block past ``x = 0`` (never from :meth:`Spring.sample_state0` with the trajectory's ``theta``:
``L0 - |s| >= 0.35 m``) is simulated as the equation says, so that a fitting method proposing
such a ``theta`` gets a trajectory, not an error.

View
----
The track from the wall to 3 m, seen side on: extent ``(-0.2, 3.0, -0.4, 0.4)`` m on a 16 x 64
frame (20 px/m both ways). The block is a bright disc of radius :data:`BLOCK_RADIUS` (3 px); the
wall (a vertical line at ``x = 0``) and the spring (a thin line from the wall to the block) are
drawn at :data:`DIM_LEVEL` of white, below the tracker's threshold, so the tracker finds the block
and never the spring.
"""

from __future__ import annotations

import numba
import numpy as np

from sysid_bench.core._validate import as_float_array, check_positive_int, check_seed
from sysid_bench.core.systems import _draw
from sysid_bench.core.systems._base import System, use_parallel
from sysid_bench.core.systems._scene import SpringScene

__all__ = ["Spring", "SUBSTEPS", "STEP_MAX", "BLOCK_RADIUS", "DIM_LEVEL", "S0_RANGE", "V0_RANGE"]

#: RK4 steps per frame interval (see the module docstring for the measurement).
SUBSTEPS = 10
#: Largest ``h * max(w_eff, c)`` accepted (RK4 is stable up to ~2.8 on the imaginary axis; 0.5
#: keeps a margin and an error per step under ~1e-4 of the amplitude). The prior at dt = 0.05 is
#: at 0.034.
STEP_MAX = 0.5
#: Block (disc) radius in metres; 3 px at the default 20 px/m.
BLOCK_RADIUS = 0.15
#: Grey level of the wall and the spring, as a fraction of white (below the tracker's threshold).
DIM_LEVEL = 0.25
#: Initial stretch magnitude and velocity ranges (design).
S0_RANGE = (0.2, 0.6)
V0_RANGE = (-0.5, 0.5)

#: Tracker: pixels dimmer than this fraction of white are ignored (above DIM_LEVEL plus noise).
_THRESHOLD = 0.5
#: Tracker: fraction of a whole disc's area the bright mass near the block must reach to count.
_MIN_MASS = 0.5
#: Tracker: bright mass allowed away from the block (in disc areas); more means the frame holds
#: something else (all white, pure noise) and the block is not reliably found.
_MAX_STRAY = 0.5

# state0_from_track: seen frames fitted, the frequency grid (rad/s), and the half-widths of the
# box around the estimate (the largest errors on 4000 prior trajectories with 1 cm noise were
# 0.031 m and 0.48 m/s)
_FIT_FRAMES = 14
_OMEGAS = np.linspace(1.0, 12.0, 221)
_X_HALF = 0.06
_V_HALF = 0.8

_njit = numba.njit(cache=True, nogil=True, error_model="numpy")


@_njit
def _acc(x, v, w2, k3, c, L0):
    s = x - L0
    return -w2 * s - k3 * (s * s * s) - c * v


@_njit
def _rk4(x, v, w2, k3, c, L0, h, h2, h6):
    """One classical RK4 step of length ``h`` (``h2 = h / 2``, ``h6 = h / 6``) from (x, v)."""
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


@_njit
def _chunk(th, s0, dt, out, b0, b1):
    """Fill ``out[:, :, b0:b1]`` (n_frames, 2, B) from ``s0`` (2, B); ``th`` is
    (1 or n_frames, 4, B).

    Frames outer, then the ``SUBSTEPS`` RK4 steps, then the trajectories: the innermost loop is
    over independent trajectories with no branches, so the compiler vectorises it and no
    trajectory waits on its own previous step (one trajectory's steps in a row are a chain of
    dependent multiplications, latency-bound).
    """
    varying = th.shape[0] > 1
    h = dt / SUBSTEPS
    h2 = 0.5 * h
    h6 = h / 6.0
    x = s0[0, b0:b1].copy()
    v = s0[1, b0:b1].copy()
    out[0, 0, b0:b1] = x
    out[0, 1, b0:b1] = v
    for t in range(out.shape[0] - 1):
        i = t if varying else 0
        w2, k3, c, L0 = th[i, 0, b0:b1], th[i, 1, b0:b1], th[i, 2, b0:b1], th[i, 3, b0:b1]
        for _ in range(SUBSTEPS):
            for j in range(b1 - b0):
                x[j], v[j] = _rk4(x[j], v[j], w2[j], k3[j], c[j], L0[j], h, h2, h6)
        out[t + 1, 0, b0:b1] = x
        out[t + 1, 1, b0:b1] = v


#: Trajectories per inner loop: its states and parameters (6 x 8 bytes each) stay in L1 cache.
_LANES = 256


@_njit
def _kernel(th, s0, dt, out):
    """Fill ``out`` (n_frames, 2, B) from ``s0`` (2, B), ``_LANES`` trajectories at a time."""
    B = s0.shape[1]
    for b0 in range(0, B, _LANES):
        _chunk(th, s0, dt, out, b0, min(B, b0 + _LANES))


@numba.njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _kernel_parallel(th, s0, dt, out):
    """:func:`_kernel` with the chunks of trajectories spread over numba's threads (each
    trajectory's arithmetic is the same: the output is bitwise the serial kernel's)."""
    B = s0.shape[1]
    for c in numba.prange((B + _LANES - 1) // _LANES):
        b0 = c * _LANES
        _chunk(th, s0, dt, out, b0, min(B, b0 + _LANES))


@_njit
def _is_constant(th):
    """Whether every row ``th[b, t]`` of (B, T, P) equals ``th[b, 0]`` (stops at the first
    difference; NumPy's ``(th == th[:, :1]).all()`` builds the whole comparison first)."""
    for b in range(th.shape[0]):
        for t in range(1, th.shape[1]):
            for p in range(th.shape[2]):
                if th[b, t, p] != th[b, 0, p]:
                    return False
    return True


#: Trajectories per kernel call: bounds the (n_frames, 2, chunk) scratch copy.
_CHUNK = 8192


def _amplitude(w2, k3, L0, x, v):
    """Largest ``|s|`` the energy ``v^2/2 + w2 s^2/2 + k3 s^4/4`` of the state allows (damping
    only lowers the energy); ``inf`` for a free block (``w2 = k3 = 0``)."""
    s = x - L0
    e = 0.5 * v * v + 0.5 * w2 * s * s + 0.25 * k3 * s**4
    # root u = A^2 of k3/4 u^2 + w2/2 u - e = 0, in the cancellation-free form
    den = 0.5 * w2 + np.sqrt(0.25 * w2 * w2 + k3 * e)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(den > 0, 2.0 * e / np.where(den > 0, den, 1.0), np.where(e > 0, np.inf, 0.0))
    return np.sqrt(u)


class Spring(System):
    """Block on a Duffing spring: parameters w2, k3, c, L0; state [x, v]; K = 1.

    See the module docstring for the physics, the numerics and the view. ``sample_state0``
    takes the trajectories' parameters (``theta=``), since the initial position is drawn about
    each trajectory's own rest position ``L0``.
    """

    name = "spring"
    params = ("w2", "k3", "c", "L0")
    prior = {"w2": (4.0, 25.0), "k3": (0.0, 20.0), "c": (0.0, 0.6), "L0": (1.0, 2.0)}
    #: experiment 4's simplified physics: the cubic term and damping held in training
    simplified_params = ("k3", "c")
    #: Beyond the prior, still physical and resolved by the integrator at dt = 0.05 (see
    #: STEP_MAX, checked per trajectory): stiffness to 100 (10 rad/s), cubic stiffness to 100,
    #: damping to 5 /s (overdamped for w2 < 6.25), rest positions across the whole view.
    envelope = {"w2": (0.0, 100.0), "k3": (0.0, 100.0), "c": (0.0, 5.0), "L0": (0.5, 2.5)}
    state = ("x", "v")
    state_bounds = {"x": (0.0, 5.0), "v": (-10.0, 10.0)}
    n_points = 1
    extent = (-0.2, 3.0, -0.4, 0.4)
    size = (16, 64)
    noise_m = 0.01
    jax_twin = "sysid_bench.core.systems.spring_jax:simulate"
    scene_type = SpringScene
    _theta_row_ok = True  # the kernel reads row 0 for every frame of a (B, 1, P) theta
    #: the smallest frames with room for the block (3 px at the default 16 x 64)
    min_size = (4, 16)

    def state_bounds_for(self, scene):
        ax = scene.anchor[0]
        if ax == 0.0:
            return self.state_bounds
        lo, hi = self.state_bounds["x"]
        return dict(self.state_bounds, x=(lo + ax, hi + ax))

    # ------------------------------------------------------------------------------------------
    # simulation
    def _simulate(self, theta, state0, n_frames, dt, scene=None):
        ax = 0.0 if scene is None else scene.anchor[0]
        if ax != 0.0:  # the kernel measures x from the anchor; the default skips the shift
            state0 = state0.copy()
            state0[:, 0] -= ax
            out = self._simulate(theta, state0, n_frames, dt)
            out[..., 0] += ax
            return out
        if _is_constant(theta):  # (B, T, P) held constant: one row (the checks cost less too)
            theta = theta[:, :1]
        self._check_step(theta, state0, dt)
        B = state0.shape[0]
        out = np.empty((B, n_frames, 2))
        for b0 in range(0, B, _CHUNK):
            b1 = min(B, b0 + _CHUNK)
            part = theta[b0:b1]
            scratch = np.empty((n_frames, 2, b1 - b0))
            kernel = _kernel_parallel if use_parallel(b1 - b0) else _kernel
            kernel(np.ascontiguousarray(part.transpose(1, 2, 0)),
                    np.ascontiguousarray(state0[b0:b1].T), dt, scratch)
            out[b0:b1] = scratch.transpose(2, 0, 1)
        return out

    def _check_step(self, theta, state0, dt) -> None:
        """Raise unless every trajectory's RK4 step resolves its stiffness and damping."""
        if not len(state0):
            return
        hi = theta.max(axis=1)  # (B, P): the stiffest parameters a trajectory meets
        w2, k3, c = hi[:, 0], hi[:, 1], hi[:, 2]
        amp = _amplitude(w2, k3, theta[:, 0, 3], state0[:, 0], state0[:, 1])
        with np.errstate(invalid="ignore"):
            w_eff2 = w2 + np.where(k3 > 0, 3.0 * k3 * amp * amp, 0.0)
        step = (dt / SUBSTEPS) * np.maximum(np.sqrt(w_eff2), c)
        worst = int(np.argmax(step))
        if not step[worst] <= STEP_MAX:
            raise ValueError(
                f"theta, state0, dt: the {self.name} system's RK4 step h = dt / {SUBSTEPS} must "
                f"resolve the stiffness and damping, h * max(sqrt(w2 + 3 k3 A^2), c) <= "
                f"{STEP_MAX:g}; trajectory {worst} (w2 = {w2[worst]:g}, k3 = {k3[worst]:g}, "
                f"c = {c[worst]:g}, amplitude A = {amp[worst]:g} m, dt = {dt:g}) gives "
                f"{step[worst]:.3g}. Use a smaller dt or stretch"
            )

    def reference(self, theta, state0, n_frames=200, dt=0.05):
        """``solve_ivp`` (DOP853, rtol = atol = 1e-12) of one trajectory at the frame times.

        Parameters
        ----------
        theta : ndarray, shape (P,)
        state0 : ndarray, shape (S,)
        n_frames : int
        dt : float

        Returns
        -------
        ndarray, shape (n_frames, S)
        """
        from scipy.integrate import solve_ivp

        n_frames, dt = self._check_frames_dt(n_frames, dt)
        th = self.check_theta(np.asarray(theta, dtype=np.float64).reshape(1, -1))[0]
        s0 = self.check_state0(np.asarray(state0, dtype=np.float64).reshape(1, -1))[0]
        w2, k3, c, L0 = (float(a) for a in th)

        def rhs(_t, y):
            s = y[0] - L0
            return [y[1], -w2 * s - k3 * s**3 - c * y[1]]

        t = np.arange(n_frames) * dt
        sol = solve_ivp(rhs, (0.0, t[-1]), s0, method="DOP853", t_eval=t, rtol=1e-12,
                        atol=1e-12)
        if not sol.success:
            raise RuntimeError(f"{self.name} reference: solve_ivp failed: {sol.message}")
        out = sol.y.T.copy()
        out[0] = s0
        return out

    # ------------------------------------------------------------------------------------------
    # initial states
    def sample_state0(self, n, rng=None, theta=None):
        """Initial states from the design's ranges.

        Parameters
        ----------
        n : int
        rng : int, None or numpy.random.Generator
        theta : ndarray, shape (n, P), optional
            The trajectories' parameters: ``x0 = L0 + s0`` uses each one's own ``L0``. Without
            it, ``L0`` is drawn from the prior (after the states' own draws, so the states'
            stretches and velocities are the same either way); pass ``theta`` whenever the
            states are simulated with known parameters, or the stretch is not the design's.

        Returns
        -------
        ndarray, shape (n, 2)
            ``[x0, v0]``: ``|x0 - L0|`` in [0.2, 0.6] with a random sign, ``v0`` in [-0.5, 0.5].
        """
        n = check_positive_int(n, "n")
        rng = check_seed(rng)
        if theta is not None:
            th = self.check_theta(theta)
            if th.ndim != 2 or th.shape[0] != n:
                raise ValueError(
                    f"theta: expected shape ({n}, {self.n_params}) for the {self.name} system's "
                    f"{n} initial states, got {th.shape}"
                )
        mag = S0_RANGE[0] + rng.random(n) * (S0_RANGE[1] - S0_RANGE[0])
        s0 = mag * rng.choice([-1.0, 1.0], size=n)
        v0 = V0_RANGE[0] + rng.random(n) * (V0_RANGE[1] - V0_RANGE[0])
        if theta is None:
            lo, hi = self.prior["L0"]
            L0 = lo + rng.random(n) * (hi - lo)
        else:
            L0 = th[:, 3]
        return np.stack([L0 + s0, v0], axis=1)

    def state0_from_track(self, positions, dt=0.05):
        """A rough initial state from a noisy track: a sinusoid fitted to the first seen frames.

        The first :data:`_FIT_FRAMES` seen frames (0.7 s at dt = 0.05, most of a period) are
        fitted by least squares with ``a + b cos(w t) + d sin(w t)`` for each ``w`` of a grid
        (1 to 12 rad/s: the prior's ``sqrt(w2)`` and the cubic term's stiffening, with room),
        keeping the best: the linear oscillator the system is to first order, damping ignored.
        ``x0 = a + b``, ``v0 = d w``. Over 2000 prior trajectories with 1 cm noise this gave
        RMS errors of 8 mm and 0.12 m/s, against 9 mm and 0.20 m/s for the best polynomial.

        Parameters
        ----------
        positions : ndarray, shape (T, K, 2) or (T, 2)
            Observed block positions in metres, NaN where unseen (noise of about 1 cm).
        dt : float

        Returns
        -------
        state0 : ndarray, shape (2,)
            ``[x0, v0]``, inside :attr:`state_bounds`.
        scale : ndarray, shape (2,)
            Half-widths of a box around it that holds the true state: ``(0.06 m, 0.8 m/s)``
            when the fit had at least 8 seen frames among the first ``2 * _FIT_FRAMES`` (the
            largest errors on 4000 prior trajectories with 1 cm noise were 0.031 m and
            0.48 m/s); otherwise the first seen position at rest and the wide box
            ``(0.6 m, 3 m/s)``.
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
        x = pos[:, 0, 0]
        seen = np.flatnonzero(np.isfinite(x))
        if seen.size == 0:
            raise ValueError(f"positions: expected at least one seen frame, got {x.size} NaN")
        idx = seen[:_FIT_FRAMES]
        idx = idx[idx < 2 * _FIT_FRAMES]
        lo = np.array([self.state_bounds[q][0] for q in self.state])
        hi = np.array([self.state_bounds[q][1] for q in self.state])
        if idx.size >= 8:
            t = idx * dt
            w = _OMEGAS[:, None]
            basis = np.stack([np.ones_like(w * t), np.cos(w * t), np.sin(w * t)], axis=-1)
            coef = np.linalg.pinv(basis) @ x[idx]  # (n_omega, 3)
            res = ((basis @ coef[..., None])[..., 0] - x[idx]) ** 2
            k = int(np.argmin(res.sum(axis=1)))
            est = np.array([coef[k, 0] + coef[k, 1], coef[k, 2] * _OMEGAS[k]])
            scale = np.array([_X_HALF, _V_HALF])
        else:
            # too little at the start: the first seen position, at rest, and a wide box
            est = np.array([x[seen[0]], 0.0])
            scale = np.array([0.6, 3.0])
        return np.clip(est, lo, hi), scale

    # ------------------------------------------------------------------------------------------
    # camera
    def _observe(self, states, theta, scene=None):
        out = np.zeros(states.shape[:2] + (1, 2))
        out[..., 0, 0] = states[..., 0]
        if scene is not None and scene.anchor[1] != 0.0:  # the block runs level with its anchor
            out[..., 0, 1] = scene.anchor[1]
        return out

    def _render(self, points, states, theta, size, **nuisance):
        opts = _draw.check_nuisance(nuisance)
        view = _draw.View(self.extent, size)
        sx, sy = view.px_per_m
        r_px = BLOCK_RADIUS * min(sx, sy)
        sub = _draw.blur_positions(points, opts["dt"], opts["blur"])  # (B, T, S, 1, 2)
        b, t, s = sub.shape[:3]
        # the wall: the same vertical line in every frame
        x0, x1, y0, y1 = self.extent
        wall_a = view.to_pixels(np.array([[[0.0, y0]]]))
        wall_b = view.to_pixels(np.array([[[0.0, y1]]]))
        wall = _draw.draw_segments(wall_a, wall_b, 1.0, size)[0]
        img = np.empty((b, t) + tuple(size), dtype=np.float32)
        for i in range(b):
            centres = view.to_pixels(sub[i, :, :, 0])  # (T, S, 2)
            block = _draw.draw_discs(centres, r_px, size)
            # the spring: from the wall to the block's near edge, along the track
            end = sub[i, :, :, 0].copy()
            end[..., 0] = np.maximum(end[..., 0] - BLOCK_RADIUS, 0.0)
            start = np.zeros_like(end)
            start[..., 1] = end[..., 1]
            spring = _draw.draw_segments(view.to_pixels(start), view.to_pixels(end), 1.0, size)
            dim = np.float32(DIM_LEVEL) * np.maximum(spring, wall[None])
            img[i] = np.maximum(block, dim)
        return _draw.finish(img * np.float32(255.0), occlusion=opts["occlusion"],
                            drop=opts["drop"], noise=opts["noise"], seed=opts["seed"])

    def _track(self, frames):
        t, h, w = frames.shape
        view = _draw.View(self.extent, (h, w))
        sx, sy = view.px_per_m
        r_px = BLOCK_RADIUS * min(sx, sy)
        disc = np.pi * r_px * r_px
        img = frames.astype(np.float32) / np.float32(255.0)
        wgt = np.where(img >= _THRESHOLD, img, np.float32(0.0))
        jc = np.arange(w, dtype=np.float32) + np.float32(0.5)
        ic = np.arange(h, dtype=np.float32) + np.float32(0.5)

        def centroid(wt):
            colsum, rowsum = wt.sum(axis=1), wt.sum(axis=2)
            mass = colsum.sum(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                return colsum @ jc / mass, rowsum @ ic / mass, mass

        c, r, total = centroid(wgt)
        # refine on the pixels within two radii of the first estimate; what lies beyond is stray
        near = ((jc[None, None, :] - c[:, None, None]) ** 2
                + (ic[None, :, None] - r[:, None, None]) ** 2) <= np.float32(2.0 * r_px) ** 2
        c, r, mass = centroid(np.where(near, wgt, np.float32(0.0)))
        seen = (mass >= _MIN_MASS * disc) & (total - mass <= _MAX_STRAY * disc)
        xy = view.to_metres(np.stack([c, r], axis=-1).astype(np.float64))
        xy[~seen] = np.nan
        return xy[:, None, :]
