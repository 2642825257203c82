"""Experiment 5 on every system: its own test cases everywhere, the off-model clips where the
system declares them (``System.calibration_conditions``: the ball's)."""

import pandas as pd
import pytest

from sysid_bench.bench.calibration import MEANINGLESS, PERTURBED, Calibration
from sysid_bench.bench.cases import SCALES
from sysid_bench.bench.experiment import Cell, Context
from sysid_bench.core import systems


def test_every_system_gets_its_test_cases_and_only_the_ball_its_perturbed_and_meaningless():
    sc = SCALES["default"]
    exp = Calibration()
    assert exp.runs_on("pendulum") and exp.runs_on("ball")
    pend = exp.cells(sc, ["lsq", "nuts"], "pendulum")
    assert {c.system for c in pend} == {"pendulum"}
    assert {c.condition for c in pend} == {""}
    per = pd.Series([c.method for c in pend]).value_counts()
    assert per["lsq"] == sc.n_for("calibration", "pendulum") == 4
    assert per["nuts"] == 3  # the reference's declared cap
    ball = exp.cells(sc, ["lsq"], "ball")
    assert {c.condition for c in ball} == {"", PERTURBED, MEANINGLESS}


def test_a_pendulum_cell_scores_the_pendulums_parameters_and_refuses_an_undeclared_condition(
        tmp_path):
    ctx = Context(SCALES["smoke"], tmp_path, 1)
    out = Calibration().run(Cell("calibration", "lsq", "video", "", 0, "pendulum"), ctx)
    metrics = {r.metric for r in out.rows}
    params = systems.get("pendulum").params
    assert {f"hit90_{p}" for p in params} <= metrics and "hit90_e" not in metrics
    df = pd.DataFrame([("pendulum", "lsq", "video", "", r.case, r.n_frames, r.metric, r.value)
                       for r in out.rows],
                      columns=["system", "method", "input", "condition", "case", "n_frames",
                               "metric", "value"])
    tab = Calibration().tables(df)
    assert "coverage 90% (e, g, d)" not in tab["calibration"].columns
    assert f"honest ({', '.join(params)})" in tab["model_check"].columns
    with pytest.raises(ValueError, match="calibration_conditions"):
        Calibration().run(Cell("calibration", "lsq", "video", PERTURBED, 0, "pendulum"), ctx)


def test_a_system_cannot_declare_off_model_clips_without_the_papers_datasets():
    from sysid_bench.core.systems import System

    with pytest.raises(TypeError, match="calibration_conditions"):
        type("Mine", (System,), {"calibration_conditions": ("perturbed",)})
