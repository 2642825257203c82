"""Vid2Param on the systems other than the ball: one network and stages for K points and P
parameters, one command that trains a system's model, the one estimator class on it
(``Vid2Param(system=S)``), n/a without a model, and a user's system with a checkpoint given."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import methods
from methods.vid2param import Vid2Param
from methods.vid2param._points import SYSTEM_CHECKPOINTS
from methods.vid2param.data import make_system_split
from methods.vid2param.model import V2PConfig, Vid2ParamNet, position_names
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation

#: a tiny network: small enough that two CPU steps take about a second
TINY = ["--hidden", "16", "--feat", "16", "--latent", "12", "--channels", "4", "--keypoints", "2",
        "--n-frames", "24", "--min-obs", "8", "--chunk", "8", "--val-n", "4", "--steps", "2",
        "--batch", "4", "--threads", "1", "--no-progress", "--no-resume",
        "--nll-only-steps", "2"]  # NLL-only throughout, as the presets' longer phase


@pytest.fixture(scope="module")
def collision_ckpt(tmp_path_factory):
    """A collision model (K = 2) trained for 2 steps by the one command, exported with its
    std_scale stage."""
    from methods.vid2param.train import main

    d = tmp_path_factory.mktemp("v2p_collision")
    out = d / "v2p_collision.pt"
    assert main(["--system", "collision", "--out", str(d / "run"), "--export", str(out),
                 "--stages", "std_scale:n=4", *TINY]) == 0
    return out


def test_system_config_targets_are_points_then_parameters():
    """Targets, the ball's parts off, bad configs refused, the ball's config unchanged."""
    c = V2PConfig.preset("collision")
    assert c.system == "collision" and c.n_points == 2
    assert c.targets == ("x", "y", "x1", "y1", "lq", "eb", "mu", "ew")
    assert c.params == ("lq", "eb", "mu", "ew") and not c.roll_features and not c.physics_prior
    assert V2PConfig.preset("pendulum").frame_size == (64, 64)
    assert position_names(3) == ("x", "y", "x1", "y1", "x2", "y2")
    # the ball's parts are refused on another system, a parameter of another system too
    with pytest.raises(ValueError, match="roll_features, physics_prior"):
        V2PConfig(system="spring", targets=("x", "y", "w2"))
    with pytest.raises(ValueError, match="targets"):
        V2PConfig(system="spring", targets=("x", "y", "e"), roll_features=False,
                  physics_prior=False)
    with pytest.raises(ValueError, match="unknown system"):
        V2PConfig(system="sprung", roll_features=False, physics_prior=False)
    # the ball's config is unchanged and round-trips; an old config (no system) is the ball's
    d = V2PConfig().to_dict()
    assert d["system"] == "ball" and d["targets"] == ["x", "y", "e", "g", "d", "r"]
    d.pop("system"), d.pop("kp_learn")
    assert V2PConfig.from_dict(d) == V2PConfig()


def test_system_targets_are_normalised_by_extent_and_prior():
    c = V2PConfig.preset("spring")
    ds = make_system_split("spring", "train", 3, 0, n_frames=10)
    tg = ds.targets(c.targets)
    x0, x1, _, _ = ds.system.extent
    np.testing.assert_allclose(tg[..., 0], (ds.points[..., 0, 0] - x0) / (x1 - x0), rtol=1e-5)
    np.testing.assert_allclose(tg[:, 0, 2:], ds.system.normalise(ds.theta), rtol=1e-5)
    assert ds.frames.shape == (3, 10, *ds.system.size)
    # the same videos whatever the threads drawing them
    again = make_system_split("spring", "train", 3, 0, n_frames=10, workers=2)
    assert np.array_equal(again.frames, ds.frames)


def test_network_carries_k_points():
    c = V2PConfig(**{**V2PConfig.preset("collision").to_dict(), "hidden": 8, "feat": 8,
                     "channels": [4], "latent": 10})
    net = Vid2ParamNet(c)
    rng = np.random.default_rng(0)
    fr = torch.as_tensor(rng.integers(0, 256, (2, 6, *c.frame_size), dtype=np.uint8))
    out = net(fr, torch.as_tensor(rng.random((2, 6, 8), dtype=np.float32)), n_obs=4)
    assert torch.isfinite(out["loss"]) and out["mse"].shape == (2, 8)
    mu, sd, state = net.filter(fr)
    assert mu.shape == (2, 6, 10) and state.last_pos.shape == (2, 4)
    m, s, z = net.rollout(state, 3)
    assert m.shape == (2, 3, 10) and ((m[..., :4] >= 0) & (m[..., :4] <= 1)).all()


@pytest.mark.slow  # the collision simulator's first call compiles (~20 s on a busy CPU)
def test_one_command_trains_exports_and_the_estimator_answers(collision_ckpt):
    card = json.loads(collision_ckpt.with_suffix(".json").read_text())
    assert card["config"]["system"] == "collision" and card["train"]["step"] == 2
    assert [s["name"] for s in card["stages"]] == ["std_scale"]
    est = methods.get("vid2param", system="collision", checkpoint=str(collision_ckpt))
    assert type(est) is Vid2Param and est.get_params()["system"] == "collision"
    ds = make_system_split("collision", "test", 2, 3, n_frames=24)
    obs = Observation(frames=ds.frames[0], dt=0.05, system="collision")
    post = est.identify(obs)
    sys_ = ds.system
    assert post.mean.shape == (4,) and post.samples.shape[1] == 4
    assert ((post.mean >= sys_.prior_lo) & (post.mean <= sys_.prior_hi)).all()
    assert (post.std > 0).all()
    pre = est.identify_prefixes(obs, [5, 24])
    np.testing.assert_allclose(pre[-1].mean, post.mean)
    fc = est.forecast(obs, 7)
    assert fc.mean.shape == (7, 2, 2) and fc.std.shape == (7, 2, 2)
    st = est.stream()
    for frame in ds.frames[0]:
        last = st.push(frame)
    assert st.n_frames == 24 and st.position().shape == (2,)
    np.testing.assert_allclose(last.mean, post.mean, rtol=1e-4, atol=1e-4 * sys_.prior_hi.max())
    assert st.forecast(3).mean.shape == (3, 2, 2)
    with pytest.raises(ValueError, match="frames"):
        est.identify(Observation(frames=np.zeros((5, 8, 8), np.uint8), dt=0.05,
                                 system="collision"))
    # a checkpoint of one system is refused for another
    with pytest.raises(ValueError, match="trained for the collision system"):
        methods.get("vid2param", system="spring", checkpoint=str(collision_ckpt))


def test_one_point_system_trains_identifies_streams_and_forecasts(tmp_path):
    """The spring (K = 1): 2 steps by the one command, then every answer's shape."""
    from methods.vid2param.train import main

    out = tmp_path / "v2p_spring.pt"
    assert main(["--system", "spring", "--out", str(tmp_path / "run"), "--export", str(out),
                 "--stages", "std_scale:n=4", *TINY]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["config"]["system"] == "spring" and card["train"]["step"] == 2
    est = methods.get("vid2param", system="spring", checkpoint=str(out))
    assert type(est) is Vid2Param
    ds = make_system_split("spring", "test", 1, 4, n_frames=12)
    obs = Observation(frames=ds.frames[0], dt=0.05, system="spring")
    post = est.identify(obs)
    assert post.mean.shape == (4,) and post.samples.shape == (200, 4) and (post.std > 0).all()
    # the one class's n_samples (200; the per-system class drew 256): the same draws, fewer
    more = methods.get("vid2param", system="spring", checkpoint=str(out), n_samples=256)
    assert np.array_equal(more.identify(obs).samples[:200], post.samples)
    # the ball's own parts are refused on the spring, naming them
    with pytest.raises(NotImplementedError, match="filtered_track reads the ball's model"):
        est.filtered_track(ds.frames[0])
    with pytest.raises(NotImplementedError, match="sysid-bench train --system spring"):
        est.fit(make_dataset("train", 1, 0, n_frames=5))
    with pytest.raises(ValueError, match="forecast: expected one of"):
        Vid2Param(system="spring", forecast="rollout")
    assert len(est.identify_prefixes(obs, [3, 12])) == 2
    fc = est.forecast(obs, 5)
    assert fc.mean.shape == (5, 2) and fc.std.shape == (5, 2)
    st = est.stream()
    for frame in ds.frames[0]:
        last = st.push(frame)
    np.testing.assert_allclose(last.mean, post.mean, rtol=1e-4, atol=1e-5)
    assert st.position().shape == (2,) and st.forecast(4).mean.shape == (4, 2)
    # on the CPU the push runs the NumPy FrameFilter, and its state forecasts as the batch pass
    assert st._fast is not None
    np.testing.assert_allclose(st.forecast(4).mean, est.forecast(obs, 4).mean, atol=1e-4)


def test_no_shipped_model_is_na_with_the_command():
    for name, path in SYSTEM_CHECKPOINTS.items():
        if path.exists():
            continue
        with pytest.raises(methods.NotAvailable, match=f"no Vid2Param model is shipped for "
                                                       f"{name}; train one with"):
            methods.get("vid2param", system=name)
        # the constructor only stores: the model is looked for on first use, n/a there too
        est = Vid2Param(system=name)
        assert est.get_params()["system"] == name and getattr(est, "points_", None) is None
        with pytest.raises(methods.NotAvailable, match="no model is shipped"):
            est.identify(Observation(frames=np.zeros((5, *est_size(name)), np.uint8),
                                     system=name))


def est_size(name):
    from sysid_bench.core import systems

    return systems.get(name).size


def test_one_class_declares_every_system_and_the_balls_variants_the_ball():
    """vid2param and vid2param-physics are one class each on any system (a checkpoint per
    system); -changing is the ball's (its changing-parameter model)."""
    from methods.vid2param import Vid2ParamChanging, Vid2ParamPhysics

    for name, cls in (("vid2param", Vid2Param), ("vid2param-physics", Vid2ParamPhysics)):
        assert methods.spec(name).systems == "any"
        for s in ("pendulum", "spring", "collision"):
            assert methods.get_class(name, system=s) is cls
    for cls, name in ((Vid2ParamChanging, "vid2param-changing"),):
        assert methods.spec(name).systems == ("ball",)
        with pytest.raises(methods.NotAvailable, match="runs on the ball system only"):
            methods.get(name, system="spring")
        with pytest.raises(ValueError, match="system: expected one of ball"):
            cls(system="spring")
    assert Vid2Param().get_params()["system"] == "ball"
    assert not hasattr(methods.Registration("x", "a:B"), "on_systems")


@pytest.fixture
def user_system(tmp_path, monkeypatch):
    """The ``decay`` system of docs/adding-a-system.md, registered as a user would."""
    import re
    import sys
    from pathlib import Path

    from sysid_bench.core import systems

    doc = Path(__file__).resolve().parents[1] / "docs" / "adding-a-system.md"
    module = re.findall(r"```python\n(.*?)```", doc.read_text(), flags=re.S)[0]
    (tmp_path / "toy_decay_v2p.py").write_text(module)
    monkeypatch.syspath_prepend(str(tmp_path))
    systems.register("decay", "toy_decay_v2p:Decay")
    yield "decay"
    systems.unregister("decay")
    sys.modules.pop("toy_decay_v2p", None)


def test_a_users_system_loads_its_checkpoint(user_system, tmp_path):
    """Issue 39, 4: a model for a system a user registered loads with
    ``methods.get("vid2param", system=S, checkpoint=F)`` and answers in its units (an
    untrained tiny network here: reachability and shapes, not accuracy)."""
    from methods.vid2param.checkpoint import FORMAT, FORMAT_VERSION, save_atomic
    from methods.vid2param.model import system_targets
    from sysid_bench.core import systems
    from sysid_bench.core.testing import estimator_checks

    sys_ = systems.get(user_system)
    with pytest.raises(methods.NotAvailable, match="n/a on the decay system: no model is shipped for it .pass checkpoint=F"):
        methods.get("vid2param", system=user_system)
    assert "check_on_system_decay" in dict(estimator_checks(methods.get("vid2param")))
    torch.manual_seed(0)
    cfg = V2PConfig(system=user_system, targets=system_targets(user_system),
                    frame_size=sys_.size, roll_features=False, physics_prior=False,
                    hidden=8, feat=8, channels=[4], latent=6)
    f = save_atomic({"format": FORMAT, "format_version": FORMAT_VERSION,
                     "config": cfg.to_dict(), "state_dict": Vid2ParamNet(cfg).state_dict()},
                    tmp_path / "v2p_decay.pt")
    est = methods.get("vid2param", system=user_system, checkpoint=str(f), n_samples=16)
    ds = make_system_split(user_system, "test", 1, 0, n_frames=10)
    obs = Observation(frames=ds.frames[0], system=user_system)
    post = est.identify(obs)
    assert post.system == user_system and post.mean.shape == (2,)
    assert post.samples.shape == (16, 2)
    assert ((post.mean >= sys_.prior_lo) & (post.mean <= sys_.prior_hi)).all()
    assert est.forecast(obs, 4).mean.shape == (4, 2)
    st = est.stream()
    for fr in ds.frames[0]:
        last = st.push(fr)
    np.testing.assert_allclose(last.mean, post.mean, rtol=1e-4, atol=1e-4)


def test_a_users_system_trains_by_the_one_command_and_its_file_answers(user_system, tmp_path,
                                                                       capsys):
    """Issue 39, 4: ``sysid-bench train --system S`` for a system a user registered (its preset
    derived from the ``System``), a small budget, a progress bar with the step, the time left
    and the latest validation nMSE; the exported file loads with ``methods.get("vid2param",
    system=S, checkpoint=F)`` and answers ``identify`` on the system's observation."""
    from sysid_bench.apps.cli import main
    from sysid_bench.core import systems

    out = tmp_path / "v2p_decay.pt"
    argv = ["train", "--system", user_system, "--out", str(tmp_path / "run"), "--export", str(out),
            "--stages", "std_scale:n=4", "--max-minutes", "5", "--val-every", "1",
            *[a for a in TINY if a != "--no-progress"]]
    assert main(argv) == 0
    bar = capsys.readouterr().err
    assert "2/2" in bar and "<00:00" in bar and "budget_left=" in bar
    card = json.loads(out.with_suffix(".json").read_text())
    # the bar's nMSE is the last validation's (step 2), averaged over the parameters
    last = card["val_metrics"]["nmse"]
    shown = np.mean(list(last[max(last, key=int)].values()))
    assert f"val_nmse={shown:.4f}" in bar
    assert card["config"]["system"] == user_system and card["train"]["step"] == 2
    assert card["train"]["command"].startswith(f"sysid-bench train --system {user_system}")
    est = methods.get("vid2param", system=user_system, checkpoint=str(out))
    sys_ = systems.get(user_system)
    ds = make_system_split(user_system, "test", 1, 5, n_frames=24)
    post = est.identify(Observation(frames=ds.frames[0], system=user_system))
    assert post.system == user_system and post.mean.shape == (len(sys_.params),)
    assert ((post.mean >= sys_.prior_lo) & (post.mean <= sys_.prior_hi)).all()
    assert (post.std > 0).all()


def test_the_benchmark_threads_option_reaches_the_n_a_sentence(tmp_path, monkeypatch):
    """The benchmark passes ``threads`` to every method that declares it; on a system without a
    shipped model that must still be n/a (NotImplementedError), not an options error."""
    import methods

    monkeypatch.setitem(SYSTEM_CHECKPOINTS, "collision", tmp_path / "no_model.pt")
    with pytest.raises(NotImplementedError, match="no model is shipped"):
        methods.get("vid2param", system="collision", threads=1)


def test_a_system_model_is_copied_and_pickled_as_the_harness_does():
    """The benchmark copies a fitted estimator per case and sends it to worker processes."""
    import copy
    import pickle

    import methods
    from sysid_bench.core.testing import contract_observation

    est = methods.get("vid2param", system="spring")
    est.fit(None)
    obs = contract_observation("both", "spring")
    want = est.identify(obs).mean
    for other in (copy.deepcopy(est), pickle.loads(pickle.dumps(est))):
        np.testing.assert_array_equal(other.identify(obs).mean, want)


def test_a_points_only_model_forecasts_with_the_simulator_and_continues_the_track():
    """The shipped pendulum model was trained on points alone (no pixel phase): its latent
    rollout is untrained, so its forecast runs the pendulum's simulator on the posterior's
    draws from the state fitted to the track; it continues the true trajectory, and asking for
    the latent rollout still gives it (far off)."""
    import methods
    from sysid_bench.core import systems
    from sysid_bench.core.estimator import Observation

    sys_ = systems.get("pendulum")
    est = methods.get("vid2param", system="pendulum")
    if not est._model().path.is_file() or est._model().latent_learnt:
        pytest.fail("the shipped pendulum model is expected, trained on points alone")
    theta, s0 = sys_.sample_cases(1, np.random.default_rng(3), split="test")
    states = sys_.simulate(theta, s0, 80, 0.05)
    truth = sys_.observe(states, theta)[0, :, 0]  # (80, 2) m
    frames = sys_.render(states[:, :60], theta)[0]
    obs = Observation(frames=frames, dt=0.05, system="pendulum")
    fc = est.forecast(obs, 20)
    assert fc.mean.shape == (20, 2) and fc.extras["forecast"] == "physics"
    assert fc.extras["n_simulations"] > 0 and fc.extras["state_fit_rms_m"] < 0.05
    err = np.abs(fc.mean - truth[60:]).max()
    assert err < 0.15, err  # metres, over 1 s of swing (L ~ 1-2 m)
    assert np.array_equal(fc.mean, est.forecast(obs, 20).mean)  # seeded
    latent = methods.get("vid2param", system="pendulum", forecast="latent").forecast(obs, 20)
    assert latent.extras.get("forecast") == "latent"


# ------------------------------------------------------------------------------------------
# vid2param-physics on another system: its physics fitted to the network's track
_PENDULUM = pytest.mark.skipif(not SYSTEM_CHECKPOINTS["pendulum"].is_file(),
                               reason="no shipped pendulum model")


@_PENDULUM
def test_vid2param_physics_fits_the_systems_physics_to_the_networks_track():
    from sysid_bench.core import systems

    est = methods.get("vid2param-physics", system="pendulum", n_samples=20)
    model = est._model()
    ds = make_system_split("pendulum", "test", 1, 7, 100, model.frame_size)
    obs = Observation(frames=np.asarray(ds.frames[0]), system="pendulum")
    p50, p100 = est.identify_prefixes(obs, [50, 100])
    sys_ = systems.get("pendulum")
    span, truth = sys_.prior_hi - sys_.prior_lo, np.asarray(ds.theta[0])
    net = model.identify_prefixes(obs, [100])[0]
    for p in (p50, p100):
        assert p.system == "pendulum" and p.check is not None and p.check.ok
        assert p.extras["n_simulations"] > 0 and p.samples.shape == (20, 4)
        assert p.extras["physics_calibration"] == "v2p_pendulum_physics.json"
        assert np.all(np.abs(p.mean - truth) <= 4 * p.std), (p.mean, p.std, truth)
    # the physics reads b and mu that the network leaves near guessing
    assert np.mean(((p100.mean - truth) / span) ** 2) < 1e-3
    assert np.mean(((p100.mean - truth) / span) ** 2) < np.mean(((net.mean - truth) / span) ** 2)
    fc = est.forecast(obs, 5)
    assert fc.mean.shape == (5, 2) and np.isfinite(fc.mean).all()
    assert est.identify(obs).mean.tolist() == p100.mean.tolist()


@pytest.mark.skipif(not SYSTEM_CHECKPOINTS["collision"].is_file(),
                    reason="no shipped collision model")
def test_vid2param_physics_answers_the_prior_for_what_the_track_does_not_inform():
    """Test video 1 of seed 2024: in its first 50 frames no cart reaches a wall, so ew is not
    informed (the fit left it at an end of its range, 3.4 of its stds from the truth)."""
    from sysid_bench.core import systems

    est = methods.get("vid2param-physics", system="collision", n_samples=20)
    ds = make_system_split("collision", "test", 4, 2024, 200, est._model().frame_size)
    obs = Observation(frames=np.asarray(ds.frames[1]), system="collision")
    post = est.identify_prefixes(obs, [50])[0]
    sys_ = systems.get("collision")
    flat = [sys_.params.index(q) for q in post.extras["uninformed"]]
    assert flat == [sys_.params.index("ew")]
    assert abs(post.mean[flat[0]] - ds.theta[1][flat[0]]) < 2 * post.std[flat[0]]
    lo, span = sys_.prior_lo[flat], (sys_.prior_hi - sys_.prior_lo)[flat]
    np.testing.assert_allclose(post.mean[flat], lo + span / 2)
    np.testing.assert_allclose(post.std[flat], span / np.sqrt(12.0))
    assert np.all((post.samples[:, flat] >= lo) & (post.samples[:, flat] <= lo + span))


@_PENDULUM
def test_vid2param_physics_reads_no_calibration_made_for_another_checkpoint(tmp_path):
    import shutil

    ck = tmp_path / "mine.pt"
    shutil.copy(SYSTEM_CHECKPOINTS["pendulum"], ck)
    cal = json.loads(SYSTEM_CHECKPOINTS["pendulum"].with_name(
        "v2p_pendulum_physics.json").read_text())
    (tmp_path / "mine_physics.json").write_text(json.dumps({**cal, "checkpoint_sha256": "0" * 64}))
    est = methods.get("vid2param-physics", system="pendulum", checkpoint=ck)
    f, source = est._model().physics_scale()
    assert f.tolist() == [1.0] * 4 and "another checkpoint" in source
    (tmp_path / "mine_physics.json").write_text("{not json")
    est = methods.get("vid2param-physics", system="pendulum", checkpoint=ck)
    with pytest.raises(ValueError, match="mine_physics.json: expected vid2param-physics"):
        est._model().physics_scale()
