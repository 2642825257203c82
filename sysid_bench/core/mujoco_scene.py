"""Bouncing-ball videos from an independent physics engine (MuJoCo), in the suite's framing.

The scene is built in code (:func:`scene_xml`): MuJoCo's z is the suite's y. The ball is a body
on two slide joints (x and z) and a hinge about y, so it can spin; a floor plane at ``z = -R``
and two wall planes at ``x = -R`` and ``x = 10 + R``, so the ball's *centre* moves in the
suite's box ``[0, 10] x [0, 10]``. The ball's radius ``R`` is the renderer's (30/256 of the view,
1.53 m in the 10 m box) so MuJoCo's picture matches the suite's.

How the suite's parameters map onto the engine, and what the engine then does
---------------------------------------------------------------------------------
``g``   the model's gravity: exact.
``e``   soft contacts (explicit ``<pair>`` contacts, ``solref = (-stiffness, -damping)``): each
        ball type has its own contact duration (how soft it is: 6-20 ms, a finite contact time)
        which sets the stiffness; the damping is found by bisection so that a drop test at
        10 m/s bounces back with the target ``e``. In a video the restitution varies with the impact speed (the contact is not
        a linear spring); the measured ``e`` is the mean of ``-vz_out / vz_in`` over the
        video's bounces faster than 1 m/s.
``d``   MuJoCo's ellipsoid fluid model (``fluidshape="ellipsoid"``): blunt drag on a sphere,
        ``C rho pi R^2 |v| v`` with C = 0.5 (the factor measured in flight), so the medium's
        density is set to give ``d = C rho pi R^2 / m``. The same model adds angular drag on the spin and a
        Magnus lift (coefficient 0.375: the lift/drag ratio ~ 2 R w / v of real balls; MuJoCo's
        default of 1.0 makes a spinning 1.5 m ball curve more than gravity pulls). Measured
        ``d``: least squares of the engine's own accelerations in free flight (contacts excluded)
        against ``-d |v| v``.
``r``   rolling friction of the floor contact (``condim=6``): a torque ``mu_r N`` resisting
        rolling decelerates a ball rolling without slip by ``mu_r |g| / (R (1 + k))``, k = I/(mR^2)
        (2/5 solid, 2/3 hollow); one roll test at 1 m/s then scales ``mu_r`` so the engine's
        deceleration is ``r`` (the soft contact adds to the torque). Sliding friction spins the ball up at each bounce (it leaves
        with spin, and a slow ball slides, then rolls). Measured ``r``: median deceleration over
        the steps of floor contacts lasting more than 0.25 s once slipping has stopped; NaN when
        the ball never rolls.

Walls: the same soft contact, nearly undamped (measured: ``e_wall``), with sliding friction.

Rendering: MuJoCo's own renderer, offscreen (``MUJOCO_GL=egl`` or ``osmesa``), through an
orthographic camera framed as :mod:`sysid_bench.core.render` frames its videos. Where that renderer
is unavailable (no OpenGL library: a fresh CI machine has pip packages only), the engine's
trajectories are drawn by :func:`sysid_bench.core.render.render` instead and every output says so
(``renderer`` in the metadata): the physics stays MuJoCo's.

``python -m sysid_bench.mujoco_scene --out DIR`` writes the default set and times it.
"""

from __future__ import annotations

import ctypes.util
import json
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sysid_bench.core._io import atomic_write
from sysid_bench.core.physics import BOX_WIDTH, PRIOR, sample_state0
from sysid_bench.core.render import RADIUS_FRACTION

__all__ = ["BallType", "BALL_TYPES", "mujoco_available", "scene_xml", "simulate_ball",
           "measure", "render_frames", "renderer_status", "draw_target", "make_video", "generate_set",
           "Episode", "RADIUS"]

#: the renderer's ball radius in metres for a square view: 30 px of 256, whose box is 196 px
RADIUS = RADIUS_FRACTION * 256 / ((256 - 2 * 30) / BOX_WIDTH)
#: engine step (s): 50 steps per frame, at most half the stiffest contact's time constant
TIMESTEP = 0.001
#: Magnus coefficient of the fluid model (see the module docstring)
MAGNUS = 0.375
#: blunt-drag coefficient of MuJoCo's ellipsoid model (its default)
BLUNT = 0.5
#: bump when what a cached episode holds changes
CACHE_VERSION = 2  # 2: H.264 written without mbtree (video.write_video)


