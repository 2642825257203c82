"""The JAX twin of the simulator: equal to the NumPy one, and its gradients are right.

Equality is checked to 1e-9 m (float64) on random balls with per-ball floors, on adversarial
ones (many contacts per frame), on time-varying parameters and on hand-made edge cases.
Gradients with respect to ``theta`` are checked against central finite differences of the
NumPy simulator: in free flight, and across a floor bounce, a wall bounce and a rolling stop,
where the contact time moves with the parameters.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sysid_bench.core import physics as P
from sysid_bench.core import physics_jax as PJ

TOL = 1e-9  # m


def _both(theta, s0, n_frames=200, floor=0.0):
    ref = P.simulate(theta, s0, n_frames=n_frames, floor=floor)
    out = np.asarray(PJ.simulate(theta, s0, n_frames=n_frames, floor=floor))
    return ref, out


def _assert_equal(ref, out, tol=TOL):
    assert out.shape == ref.shape and out.dtype == np.float64
    pos = np.abs(out[..., :2] - ref[..., :2]).max()
    vel = np.abs(out[..., 2:] - ref[..., 2:]).max()
    assert pos <= tol, f"max position difference {pos:.3g} m"
    assert vel <= 100 * tol, f"max velocity difference {vel:.3g} m/s"


# ---------------------------------------------------------------------------------------------
# equality with the NumPy simulator
def test_equal_on_random_balls_with_per_ball_floor():
    rng = np.random.default_rng(2024)
    n = 500
    theta = P.sample_theta(n, rng)
    floor = rng.uniform(-1.0, 1.0, n)
    s0 = P.sample_state0(n, rng, floor=floor)
    ref, out = _both(theta, s0, floor=floor)
    _assert_equal(ref, out)
    # the sample does exercise the contact types
    y = ref[..., 1] - floor[:, None]
    assert (np.abs(y[:, -1]) < 1e-12).sum() > 50  # rolling or stopped at the end
    assert (np.diff(np.sign(ref[..., 2]), axis=1) != 0).any(axis=1).mean() > 0.5  # wall bounces
    assert ((ref[:, -50:, 2] == 0) & (np.abs(y[:, -50:]) < 1e-12)).any(axis=1).sum() > 10  # stops


def test_equal_on_adversarial_many_contact_balls():
    """Strong gravity, e near 1, skimming the floor at 15 m/s between the walls: more balls
    than contact lanes hit in most frames, so the passes also run at full width."""
    rng = np.random.default_rng(5)
    n = 300
    theta = P.sample_theta(n, rng)
    theta[:, 0] = rng.uniform(0.9, 1.0, n)
    theta[:, 1] = P.PRIOR["g"][0]
    theta[:, 2] = rng.uniform(0.0, 0.002, n)
    s0 = np.column_stack(
        [rng.choice([0.0, 10.0], n), rng.uniform(0.0, 0.05, n), rng.choice([-15.0, 15.0], n), rng.uniform(-0.5, 0.5, n)]
    )
    ref, out = _both(theta, s0)
    _assert_equal(ref, out, tol=1e-9)


def test_equal_when_more_balls_hit_than_there_are_contact_lanes():
    """200 balls dropped together bounce in the same frames: the passes run at full width."""
    rng = np.random.default_rng(4)
    n = 200
    theta = np.column_stack(
        [rng.uniform(0.6, 1.0, n), np.full(n, -9.81), rng.uniform(0.0, 0.001, n), rng.uniform(0, 0.7, n)]
    )
    s0 = np.column_stack([rng.uniform(0, 10, n), np.full(n, 5.0), rng.uniform(-8, 8, n), np.zeros(n)])
    ref, out = _both(theta, s0, n_frames=60)
    t_hit = np.sqrt(2 * 5.0 / 9.81)  # ~1.01 s: every ball's first bounce is in frame 20
    assert (ref[:, 20, 3] < 0).all() and (ref[:, 21, 3] > 0).all() and n > PJ._slots(n)
    _assert_equal(ref, out)
    assert 20 * 0.05 < t_hit < 21 * 0.05


def test_equal_with_time_varying_theta():
    rng = np.random.default_rng(9)
    n, T = 100, 200
    blocks = np.stack([P.sample_theta(n, rng) for _ in range(T // 50)], axis=1)  # (n, 4, 4)
    theta = np.repeat(blocks, 50, axis=1)  # changes every 50 frames
    s0 = P.sample_state0(n, rng)
    ref, out = _both(theta, s0, n_frames=T)
    _assert_equal(ref, out)


@pytest.mark.parametrize(
    "theta, s0",
    [
        ([0.6, -9.81, 0.01, 0.5], [5.0, 0.0, 3.0, 0.0]),  # rolls at once, hits a wall, stops
        ([0.9, -9.81, 0.0, 0.0], [5.0, 5.0, 0.0, 0.0]),  # vertical drop, no drag, never stops
        ([1.0, -6.81, 0.0, 0.3], [0.0, 10.0, -8.0, 4.0]),  # corner start moving out, elastic
        ([0.6, -12.81, 0.05, 0.7], [10.0, 0.0, 8.0, -4.0]),  # corner on the floor moving out
        ([0.8, -9.81, 0.02, 0.0], [2.0, 0.0, 1.0, 0.0]),  # rolls forever (r = 0)
    ],
)
def test_equal_on_edge_cases(theta, s0):
    ref, out = _both(np.array([theta]), np.array([s0]))
    _assert_equal(ref, out)


def test_single_frame_and_batch_of_one():
    theta, s0 = np.array([[0.8, -9.81, 0.01, 0.1]]), np.array([[3.0, 5.0, 4.0, 3.0]])
    ref, out = _both(theta, s0, n_frames=1)
    np.testing.assert_array_equal(out, ref)
    ref, out = _both(theta, s0, n_frames=3)
    _assert_equal(ref, out)


# ---------------------------------------------------------------------------------------------
# transformations
def test_jit_vmap_and_traced_inputs_agree():
    rng = np.random.default_rng(1)
    theta = P.sample_theta(8, rng)
    s0 = P.sample_state0(8, rng)
    ref = P.simulate(theta, s0, n_frames=100)
    jitted = jax.jit(lambda th, s: PJ.simulate(th, s, n_frames=100))
    _assert_equal(ref, np.asarray(jitted(theta, s0)))
    one = jax.vmap(lambda th, s: PJ.simulate(th[None], s[None], n_frames=100)[0])
    _assert_equal(ref, np.asarray(one(jnp.asarray(theta), jnp.asarray(s0))))


N_GRAD = 120  # frames of every gradient check: one compiled Jacobian serves them all


@pytest.fixture(scope="module")
def jac_states():
    """Jitted forward-mode Jacobian d states (N_GRAD, 4) / d theta (4,) of one ball."""

    def states(theta, s0):
        return PJ.simulate_core(theta[None], s0[None], jnp.zeros(1), n_frames=N_GRAD)[0][0]

    return jax.jit(jax.jacfwd(states))


def test_reverse_and_forward_mode_agree(jac_states):
    """Reverse mode (what a user's jax.grad does) through the scan, the masked contact passes and
    the gather/scatter of a large batch's contact lanes gives, ball by ball, the forward-mode
    gradient of a batch of one, on bouncing and rolling balls."""
    rng = np.random.default_rng(3)
    n = 136  # > 128: the contact passes run on gathered lanes
    assert PJ._slots(n) < n
    theta = P.sample_theta(n, rng)
    s0 = P.sample_state0(n, rng)
    w = rng.standard_normal((n, N_GRAD, 4))

    def f(th):
        return jnp.sum(w * PJ.simulate_core(th, jnp.asarray(s0), jnp.zeros(n), n_frames=N_GRAD)[0])

    g_rev = np.asarray(jax.jit(jax.grad(f))(jnp.asarray(theta)))
    assert np.isfinite(g_rev).all()
    for i in range(0, n, 9):
        J = np.asarray(jac_states(jnp.asarray(theta[i]), jnp.asarray(s0[i])))
        g_fwd = np.einsum("tk,tkp->p", w[i], J)
        np.testing.assert_allclose(g_rev[i], g_fwd, rtol=1e-9, atol=1e-9 * np.abs(g_fwd).max())


# ---------------------------------------------------------------------------------------------
# gradients against finite differences of the NumPy simulator
def _fd_jacobian(fun, theta, rel=1e-6):
    """Central differences of fun (4,) -> (...) with steps rel * max(|theta_i|, 1e-3)."""
    cols = []
    for i in range(4):
        h = rel * max(abs(theta[i]), 1e-3)
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        cols.append((fun(tp) - fun(tm)) / (2 * h))
    return np.stack(cols, axis=-1)


def _check_grad(jac_states, theta, s0, frames, idx=(0, 1)):
    """d state[frames, idx] / d theta: JAX (through the contact times) vs central differences
    of the NumPy simulator. Returns the JAX Jacobian, shape (len(frames), len(idx), 4)."""
    theta = np.asarray(theta, dtype=np.float64)
    s0 = np.asarray(s0, dtype=np.float64)
    sel = np.ix_(frames, idx)

    def np_fun(th):
        return P.simulate(th[None], s0[None], n_frames=N_GRAD)[0][sel]

    J = np.asarray(jac_states(jnp.asarray(theta), jnp.asarray(s0)))[sel]
    J_fd = _fd_jacobian(np_fun, theta)
    assert np.abs(J).max() > 0
    np.testing.assert_allclose(J, J_fd, rtol=2e-5, atol=2e-6 * np.abs(J_fd).max())
    return J


def test_gradient_in_free_flight(jac_states):
    # thrown up from the middle: no contact within 20 frames
    J = _check_grad(jac_states, [0.8, -9.81, 0.02, 0.3], [5.0, 5.0, 1.0, 2.0], frames=[5, 12, 19])
    assert np.all(J[..., [0, 3]] == 0.0)  # e and r do nothing in flight


def test_gradient_across_a_floor_bounce(jac_states):
    """Dropped from 2 m: the bounce falls inside a frame interval; positions 1-6 frames after it
    depend on e (rebound), g and d, also through the moving contact time."""
    theta = [0.8, -9.81, 0.02, 0.3]
    s0 = [5.0, 2.0, 1.5, 0.0]
    ref = P.simulate(np.array([theta]), np.array([s0]), n_frames=20)[0]
    k = int(np.argmin(ref[:, 1]))
    assert 0.0 < ref[k, 1] < 0.5 and ref[k + 1, 3] > 0  # bounced between frames k and k + 1
    J = _check_grad(jac_states, theta, s0, frames=[k + 1, k + 3, k + 6])
    assert np.abs(J[..., 0]).max() > 0.1  # e matters after the bounce


def test_gradient_across_a_wall_bounce(jac_states):
    theta = [0.8, -9.81, 0.03, 0.3]
    s0 = [8.5, 8.0, 6.0, 3.0]  # hits x = 10 after ~0.26 s
    ref = P.simulate(np.array([theta]), np.array([s0]), n_frames=15)[0]
    assert (ref[:, 2] < 0).any()  # reflected
    _check_grad(jac_states, theta, s0, frames=[7, 10, 14], idx=(0, 1, 2))


def test_gradient_while_rolling_to_a_stop(jac_states):
    """On the floor from the start: x at the end depends on r through the stopping time."""
    theta = [0.7, -9.81, 0.01, 0.4]
    s0 = [2.0, 0.0, 2.0, 0.0]
    ref = P.simulate(np.array([theta]), np.array([s0]), n_frames=N_GRAD)[0]
    assert ref[-1, 2] == 0.0  # stopped
    J = _check_grad(jac_states, theta, s0, frames=[20, 60, N_GRAD - 1], idx=(0,))
    np.testing.assert_allclose(J[-1, 0, 3], -(2.0**2) / (2 * 0.4**2), rtol=1e-6)  # d(v^2/2r)/dr


def test_gradient_of_whole_trajectories_matches_finite_differences(jac_states):
    """All positions of bouncing balls (several floor and wall contacts) up to the frame before
    they first come within 1 mm of the floor's rolling switch: smooth in theta, and the
    contact-time derivative gets it right."""
    rng = np.random.default_rng(12)
    theta = P.sample_theta(40, rng, subranges=(5, 7, 9))
    s0 = P.sample_state0(40, rng)
    ref = P.simulate(theta, s0, n_frames=N_GRAD)
    done = 0
    for i in range(40):
        on_floor = np.flatnonzero(np.abs(ref[i, :, 1]) < 1e-9)
        stop = on_floor[0] if on_floor.size else N_GRAD
        if stop < 60:
            continue
        n_contacts = (np.diff(np.sign(ref[i, :stop, 3])) > 0).sum() + (np.diff(np.sign(ref[i, :stop, 2])) != 0).sum()
        assert n_contacts >= 2
        _check_grad(jac_states, theta[i], s0[i], frames=list(range(stop)))
        done += 1
        if done == 5:
            break
    assert done == 5


# ---------------------------------------------------------------------------------------------
# limits and bad input
def test_too_many_contacts_is_reported_not_wrong(monkeypatch):
    theta = np.array([[0.95, -12.81, 0.0005, 0.1]])
    s0 = np.array([[0.0, 0.02, 15.0, 0.3]])
    states, bad = PJ.simulate_core(theta, s0, jnp.zeros(1), n_frames=50, dt=0.05, max_passes=1)
    assert bool(bad[0])
    assert np.isnan(np.asarray(states)[0, -1]).all()
    monkeypatch.setattr(PJ, "MAX_PASSES", 1)
    with pytest.raises(RuntimeError, match="contacts in one frame"):
        PJ.simulate(theta, s0, n_frames=50)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"theta": [[1.2, -9.8, 0.01, 0.1]]}, "theta"),
        ({"theta": [[0.8, 1.0, 0.01, 0.1]]}, "theta"),
        ({"theta": [[0.8, -9.8, 0.01]]}, "theta"),
        ({"state0": [[11.0, 5.0, 1.0, 1.0]]}, "state0"),
        ({"state0": [[np.nan, 5.0, 1.0, 1.0]]}, "state0"),
        ({"n_frames": 0}, "n_frames"),
        ({"dt": -0.1}, "dt"),
        ({"floor": [0.0, 1.0]}, "floor"),
    ],
)
def test_bad_input_names_the_argument(kwargs, match):
    args = {"theta": [[0.8, -9.8, 0.01, 0.1]], "state0": [[5.0, 5.0, 1.0, 1.0]]}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        PJ.simulate(**args)


def test_constants_come_from_the_numpy_module():
    assert PJ.PARAMS is P.PARAMS
    assert PJ.SUBSTEPS == P.SUBSTEPS and PJ.ROLL_SPEED == P.ROLL_SPEED and PJ.BOX_WIDTH == P.BOX_WIDTH
    assert PJ.MAX_PASSES >= P.SUBSTEPS + 2


# ---------------------------------------------------------------------------------------------
# speed (pytest-benchmark; skipped in the default run)
@pytest.fixture(scope="module")
def bench_cases():
    rng = np.random.default_rng(0)
    return P.sample_theta(2000, rng), P.sample_state0(2000, rng)


@pytest.mark.benchmark(group="physics-jax")
def test_bench_jax_simulate_2000x200(benchmark, bench_cases):
    """Jitted JAX simulator after compilation vs the NumPy simulator on the same 2000 balls."""
    import time

    theta, s0 = bench_cases
    th, s = jnp.asarray(theta), jnp.asarray(s0)
    fl = jnp.zeros(len(theta))

    def run():
        return PJ.simulate_core(th, s, fl)[0].block_until_ready()

    run()  # compile
    out = benchmark.pedantic(run, rounds=7, iterations=1, warmup_rounds=1)
    assert out.shape == (2000, 200, 4)
    t = []
    for _ in range(3):
        t0 = time.perf_counter()
        P.simulate(theta, s0)
        t.append(time.perf_counter() - t0)
    np_s, jax_s = float(np.median(t)), benchmark.stats.stats.median
    benchmark.extra_info.update({"numpy_median_s": np_s, "jax_median_s": jax_s, "numpy_over_jax": np_s / jax_s})
    print(f"\nJAX {jax_s * 1e3:.0f} ms, NumPy {np_s * 1e3:.0f} ms (NumPy/JAX = {np_s / jax_s:.2f})")


@pytest.mark.parametrize(
    "theta, state0, kwargs, name",
    [
        ([[0.8, -9.8, 0.01, 0.1]], [[5.0, 5.0, 1e6, 1.0]], {}, "state0"),
        ([[0.8, -9.8, 1e6, 0.1]], [[5.0, 5.0, 1.0, 1.0]], {}, "theta"),
        ([[0.8, -1e9, 0.01, 0.1]], [[5.0, 5.0, 1.0, 1.0]], {}, "theta"),
        ([[0.8, -9.8, 0.01, 0.1]], [[5.0, 5.0, 1.0, 1.0]], {"dt": 100.0}, "dt"),
        ([[0.8, -9.8, 0.01, 0.1]], [[5.0, 1e300, 1.0, 1.0]], {"floor": 1e300}, "floor"),
        ([[0.8, -9.8, 1.5, 0.1]], [[5.0, 5.0, 90.0, 90.0]], {}, "drag per integration step"),
    ],
)
def test_jax_twin_has_the_same_envelope(theta, state0, kwargs, name):
    with pytest.raises(ValueError, match=name):
        P.simulate(np.array(theta), np.array(state0), n_frames=5, **kwargs)
    with pytest.raises(ValueError, match=name):
        PJ.simulate(np.array(theta), np.array(state0), n_frames=5, **kwargs)
