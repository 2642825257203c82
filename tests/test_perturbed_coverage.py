"""Issue 29, honest intervals off our physics: experiment 5's perturbed-physics cases and
experiment 6's coverage column, computed from stored cells."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sysid_bench.bench.calibration import (
    DWELL,
    PERTURBED,
    PERTURBED_CONFIG,
    SPIN,
    Calibration,
    perturbation,
    perturbed_cases,
    perturbed_observation,
)
from sysid_bench.bench.cases import SCALES, observation
from sysid_bench.bench.cases import test_set as make_test_set
from sysid_bench.bench.experiment import Cell, execute
from sysid_bench.bench.foreign import Foreign


def test_perturbed_cells_per_method_and_the_reference_minimum():
    sc = SCALES["default"]
    cells = Calibration().cells(sc, ["nuts", "bo", "emcee", "lsq", "prior"])
    pert = pd.DataFrame([c.key() for c in cells if c.condition == PERTURBED])
    n = pert.groupby("method").case.nunique().to_dict()
    # nuts (the reference) gets at least 10 whatever its calibration cap (3); bo keeps its cap
    full = PERTURBED_CONFIG["default"]["n"]
    assert n == {"nuts": 10, "bo": 4, "emcee": full, "lsq": full, "prior": full}
    assert perturbed_cases(sc, "nuts") == 10
    assert set(pert.input) == {"video"}
    # the in-model cells are as before
    ours = [c for c in cells if c.condition == ""]
    assert len([c for c in ours if c.method == "nuts"]) == 3


def test_perturbation_is_seeded_in_range_and_zero_is_our_physics():
    draws = np.array([perturbation(2024, i) for i in range(50)])
    assert (draws[:, 0] >= 0).all() and (draws[:, 0] < SPIN).all()
    assert (draws[:, 1] >= 0).all() and (draws[:, 1] < DWELL).all()
    assert draws[:, 0].std() > 0.05 and perturbation(2024, 3) == tuple(draws[3])
    ds = make_test_set("interleaved", 2, SCALES["smoke"].seed)
    for inp in ("video", "privileged"):
        same = perturbed_observation(ds, 1, inp, 100, 0.0, 0.0)
        ours = observation(ds, 1, inp)
        if inp == "video":
            np.testing.assert_array_equal(same.frames, ours.frames[:100])
        else:
            np.testing.assert_array_equal(same.positions, ours.positions[:100])
            np.testing.assert_array_equal(same.state0, ours.state0)
    bent = perturbed_observation(ds, 1, "privileged", 100, SPIN * 0.99, DWELL * 0.99)
    assert np.abs(bent.positions - same.positions).max() > 0.05
    with pytest.raises(ValueError, match="input"):
        perturbed_observation(ds, 1, "frames", 100, 0.1, 0.0)


def test_a_perturbed_cell_stores_hits_check_and_its_perturbation(tmp_path):
    res = execute(Cell("calibration", "lsq", "video", PERTURBED, 1), SCALES["smoke"],
                  str(tmp_path))
    assert res["status"] == "ok", res["error"]
    rows = pd.DataFrame([r.__dict__ if hasattr(r, "__dict__") else r._asdict()
                         for r in res["rows"]])
    assert set(rows.n_frames) == {0, 100}
    at = rows[rows.n_frames == 100].set_index("metric").value
    assert {"hit90_e", "hit90_g", "hit90_d", "hit50_e", "check_ok"} <= set(at.index)
    spin, dwell = perturbation(SCALES["smoke"].seed, 1)
    zero = rows[rows.n_frames == 0].set_index("metric").value
    assert zero["spin"] == spin and zero["dwell"] == dwell
    with pytest.raises(ValueError, match="condition"):
        Calibration().run(Cell("calibration", "prior", "video", "other", 0), _ctx(tmp_path))


def _ctx(tmp_path):
    from sysid_bench.bench.experiment import Context

    return Context(SCALES["smoke"], tmp_path)


def _rows(method, cond, cases, hit, ok=None, n=100, params="egdr"):
    """Calibration rows: ``hit(case, p)`` -> 0/1, ``ok(case)`` -> check verdict or None."""
    out = []
    for c in range(cases):
        for p in params:
            h = float(hit(c, p))
            out += [(method, "video", cond, c, n, f"hit90_{p}", h),
                    (method, "video", cond, c, n, f"hit50_{p}", h),
                    (method, "video", cond, c, n, f"std_{p}", 0.1),
                    (method, "video", cond, c, n, f"nll_{p}", 0.0)]
        if ok is not None:
            out.append((method, "video", cond, c, n, "check_ok", float(ok(c))))
    return out


def _frame(rows):
    return pd.DataFrame(rows, columns=["method", "input", "condition", "case", "n_frames",
                                       "metric", "value"])


def test_tables_and_readings_split_our_physics_from_perturbed():
    rows = (_rows("nuts", "", 3, lambda c, p: 1, ok=lambda c: 1, n=200)
            # reference: 12 cases, e always in, g and d in on 11 of 12 cases -> 0.94 ... in band
            + _rows("nuts", PERTURBED, 12, lambda c, p: p == "e" or c != 0 or p == "r",
                    ok=lambda c: 1)
            + _rows("lsq", "", 20, lambda c, p: 1, ok=lambda c: 1, n=200)
            # lsq off our physics: never holds the truth, its check fails on half the cases
            + _rows("lsq", PERTURBED, 20, lambda c, p: 0, ok=lambda c: c % 2))
    df = _frame(rows)
    cal = Calibration()
    t = cal.tables(df)
    tab = t["calibration"].set_index(["method", "physics"])
    assert list(t["calibration"].columns[:5]) == ["method", "input", "physics", "cases", "frames"]
    # all cases alike: the open side is the exact bound over 20 cases, 0.025 ** (1 / 20)
    assert tab.loc[("lsq", "perturbed"), "coverage 90% (e, g, d)"] == "0 [0, 0.17]"
    assert tab.loc[("lsq", "ours"), "coverage 90% (e, g, d)"] == "1 [0.83, 1]"
    assert tab.loc[("nuts", "perturbed"), "cases"] == 12
    assert tab.loc[("nuts", "perturbed"), "frames"] == "100"
    cov = cal.coverage(df, "90", ("e", "g", "d")).set_index(["method", "condition"])
    # computed from the rows: per case mean over e, g, d, then over cases
    assert cov.loc[("nuts", PERTURBED), "mean"] == pytest.approx((11 + 1 / 3) / 12)
    chk = t["model_check"].set_index(["method", "physics"])
    # honest: held or the check failed -> the failing half of lsq's cases
    assert chk.loc[("lsq", "perturbed"), "honest (e, g, d)"].startswith("0.5 ")
    assert chk.loc[("lsq", "perturbed"), "failing the check"].startswith("0.5 ")
    text = " ".join(cal.reading(df))
    assert "below it (whole CI under 80%): lsq" in text
    assert "NUTS, the reference posterior" in text and "12 cases" in text
    assert "drops where the CIs are disjoint: lsq 1.00 -> 0.00" in text
    # the in-model sentence does not pool perturbed cases
    assert "lsq (video, 20 cases) 1.00 [0.83, 1.00]/1.00 [0.83, 1.00]" in text


@pytest.mark.parametrize("cases, verdict", [(3, "cannot tell"), (12, "not enough cases to tell"),
                                            (100, "the reference holds")])
def test_reference_verdict_needs_cases_and_a_ci_inside_the_band(cases, verdict):
    # 3 of every 10 cases miss d: coverage of e, g, d 0.9, its CI narrows with cases
    df = _frame(_rows("nuts", PERTURBED, cases, lambda c, p: p != "d" or c % 10 > 2,
                      ok=lambda c: 1)
                + _rows("lsq", PERTURBED, cases, lambda c, p: 1, ok=lambda c: 1))
    text = " ".join(Calibration().reading(df))
    assert verdict in text, text


def test_summary_coverage_is_our_physics_only():
    from sysid_bench.apps.report import summary_table

    df = _frame(_rows("lsq", "", 4, lambda c, p: 1, n=200)
                + _rows("lsq", PERTURBED, 4, lambda c, p: 0)).assign(experiment="calibration",
                                                                     status="ok")
    assert summary_table(df).set_index("method").loc["lsq", "90% coverage"] == 1.0


@pytest.mark.parametrize("n", [6, 12])
def test_foreign_coverage_column_and_reading(n):
    rows = []
    for c in range(n):
        for m, hit, ok in (("vid2param", c < n // 3, 1.0), ("lsq", 1, 1.0), ("prior", 1, None)):
            for p in "egd":
                rows.append((m, "video", "", c, 200, f"hit90_{p}", float(hit)))
                rows.append((m, "video", "", c, 200, f"se_{p}", 0.01))
            rows.append((m, "video", "", c, 200, "se", 0.01))
            # an earlier prefix whose hits must not count
            rows.append((m, "video", "", c, 50, "hit90_e", 0.0))
            if ok is not None:
                rows.append((m, "video", "", c, 200, "check_ok", ok if c != n - 1 else 0.0))
    df = _frame(rows)
    tab = Foreign().tables(df)["foreign_identification"].set_index("method")
    # cases that all hold: a bootstrap says [1, 1], the exact bound over cases 0.54 (6), 0.74
    assert tab.loc["lsq", "coverage 90% (e, g, d)"] == {6: "1 [0.54, 1]", 12: "1 [0.74, 1]"}[n]
    assert tab.loc["vid2param", "coverage 90% (e, g, d)"].startswith("0.33 ")
    # honest: the first third hold, the last case's check failed
    assert tab.loc["vid2param", "honest (e, g, d)"].startswith({6: "0.5 ", 12: "0.42 "}[n])
    assert tab.loc["prior", "honest (e, g, d)"] == "-"
    text = " ".join(Foreign().reading(df))
    # six cases' t interval reaches 80% (no verdict); twelve cases' bootstrap lies below it
    assert ("below it (whole CI under 80%): vid2param" in text) == (n == 12), text
    assert "above it" not in text  # six cases cannot put a share above 97%


def test_share_ci_is_exact_where_every_case_agrees_and_few_cases_get_no_verdict():
    from sysid_bench.bench.calibration import share_ci

    ones = pd.DataFrame({"case": np.repeat(np.arange(10), 3), "value": 1.0})
    s = share_ci(ones)
    assert s["mean"] == 1.0 and s["hi"] == 1.0 and s["lo"] == pytest.approx(0.025 ** 0.1)
    s0 = share_ci(ones.assign(value=0.0))
    assert s0["lo"] == 0.0 and s0["hi"] == pytest.approx(1 - 0.025 ** 0.1)
    mixed = ones.assign(value=(ones.case % 2).astype(float))
    assert 0.1 < share_ci(mixed)["lo"] < 0.5 < share_ci(mixed)["hi"] < 0.9  # the bootstrap's
    # two cases that never hold: no band verdict, and said so
    df = _frame(_rows("lsq", PERTURBED, 2, lambda c, p: 0, ok=lambda c: 1))
    text = " ".join(Calibration().reading(df))
    assert "lsq (video, 2 cases) 0 [0, 0.84], too few cases to tell" in text
    assert "no CI lies wholly below 80%" in text
