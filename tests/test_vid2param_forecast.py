"""Vid2Param's forecasts: the state fit, the physics prior, both forecast kinds, the stream."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import methods
from methods.vid2param import FORECASTS, SHIPPED_CHECKPOINTS, V2PConfig
from methods.vid2param.rollout import backtest_error, fit_state, sample_trajectories
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation
from sysid_bench.core.metrics import position_mse
from sysid_bench.core.physics import simulate, simulate_perturbed

needs_shipped = pytest.mark.skipif(not SHIPPED_CHECKPOINTS["28x28"].exists(),
                                   reason="shipped checkpoint missing")
THETA = np.array([0.8, -9.81, 0.02, 0.3])
STD = np.array([0.01, 0.07, 0.003, 0.15])


def _track(state0, n=60, noise=0.005, seed=0):
    states = simulate(THETA[None], np.asarray(state0, float)[None], n)[0]
    rng = np.random.default_rng(seed)
    return states, states[:, :2] + noise * rng.standard_normal((n, 2))


@pytest.mark.parametrize("state0", [[2.0, 6.0, 5.0, 3.5], [8.0, 1.0, -6.0, -4.0]])
def test_fit_state_recovers_the_state_through_bounces_and_walls(state0):
    states, pos = _track(state0)
    fit = fit_state(pos, THETA, STD)
    truth = states[fit.start]
    assert np.abs(fit.state0[:2] - truth[:2]).max() < 0.02
    assert np.abs(fit.state0[2:] - truth[2:]).max() < 0.2
    # e, g, d stay near the (right) network posterior, r where the window says nothing
    assert abs(fit.theta[3] - THETA[3]) < 0.05
    sd = np.sqrt(np.diag(fit.cov))
    assert (sd > 0).all() and sd[2] < 0.5


def test_fit_state_finds_a_raised_floor_from_a_bounce():
    states, pos = _track([3.0, 1.5, 4.0, -3.0])
    raised = pos - [0.0, 0.6]  # heights read above a floor 0.6 m higher than the truth's
    fit = fit_state(raised, THETA, STD, floor=(0.0, 0.3))
    assert abs(fit.floor + 0.6) < 0.03
    assert abs(fit.state0[1] - states[fit.start, 1]) < 0.03


def test_fit_state_drops_misread_frames():
    # two frames a metre off (an occluded or dropped frame misread by the network) must not
    # drag the fit: e (from the bounce in the window) and the state as without them
    states, pos = _track([3.0, 1.5, 4.0, -3.0])
    prior_e = THETA.copy()
    prior_e[0] = 0.7  # the network's e is off; the bounce in the window corrects it
    std = STD.copy()
    std[0] = 0.1
    clean = fit_state(pos, prior_e, std)
    bad = pos.copy()
    bad[-12] += [0.0, -1.2]
    bad[-20] += [0.4, 0.9]
    fit = fit_state(bad, prior_e, std)
    assert fit.n_used == clean.n_used - 2
    assert abs(fit.theta[0] - clean.theta[0]) < 0.01
    assert abs(fit.theta[0] - THETA[0]) < 0.03
    assert np.abs(fit.state0 - clean.state0).max() < 0.02
    assert fit.sigma < 0.02


def test_fit_state_caps_the_spread_the_window_leaves_open_and_handles_unseen_frames():
    # a ball rolling on the floor: vy is not seen (a hop changes no position to first order)
    states = simulate(THETA[None], np.array([[2.0, 0.0, 3.0, 0.0]]), 40)[0]
    pos = states[:, :2].copy()
    pos[5:12] = np.nan
    fit = fit_state(pos, THETA, STD)
    assert np.sqrt(fit.cov[3, 3]) <= 1.0 + 1e-9
    none = fit_state(np.full((10, 2), np.nan), THETA, STD)  # nothing seen: wide, at rest
    assert none.n_used == 0 and none.cov[2, 2] >= 16.0


def test_sampled_trajectories_start_at_the_last_frame_and_are_seeded():
    _, pos = _track([2.0, 6.0, 5.0, 3.5])
    fit = fit_state(pos, THETA, STD)
    a, th, fl = sample_trajectories(fit, len(pos), 20, 16, np.random.default_rng(3))
    b, _, _ = sample_trajectories(fit, len(pos), 20, 16, np.random.default_rng(3))
    assert np.abs(fl).max() < 0.05  # the floor's prior is 0 +- 5 mm
    assert a.shape == (16, 21, 4) and th.shape == (16, 4)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a[:, 0, :2].mean(0) - pos[-1]).max() < 0.05


def test_physics_prior_without_noise_is_the_simulator():
    from methods.vid2param.model import Vid2ParamNet

    net = Vid2ParamNet(V2PConfig(latent=8, hidden=16, feat=16, channels=(4, 8)))
    s0 = np.array([[2.0, 6.0, 5.0, 3.5], [8.0, 1.0, -6.0, -4.0]])
    th = np.tile(THETA, (2, 1))
    with torch.no_grad():
        mean, std, states = net.rollout_physics(torch.tensor(s0, dtype=torch.float64),
                                                torch.tensor(th, dtype=torch.float64), 30,
                                                sample=False)
    want = simulate(th, s0, 31)[:, 1:]
    np.testing.assert_allclose(states.numpy(), want, atol=1e-9)
    assert (std > 0).all()


def test_backtest_error_tells_a_ball_our_physics_misses_from_one_it_predicts():
    s0 = np.array([[2.0, 6.0, 5.0, 3.5]])
    rng = np.random.default_rng(0)
    ours = simulate(THETA[None], s0, 90)[0, :, :2] + 0.005 * rng.standard_normal((90, 2))
    spun = simulate_perturbed(THETA[None], s0, spin=0.3, dwell=0.01, n_frames=90)[0, :, :2]
    assert backtest_error(ours, THETA, STD) < 0.03
    assert backtest_error(spun, THETA, STD) > 5 * backtest_error(ours, THETA, STD)
    assert np.isnan(backtest_error(ours[:10], THETA, STD))  # too short to hold frames out
    held_out_unseen = ours.copy()
    held_out_unseen[-30:] = np.nan
    assert np.isnan(backtest_error(held_out_unseen, THETA, STD))


def test_physics_prior_noise_scales_with_the_backtest_by_its_gain():
    from methods.vid2param.prior import SKILL_REF, PhysicsPrior

    prior = PhysicsPrior().double()
    s0 = torch.tensor([[2.0, 6.0, 5.0, 3.5], [2.0, 6.0, 5.0, 3.5]], dtype=torch.float64)
    th = torch.tensor(np.tile(THETA, (2, 1)))
    skill = torch.tensor([SKILL_REF * 4, float("nan")], dtype=torch.float64)
    with torch.no_grad():
        _, base = prior(s0, th, 0.05)
        _, same = prior(s0, th, 0.05, skill)  # a gain of 0 (older priors) ignores it
        prior.skill_gain.fill_(0.5)
        mean, scaled = prior(s0, th, 0.05, skill)
    torch.testing.assert_close(same, base)
    torch.testing.assert_close(scaled[0], 2.0 * base[0])  # (4 ref / ref) ** 0.5
    torch.testing.assert_close(scaled[1], base[1])  # unknown backtest: the reference noise


def test_a_prior_saved_before_the_gain_existed_loads_ignoring_the_backtest():
    from methods.vid2param.checkpoint import build_net
    from methods.vid2param.model import Vid2ParamNet

    cfg = V2PConfig(latent=8, hidden=16, feat=16, channels=(4, 8), physics_prior=True)
    old = {k: v for k, v in Vid2ParamNet(cfg).state_dict().items() if k != "phys_prior.skill_gain"}
    net = build_net({"config": cfg.to_dict(), "state_dict": old})
    assert (net.phys_prior.skill_gain == 0).all()


def test_unknown_forecast_kind_lists_the_known_ones():
    with pytest.raises(ValueError, match="forecast: expected one of .*latent.*physics"):
        methods.get("vid2param", forecast="rollout")
    est = methods.get("vid2param", forecast="physics")
    assert est.get_params()["forecast"] == "physics" and set(FORECASTS) == {"latent", "physics"}
    with pytest.raises(ValueError, match="forecast"):
        est.set_params(forecast="nope")


def test_a_config_missing_fields_is_refused_naming_them():
    d = V2PConfig().to_dict()
    del d["kp_visibility"], d["physics_prior"]
    with pytest.raises(ValueError, match=r"lacks fields \['kp_visibility'\]"):
        V2PConfig.from_dict(d)
    # a field added later takes the value that reproduces older checkpoints
    d = V2PConfig().to_dict()
    del d["physics_prior"]
    assert V2PConfig.from_dict(d).physics_prior is False
    with pytest.raises(ValueError, match="preset"):
        V2PConfig.preset("huge")


@needs_shipped
def test_shipped_config_is_the_default():
    est = methods.get("vid2param")
    est._ensure_net()
    assert est.config_ == V2PConfig()


@pytest.fixture(scope="module")
def test_videos():
    return make_dataset("test", n=4, seed=11, n_frames=150)


@needs_shipped
@pytest.mark.parametrize("kind", ["physics", "latent"])
def test_forecasts_beat_lsq_on_the_same_video(kind, test_videos):
    ds = test_videos
    v2p = methods.get("vid2param", forecast=kind, n_samples=50)
    lsq = methods.get("lsq")
    ours, theirs, inside = [], [], []
    for i in range(len(ds.states)):
        obs = Observation(frames=np.asarray(ds.frames[i, :50]), floor=float(ds.floor[i]))
        truth = ds.states[i, 50:150, :2]
        fc = v2p.forecast(obs, 100)
        assert fc.mean.shape == (100, 2) and fc.samples.shape == (50, 100, 2)
        ours.append(position_mse(truth, fc.mean))
        theirs.append(position_mse(truth, lsq.forecast(obs, 100).mean))
        inside.append(np.mean(np.abs(truth - fc.mean) <= 1.645 * fc.std + 1e-9))
    assert np.mean(ours) < np.mean(theirs)
    assert np.mean(inside) > 0.6


@needs_shipped
def test_stream_forecast_is_the_forecast_of_the_pushed_frames(test_videos):
    frames = np.asarray(test_videos.frames[0, :60])
    est = methods.get("vid2param", forecast="physics", n_samples=20)
    s = est.stream()
    with pytest.raises(ValueError, match="push"):
        s.forecast(5)
    for f in frames:
        s.push(f)
    a = s.forecast(30)
    b = est.forecast(Observation(frames=frames), 30)
    np.testing.assert_allclose(a.mean, b.mean, atol=1e-3)
    np.testing.assert_allclose(a.std, b.std, atol=1e-3)


def test_prior_calibration_gives_each_half_of_the_backtest_its_coverage():
    # balls our physics predicts (small backtest error) and balls it misses (spin, soft
    # contacts: large backtest error); one noise cannot serve both, the calibrated scale can
    from methods.vid2param.fit_prior import PriorFitConfig, _coverage_by_skill, calibrate
    from methods.vid2param.model import Vid2ParamNet

    rng = np.random.default_rng(5)
    n, P, H = 40, 16, 60
    cfg = PriorFitConfig(particles=P, horizon=H, seed=0)
    net = Vid2ParamNet(V2PConfig(latent=8, hidden=16, feat=16, channels=(4, 8), physics_prior=True))
    pool = {"phys": [], "theta": [], "truth": [], "skill": []}
    for i in range(n):
        s0 = np.array([rng.uniform(1, 9), rng.uniform(1, 8), rng.uniform(-6, 6), rng.uniform(-3, 3)])
        deviates = i % 2 == 1
        truth = (simulate_perturbed(THETA[None], s0[None], spin=rng.uniform(0.1, 0.3),
                                    dwell=rng.uniform(0, 0.01), n_frames=H + 1)
                 if deviates else simulate(THETA[None], s0[None], H + 1))[0, 1:, :2]
        truth = truth + 0.02 * rng.standard_normal(truth.shape)  # more than the particles' 1 cm
        pool["phys"].append(s0 + [0.01, 0.01, 0.02, 0.02] * rng.standard_normal((P, 4)))
        pool["theta"].append(np.tile(THETA, (P, 1)))
        pool["truth"].append(truth)
        pool["skill"].append(rng.uniform(0.15, 0.4) if deviates else rng.uniform(0.005, 0.02))
    rec = calibrate(net, pool, cfg, log=lambda *a: None)
    cov = _coverage_by_skill(net, pool, cfg, rec["split_m"])
    assert 0.05 < rec["split_m"] < 0.15
    # the scale is set at each half's median backtest and is log-linear in between, so a
    # half's coverage lands near, not on, the level (0.86 here, 0.90 on the 28x28 model's)
    assert abs(cov["above"] - 0.9) < 0.06
    assert abs(cov["below"] - 0.9) < 0.06
    assert rec["slope"] > 0  # the worse the backtest, the wider the bands
