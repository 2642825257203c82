"""The bouncing ball of the Vid2Param paper as a :class:`System`.

A thin wrapper: the physics is :mod:`sysid_bench.core.physics` (and its JAX twin
:mod:`sysid_bench.core.physics_jax`), the look :mod:`sysid_bench.core.render`, the tracker
:mod:`sysid_bench.core.tracking`, all unchanged, with the floor at 0 (the renderer's convention).
"""

from __future__ import annotations

import numpy as np

from sysid_bench.core import physics
from sysid_bench.core._observation_checks import BOX_MARGIN, check_dt, check_in_box
from sysid_bench.core._validate import as_float_array, check_number
from sysid_bench.core.systems._base import System
from sysid_bench.core.systems._scene import COORD_MAX, BallScene, check_within

__all__ = ["Ball"]


class Ball(System):
    """Ball in a 10 m box: parameters e, g, d, r; state [x, y, vx, vy]; K = 1."""

    name = "ball"
    params = physics.PARAMS
    prior = dict(physics.PRIOR)
    envelope = dict(physics.ENVELOPE)
    state = ("x", "y", "vx", "vy")
    state_bounds = {
        "x": (0.0, physics.BOX_WIDTH),
        "y": (0.0, physics.BOX_WIDTH),
        "vx": (-physics.V_MAX, physics.V_MAX),
        "vy": (-physics.V_MAX, physics.V_MAX),
    }
    n_points = 1
    extent = (0.0, physics.BOX_WIDTH, 0.0, physics.BOX_WIDTH)
    size = (28, 28)
    noise_m = 0.01
    jax_twin = "sysid_bench.core.systems.ball:_jax_simulate"
    scene_type = BallScene
    #: below 7 x 7 the tracker loses the ball in over 10% of frames (measured, clean video)
    min_size = (7, 7)
    paper = "Vid2Param (Asenov et al.)"
    #: r is unknowable until the ball rolls (about half the test videos never do)
    headline_groups = (("e", "g", "d"), ("r",))
    #: the paper's test videos: sysid_bench.core.datasets (splits, nuisances, variants)
    datasets = True
    #: experiment 5 also on re-simulated perturbed physics and on clips no physics explains
    calibration_conditions = ("perturbed", "meaningless")
    # experiments 3 and 4 use the paper's own test and training sets (sysid_bench.core.datasets):
    # all four parameters jump every `every` frames
    changing_params = physics.PARAMS
    changing_dataset = "changing"
    sensitivity_training = True
    #: experiment 4's simplified physics: drag and rolling held in training (the paper's)
    simplified_params = ("d", "r")

    def state_bounds_for(self, scene):
        if scene == self.default_scene:
            return self.state_bounds
        x = scene.walls if scene.walls is not None else (-COORD_MAX, COORD_MAX)
        y = (scene.floor if scene.floor is not None else -COORD_MAX, COORD_MAX)
        return dict(self.state_bounds, x=x, y=y)

    def check_theta(self, theta, n_frames=None, name="theta"):
        th = super().check_theta(theta, n_frames, name)
        return physics.check_theta(th, n_frames, name)  # g < 0 and the physics' own envelope

    def _simulate(self, theta, state0, n_frames, dt, scene=None):
        if scene is None or scene == self.default_scene:  # the design's box, as it always was
            return physics.simulate(theta, state0, n_frames=n_frames, dt=dt, floor=0.0)
        return physics.simulate(theta, state0, n_frames=n_frames, dt=dt, floor=scene.floor,
                                walls=scene.walls)

    def sample_state0(self, n, rng=None):
        return physics.sample_state0(n, rng)

    def _mean_bounds(self):
        # g above 0 is a ball falling up, however little: no margin there
        return [(lo, 0.0) if q == "g" else (lo, hi)
                for q, (lo, hi) in zip(self.params, super()._mean_bounds())]

    def known_geometry(self, scene=None):
        # the ball's Observation carries its floor as a field of its own (design.md)
        floor = (scene if scene is not None else self.default_scene).floor
        return {} if floor is None else {"floor": float(floor)}

    def check_observation(self, obs, default_scene):
        """The ball's Observation (design.md): positions (T, 2) ((T, 1, 2) accepted) within
        ``BOX_MARGIN`` of the box above ``floor`` (of the scene's walls and floor in a scene of
        its own), ``floor`` within the simulator's ``physics.FLOOR_MAX`` and equal to the
        scene's, ``state0`` [x, y, vx, vy] in the box at speeds up to ``physics.V_MAX``."""
        if obs.positions is not None:
            pos = as_float_array(obs.positions, "positions", ndim=(2, 3), last=2, allow_nan=True)
            if pos.ndim == 3:  # the ball's one tracked point as (T, 1, 2)
                if pos.shape[1] != 1:
                    raise ValueError(
                        f"positions: expected (T, 2) or (T, 1, 2) for the ball (K = 1), got shape {pos.shape}"
                    )
                pos = pos[:, 0]
            if pos.shape[0] < 1:
                raise ValueError("positions: expected at least 1 frame, got 0")
            obs.positions = pos
        if obs.frames is not None and obs.positions is not None:
            if obs.frames.shape[0] != obs.positions.shape[0]:
                raise ValueError(
                    "positions: expected as many rows as frames "
                    f"({obs.frames.shape[0]}), got {obs.positions.shape[0]}"
                )
        obs.dt = check_dt(obs.dt)
        if obs.floor is not None:
            # the simulator's bound (physics.FLOOR_MAX): every method simulates this floor
            obs.floor = check_number(obs.floor, "floor", lo=-physics.FLOOR_MAX,
                                     hi=physics.FLOOR_MAX, unit="m")
            if (obs.scene is not None and obs.scene.floor is not None
                    and obs.scene.floor != obs.floor):
                raise ValueError(f"floor: expected the scene's floor {obs.scene.floor:g} m (or "
                                 f"None), got {obs.floor:g}")
        check = check_in_box if default_scene else _check_in_ball_scene
        where = obs.floor if default_scene else obs.scene
        if obs.positions is not None:
            check(obs.positions, where, "positions")
        if obs.state0 is not None:
            obs.state0 = as_float_array(obs.state0, "state0", ndim=1, last=4)
            check(obs.state0[None, :2], where, "state0")
            v = float(np.abs(obs.state0[2:]).max())
            if v > physics.V_MAX:  # the simulator's bound: methods simulate from this state
                raise ValueError(f"state0: expected |vx|, |vy| <= {physics.V_MAX:g} m/s "
                                 f"(physics.V_MAX), got {v:g}")

    def _observe(self, states, theta, scene=None):
        # the state is the centre in world metres, whatever the scene
        return states[..., None, :2].copy()

    def _render(self, points, states, theta, size, **nuisance):
        from sysid_bench.core.render import render

        return render(states, size=size, **nuisance)

    def _track(self, frames):
        from sysid_bench.core.tracking import track

        return track(frames)[:, None, :]

    def track_observed(self, frames, floor=None):
        # the tracker places heights above the observation's floor (0 when unknown), as
        # observed_positions does; frames as the tracker takes them
        from sysid_bench.core.tracking import track

        return track(frames, floor=0.0 if floor is None else floor)[:, None, :]

    def reference(self, theta, state0, n_frames=200, dt=0.05):
        """The ball's reference is its own tested kernel (``tests/test_physics.py`` checks it
        against an event-located ``solve_ivp``)."""
        th = self.check_theta(np.asarray(theta, dtype=np.float64)[None])
        return self.simulate(th, np.asarray(state0, dtype=np.float64)[None], n_frames, dt)[0]