@dataclass(frozen=True)
class BallType:
    """A kind of ball: how soft, how rough, how draggy.

    Attributes
    ----------
    name : str
    e, d, r : (float, float)
        Ranges the targets are drawn from (the suite's units).
    contact_s : float
        Duration of a bounce, s (softer = longer contact).
    friction : float
        Sliding friction coefficient (spin-up at bounces).
    hollow : bool
        Moment of inertia of a shell (2/3 m R^2) instead of a solid ball (2/5 m R^2).
    """

    name: str
    e: tuple
    d: tuple
    r: tuple
    contact_s: float
    friction: float
    hollow: bool

    @property
    def kappa(self) -> float:
        return 2 / 3 if self.hollow else 2 / 5


BALL_TYPES = {
    b.name: b
    for b in (
        BallType("rubber", e=(0.75, 0.9), d=(0.001, 0.01), r=(0.1, 0.4), contact_s=0.010,
                 friction=1.0, hollow=False),
        BallType("tennis", e=(0.65, 0.8), d=(0.01, 0.03), r=(0.2, 0.6), contact_s=0.020,
                 friction=0.7, hollow=True),
        BallType("pingpong", e=(0.85, 0.95), d=(0.03, 0.05), r=(0.05, 0.3), contact_s=0.006,
                 friction=0.3, hollow=True),
    )
}


def mujoco_available() -> str | None:
    """None when ``import mujoco`` works, else the reason it does not."""
    _choose_gl()
    try:
        import mujoco  # noqa: F401
    except Exception as exc:  # ImportError, or a broken GL setup at import
        return f"MuJoCo is not installed or does not import ({type(exc).__name__}: {exc}); " \
               "pip install -e .[mujoco]"
    return None


def _choose_gl() -> None:
    """Pick an offscreen GL backend before mujoco is imported (it reads MUJOCO_GL then)."""
    if "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "osmesa" if ctypes.util.find_library("OSMesa") else "egl"
    if os.environ["MUJOCO_GL"] == "osmesa":
        os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


_choose_gl()  # at import: before anything here imports mujoco


def _spring(contact_s: float, e: float) -> tuple[float, float]:
    """Stiffness and damping (per unit mass) of a linear contact lasting ``contact_s`` with
    restitution ``e`` (a damped half-oscillation): MuJoCo's ``solref = (-k, -b)``."""
    zeta = -math.log(e) / math.sqrt(math.pi**2 + math.log(e) ** 2)
    omega = math.pi / (contact_s * math.sqrt(1 - zeta**2))
    return omega**2, 2 * zeta * omega


def scene_xml(ball: BallType, g: float, d: float, r: float, damping: float,
              wall_e: float = 0.95, mass: float = 1.0) -> str:
    """The MJCF of the scene (see the module docstring for the mapping)."""
    R = RADIUS
    inertia = ball.kappa * mass * R * R
    area = math.pi * R * R
    density = d * mass / (BLUNT * area)  # d = rho * C * A / m (as measured in flight)
    mu_r = r * R * (1 + ball.kappa) / abs(g)
    view = BOX_WIDTH + 2 * R
    k, _ = _spring(ball.contact_s, 0.8)
    kw, bw = _spring(ball.contact_s, wall_e)
    return f"""
<mujoco model="ball_{ball.name}">
  <option timestep="{TIMESTEP}" gravity="0 0 {g}" density="{density:.9g}" viscosity="0"
          integrator="implicitfast" cone="elliptic"/>
  <visual><global offwidth="640" offheight="640"/><headlight ambient="0.45 0.45 0.45"
          diffuse="0.6 0.6 0.6" specular="0 0 0"/><quality shadowsize="0"/></visual>
  <worldbody>
    <camera name="side" mode="fixed" pos="{BOX_WIDTH / 2} -40 {BOX_WIDTH / 2}"
            xyaxes="1 0 0 0 0 1" projection="orthographic" fovy="{view:.9g}"/>
    <geom name="floor" type="plane" pos="0 0 {-R:.9g}" size="40 40 1" rgba="0.25 0.25 0.25 1"
          contype="0" conaffinity="0"/>
    <geom name="wall_l" type="plane" pos="{-R:.9g} 0 0" zaxis="1 0 0" size="40 40 1"
          rgba="0 0 0 0" contype="0" conaffinity="0"/>
    <geom name="wall_r" type="plane" pos="{BOX_WIDTH + R:.9g} 0 0" zaxis="-1 0 0"
          size="40 40 1" rgba="0 0 0 0" contype="0" conaffinity="0"/>
    <body name="ball">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="z" type="slide" axis="0 0 1"/>
      <joint name="spin" type="hinge" axis="0 1 0"/>
      <inertial pos="0 0 0" mass="{mass}" diaginertia="{inertia:.9g} {inertia:.9g} {inertia:.9g}"/>
      <geom name="ball" type="sphere" size="{R:.9g}" rgba="0.95 0.95 0.95 1" contype="0"
            conaffinity="0" fluidshape="ellipsoid" fluidcoef="{BLUNT} 0.25 1.5 1.0 {MAGNUS}"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="ball" geom2="floor" condim="6" friction="{ball.friction} {ball.friction} 0.001 {mu_r:.9g} {mu_r:.9g}"
          solref="{-k:.9g} {-damping:.9g}" solimp="0.99 0.99 0.001 0.5 2"/>
    <pair geom1="ball" geom2="wall_l" condim="3" friction="{ball.friction} {ball.friction} 0.001 0 0"
          solref="{-kw:.9g} {-bw:.9g}" solimp="0.99 0.99 0.001 0.5 2"/>
    <pair geom1="ball" geom2="wall_r" condim="3" friction="{ball.friction} {ball.friction} 0.001 0 0"
          solref="{-kw:.9g} {-bw:.9g}" solimp="0.99 0.99 0.001 0.5 2"/>
  </contact>
</mujoco>
"""


