"""Experiment 0 (every method on every system) on the smoke scale: cells, rows and table."""

from __future__ import annotations

import numpy as np
import pytest

import methods
from sysid_bench.bench import EXPERIMENTS
from sysid_bench.bench.runner import STORE_NAME, run
from sysid_bench.bench.store import Store
from sysid_bench.bench.systems import system_case

pytestmark = pytest.mark.skipif("lsq" not in methods.available(), reason="lsq not installed")


def test_system_case_protocol():
    """Positions with 1 cm noise and no initial state; the ball's floor (its geometry) given."""
    obs, truth, points = system_case("pendulum", 0, 2, 7, "positions")
    assert obs.system == "pendulum" and obs.state0 is None
    assert obs.positions.shape == points.shape == (200, 1, 2) and truth.shape == (4,)
    noise = np.std(obs.positions - points)
    assert 0.005 < noise < 0.02
    ball, _, _ = system_case("ball", 0, 2, 7, "positions")
    assert ball.floor == 0.0 and ball.positions.shape == (200, 2) and ball.state0 is None
    # same seed, same case
    again, _, _ = system_case("pendulum", 0, 2, 7, "positions")
    assert np.array_equal(again.positions, obs.positions)


def test_systems_experiment_smoke(tmp_path):
    out = run(scale="smoke", methods=["prior", "lsq"], experiments=["systems"],
              systems=["pendulum"], run_dir=tmp_path, workers=0, progress=False)
    assert out["ok"] == out["cells"] > 0
    with Store(tmp_path / STORE_NAME) as s:
        df = s.results()
    assert set(df.system) == {"pendulum"} and set(df.method) == {"prior", "lsq"}
    last = df[df.n_frames == 200]
    se = last[last.metric == "se"].groupby("method").value.mean()
    # lsq on 200 frames of a pendulum identifies far better than guessing (prior mean: ~0.08)
    assert se["lsq"] < 0.01 < se["prior"]
    assert {"cov90", "wall_s", "u_g", "se_L"} <= set(df.metric)
    assert (df[df.metric == "check_ok"].method == "lsq").all()
    table = EXPERIMENTS["systems"].summary(df[df.status == "ok"])
    assert {"system", "method", "input", "rank"} <= set(table.columns)
    rank = table.set_index("method")["rank"]
    assert rank["lsq"] < rank["prior"]


def test_identification_and_forecasting_run_on_another_system(tmp_path):
    """Experiments 1 and 2 on the spring (issue 37: every experiment on every system): rows
    named by the spring's parameters, lsq given true positions beats guessing, forecasts scored
    against the spring's own track, and the tables build from one system's rows."""
    from sysid_bench.bench.forecasting import Forecasting
    from sysid_bench.bench.identification import Identification

    out = run(scale="smoke", methods=["prior", "lsq"], experiments=["identification",
                                                                   "forecasting"],
              systems=["spring"], run_dir=tmp_path, workers=0, progress=False)
    assert out["errors"] == 0 and out["ok"] == out["cells"] > 0
    with Store(tmp_path / STORE_NAME) as s:
        df = s.results()
    assert set(df.system) == {"spring"}
    ident = df[df.experiment == "identification"]
    assert {f"se_{p}" for p in ("w2", "k3", "c", "L0")} <= set(ident.metric)
    last = ident[(ident.metric == "se") & (ident.n_frames == ident.n_frames.max())]
    lsq = last[(last.method == "lsq") & (last.input == "privileged")].value.mean()
    assert lsq < 0.5 * last[last.method == "prior"].value.mean()
    fc = df[(df.experiment == "forecasting") & (df.metric == "pos_mse")]
    assert len(fc) and np.isfinite(fc.value).all()
    assert "identification_params_at_100" in Identification().tables(ident)
    assert "w2" in Identification().tables(ident)["identification_params_at_100"].columns
    assert "forecast_mse" in Forecasting().tables(df[df.experiment == "forecasting"])
