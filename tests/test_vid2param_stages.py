"""The stages after Vid2Param's network (methods/vid2param/stages.py): the shipped checkpoints'
stage lists, the older format converted on load with the same numbers, one loop for batch and
stream, bad stage lists refused, and the fitting driver."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from methods.vid2param import SHIPPED_CHECKPOINTS, Vid2Param
from methods.vid2param.checkpoint import build_net, load_checkpoint, save_atomic
from methods.vid2param.stages import (
    LEGACY_KEYS,
    STAGES,
    Pipeline,
    Stage,
    register_stage,
)
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation

#: Each shipped checkpoint's stages (from the older format's keys, converted on load).
EXPECTED = {
    "28x28": ["std_scale", "prior_noise"],
    "camera": ["prior_noise", "drag_evidence", "physics_calibration"],
    "changing": [],
    **{f"sensitivity/{c}": ["prior_noise"] for c in (
        "extrapolation_e", "extrapolation_g", "extrapolation_d", "extrapolation_r", "noise_0",
        "noise_0.1", "noise_0.25", "noise_0.5", "simplified")},
}


def _shipped(name):
    path = SHIPPED_CHECKPOINTS.get(name)
    if path is None or not path.exists():
        pytest.skip(f"no shipped {name} checkpoint")
    return path


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_each_shipped_checkpoint_has_its_stages(name):
    path = _shipped(name)
    ck = load_checkpoint(path)
    net = build_net(ck, path)
    pipe = Pipeline.from_checkpoint(ck, name, net)
    assert pipe.names == EXPECTED[name]
    # every fitted record of the older format became a stage: none skipped
    assert len(pipe.names) == sum(bool(ck.get(k)) for k in LEGACY_KEYS)


def test_describe_checkpoints_gives_one_line_each():
    import methods

    lines = methods.get_class("vid2param").describe_checkpoints()
    assert set(lines) == set(SHIPPED_CHECKPOINTS)
    for name, line in lines.items():
        assert "\n" not in line and line.startswith("network (")
        assert [p.split()[0] for p in line.split(" [")[0].split(" -> ")[1:]] == EXPECTED[name]
    assert "rolling statistic 'fit'" in lines["camera"]


def test_sysid_bench_list_checkpoints_prints_one_line_each(capsys):
    from sysid_bench.apps.cli import main

    assert main(["list", "--checkpoints"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == len(SHIPPED_CHECKPOINTS)  # the three vid2param classes print once
    assert any(ln.startswith("vid2param camera: network (50x100") for ln in out)


def _staged_copy(src, dst):
    """The checkpoint at ``src`` in today's format: ``stages`` instead of the older keys."""
    ck = dict(load_checkpoint(src))
    pipe = Pipeline.from_checkpoint(ck, src, build_net(ck, src))
    for key in LEGACY_KEYS:
        ck.pop(key, None)
    ck["stages"] = pipe.records()
    save_atomic(ck, dst)
    return dst


@pytest.mark.parametrize("name", ["28x28", "camera"])
def test_a_checkpoint_in_either_format_answers_bitwise_the_same(name, tmp_path):
    path = _shipped(name)
    staged = _staged_copy(path, tmp_path / "staged.pt")
    old = Vid2Param(checkpoint=name, device="cpu", n_samples=8, threads=1)
    new = Vid2Param(checkpoint=staged, device="cpu", n_samples=8, threads=1)
    ds = make_dataset("test", 2, 31, size=old.frame_size,
                      nuisance=load_checkpoint(path)["train"].get("nuisance"), n_frames=90)
    frames = np.asarray(ds.frames)
    for a, b in zip(old.normalised_prefixes(frames, [30, 90]), new.normalised_prefixes(frames, [30, 90])):
        np.testing.assert_array_equal(a, b)
    sa, sb = old.stream(), new.stream()
    for f in frames[0]:
        pa, pb = sa.push(f), sb.push(f)
        np.testing.assert_array_equal(pa.mean, pb.mean)
        np.testing.assert_array_equal(pa.std, pb.std)
    fa, fb = sa.forecast(10), sb.forecast(10)
    np.testing.assert_array_equal(fa.samples, fb.samples)
    np.testing.assert_array_equal(old.physics_scale_, new.physics_scale_)