def _drop_restitution(model, data, damping: float, v_in: float = 10.0) -> float:
    """Restitution of one floor bounce at ``v_in`` m/s with the floor pair's damping."""
    import mujoco

    model.pair_solref[0, 1] = -damping
    mujoco.mj_resetData(model, data)
    data.qpos[:] = (5.0, 0.01, 0.0)
    data.qvel[:] = (0.0, -v_in, 0.0)
    touched = False
    for _ in range(2000):
        mujoco.mj_step(model, data)
        if data.qpos[1] < 0:
            touched = True
        elif touched:
            return float(data.qvel[1] / v_in)
    return 0.0


def _calibrate_rolling(model, data, r: float, d: float) -> float:
    """Scale the floor pair's rolling friction so a ball rolling at 1 m/s decelerates by ``r``.

    The torque ``mu_r N`` of the formula in the module docstring is not all the engine does
    (the soft contact's compliance also enters), so one roll test corrects it; drag at 1 m/s
    (``d``) is taken off. Returns the factor applied.
    """
    import mujoco

    if r <= 0:
        return 1.0
    mujoco.mj_resetData(model, data)
    data.qpos[:] = (3.0, 0.0, 0.0)
    data.qvel[:] = (1.0, 0.0, 1.0 / RADIUS)
    n = int(0.3 / TIMESTEP)
    vx = np.empty(n)
    for k in range(n):
        mujoco.mj_step(model, data)
        vx[k] = data.qvel[0]
    half = n // 3
    decel = -np.polyfit(np.arange(n - half) * TIMESTEP, vx[half:], 1)[0] - d * np.mean(vx[half:]) ** 2
    factor = r / decel if decel > 1e-6 else 1.0
    model.pair_friction[0, 3:5] *= factor
    return float(factor)


def _calibrate_damping(model, data, e: float) -> float:
    """The floor contact's damping that bounces a 10 m/s drop back with ``e`` (bisection)."""
    k = -float(model.pair_solref[0, 0])
    lo, hi = 0.0, 2.0 * math.sqrt(k)  # undamped .. critically damped
    if _drop_restitution(model, data, lo) < e:  # as bouncy as this contact gets
        return lo
    for _ in range(25):
        mid = 0.5 * (lo + hi)
        if _drop_restitution(model, data, mid) > e:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@dataclass
class Episode:
    """One MuJoCo video's physics.

    Attributes
    ----------
    ball : str
    target : ndarray, shape (4,)
        ``(e, g, d, r)`` the engine was set up for.
    measured : ndarray, shape (4,)
        What the engine did (``r`` NaN when the ball never rolled).
    states : ndarray, shape (T, 4)
        ``[x, y, vx, vy]`` at the frames.
    spin : ndarray, shape (T,)
        Angular velocity about y, rad/s.
    info : dict
        Per-bounce restitutions, wall restitution, contact times, dampratio, engine settings.
    """

    ball: str
    target: np.ndarray
    measured: np.ndarray
    states: np.ndarray
    spin: np.ndarray
    info: dict


