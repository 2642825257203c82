"""Experiment 4 (sensitivity): ready-trained condition models, and a reading that says whether
each of the paper's claims holds, by a stated rule."""

import numpy as np
import pandas as pd
import pytest

import methods
from sysid_bench.bench.cases import get_scale
from sysid_bench.bench.experiment import Context
from sysid_bench.bench.sensitivity import Sensitivity, conditions, trained_model
from sysid_bench.estimator import Estimator, Posterior
from sysid_bench.physics import PARAMS
from sysid_bench.spec import spec_of


def _rows(cond, se_by_param, n_cases=20, n_frames=50, distance=None, seed=0):
    rng = np.random.default_rng(seed)
    recs = []
    for i in range(n_cases):
        vals = {p: max(0.0, v * (1 + 0.1 * rng.standard_normal())) for p, v in se_by_param.items()}
        for p, v in vals.items():
            recs.append(dict(method="m", condition=cond, case=i, n_frames=n_frames,
                             metric=f"se_{p}", value=v))
        recs.append(dict(method="m", condition=cond, case=i, n_frames=n_frames, metric="se",
                         value=float(np.mean(list(vals.values())))))
        if distance is not None:
            recs.append(dict(method="m", condition=cond, case=i, n_frames=0, metric="distance",
                             value=float(distance[i])))
    return recs


def _frame(*parts):
    return pd.DataFrame([r for p in parts for r in p])


GOOD = {"e": 0.01, "g": 0.002, "d": 0.01, "r": 0.05}


def test_reading_states_the_control_and_whether_label_noise_claim_holds():
    df = _frame(_rows("noise:0", GOOD), _rows("noise:0.5", {k: 1.5 * v for k, v in GOOD.items()}))
    lines = Sensitivity().reading(df)
    assert lines[0].startswith("Control (clean labels, full physics)")
    noise = [ln for ln in lines if "label noise" in ln]
    assert len(noise) == 1 and "Holds" in noise[0] and "Does not" not in noise[0]


def test_reading_says_when_label_noise_claim_does_not_hold():
    df = _frame(_rows("noise:0", GOOD), _rows("noise:0.5", {k: 4 * v for k, v in GOOD.items()}))
    noise = [ln for ln in Sensitivity().reading(df) if "label noise" in ln]
    assert "Does not hold" in noise[0]


def test_reading_warns_when_the_control_is_at_guessing_level():
    bad = {p: 0.08 for p in PARAMS}
    lines = Sensitivity().reading(_frame(_rows("noise:0", bad), _rows("noise:0.5", bad)))
    assert lines[0].startswith("CAVEAT")


def test_extrapolation_rule_compares_with_answering_the_training_range_edge():
    d = np.r_[np.full(10, 0.05), np.full(10, 0.4)]
    # an extrapolating model: small error far out (0.4^2 = 0.16 would be "stuck at the edge")
    far_ok = _rows("extrapolation:e", {"e": 0.02, "g": 0.01, "d": 0.01, "r": 0.05}, distance=d)
    line = [ln for ln in Sensitivity().reading(_frame(_rows("noise:0", GOOD), far_ok))
            if "extrapolation" in ln][0]
    assert "Holds" in line
    stuck = [dict(r) for r in far_ok]
    for r in stuck:
        if r["metric"] == "se_e" and r["case"] >= 10:
            r["value"] = 0.16
    line = [ln for ln in Sensitivity().reading(_frame(_rows("noise:0", GOOD), stuck))
            if "extrapolation" in ln][0]
    assert "Does not hold" in line


def test_simplified_rule():
    ok = _frame(_rows("noise:0", GOOD), _rows("simplified", {**GOOD, "e": 0.015}))
    assert "Holds" in [ln for ln in Sensitivity().reading(ok) if "simpler physics" in ln][0]
    bad = _frame(_rows("noise:0", GOOD), _rows("simplified", {**GOOD, "e": 0.06}))
    assert "Does not hold" in [ln for ln in Sensitivity().reading(bad) if "simpler physics" in ln][0]