def test_batch_and_stream_run_the_same_loop():
    path = _shipped("camera")
    ck = load_checkpoint(path)
    net = build_net(ck, path)
    pipe = Pipeline.from_checkpoint(ck, path, net)
    # a std_scale stage in front of the camera's stages, so both kinds of stage are exercised
    std = STAGES["std_scale"]({"std_scale": [1.5, 0.5, 2.0, 1.0], "targets": ["e", "g", "d", "r"]})
    pipe = Pipeline([std, *pipe.stages])
    rng = np.random.default_rng(0)
    B, T, K = 3, 60, len(net.config.targets)
    mu = rng.uniform(0.1, 0.9, (B, T, K))
    sd = rng.uniform(0.01, 0.2, (B, T, K))
    # a flying track (x moves, heights spread) so that the drag statistic counts windows
    t = np.arange(T) * 0.05
    mu[..., 0] = (2.0 + 3.0 * t * (1 + 0.1 * np.arange(B)[:, None])) / 10
    mu[..., 1] = np.abs(np.sin(3 * t))[None] * 0.2
    m, s, pos = pipe.apply(mu.copy(), sd.copy(), net.config.targets)
    carries = pipe.start(B)
    idx = [net.config.targets.index(p) for p in ("e", "g", "d", "r")]
    for k in range(T):
        ms, ss = pipe.step(carries, mu[:, k, idx].copy(), sd[:, k, idx].copy(), pos[:, k])
        np.testing.assert_array_equal(ms, m[:, k])
        np.testing.assert_array_equal(ss, s[:, k])
    assert not np.array_equal(m[..., 2], mu[..., idx[2]])  # the drag evidence moved d


def test_unknown_or_misordered_stages_are_refused_naming_checkpoint_and_stage(tmp_path):
    path = _shipped("28x28")
    ck = dict(load_checkpoint(path))
    net = build_net(ck, path)
    records = Pipeline.from_checkpoint(ck, path, net).records()
    for key in LEGACY_KEYS:
        ck.pop(key, None)

    def load(stages, name):
        save_atomic({**ck, "stages": stages}, tmp_path / name)
        return Vid2Param(checkpoint=tmp_path / name, device="cpu").identify(
            Observation(frames=np.zeros((5, 28, 28), np.uint8)))

    with pytest.raises(ValueError, match=r"unknown\.pt: stage 1 'dragg' is unknown"):
        load([records[0], {"name": "dragg", "state": {}}], "unknown.pt")
    with pytest.raises(ValueError, match=r"twice\.pt: stage 1 'std_scale' appears twice"):
        load([records[0], records[0]], "twice.pt")
    with pytest.raises(ValueError, match=r"notalist\.pt: stages: expected a list"):
        load({"std_scale": 1}, "notalist.pt")
    with pytest.raises(ValueError, match=r"badstate\.pt: stage 'std_scale'.*finite"):
        load([{"name": "std_scale", "state": {"std_scale": [np.nan] * 6,
                                              "targets": list(net.config.targets)}}],
             "badstate.pt")
    # a network without a physics prior gives no "physics_prior" to the prior noise stage
    no_prior = {**ck, "config": {**ck["config"], "physics_prior": False},
                "state_dict": {k: v for k, v in ck["state_dict"].items()
                               if not k.startswith("phys_prior.")}}
    save_atomic({**no_prior, "stages": records}, tmp_path / "noprior.pt")
    with pytest.raises(ValueError, match=r"noprior\.pt: stage 1 'prior_noise' needs "
                                         r"\['physics_prior'\]"):
        Vid2Param(checkpoint=tmp_path / "noprior.pt", device="cpu")._ensure_net()

    # a stage whose input only a later stage gives
    @register_stage
    class NeedsNoise(Stage):
        name = "test_needs_forecast_noise"
        needs = frozenset({"forecast_noise"})

    try:
        with pytest.raises(ValueError, match=r"order\.pt: stage 1 'test_needs_forecast_noise' "
                                             r"needs \['forecast_noise'\]"):
            load([records[0], {"name": NeedsNoise.name, "state": {}}, records[1]], "order.pt")
        # after the stage that gives it, the same list loads
        load([*records, {"name": NeedsNoise.name, "state": {}}], "ordered.pt")
    finally:
        del STAGES[NeedsNoise.name]


