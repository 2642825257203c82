"""The collision system: the public contract (``check_system``, one test per check), its physics
against the design's rules (closed forms between events, the contact and wall laws, energy, a
stopped puck hit by the other, the wall/puck/puck sequence, each against the solve_ivp
reference), the exact simulator's independence of dt, the JAX twin's gradients, the tracker on
touching pucks and on frames without pucks, the initial state from a track, and bad input."""

import numpy as np
import pytest

from sysid_bench.core import systems
from sysid_bench.core._system_checks import system_checks
from sysid_bench.core.systems import collision as col

SYS = systems.get("collision")
DT = 0.05
T = 200
R = col.R


def _sim(theta, state0, n_frames=T, dt=DT):
    return SYS.simulate(np.atleast_2d(theta), np.atleast_2d(state0), n_frames, dt)[0]


def _ref_err(theta, state0):
    ours = _sim(theta, state0)
    ref = SYS.reference(np.asarray(theta, float), np.asarray(state0, float), T, DT)
    return ours, float(np.abs(ours[:, [0, 2]] - ref[:, [0, 2]]).max())


@pytest.mark.parametrize("name, run", list(system_checks("collision")),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_check_system(name, run):
    run()


# ----------------------------------------------------------------------------------------------
# physics
def test_elastic_equal_masses_swap_velocities_in_closed_form():
    # no friction, lq = 0, eb = 1: contact at t* = 1.5 s (x1 = 5, x2 = 5.5), then the velocities
    # swap; puck 2 reaches its wall at 3.625 s
    s = _sim([0.0, 1.0, 0.0, 1.0], [2.0, 2.0, 7.0, -1.0])
    t = np.arange(T) * DT
    k = t < 3.6
    ts = 1.5
    x1 = np.where(t < ts, 2.0 + 2.0 * t, 5.0 - (t - ts))
    x2 = np.where(t < ts, 7.0 - t, 5.5 + 2.0 * (t - ts))
    assert np.abs(s[k, 0] - x1[k]).max() <= 1e-12
    assert np.abs(s[k, 2] - x2[k]).max() <= 1e-12
    assert s[k & (t > ts), 1] == pytest.approx(-1.0) and s[k & (t > ts), 3] == pytest.approx(2.0)


def test_friction_decelerates_then_stops_and_a_stopped_puck_is_hit():
    # puck 1 stops at 10/3 s at x = 1 + 1 / 0.6; puck 2 (9.5, -2.2) reaches it at ~3.93 s
    theta = [1.0, 0.8, 0.3, 0.9]
    state0 = [1.0, 1.0, 9.5, -2.2]
    s, err = _ref_err(theta, state0)
    t = np.arange(T) * DT
    mu = 0.3
    before = t < 3.9
    tc1 = np.minimum(t, 1.0 / mu)
    x1 = 1.0 + tc1 - 0.5 * mu * tc1**2
    x2 = 9.5 - 2.2 * t + 0.5 * mu * t**2
    assert np.abs(s[before, 0] - x1[before]).max() <= 1e-12
    assert np.abs(s[before, 2] - x2[before]).max() <= 1e-12
    stopped = (t > 1.0 / mu) & before
    assert stopped.sum() >= 10 and (s[stopped, 1] == 0.0).all()  # stopped for good...
    assert (s[t > 4.0, 1] < 0).any()  # ...until puck 2 hits it (puck 1 heavier: pushed left)
    assert err <= 1e-6


def test_contact_keeps_momentum_and_scales_the_closing_speed_by_eb():
    rng = np.random.default_rng(4)
    for _ in range(10):
        lq, eb = rng.uniform(-2, 2), rng.uniform(0.5, 1.0)
        state0 = SYS.sample_state0(1, rng)[0]
        s = _sim([lq, eb, 0.0, 1.0], state0)
        k = int(np.flatnonzero(s[:, 1] != state0[1])[0])  # first frame after the contact
        v1, v2 = s[k, 1], s[k, 3]
        if not (col.XL < s[k, 0] and s[k, 2] < col.XR and v1 > -1e3):
            continue
        if (np.sign(v1) != np.sign(s[k + 1, 1])) or (np.sign(v2) != np.sign(s[k + 1, 3])):
            continue  # a wall in the same frame: checked by the wall test
        m2 = 2.0**lq
        assert v1 + m2 * v2 == pytest.approx(state0[1] + m2 * state0[3], abs=1e-12)
        assert v2 - v1 == pytest.approx(eb * (state0[1] - state0[3]), abs=1e-12)


def test_wall_bounce_scales_the_speed_by_ew():
    # light puck 2 thrown right by a heavy puck 1, no friction: at its wall v2 <- -ew v2
    ew = 0.7
    s = _sim([-2.0, 0.9, 0.0, ew], [3.0, 3.0, 6.0, -1.0])
    v2 = s[:, 3]
    flip = np.flatnonzero((v2[:-1] > 0) & (v2[1:] < 0))
    assert flip.size >= 1
    k = flip[0]
    assert v2[k + 1] == pytest.approx(-ew * v2[k], abs=1e-12)
    assert np.abs(s[:, 2]).max() <= col.XR


def test_energy_never_grows_and_friction_ends_in_rest():
    rng = np.random.default_rng(5)
    theta = SYS.sample_theta(50, rng)
    theta[:, 2] = rng.uniform(0.1, 0.3, 50)
    s = SYS.simulate(theta, SYS.sample_state0(50, rng), 400)
    m2 = 2.0 ** theta[:, 0]
    e = 0.5 * (s[..., 1] ** 2 + m2[:, None] * s[..., 3] ** 2)
    assert (np.diff(e, axis=1) <= 1e-12).all()
    # 20 s at mu >= 0.1 stops pucks started at <= 4 m/s (bounces only lose speed)
    assert (s[:, -1, [1, 3]] == 0.0).all()
    assert (s[:, -1] == s[:, -2]).all()
    assert (s[..., 2] - s[..., 0] >= 2 * R - 1e-9).all()
    assert (s[..., 0] >= col.XL).all() and (s[..., 2] <= col.XR).all()


def test_wall_puck_puck_sequence_matches_the_reference():
    # heavy puck 2 drives the light puck 1 into its wall: a run of contacts, some in one frame
    theta = [2.0, 0.5, 0.05, 0.6]
    state0 = [1.0, 1.0, 3.0, -4.0]
    s, err = _ref_err(theta, state0)
    flips = int((np.diff(np.sign(s[:, 1])) != 0).sum())
    assert flips >= 4
    assert s[:, 0].min() == pytest.approx(col.XL, abs=0.05)
    assert err <= 1e-6


def test_reference_agreement_over_prior_cases_with_many_events():
    rng = np.random.default_rng(6)
    theta = SYS.sample_theta(4, rng)
    theta[:, 2] = [0.0, 0.02, 0.15, 0.3]
    state0 = SYS.sample_state0(4, rng)
    for i in range(4):
        assert _ref_err(theta[i], state0[i])[1] <= 1e-6


def test_exact_simulator_does_not_depend_on_dt():
    rng = np.random.default_rng(7)
    theta, state0 = SYS.sample_theta(20, rng), SYS.sample_state0(20, rng)
    coarse = SYS.simulate(theta, state0, 41, 0.25)
    fine = SYS.simulate(theta, state0, 1001, 0.01)[:, ::25]
    assert np.abs(coarse - fine).max() <= 1e-11


def test_time_varying_theta_holds_from_frame_to_frame():
    theta = np.array([[0.5, 0.8, 0.1, 0.9]])
    state0 = np.array([[2.0, 3.0, 7.0, -2.0]])
    varying = np.repeat(theta[:, None], 100, axis=1)
    varying[:, 50:, 2] = 0.3  # more friction from frame 50 on
    a = SYS.simulate(theta, state0, 100)
    b = SYS.simulate(varying, state0, 100)
    assert np.array_equal(a[:, :51], b[:, :51])
    assert not np.allclose(a[:, 60:], b[:, 60:])
    tail = SYS.simulate(np.full((1, 4), [0.5, 0.8, 0.3, 0.9]), a[:, 50], 50)
    assert np.abs(tail - b[:, 50:]).max() <= 1e-12


def test_inelastic_collapse_is_refused_not_simulated():
    # beyond the envelope (m2 = 10.7 m1, ew = 0.11) the light puck squeezed against its wall
    # collides without end at ~2.5 s; the kernel reports the trajectory instead of looping
    th = np.broadcast_to(np.array([3.414, 0.622, 0.233, 0.113]), (2, 60, 4)).copy()
    s0 = np.array([[2.0, 1.0, 7.0, -1.0], [3.982, 2.353, 6.030, -3.131]])
    out = np.empty((2, 60, 4))
    assert col._simulate_kernel(th, s0, 0.05, out) == 1
    with pytest.raises(ValueError, match="lq"):
        SYS.simulate(th[:, 0], s0, 10)


# ----------------------------------------------------------------------------------------------
# the JAX twin
@pytest.mark.slow  # compiles the reverse-mode scan (~10 s idle, minutes on a loaded machine)
def test_jax_twin_gradients_match_finite_differences_across_contacts():
    import jax
    import jax.numpy as jnp

    from sysid_bench.core.systems.collision_jax import simulate_core

    theta = np.array([0.7, 0.75, 0.12, 0.8])
    state0 = np.array([2.0, 3.0, 7.5, -2.5])

    @jax.jit
    def loss(th, s0):
        st, _ = simulate_core(th, s0, n_frames=120, dt=DT)
        return jnp.sum(st[:, 0] ** 2 + 0.5 * st[:, 2] ** 2)

    g_th, g_s0 = jax.grad(loss, argnums=(0, 1))(jnp.asarray(theta), jnp.asarray(state0))
    assert np.isfinite(g_th).all() and np.isfinite(g_s0).all()
    eps = 1e-6
    for k in range(4):
        d = np.zeros(4)
        d[k] = eps
        fd = (loss(theta + d, state0) - loss(theta - d, state0)) / (2 * eps)
        assert float(g_th[k]) == pytest.approx(float(fd), rel=1e-5, abs=1e-4)
        fd = (loss(theta, state0 + d) - loss(theta, state0 - d)) / (2 * eps)
        assert float(g_s0[k]) == pytest.approx(float(fd), rel=1e-5, abs=1e-4)


@pytest.mark.slow  # one more compilation of the twin
def test_jax_twin_marks_a_frame_short_of_passes_bad():
    import jax  # noqa: F401 (a dependency of [test]: missing fails, not skips)

    from sysid_bench.core.systems.collision_jax import simulate_core

    theta = np.array([2.0, 0.5, 0.05, 0.6])
    state0 = np.array([1.0, 1.0, 3.0, -4.0])  # first contact at 0.3 s
    st, bad = simulate_core(theta, state0, n_frames=60, dt=DT, max_passes=1)
    st = np.asarray(st)
    assert bool(bad)
    first = int(np.flatnonzero(np.isnan(st).any(axis=1))[0])
    assert first > 0 and np.isnan(st[first:]).all() and np.isfinite(st[:first]).all()


# ----------------------------------------------------------------------------------------------
# camera and tracker
def _touching_states():
    # touching pucks across the track, puck 1 at its wall, puck 2 at its wall
    x1 = np.array([col.XL, 1.37, 3.0, 4.911, 6.2, 8.0, col.XR - 2 * R])
    return np.stack([x1, np.zeros_like(x1), x1 + 2 * R, np.zeros_like(x1)], axis=-1)[None]


def test_tracker_stays_on_touching_pucks():
    st = _touching_states()
    theta = np.array([[0.0, 0.8, 0.1, 0.9]])
    truth = SYS.observe(st, theta)[0]
    px = SYS.size[1] / 10.0
    err = np.abs(SYS.track(SYS.render(st, theta)[0]) - truth) * px
    assert np.nanmax(err) <= 0.1 and np.isfinite(err).all()
    noisy = SYS.render(st, theta, noise=8.0, seed=1)[0]
    err = np.abs(SYS.track(noisy) - truth) * px
    assert np.nanmax(err) <= 0.3 and np.isfinite(err).all()


def test_tracker_round_trip_with_blur_and_noise():
    rng = np.random.default_rng(8)
    theta, state0 = SYS.sample_theta(3, rng), SYS.sample_state0(3, rng)
    st = SYS.simulate(theta, state0, 80)
    pts = SYS.observe(st, theta)
    frames = SYS.render(st, theta, blur=0.5, noise=8.0, seed=2)
    px = SYS.size[1] / 10.0
    for i in range(3):
        err = np.abs(SYS.track(frames[i]) - pts[i]) * px
        assert np.isfinite(err).all() and err.max() <= 0.5


def test_frames_without_pucks_give_nan():
    rng = np.random.default_rng(9)
    h, w = SYS.size
    frames = np.stack([
        np.zeros((h, w)), np.full((h, w), 255.0), rng.integers(0, 256, (h, w)),
        np.clip(rng.normal(0, 8, (h, w)), 0, 255), np.full((h, w), 130.0),
    ]).astype(np.uint8)
    assert np.isnan(SYS.track(frames)).all()


def test_a_hidden_puck_is_unseen_and_the_other_still_tracked():
    st = np.array([[[2.0, 0.0, 7.0, 0.0]]])
    theta = np.array([[0.0, 0.8, 0.1, 0.9]])
    fr = SYS.render(st, theta)[0].copy()
    fr[:, :, 70:] = 0  # puck 2 (x = 7 m -> column 89.6) blacked out
    tr = SYS.track(fr)
    assert np.isnan(tr[0, 1]).all()
    assert np.abs(tr[0, 0] - [2.0, R]).max() * 12.8 <= 0.1
    fr = SYS.render(st, theta)[0].copy()
    fr[:, :, :40] = 0  # puck 1 blacked out
    tr = SYS.track(fr)
    assert np.isnan(tr[0, 0]).all() and np.abs(tr[0, 1] - [7.0, R]).max() * 12.8 <= 0.1


def test_pucks_are_drawn_in_their_two_greys():
    st = np.array([[[2.0, 0.0, 7.0, 0.0]]])
    fr = SYS.render(st, np.array([[0.0, 0.8, 0.1, 0.9]]))[0, 0]
    assert fr[:, :40].max() == 255 and fr[:, 70:].max() == 130


def test_state0_from_track_boxes_the_truth():
    rng = np.random.default_rng(10)
    theta, state0 = SYS.sample_theta(40, rng), SYS.sample_state0(40, rng)
    pts = SYS.observe(SYS.simulate(theta, state0, 40), theta)
    pts = pts + rng.normal(0, SYS.noise_m, pts.shape)
    inside = 0
    for i in range(40):
        est, scale = SYS.state0_from_track(pts[i], DT)
        assert est.shape == (4,) and scale.shape == (4,) and (scale > 0).all()
        inside += bool((np.abs(est - state0[i]) <= scale).all())
    assert inside >= 38
    blind = np.full((40, 2, 2), np.nan)
    est, scale = SYS.state0_from_track(blind, DT)
    assert np.isfinite(est).all() and est[2] - est[0] >= 2 * R


# ----------------------------------------------------------------------------------------------
# bad input
def test_overlapping_pucks_are_refused():
    with pytest.raises(ValueError, match="state0.*x2 - x1.*collision"):
        SYS.simulate([[0.0, 0.8, 0.1, 0.9]], [[5.0, 1.0, 5.3, -1.0]], 5)


@pytest.mark.parametrize("theta, needle", [
    ([[0.0, 0.8, 0.1]], "theta"),
    ([[3.0, 0.8, 0.1, 0.9]], "lq"),
    ([[0.0, 1.2, 0.1, 0.9]], "eb"),
    ([[0.0, 0.8, -0.1, 0.9]], "mu"),
    ([[0.0, 0.8, 0.1, 0.3]], "ew"),
])
def test_theta_outside_the_envelope_is_refused(theta, needle):
    with pytest.raises(ValueError, match=needle) as info:
        SYS.simulate(theta, [[2.0, 1.0, 7.0, -1.0]], 5)
    assert "collision" in str(info.value)


def test_state_outside_the_track_is_refused():
    with pytest.raises(ValueError, match="x2"):
        SYS.simulate([[0.0, 0.8, 0.1, 0.9]], [[2.0, 1.0, 9.9, -1.0]], 5)
    with pytest.raises(ValueError, match="state0"):
        SYS.simulate([[0.0, 0.8, 0.1, 0.9]], [[2.0, 1.0, 7.0]], 5)


def test_unknown_nuisance_is_refused():
    st = np.array([[[2.0, 0.0, 7.0, 0.0]]])
    with pytest.raises(ValueError, match="nuisance"):
        SYS.render(st, np.array([[0.0, 0.8, 0.1, 0.9]]), glare=0.5)


def test_same_seed_same_bytes():
    a = SYS.sample_state0(5, 3), SYS.sample_theta(5, 3)
    b = SYS.sample_state0(5, 3), SYS.sample_theta(5, 3)
    assert a[0].tobytes() == b[0].tobytes() and a[1].tobytes() == b[1].tobytes()
    s = SYS.simulate(a[1], a[0], 30)
    f1 = SYS.render(s, a[1], blur=0.5, noise=8.0, drop=0.1, occlusion=0.1, seed=4)
    f2 = SYS.render(s, a[1], blur=0.5, noise=8.0, drop=0.1, occlusion=0.1, seed=4)
    assert f1.tobytes() == f2.tobytes()