def simulate_ball(ball: str | BallType, target, state0, n_frames: int = 200,
                  dt: float = 0.05) -> Episode:
    """Run the scene for ``n_frames`` frames and measure what the engine did.

    Parameters
    ----------
    ball : str or BallType
        ``"rubber"``, ``"tennis"`` or ``"pingpong"``.
    target : array_like, shape (4,)
        ``(e, g, d, r)`` to map onto the engine.
    state0 : array_like, shape (4,)
        ``[x, y, vx, vy]`` of the ball's centre.

    Returns
    -------
    Episode
    """
    import mujoco

    bt = BALL_TYPES[ball] if isinstance(ball, str) else ball
    e, g, d, r = (float(v) for v in target)
    if not (g < 0 and 0 < e <= 1 and d >= 0 and r >= 0):
        raise ValueError(f"target: expected e in (0, 1], g < 0, d >= 0, r >= 0, got {target!r}")
    s0 = np.asarray(state0, dtype=np.float64)
    if s0.shape != (4,):
        raise ValueError(f"state0: expected shape (4,), got {s0.shape}")
    model = mujoco.MjModel.from_xml_string(scene_xml(bt, g, d, r, 0.0))
    data = mujoco.MjData(model)
    damping = _calibrate_damping(model, data, e)
    model.pair_solref[0, 1] = -damping
    roll_factor = _calibrate_rolling(model, data, r, d)
    mujoco.mj_resetData(model, data)
    data.qpos[:] = (s0[0], s0[1], 0.0)
    data.qvel[:] = (s0[2], s0[3], 0.0)
    sub = int(round(dt / TIMESTEP))
    n_steps = (n_frames - 1) * sub
    q = np.empty((n_steps + 1, 3))
    v = np.empty((n_steps + 1, 3))
    a = np.zeros((n_steps + 1, 3))
    q[0], v[0] = data.qpos, data.qvel
    for k in range(1, n_steps + 1):
        mujoco.mj_step(model, data)
        q[k], v[k], a[k] = data.qpos, data.qvel, data.qacc
    frames = np.arange(n_frames) * sub
    states = np.column_stack([q[frames, 0], q[frames, 1], v[frames, 0], v[frames, 1]])
    measured, info = measure(q, v, a, g, TIMESTEP)
    info.update({"damping": damping, "stiffness": -float(model.pair_solref[0, 0]),
                 "contact_s_design": bt.contact_s, "friction": bt.friction,
                 "rolling_friction": float(model.pair_friction[0, 3]), "roll_factor": roll_factor,
                 "fluid_density": d / (BLUNT * math.pi * RADIUS**2), "magnus": MAGNUS,
                 "radius_m": RADIUS, "timestep": TIMESTEP, "mujoco": mujoco.__version__})
    return Episode(bt.name, np.array([e, g, d, r]), measured, states, v[frames, 2], info)


