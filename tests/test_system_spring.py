"""The spring system: the public contract (``check_system``, one test per check) and its physics
against the design's rules (analytic linear cases, energy, the Duffing stiffening, the
solve_ivp reference at the prior's stiffest corner), the JAX twin's gradients, the camera, and
bad input."""

import numpy as np
import pytest

from sysid_bench.core import systems
from sysid_bench.core._system_checks import system_checks
from sysid_bench.core.systems import spring as spring_mod

SPRING = systems.get("spring")
DT = 0.05
T = 200


def _x(theta, state0, n_frames=T, dt=DT):
    return SPRING.simulate(np.atleast_2d(theta), np.atleast_2d(state0), n_frames, dt)[..., 0]


@pytest.mark.parametrize("name, run", list(system_checks("spring")), ids=lambda v: v if
                         isinstance(v, str) else "")
def test_check_system(name, run):
    run()


# ----------------------------------------------------------------------------------------------
# physics
def test_linear_undamped_matches_the_closed_form():
    w2, L0, s0, v0 = 16.0, 1.3, -0.45, 0.3
    x = _x([w2, 0.0, 0.0, L0], [L0 + s0, v0])[0]
    t = np.arange(T) * DT
    w = np.sqrt(w2)
    exact = L0 + s0 * np.cos(w * t) + v0 / w * np.sin(w * t)
    assert np.abs(x - exact).max() <= 1e-6


def test_linear_damped_matches_the_closed_form():
    w2, c, L0, s0, v0 = 9.0, 0.6, 1.8, 0.5, -0.4
    x = _x([w2, 0.0, c, L0], [L0 + s0, v0])[0]
    t = np.arange(T) * DT
    wd = np.sqrt(w2 - c * c / 4)
    exact = L0 + np.exp(-c * t / 2) * (s0 * np.cos(wd * t) + (v0 + c * s0 / 2) / wd * np.sin(wd * t))
    assert np.abs(x - exact).max() <= 1e-6


def _energy(theta, states):
    w2, k3, _, L0 = theta
    s = states[..., 0] - L0
    return 0.5 * states[..., 1] ** 2 + 0.5 * w2 * s**2 + 0.25 * k3 * s**4


def test_energy_is_kept_without_damping_and_falls_with_it():
    s0 = np.array([[1.5 + 0.6, 0.5]])
    undamped = np.array([25.0, 20.0, 0.0, 1.5])
    e = _energy(undamped, SPRING.simulate(undamped[None], s0)[0])
    assert np.abs(e / e[0] - 1).max() <= 1e-7
    damped = np.array([25.0, 20.0, 0.4, 1.5])
    e = _energy(damped, SPRING.simulate(damped[None], s0)[0])
    assert (np.diff(e) < 0).all()
    # the linear part decays as exp(-c t) on average: after 10 s the energy is ~exp(-4) of e0
    assert e[-1] / e[0] < 0.05


def _period(x, L0):
    """Mean time between upward crossings of L0, linearly interpolated."""
    s = x - L0
    i = np.flatnonzero((s[:-1] < 0) & (s[1:] >= 0))
    t = (i + s[i] / (s[i] - s[i + 1])) * DT
    return float(np.diff(t).mean())


def test_the_cubic_term_stiffens_large_swings_only():
    # Duffing: the period shortens with amplitude when k3 > 0, and does not depend on it when
    # k3 = 0 (the linear oscillator)
    L0 = 1.5
    lin = [_period(_x([9.0, 0.0, 0.0, L0], [L0 + a, 0.0])[0], L0) for a in (0.2, 0.6)]
    assert lin[0] == pytest.approx(2 * np.pi / 3, abs=1e-4)
    assert lin[1] == pytest.approx(lin[0], abs=1e-4)
    cub = [_period(_x([9.0, 20.0, 0.0, L0], [L0 + a, 0.0])[0], L0) for a in (0.2, 0.6)]
    assert cub[0] < lin[0] and cub[1] < cub[0] - 0.1


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("v0", [0.5, -0.5])
def test_the_stiffest_prior_corner_agrees_with_solve_ivp(sign, v0):
    theta = np.array([25.0, 20.0, 0.0, 1.5])
    state0 = np.array([1.5 + sign * 0.6, v0])
    ours = _x(theta, state0)[0]
    ref = SPRING.reference(theta, state0)[:, 0]
    assert np.abs(ours - ref).max() <= 1e-6