def _check_in_ball_scene(pos: np.ndarray, scene, name: str) -> None:
    """The ball's positions (N, 2) in a scene of its own: between its walls and above its floor
    (where it has them) within :data:`~sysid_bench.core.estimator.BOX_MARGIN`."""
    check_within(pos, name)
    seen = pos[np.isfinite(pos).all(axis=1)]
    if not seen.size:
        return
    m = BOX_MARGIN
    x, y = seen[:, 0], seen[:, 1]
    if scene.walls is not None and (x.min() < scene.walls[0] - m or x.max() > scene.walls[1] + m):
        raise ValueError(f"{name}: expected x within {m:g} m of the scene's walls {scene.walls}, "
                         f"got x in [{x.min():.4g}, {x.max():.4g}]")
    if scene.floor is not None and y.min() < scene.floor - m:
        raise ValueError(f"{name}: expected y above the scene's floor {scene.floor:g} m (within "
                         f"{m:g} m), got y down to {y.min():.4g}")


def _jax_simulate(theta, state0, n_frames=200, dt=0.05):
    """JAX twin for one trajectory: (4,), (4,) -> (n_frames, 4)."""
    from sysid_bench.core import physics_jax

    states, _bad = physics_jax.simulate_core(theta[None], state0[None], 0.0, int(n_frames), float(dt))
    return states[0]
