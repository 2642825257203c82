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


def test_section0_draws_calibrations_cases():
    """One protocol (issue 37 section 6): section 0's first cases are calibration's, the same
    bytes (so a pure fit is shared), the others further test cases from an independent stream;
    the ball's sets are prefixes of larger ones."""
    from sysid_bench.bench.cases import bench_case, extended_case
    from sysid_bench.bench.fitcache import observation_digest as digest

    for system, inp in (("pendulum", "positions"), ("ball", "video")):
        mine = [extended_case(system, i, 5, 2, 7, inp) for i in range(5)]
        for i in range(2):
            theirs = bench_case(system, i, 2, 7, inp)
            assert digest(mine[i][0]) == digest(theirs[0])
            assert np.array_equal(mine[i][1], theirs[1])
        assert len({digest(o) for o, _, _ in mine}) == 5
        assert digest(extended_case(system, 4, 5, 2, 7, inp)[0]) == digest(mine[4][0])
    assert digest(extended_case("ball", 3, 5, 2, 7, "video")[0]) == \
        digest(bench_case("ball", 3, 5, 7, "video")[0])
    # the pendulum's further cases are not those of its own set of 5 (another stream)
    other = bench_case("pendulum", 3, 5, 7, "positions")[1]
    assert not np.array_equal(extended_case("pendulum", 3, 5, 2, 7, "positions")[1], other)
    for bad, msg in (((5, 5, 2), "i: expected a case"), ((-1, 5, 2), "i: expected an int"),
                     ((0, 5, 1.5), "n_shared: expected an int")):
        with pytest.raises(ValueError, match=msg):
            extended_case("pendulum", *bad, 7, "positions")


def test_systems_experiment_smoke(tmp_path):
    """Section 0 on calibration's cases and input reads calibration's fits (fitcache)."""
    from sysid_bench.bench import fitcache

    out = run(scale="smoke", methods=["prior", "lsq"], experiments=["calibration"],
              systems=["pendulum"], run_dir=tmp_path, workers=0, progress=False)
    h0 = fitcache.stats()["hits"]
    out = run(scale="smoke", methods=["prior", "lsq"], experiments=["systems"],
              systems=["pendulum"], run_dir=tmp_path, workers=0, progress=False)
    assert out["ok"] == out["cells"] > 0
    # lsq's fits of case 0 after 50 and 100 frames and its forecast's after 50: calibration's
    assert fitcache.stats()["hits"] - h0 == 3
    with Store(tmp_path / STORE_NAME) as s:
        every = s.results()
    df = every[every.experiment == "systems"]
    assert set(df.system) == {"pendulum"} and set(df.method) == {"prior", "lsq"}
    assert set(df.input) == {"video"}
    # the same posterior: section 0's squared errors are calibration's errors squared
    cal = every[(every.experiment == "calibration") & (every.method == "lsq")
                & (every.case == 0) & every.metric.str.startswith("err_")]
    se = df[(df.method == "lsq") & df.metric.str.startswith("se_")]
    a = cal.assign(p=cal.metric.str[4:]).set_index(["n_frames", "p"]).value ** 2
    b = se.assign(p=se.metric.str[3:]).set_index(["n_frames", "p"]).value
    both = a.index.intersection(b.index)
    assert len(both) == 8 and np.array_equal(a[both].to_numpy(), b[both].to_numpy())
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