def test_default_scale_has_every_condition_of_the_paper():
    got = conditions(get_scale("default"))
    assert set(got) == {"extrapolation:e", "extrapolation:g", "extrapolation:d", "extrapolation:r",
                        "noise:0", "noise:0.1", "noise:0.25", "noise:0.5", "simplified"}


# -- the `pretrained` declaration -------------------------------------------------------------
class _Trainable(Estimator):
    name = "toy-trainable"
    trains = True
    inline = True
    pretrained = {"default": {"noise:0": {"level": 0.25}}}

    def __init__(self, level: float = 0.5, seed: int = 0):
        self.level = level
        self.seed = seed

    def fit(self, train=None):
        self.fitted_ = True
        return self

    def identify(self, obs):
        return Posterior(mean=np.full(4, self.level), std=np.ones(4))

    def training_wall_s(self):
        return 12.5


def test_pretrained_is_checked_and_read_per_scale_and_condition():
    spec = spec_of(_Trainable)
    assert spec.pretrained_options("default", "noise:0") == {"level": 0.25}
    assert spec.pretrained_options("default", "simplified") is None
    assert spec.pretrained_options("paper", "noise:0") is None

    class Bad(_Trainable):
        pretrained = {"default": {"noise:0": {"nope": 1}}}

    with pytest.raises(ValueError, match=r"Bad\.pretrained\['default'\].*nope"):
        spec_of(Bad)

    class Bad2(_Trainable):
        pretrained = ["noise:0"]

    with pytest.raises(ValueError, match=r"Bad2\.pretrained"):
        spec_of(Bad2)


def test_sensitivity_loads_a_declared_model_instead_of_training(tmp_path):
    methods.register("toy-trainable", f"{__name__}:_Trainable")
    try:
        ctx = Context(get_scale("default"), tmp_path)
        est, wall = trained_model(ctx, "toy-trainable", "noise:0")
        assert est.level == 0.25 and wall == 12.5
        assert not (tmp_path / "models").exists()  # nothing trained, nothing pickled
    finally:
        methods.unregister("toy-trainable")


def test_vid2param_declares_only_condition_checkpoints_it_ships():
    from methods.vid2param.estimator import (
        SENSITIVITY_CONDITIONS,
        SHIPPED_CHECKPOINTS,
        condition_checkpoint,
    )

    declared = methods.spec("vid2param").pretrained.get("default", {})
    # all conditions or none: one budget for every condition
    assert set(declared) in (set(), set(SENSITIVITY_CONDITIONS))
    for cond, opts in declared.items():
        assert opts["checkpoint"] == condition_checkpoint(cond)
        assert SHIPPED_CHECKPOINTS[opts["checkpoint"]].exists()


def test_conditions_driver_refuses_unknown_conditions():
    pytest.importorskip("torch")
    from methods.vid2param.conditions import condition_data, main

    assert condition_data("extrapolation:g") == ("extrapolation", {"param": "g"})
    with pytest.raises(ValueError, match="condition: expected one of"):
        condition_data("noise:0.3")
    with pytest.raises(ValueError, match="condition"):
        main(["--out", "unused", "--only", "noise:0", "bogus"])


def test_training_config_takes_a_data_variant():
    pytest.importorskip("torch")
    from methods.vid2param.train import TrainConfig, _Feed

    with pytest.raises(ValueError, match="variant: expected one of"):
        TrainConfig(variant="bogus")
    tc = TrainConfig(variant="extrapolation", variant_options={"param": "e"}, chunk=8, batch=4,
                     n_frames=10)
    frames, targets = _Feed(tc, ("x", "y", "e", "g", "d", "r")).batch(0)
    assert frames.shape == (4, 10, 28, 28)
    # trained on the lower half of e's range only: normalised e below 0.5
    assert (targets[..., 2] <= 0.5 + 1e-6).all()



def test_no_verdict_when_the_control_is_at_guessing_level():
    bad = {p: 0.08 for p in PARAMS}
    lines = Sensitivity().reading(_frame(_rows("noise:0", bad), _rows("noise:0.5", bad),
                                         _rows("simplified", bad)))
    assert all("Holds" not in ln and "Does not hold" not in ln for ln in lines)
    assert sum("Cannot tell" in ln for ln in lines) == 2
