"""The scene as data (issue 38 section 1): each system's geometry is a frozen dataclass with the
design's numbers as defaults; ``simulate``/``observe`` honour it, ``scene=None`` is the design bit
for bit, and ``Observation.scene`` is checked on construction."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sysid_bench.core import physics, systems
from sysid_bench.core.estimator import Observation
from sysid_bench.core.systems import BallScene, CollisionScene, PendulumScene, Scene, SpringScene

NAMES = ("ball", "collision", "pendulum", "spring")


@pytest.mark.parametrize("name", NAMES)
def test_the_default_scene_is_the_design_bit_for_bit(name):
    s = systems.get(name)
    assert isinstance(s.default_scene, Scene) and s.default_scene.system == name
    assert s.scene() == s.default_scene == s.scene_type()
    theta, state0 = s.sample_cases(6, 21)
    base = s.simulate(theta, state0, 80)
    pts = s.observe(base, theta)
    for sc in (s.default_scene, s.scene(), s.scene_type(**{
            f.name: getattr(s.default_scene, f.name) for f in dataclasses.fields(s.scene_type)})):
        again = s.simulate(theta, state0, 80, scene=sc)
        assert again.tobytes() == base.tobytes()
        assert s.observe(again, theta, scene=sc).tobytes() == pts.tobytes()


def test_the_balls_default_scene_is_its_kernel_with_floor_zero():
    b = systems.get("ball")
    theta, state0 = b.sample_cases(20, 2)
    want = physics.simulate(theta, state0, 100, floor=0.0)
    assert b.simulate(theta, state0, 100, scene=BallScene()).tobytes() == want.tobytes()
    assert physics.simulate(theta, state0, 100, walls=(0.0, 10.0)).tobytes() == want.tobytes()


def test_scenes_are_checked_where_they_are_made():
    with pytest.raises(ValueError, match=r"scene\.walls"):
        BallScene(walls=(3.0, 1.0))
    with pytest.raises(ValueError, match=r"scene\.pivot\[1\]"):
        PendulumScene(pivot=(0.0, float("nan")))
    with pytest.raises(ValueError, match=r"scene\.anchor"):
        SpringScene(anchor=(0.0,))
    with pytest.raises(ValueError, match=r"scene\.half_sizes"):
        CollisionScene(half_sizes=(0.0, 0.25))
    with pytest.raises(ValueError, match=r"scene\.ends"):
        CollisionScene(ends=(0.0, 1e9))
    with pytest.raises(ValueError, match="no field 'wall'"):
        systems.get("ball").scene(wall=None)
    with pytest.raises(ValueError, match=r"scene\.floor"):
        BallScene(floor="0")
    with pytest.raises(dataclasses.FrozenInstanceError):
        BallScene().floor = 1.0
    sc = systems.get("ball").scene(walls=None, floor=np.float32(0.5))
    assert sc.walls is None and sc.floor == 0.5 and type(sc.floor) is float
    with pytest.raises(TypeError, match="BallScene for the ball system.*PendulumScene"):
        systems.get("ball").simulate(*systems.get("ball").sample_cases(1, 0), 5, scene=PendulumScene())


def test_the_ball_free_of_floor_and_walls_is_a_parabola():
    b = systems.get("ball")
    theta = np.array([[0.8, -9.81, 0.0, 0.3]])  # no drag: RK4 is exact on a parabola
    s0 = np.array([[5.0, 7.0, 6.0, 3.5]])
    out = b.simulate(theta, s0, 60, scene=b.scene(floor=None, walls=None))
    t = np.arange(60) * 0.05
    np.testing.assert_allclose(out[0, :, 0], 5.0 + 6.0 * t, atol=1e-9)
    np.testing.assert_allclose(out[0, :, 1], 7.0 + 3.5 * t - 0.5 * 9.81 * t**2, atol=1e-9)
    # a floor alone: the bounces as in the box, and x leaves the old box freely
    fl = b.simulate(theta, s0, 60, scene=b.scene(walls=None))
    assert fl[0, :, 0].max() > 10.0 + 5.0 and fl[0, :, 1].min() >= 0.0
    box = b.simulate(theta, s0, 60)
    first_wall = int(np.argmax(box[0, :, 0] >= 9.99))
    np.testing.assert_array_equal(fl[0, :first_wall], box[0, :first_wall])


@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_the_ball_in_a_moved_and_scaled_box(scale):
    # a box of 10 * scale m, its floor and walls moved: the motion (g scaled with it, so the
    # trajectory is the design's scaled) stays inside and matches the scaled design's (rolling
    # starts below a fixed speed, so only while no ball rolls: r = 0, 100 frames)
    b = systems.get("ball")
    theta, s0 = b.sample_cases(5, 8)
    theta[:, 2] = 0.0  # drag is not scale-free; the rest is
    theta[:, 3] = 0.0
    ref = b.simulate(theta, s0, 100)
    off = np.array([-3.0, 1.5])
    sc = b.scene(floor=1.5, walls=(-3.0, -3.0 + 10.0 * scale))
    th = theta.copy()
    th[:, 1] *= scale
    s = s0.copy()
    s[:, :2] = off + scale * s0[:, :2]
    s[:, 2:] *= scale
    out = b.simulate(th, s, 100, scene=sc)
    np.testing.assert_allclose(out[..., :2], off + scale * ref[..., :2], atol=1e-9 * max(scale, 1) + 1e-10)
    assert out[..., 0].min() >= -3.0 and out[..., 0].max() <= -3.0 + 10.0 * scale
    assert out[..., 1].min() >= 1.5 - 1e-12


def test_the_ball_in_a_tall_scene():
    b = systems.get("ball")
    sc = b.scene(floor=0.0, walls=(0.0, 40.0))
    out = b.simulate(np.array([[0.9, -9.81, 0.001, 0.2]]), np.array([[20.0, 25.0, 3.0, 0.0]]), 200,
                     scene=sc)
    assert out[0, :, 1].max() == 25.0 and out[0, :, 1].min() >= 0.0
    with pytest.raises(ValueError, match=r"state0: expected x in \[0, 40\]"):
        b.simulate(np.array([[0.9, -9.81, 0.001, 0.2]]), np.array([[41.0, 5.0, 0.0, 0.0]]), 5, scene=sc)


def test_a_centimetre_ball_bounces_inside_its_box():
    b = systems.get("ball")
    sc = b.scene(floor=0.0, walls=(0.0, 0.2))
    out = b.simulate(np.array([[0.8, -9.81, 0.02, 0.5]]), np.array([[0.1, 0.15, 0.3, 0.0]]), 200,
                     scene=sc)[0]
    assert 0.0 <= out[:, 0].min() and out[:, 0].max() <= 0.2 and out[:, 1].min() >= 0.0
    assert (np.diff(np.sign(out[:, 2])) != 0).sum() >= 2  # wall hits turn vx
    assert out[-1, 1] == 0.0 and out[-1, 2] == 0.0  # bounced down to rolling, then stopped


def test_the_pendulum_hangs_from_its_pivot():
    p = systems.get("pendulum")
    theta, s0 = p.sample_cases(4, 3)
    sc = p.scene(pivot=(12.0, -30.0))
    st = p.simulate(theta, s0, 50, scene=sc)
    assert st.tobytes() == p.simulate(theta, s0, 50).tobytes()  # angles: the pivot moves no motion
    np.testing.assert_allclose(p.observe(st, theta, scene=sc) - p.observe(st, theta), 0 * st[..., None, :]
                               + np.array([12.0, -30.0]), atol=1e-12)


def test_the_spring_is_tied_to_its_anchor():
    s = systems.get("spring")
    theta, s0 = s.sample_cases(4, 3)
    sc = s.scene(anchor=(7.5, 1.25))
    moved = s0 + [7.5, 0.0]
    st = s.simulate(theta, moved, 120, scene=sc)
    ref = s.simulate(theta, s0, 120)
    np.testing.assert_allclose(st - [7.5, 0.0], ref, atol=1e-12)
    pts = s.observe(st, theta, scene=sc)
    assert (pts[..., 1] == 1.25).all()
    with pytest.raises(ValueError, match="state0: expected x in"):
        s.simulate(theta, s0 - [1.0, 0.0], 5, scene=sc)  # left of the anchor's wall


def test_the_collision_track_and_pucks_follow_the_scene():
    c = systems.get("collision")
    theta, s0 = c.sample_cases(6, 4)
    sc = c.scene(ends=(-20.0, -10.0))
    st = c.simulate(theta, s0 - [20.0, 0.0, 20.0, 0.0], 200, scene=sc)
    np.testing.assert_allclose(st + [20.0, 0.0, 20.0, 0.0], c.simulate(theta, s0, 200), atol=1e-8)
    sc = c.scene(ends=(0.0, 10.0), half_sizes=(0.1, 0.6))
    st = c.simulate(theta, s0, 200, scene=sc)
    assert (st[..., 2] - st[..., 0] >= 0.7 - 1e-9).all()
    assert st[..., 0].min() >= 0.1 - 1e-9 and st[..., 2].max() <= 9.4 + 1e-9
    pts = c.observe(st, theta, scene=sc)
    assert (pts[..., 0, 1] == 0.1).all() and (pts[..., 1, 1] == 0.6).all()
    with pytest.raises(ValueError, match="r1 \\+ r2"):
        c.simulate(theta, np.array([[3.0, 1.0, 3.6, -1.0]] * 6), 5, scene=sc)
    # centimetre pucks on a 1 m track
    small = c.scene(ends=(0.0, 1.0), half_sizes=(0.02, 0.02))
    st = c.simulate(theta[:1], np.array([[0.2, 0.3, 0.7, -0.2]]), 200, scene=small)
    assert st[..., 0].min() >= 0.02 - 1e-12 and st[..., 2].max() <= 0.98 + 1e-12


def test_observation_holds_a_checked_scene():
    b, p = systems.get("ball"), systems.get("pendulum")
    pos = np.zeros((5, 2)) + [5.0, 3.0]
    assert Observation(positions=pos).scene is None
    assert Observation(positions=pos, scene=b.default_scene).scene == BallScene()
    with pytest.raises(TypeError, match="scene: expected a BallScene.*pendulum system's PendulumScene"):
        Observation(positions=pos, scene=PendulumScene())
    with pytest.raises(TypeError, match="scene: expected a PendulumScene"):
        Observation(positions=pos, system="pendulum", scene={"pivot": (0, 0)})
    broken = PendulumScene()
    object.__setattr__(broken, "pivot", (float("inf"), 0.0))
    with pytest.raises(ValueError, match="scene: expected finite"):
        Observation(positions=pos, system="pendulum", scene=broken)
    with pytest.raises(ValueError, match="floor: expected the scene's floor"):
        Observation(positions=pos, floor=1.0, scene=b.scene(floor=0.5))
    # a scene of its own size: positions far outside the design's box are its, not a wrong unit
    far = np.zeros((5, 2)) + [35.0, 12.0]
    obs = Observation(positions=far, scene=b.scene(walls=(0.0, 40.0)))
    assert obs.prefix(3).scene == obs.scene
    with pytest.raises(ValueError, match="positions"):
        Observation(positions=far)
    with pytest.raises(ValueError, match="walls"):
        Observation(positions=far, scene=b.scene(walls=(0.0, 20.0)))
    bob = np.zeros((5, 1, 2)) + [40.0, -31.0]
    obs = Observation(positions=bob, system="pendulum", scene=p.scene(pivot=(40.0, -30.0)))
    assert obs.scene.pivot == (40.0, -30.0)
    with pytest.raises(ValueError, match="positions"):
        Observation(positions=bob, system="pendulum")
    with pytest.raises(ValueError, match="state0"):
        Observation(positions=np.zeros((5, 1, 2)) + [5.0, 0.0], system="spring",
                    scene=systems.get("spring").scene(anchor=(4.0, 0.0)), state0=np.array([1.0, 0.0]))