@pytest.mark.slow
def test_the_driver_fits_every_stage_in_order_on_a_tiny_network(tmp_path):
    from methods.vid2param.model import V2PConfig
    from methods.vid2param.train import TrainConfig, export, train

    data = make_dataset("train", 4, 0, n_frames=24)
    cfg = V2PConfig(keypoints=1, roll_features=False, latent=8, hidden=16, feat=16,
                    channels=(4, 8))
    tc = TrainConfig(steps=2, batch=2, n_frames=24, val_n=0, warmup=1, min_obs=10)
    train(cfg, tc, dataset=data, out=tmp_path, progress=False, device="cpu", log=lambda s: None)
    out = export(tmp_path / "state.pt", tmp_path / "f.pt",
                 stages=[("std_scale", {"n": 3}),
                         ("prior_noise", {"steps": 2, "n_videos": 3, "n_val": 2, "particles": 4,
                                          "batch": 2, "horizon": 5, "obs_range": (40, 60)}),
                         ("drag_evidence", {"n_videos": 3, "n_val": 2}),
                         ("physics_calibration", {"n": 1})])
    names = ["std_scale", "prior_noise", "drag_evidence", "physics_calibration"]
    ck = load_checkpoint(out)
    assert [s["name"] for s in ck["stages"]] == names
    assert not any(k in ck for k in LEGACY_KEYS)
    # the prior noise stage owns the noise it trained, and the network carries the same
    noise = ck["stages"][1]["state"]["weights"]
    for k, v in noise.items():
        torch.testing.assert_close(ck["state_dict"]["phys_prior." + k], v, rtol=0, atol=0)
    est = Vid2Param(checkpoint=out, device="cpu", n_samples=0)
    est._ensure_net()
    assert est.pipeline_.names == names
    assert est.drag_ is not None and est.physics_scale_.shape == (4,)
    # refitting only the last stage keeps the others as they were
    again = tmp_path / "g.pt"
    from methods.vid2param.train import fit_stages

    fit_stages(out, again, ["std_scale:keep=true", "prior_noise:keep=true",
                            "drag_evidence:keep=true", "physics_calibration:n=1,seed=5"],
               log=lambda s: None)
    ck2 = load_checkpoint(again)
    assert [s["name"] for s in ck2["stages"]] == names
    assert ck2["stages"][2]["state"] == ck["stages"][2]["state"]
    assert ck2["stages"][3]["state"]["seed"] == 5
    fit_stages(out, tmp_path / "h.pt", ["std_scale:keep=true"], log=lambda s: None)
    with pytest.raises(ValueError, match=r"'drag_evidence' is to be kept, but checkpoint .*h\.pt"):
        fit_stages(tmp_path / "h.pt", tmp_path / "i.pt", ["drag_evidence:keep=true"])


def test_the_sensitivity_conditions_agree_with_the_benchmarks():
    # methods import no benchmark code, so the condition list and each condition's training
    # data are written in methods/vid2param; the benchmark (a test may import it) must agree
    from methods.vid2param.checkpoint import SENSITIVITY_CONDITIONS
    from methods.vid2param.conditions import condition_data, conditions_of
    from sysid_bench.bench.cases import get_scale
    from sysid_bench.bench.sensitivity import _train_spec

    assert list(SENSITIVITY_CONDITIONS) == get_scale("default").sensitivity_conditions()
    for c in SENSITIVITY_CONDITIONS:
        assert condition_data(c) == _train_spec(c)
    for system in ("pendulum", "spring", "collision"):
        assert list(conditions_of(system)) == get_scale("default").sensitivity_conditions(system)
        for c in conditions_of(system):
            assert condition_data(c, system) == _train_spec(c)
    with pytest.raises(ValueError, match="condition: expected one of"):
        condition_data("noise:0.3")