def test_random_prior_cases_agree_with_solve_ivp():
    theta, state0 = SPRING.sample_cases(10, np.random.default_rng(21))
    ours = SPRING.simulate(theta, state0)[..., 0]
    ref = np.stack([SPRING.reference(theta[i], state0[i])[:, 0] for i in range(10)])
    assert np.abs(ours - ref).max() <= 1e-6


def test_time_varying_theta_holds_from_frame_t_to_t_plus_1():
    a = np.array([9.0, 5.0, 0.2, 1.4])
    b = np.array([20.0, 15.0, 0.5, 1.6])
    s0 = np.array([[1.9, 0.2]])
    th = np.empty((1, 120, 4))
    th[:, :60], th[:, 60:] = a, b
    whole = SPRING.simulate(th, s0, 120)[0]
    first = SPRING.simulate(a[None], s0, 61)[0]
    second = SPRING.simulate(b[None], first[-1:], 60)[0]
    np.testing.assert_array_equal(whole[:61], first)
    np.testing.assert_array_equal(whole[60:], second)


def test_batch_order_and_size_do_not_change_a_trajectory():
    theta, state0 = SPRING.sample_cases(6, np.random.default_rng(2))
    whole = SPRING.simulate(theta, state0, 50)
    for i in (0, 5):
        np.testing.assert_array_equal(SPRING.simulate(theta[i : i + 1], state0[i : i + 1], 50)[0],
                                      whole[i])
    perm = np.random.default_rng(0).permutation(6)
    np.testing.assert_array_equal(SPRING.simulate(theta[perm], state0[perm], 50), whole[perm])


# ----------------------------------------------------------------------------------------------
# initial states
def test_sample_state0_uses_each_trajectorys_rest_position():
    rng = np.random.default_rng(4)
    theta = SPRING.sample_theta(4000, rng)
    s = SPRING.sample_state0(4000, rng, theta=theta)
    stretch = s[:, 0] - theta[:, 3]
    assert (np.abs(stretch) >= 0.2).all() and (np.abs(stretch) <= 0.6).all()
    assert 0.45 < (stretch > 0).mean() < 0.55
    assert (np.abs(s[:, 1]) <= 0.5).all() and s[:, 1].min() < -0.45 and s[:, 1].max() > 0.45
    # without theta: a rest position from the prior, the same stretches and velocities
    rng2 = np.random.default_rng(4)
    SPRING.sample_theta(4000, rng2)
    s2 = SPRING.sample_state0(4000, rng2)
    np.testing.assert_array_equal(s2[:, 1], s[:, 1])
    assert (s2[:, 0] >= 1.0 - 0.6).all() and (s2[:, 0] <= 2.0 + 0.6).all()


def test_sample_state0_refuses_theta_of_the_wrong_shape():
    theta = SPRING.sample_theta(3, 0)
    with pytest.raises(ValueError, match="theta"):
        SPRING.sample_state0(4, 0, theta=theta)
    with pytest.raises(ValueError, match="theta"):
        SPRING.sample_state0(3, 0, theta=theta[:, :3])