def measure(q, v, a, g: float, step: float) -> tuple[np.ndarray, dict]:
    """What the engine did, from its step-by-step trajectory.

    Parameters
    ----------
    q, v, a : ndarray, shape (N, 3)
        Positions, velocities and accelerations of the joints ``(x, z, spin)`` at each step.
    g : float
        The model's gravity (exact).
    step : float
        Seconds per step.

    Returns
    -------
    measured : ndarray, shape (4,)
        ``(e, g, d, r)``; ``e`` / ``d`` / ``r`` NaN when there was no bounce / flight / roll.
    info : dict
    """
    # in contact: within 1 mm of touching (a rolling ball hovers at +-0.1 mm on the soft floor)
    floor = q[:, 1] < 1e-3
    wall = (q[:, 0] < 1e-3) | (q[:, 0] > BOX_WIDTH - 1e-3)
    # -- restitution: velocity one step before a floor contact starts and one after it ends
    e_b, v_in_b, t_c = [], [], []
    starts = np.flatnonzero(~floor[:-1] & floor[1:]) + 1
    for s in starts:
        ends = np.flatnonzero(~floor[s:])
        if not len(ends):
            break
        e_ = s + ends[0]
        vin, vout = v[s - 1, 1], v[e_, 1]
        if vin < -1.0:
            e_b.append(-vout / vin)
            v_in_b.append(-vin)
            t_c.append((e_ - s) * step)
    ew = []
    wstarts = np.flatnonzero(~wall[:-1] & wall[1:]) + 1
    for s in wstarts:
        ends = np.flatnonzero(~wall[s:])
        if len(ends) and abs(v[s - 1, 0]) > 0.5:
            ew.append(-v[s + ends[0], 0] / v[s - 1, 0])
    # -- drag: free flight at least 5 steps away from any contact
    contact = floor | wall
    near = np.convolve(contact.astype(float), np.ones(11), mode="same") > 0
    free = ~near
    vx, vz = v[:, 0], v[:, 1]
    speed = np.hypot(vx, vz)
    ax, az = a[:, 0], a[:, 1] - g
    num = -(ax * speed * vx + az * speed * vz)[free].sum()
    den = (speed**4)[free].sum()
    d_m = num / den if den > 0 else float("nan")
    # -- rolling: floor contacts lasting > 0.25 s, after slipping has stopped
    r_samples = []
    rolled_s = 0.0
    for s in np.flatnonzero(np.diff(np.r_[0, floor.astype(int)]) == 1):
        ends = np.flatnonzero(~floor[s:])
        e_ = s + ends[0] if len(ends) else len(floor)
        if (e_ - s) * step < 0.25:
            continue
        seg = np.arange(s, e_)
        slip = np.abs(vx[seg] - v[seg, 2] * RADIUS)  # contact point speed (hinge about +y)
        ok = (slip < 0.02) & (np.abs(vx[seg]) > 0.05) & ~wall[seg]
        if ok.sum() > 20:
            idx = seg[ok]
            r_samples.append(-ax[idx] * np.sign(vx[idx]))
            rolled_s += len(idx) * step
    r_m = float(np.median(np.concatenate(r_samples))) if r_samples else float("nan")
    info = {"bounces": len(e_b), "e_per_bounce": [float(x) for x in e_b],
            "impact_speed": [float(x) for x in v_in_b],
            "contact_s": float(np.mean(t_c)) if t_c else None,
            "e_wall": float(np.mean(ew)) if ew else None, "rolled_s": rolled_s,
            "flight_steps": int(free.sum())}
    e_m = float(np.mean(e_b)) if e_b else float("nan")
    return np.array([e_m, g, d_m, r_m]), info


# -- rendering ------------------------------------------------------------------------------------
_RENDER_STATE: dict = {}


def renderer_status() -> str | None:
    """None when MuJoCo's offscreen renderer works here, else why not (probed once)."""
    if "why" not in _RENDER_STATE:
        why = mujoco_available()
        if why is None:
            try:
                import mujoco

                m = mujoco.MjModel.from_xml_string(scene_xml(BALL_TYPES["rubber"], -9.8, 0.01,
                                                             0.1, 0.1))
                with mujoco.Renderer(m, 16, 16) as rd:
                    dd = mujoco.MjData(m)
                    mujoco.mj_forward(m, dd)
                    rd.update_scene(dd, camera="side")
                    rd.render()
            except Exception as exc:
                why = (f"MuJoCo's offscreen renderer is unavailable (MUJOCO_GL="
                       f"{os.environ.get('MUJOCO_GL')}: {type(exc).__name__}: {exc})"[:300])
        _RENDER_STATE["why"] = why
    return _RENDER_STATE["why"]


def render_frames(ep: Episode, size: int = 256) -> tuple[np.ndarray, str]:
    """Grey frames of an episode, (T, size, size) uint8, and the name of the renderer used.

    MuJoCo's renderer when it works here, else :func:`sysid_bench.core.render.render` of the engine's
    states (named ``"sysid_bench.core.render (fallback: ...)"``).
    """
    why = renderer_status()
    if why is None:
        import mujoco

        bt = BALL_TYPES[ep.ball]
        e, g, d, r = ep.target
        m = mujoco.MjModel.from_xml_string(scene_xml(bt, g, d, r, ep.info["damping"]))
        dd = mujoco.MjData(m)
        out = np.empty((len(ep.states), size, size), dtype=np.uint8)
        angle = np.concatenate([[0.0], np.cumsum(ep.spin[1:] * 0.05)])  # approx. for drawing
        with mujoco.Renderer(m, size, size) as rd:
            for t, s in enumerate(ep.states):
                dd.qpos[:] = (s[0], s[1], angle[t])
                mujoco.mj_kinematics(m, dd)
                mujoco.mj_camlight(m, dd)  # the camera pose is not part of kinematics
                rd.update_scene(dd, camera="side")
                rgb = rd.render()
                out[t] = np.clip(rgb @ np.array([0.299, 0.587, 0.114]), 0, 255).astype(np.uint8)
        return out, f"mujoco {mujoco.__version__} ({os.environ.get('MUJOCO_GL')})"
    from sysid_bench.core.render import render

    return render(ep.states[None], size=(size, size))[0], f"sysid_bench.core.render (fallback: {why})"


