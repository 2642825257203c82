"""The bouncing ball of the Vid2Param paper as a :class:`System`.

A thin wrapper: the physics is :mod:`sysid_bench.physics` (and its JAX twin
:mod:`sysid_bench.physics_jax`), the look :mod:`sysid_bench.render`, the tracker
:mod:`sysid_bench.tracking`, all unchanged, with the floor at 0 (the renderer's convention).
"""

from __future__ import annotations

import numpy as np

from sysid_bench import physics
from sysid_bench.systems._base import System
from sysid_bench.systems._scene import COORD_MAX, BallScene

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
    jax_twin = "sysid_bench.systems.ball:_jax_simulate"
    scene_type = BallScene
    #: below 7 x 7 the tracker loses the ball in over 10% of frames (measured, clean video)
    min_size = (7, 7)
    paper = "Vid2Param (Asenov et al.)"
    #: r is unknowable until the ball rolls (about half the test videos never do)
    headline_groups = (("e", "g", "d"), ("r",))
    #: the paper's test videos: sysid_bench.datasets (splits, nuisances, variants)
    datasets = True
    #: experiment 5 also on re-simulated perturbed physics and on clips no physics explains
    calibration_conditions = ("perturbed", "meaningless")
    # experiments 3 and 4 use the paper's own test and training sets (sysid_bench.datasets):
    # all four parameters jump every `every` frames
    changing_params = physics.PARAMS
    changing_dataset = "changing"
    sensitivity_training = True

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

    def _observe(self, states, theta, scene=None):
        # the state is the centre in world metres, whatever the scene
        return states[..., None, :2].copy()

    def _render(self, points, states, theta, size, **nuisance):
        from sysid_bench.render import render

        return render(states, size=size, **nuisance)

    def _track(self, frames):
        from sysid_bench.tracking import track

        return track(frames)[:, None, :]

    def reference(self, theta, state0, n_frames=200, dt=0.05):
        """The ball's reference is its own tested kernel (``tests/test_physics.py`` checks it
        against an event-located ``solve_ivp``)."""
        th = self.check_theta(np.asarray(theta, dtype=np.float64)[None])
        return self.simulate(th, np.asarray(state0, dtype=np.float64)[None], n_frames, dt)[0]


def _jax_simulate(theta, state0, n_frames=200, dt=0.05):
    """JAX twin for one trajectory: (4,), (4,) -> (n_frames, 4)."""
    from sysid_bench import physics_jax

    states, _bad = physics_jax.simulate_core(theta[None], state0[None], 0.0, int(n_frames), float(dt))
    return states[0]