def test_state0_from_track_holds_the_truth_in_its_box():
    rng = np.random.default_rng(8)
    theta, state0 = SPRING.sample_cases(300, rng)
    pts = SPRING.observe(SPRING.simulate(theta, state0, 40), theta)
    noisy = pts + rng.normal(0.0, 0.01, pts.shape)
    err, inside = [], []
    for i in range(300):
        est, scale = SPRING.state0_from_track(noisy[i])
        err.append(est - state0[i])
        inside.append((np.abs(est - state0[i]) <= scale).all())
    err = np.array(err)
    assert np.mean(inside) == 1.0
    assert np.sqrt((err[:, 0] ** 2).mean()) < 0.015 and np.sqrt((err[:, 1] ** 2).mean()) < 0.2
    # (T, 2) reads as K = 1; few seen frames give the wide box around the first seen position
    est2, _ = SPRING.state0_from_track(noisy[0][:, 0])
    np.testing.assert_array_equal(est2, SPRING.state0_from_track(noisy[0])[0])
    sparse = noisy[0].copy()
    sparse[:30] = np.nan
    est, scale = SPRING.state0_from_track(sparse)
    assert est[0] == sparse[30, 0, 0] and (scale >= [0.6, 3.0]).all()
    with pytest.raises(ValueError, match="positions"):
        SPRING.state0_from_track(np.full((40, 1, 2), np.nan))
    with pytest.raises(ValueError, match="positions"):
        SPRING.state0_from_track(np.zeros((40, 2, 2)))


