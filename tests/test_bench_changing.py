"""Experiment 3 (changing parameters): the reading states the paper's claim per Vid2Param model."""

import pandas as pd


def test_changing_reading_states_the_claim_per_vid2param_model():
    from sysid_bench.bench.changing import Changing

    def rows(method, followed):
        return [dict(method=method, condition="all", case=i, n_frames=50 * (i + 1),
                     metric="followed_e", value=float(f)) for i, f in enumerate(followed)]

    df = pd.DataFrame(rows("vid2param", [0, 0, 1, 0]) + rows("vid2param-changing", [1, 1, 1, 0])
                      + rows("lsq", [1, 0, 0, 0]))
    lines = Changing().reading(df)
    const = [ln for ln in lines if "`vid2param` " in ln][0]
    moving = [ln for ln in lines if "`vid2param-changing`" in ln][0]
    assert "25%" in const and "does not hold" in const
    assert "75%" in moving and "claim holds" in moving
    assert lines[-1].startswith("Other methods") and "lsq 25%" in lines[-1]


def test_systems_declare_which_parameters_jump():
    import numpy as np
    import pytest

    from sysid_bench.core import systems
    from sysid_bench.core.systems.ball import Ball

    # the ball reaches the paper's own test videos through its declaration
    assert Ball.changing_dataset == "changing" and set(Ball.changing_params) == set(Ball.params)
    sys_ = systems.get("pendulum")
    th = sys_.changing_theta(3, 120, 50, rng=0)
    assert th.shape == (3, 120, sys_.n_params)
    u = sys_.normalise(th)
    assert ((u >= 0) & (u <= 1)).all()
    assert (np.diff(th, axis=1)[:, [k for k in range(119) if (k + 1) % 50]] == 0).all()

    class OnlyG(type(sys_)):
        changing_params = ("g",)

    th = OnlyG().changing_theta(4, 150, 50, rng=1)
    moved = (th[:, 1:] != th[:, :-1]).any(axis=(0, 1))
    assert moved.tolist() == [p == "g" for p in sys_.params]
    OnlyG.changing_params = ("nope",)
    with pytest.raises(ValueError, match="changing_params"):
        OnlyG().changing_theta(1, 10, 5)


def test_changing_runs_on_another_system_with_its_parameter_names(tmp_path):
    import dataclasses

    import numpy as np

    from sysid_bench.bench.cases import get_scale
    from sysid_bench.bench.changing import Changing
    from sysid_bench.bench.experiment import execute
    from sysid_bench.core import systems

    scale = get_scale("smoke")
    exp = Changing()
    assert exp.runs_on("spring")
    cells = exp.cells(scale, ["prior"], "spring")
    assert cells and {c.system for c in cells} == {"spring"}
    res = execute(cells[0], scale, tmp_path)
    assert res["status"] == "ok", res
    rows = pd.DataFrame([dataclasses.asdict(r) for r in res["rows"]])
    params = systems.get("spring").params
    metrics = set(rows.metric)
    assert {f"mean_{p}" for p in params} <= metrics and "mean_e" not in metrics
    means = rows[rows.metric.str.startswith("mean_")].value
    assert np.isfinite(means).all() and ((means > -0.5) & (means < 1.5)).all()
    assert (rows[rows.metric == "se"].value >= 0).all()
    # one system's rows make its tables, with its parameter names
    rows = rows.assign(system="spring", method="prior", input="video")
    t = exp.tables(rows)["changing_follow"]
    assert {f"{p}: followed" for p in params} <= set(t.columns)
    assert any(ln.startswith("Other methods") and "prior" in ln for ln in exp.reading(rows))