# -- cached sets --------------------------------------------------------------------------------
def draw_target(ball: str, rng: np.random.Generator) -> np.ndarray:
    """``(e, g, d, r)`` for a ball of type ``ball``: its ranges, g from the suite's prior."""
    bt = BALL_TYPES[ball]
    return np.array([rng.uniform(*bt.e), rng.uniform(*PRIOR["g"]), rng.uniform(*bt.d),
                     rng.uniform(*bt.r)])


def make_video(cache_dir, case: int, seed: int = 0, n_frames: int = 200, size: int = 256,
               balls=tuple(BALL_TYPES)) -> tuple[Path, dict]:
    """The H.264 video of case ``case`` and its metadata, generated once and cached.

    Case ``i`` is ball type ``balls[i % len(balls)]``, seeded by ``(seed, i)``. Files are
    ``<key>.mp4`` and ``<key>.json`` (written last, atomically: it marks a complete case).

    Returns
    -------
    path : Path
        The video file.
    meta : dict
        ``ball``, ``target``, ``measured`` (e, g, d, r; r None if the ball never rolled),
        ``states`` (T x 4 list), ``renderer``, ``info``, ``wall_s``.
    """
    from sysid_bench.core.footage import write_video

    cache = Path(cache_dir)
    cache.mkdir(parents=True, exist_ok=True)
    ball = balls[case % len(balls)]
    key = f"mj{CACHE_VERSION}_{ball}_s{seed}_c{case}_n{n_frames}_px{size}"
    jpath, vpath = cache / f"{key}.json", cache / f"{key}.mp4"
    if jpath.is_file() and vpath.is_file():
        return vpath, json.loads(jpath.read_text())
    t0 = time.perf_counter()
    rng = np.random.default_rng([int(seed), int(case), 12])
    target = draw_target(ball, rng)
    s0 = sample_state0(1, rng)[0]
    ep = simulate_ball(ball, target, s0, n_frames=n_frames)
    t_sim = time.perf_counter() - t0
    frames, renderer = render_frames(ep, size)
    write_video(vpath, frames, 20.0)
    meta = {"ball": ball, "case": case, "seed": seed, "target": ep.target.tolist(),
            "measured": [None if not np.isfinite(x) else float(x) for x in ep.measured],
            "state0": s0.tolist(), "states": ep.states.tolist(), "renderer": renderer,
            "info": ep.info, "sim_s": t_sim, "wall_s": time.perf_counter() - t0,
            "ball_type": asdict(BALL_TYPES[ball])}
    meta = json.loads(json.dumps(meta))  # the same types as when read back from the cache
    atomic_write(jpath, json.dumps(meta))
    return vpath, meta


def generate_set(cache_dir, n: int = 12, seed: int = 0, n_frames: int = 200, size: int = 256,
                 progress: bool = True) -> list[tuple[Path, dict]]:
    """The first ``n`` cases (see :func:`make_video`), generated or read from the cache."""
    from tqdm.auto import tqdm

    return [make_video(cache_dir, i, seed, n_frames, size)
            for i in tqdm(range(n), desc="MuJoCo videos", unit="video", disable=not progress)]


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m sysid_bench.mujoco_scene",
                                description="Generate (or read from the cache) MuJoCo videos.")
    p.add_argument("--out", default="runs/foreign_videos")
    p.add_argument("-n", type=int, default=12)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=200)
    args = p.parse_args(argv)
    why = mujoco_available()
    if why:
        print(f"skipped: {why}")
        return 0
    t0 = time.perf_counter()
    vids = generate_set(args.out, args.n, args.seed, args.frames)
    for path, meta in vids:
        m = meta["measured"]
        print(f"{path.name}: {meta['ball']:8s} target e/g/d/r "
              + "/".join(f"{x:.3g}" for x in meta["target"]) + "  measured "
              + "/".join("-" if x is None else f"{x:.3g}" for x in m)
              + f"  bounces {meta['info']['bounces']}, rolled {meta['info']['rolled_s']:.1f} s, "
              f"{meta['wall_s']:.1f} s")
    print(f"{len(vids)} videos in {time.perf_counter() - t0:.1f} s; renderer "
          f"{vids[0][1]['renderer'] if vids else '-'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