# ----------------------------------------------------------------------------------------------
# the JAX twin
def test_jax_twin_time_varying_and_gradients():
    import jax
    import jax.numpy as jnp

    from sysid_bench.core.systems.spring_jax import simulate

    th = np.empty((80, 4))
    th[:40], th[40:] = [9.0, 5.0, 0.2, 1.4], [20.0, 15.0, 0.5, 1.6]
    s0 = np.array([1.9, 0.2])
    twin = np.asarray(simulate(th, s0, 80, DT))
    ours = SPRING.simulate(th[None], s0[None], 80)[0]
    assert np.abs(twin - ours).max() <= 1e-9

    theta = jnp.array([16.0, 10.0, 0.3, 1.5])
    state0 = jnp.array([1.9, -0.2])

    def loss(p, s):
        return jnp.sum(simulate(p, s, 60, DT)[:, 0] ** 2)

    g_th, g_s = jax.jit(jax.grad(loss, argnums=(0, 1)))(theta, state0)
    eps = 1e-6
    for i in range(4):
        e = np.zeros(4)
        e[i] = eps
        fd = (loss(theta + e, state0) - loss(theta - e, state0)) / (2 * eps)
        assert float(g_th[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-7)
    fd = (loss(theta, state0 + jnp.array([eps, 0.0])) - loss(theta, state0 - jnp.array([eps, 0.0])))
    assert float(g_s[0]) == pytest.approx(float(fd) / (2 * eps), rel=1e-5)
    # vmapped over a batch of parameters, as NUTS uses it
    batch = jnp.stack([theta, theta.at[0].set(9.0)])
    out = jax.vmap(lambda p: simulate(p, state0, 60, DT))(batch)
    assert out.shape == (2, 60, 2)
    with pytest.raises(ValueError, match="theta"):
        simulate(np.zeros(5), s0, 10, DT)
    with pytest.raises(ValueError, match="w2"):
        simulate(np.array([1e4, 0.0, 0.0, 1.5]), s0, 10, DT)


# ----------------------------------------------------------------------------------------------
# the camera
def test_track_within_a_fraction_of_a_pixel_with_nuisances():
    theta, state0 = SPRING.sample_cases(5, np.random.default_rng(31))
    states = SPRING.simulate(theta, state0, 100)
    pts = SPRING.observe(states, theta)
    frames = SPRING.render(states, theta, blur=0.5, noise=8.0, seed=3)
    px_per_m = SPRING.size[1] / (SPRING.extent[1] - SPRING.extent[0])
    for i in range(5):
        tr = SPRING.track(frames[i])
        assert np.isfinite(tr).all()
        assert np.abs(tr - pts[i]).max() * px_per_m <= 0.5


def test_the_tracker_finds_the_block_not_the_spring_or_the_wall():
    theta = np.array([[9.0, 0.0, 0.0, 1.5]])
    states = np.array([[[0.5, 0.0], [2.7, 0.0]]])
    frames = SPRING.render(states, theta)
    # the spring (rows 7-8 about y = 0, from the wall at column 4 to the block) is drawn dim
    spring = frames[0, 1, 7:9, 10:45]
    assert frames[0, 1].max() == 255 and (spring > 10).all() and (spring < 128).all()
    # the spring is visible left of the block; take the block away and nothing is tracked
    block_free = frames[0].copy()
    block_free[block_free > 128] = 0
    assert np.isnan(SPRING.track(block_free)).all()
    np.testing.assert_allclose(SPRING.track(frames[0])[:, 0, 0], [0.5, 2.7], atol=0.01)


def test_frames_with_no_block_give_nan():
    h, w = SPRING.size
    rng = np.random.default_rng(0)
    frames = np.stack([
        np.zeros((h, w)),
        np.full((h, w), 255.0),
        rng.integers(0, 256, (h, w)),
        np.clip(rng.normal(0.0, 8.0, (h, w)), 0, 255),
    ]).astype(np.uint8)
    assert np.isnan(SPRING.track(frames)).all()


def test_render_at_another_size_tracks_back():
    theta, state0 = SPRING.sample_cases(2, np.random.default_rng(1))
    states = SPRING.simulate(theta, state0, 30)
    frames = SPRING.render(states, theta, size=(32, 128))
    assert frames.shape == (2, 30, 32, 128)
    tr = SPRING.track(frames[1])
    pts = SPRING.observe(states, theta)[1]
    assert np.abs(tr - pts).max() * 40.0 <= 1.0  # 40 px/m at this size


# ----------------------------------------------------------------------------------------------
# bad input
def test_bad_input_names_the_argument_and_the_system():
    theta, state0 = SPRING.sample_cases(2, np.random.default_rng(0))
    with pytest.raises(ValueError, match="theta.*spring"):
        SPRING.simulate(theta[:, :3], state0)
    with pytest.raises(ValueError, match="state0.*spring"):
        SPRING.simulate(theta, np.ones((2, 3)))
    for i, (q, (a, b)) in enumerate(SPRING.envelope.items()):
        far = theta.copy()
        far[0, i] = b + 1.0
        with pytest.raises(ValueError, match=f"{q}.*spring"):
            SPRING.simulate(far, state0)
        far[0, i] = a - 1.0
        with pytest.raises(ValueError, match=f"{q}.*spring"):
            SPRING.simulate(far, state0)
    with pytest.raises(ValueError, match="state0.*v.*spring"):
        SPRING.simulate(theta, np.array([[1.5, 50.0], [1.5, 0.0]]))
    with pytest.raises(ValueError, match="nuisance"):
        SPRING.render(SPRING.simulate(theta, state0, 3), theta, glare=1.0)


def test_a_step_too_coarse_for_the_stiffness_is_refused():
    stiff = np.array([[100.0, 100.0, 0.0, 2.0]])
    s0 = np.array([[2.4, 0.0]])
    SPRING.simulate(stiff, s0, 20, DT)  # inside what RK4 resolves at dt = 0.05
    with pytest.raises(ValueError, match="dt"):
        SPRING.simulate(stiff, s0, 20, 1.0)


def test_a_start_that_swings_past_the_wall_is_simulated_as_the_equation_says():
    # no wall contact in the model (no events): at L0 = 0.5 a stretch of 0.6 carries the block
    # past x = 0, and a fitting method proposing such a theta still gets the trajectory
    theta, state0 = np.array([9.0, 0.0, 0.0, 0.5]), np.array([1.1, 0.0])
    x = _x(theta, state0)[0]
    assert x.min() < -0.05
    assert np.abs(x - SPRING.reference(theta, state0)[:, 0]).max() <= 1e-6


def test_spring_constants_are_the_design_ones():
    assert SPRING.params == ("w2", "k3", "c", "L0")
    assert SPRING.prior == {"w2": (4.0, 25.0), "k3": (0.0, 20.0), "c": (0.0, 0.6),
                            "L0": (1.0, 2.0)}
    assert SPRING.state == ("x", "v") and SPRING.n_points == 1
    assert spring_mod.S0_RANGE == (0.2, 0.6) and spring_mod.V0_RANGE == (-0.5, 0.5)
