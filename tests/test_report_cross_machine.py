"""Issue 29, "the report is a function of the code, on any machine": every figure carries a
CI a rerun elsewhere can be held to (medians, small case counts, ranks), and
scripts/compare_reports.py holds one report to another's."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scripts_loader import load_script

from sysid_bench.bench.experiment import ci_summary, median_ci, small_sample_widen
from sysid_bench.bench.systems import _ci_rank, _rank_text, _share_bounds


def _compare():
    return load_script("compare_reports")


def test_median_ci_resamples_cases_and_ignores_row_order():
    rng = np.random.default_rng(3)
    df = pd.DataFrame({"case": np.repeat(np.arange(15), 4), "value": rng.normal(size=60)})
    med, lo, hi = median_ci(df, ("k",))
    assert med == pytest.approx(np.median(df.value))
    assert lo < med < hi
    assert median_ci(df.sample(frac=1.0, random_state=1), ("k",)) == (med, lo, hi)
    # a naive case bootstrap gives about the same interval
    cases = [g.value.to_numpy() for _, g in df.groupby("case")]
    r = np.random.default_rng(0)
    meds = [np.median(np.concatenate([cases[i] for i in r.integers(0, 15, 15)]))
            for _ in range(3000)]
    q = np.quantile(meds, [0.025, 0.975])
    assert abs(lo - q[0]) < 0.15 and abs(hi - q[1]) < 0.15
    # fewer than 10 cases: at least the range of the values (3 cases' resamples are too alike)
    few = df[df.case < 3]
    m3, lo3, hi3 = median_ci(few, ("k",))
    assert (m3, lo3, hi3) == (np.median(few.value), few.value.min(), few.value.max())
    one = df[df.case == 2]
    assert median_ci(one, ("k",)) == (np.median(one.value), one.value.min(), one.value.max())


def test_few_cases_get_at_least_the_t_interval():
    v = np.array([3.4e-7, 4.0e-7, 1.74e-6])  # three cases' squared errors
    df = pd.DataFrame({"k": 0, "value": v})
    boot = ci_summary(df.assign(value=v), ["k"])  # widened inside
    lo, hi = float(boot["lo"].iloc[0]), float(boot["hi"].iloc[0])
    half = 4.303 * v.std(ddof=1) / np.sqrt(3)
    assert lo == 0.0  # clipped: squared errors are not negative
    assert hi == pytest.approx(v.mean() + half, rel=1e-3)
    # ten cases and more keep the bootstrap's interval
    w = np.linspace(0, 1, 12)
    assert small_sample_widen(w, 0.4, 0.6) == (0.4, 0.6)
    # shares stay inside [0, 1]
    lo, hi = small_sample_widen(np.array([0.0, 1.0, 1.0]), 0.33, 1.0)
    assert 0.0 <= lo < 0.33 and hi == 1.0


def test_identical_cases_get_the_binomial_interval():
    c = pd.DataFrame({"method": ["bo"], "mean": [0.75], "lo": [0.75], "hi": [0.75]})
    out = _share_bounds(c, [0.75, 0.75, 0.75], trials=4)  # 9 of 12 intervals held
    assert out["lo"].iloc[0] == pytest.approx(0.428, abs=0.01)
    assert out["hi"].iloc[0] == pytest.approx(0.945, abs=0.01)
    assert _share_bounds(c, [0.5, 1.0], 4) is c  # cases differ: the bootstrap stands


def test_ranks_are_the_places_the_cis_allow():
    mean = np.array([0.01, 0.02, 0.09, np.nan])
    lo = np.array([0.0, 0.0, 0.07, np.nan])
    hi = np.array([0.03, 0.05, 0.12, np.nan])
    best = _ci_rank(mean, lo, hi)
    worst = np.isfinite(mean).sum() + 1 - _ci_rank(-mean, -hi, -lo)
    assert list(best[:3]) == [1, 1, 3] and np.isnan(best[3])
    assert list(worst[:3]) == [2, 2, 3]
    assert [_rank_text(b, w) for b, w in zip(best, worst)] == ["1-2", "1-2", "3", "-"]


def _report(path: Path, table: dict[str, pd.DataFrame]):
    (path / "tables").mkdir(parents=True)
    for name, df in table.items():
        df.to_csv(path / "tables" / f"{name}.csv", index=False)


def test_compare_holds_each_figure_to_the_committed_ci(tmp_path):
    cmp = _compare()
    ref = pd.DataFrame({"method": ["a", "b"], "cases": [4, 4],
                        "MSE": ["0.05 [0.03, 0.08]", "0.1 [0.09, 0.11]"],
                        "median std": ["0.2", "0.3"], "s / identification": ["1.0", "2.0"],
                        "rank": ["1-2", "3"], "followed": ["7/19", "2/5"]})
    same = ref.copy()
    inside = ref.assign(MSE=["0.079 [0.01, 0.2]", "0.1 [0.09, 0.11]"],
                        **{"s / identification": ["9", "9"], "rank": ["2", "2-3"]})
    outside = ref.assign(MSE=["0.05 [0.03, 0.08]", "0.12 [0.1, 0.2]"],
                         **{"median std": ["0.2", "0.31"], "rank": ["3", "1"],
                            "followed": ["8/20", "2/5"]})
    _report(tmp_path / "ref", {"t": ref})
    for name, df in (("same", same), ("inside", inside), ("outside", outside)):
        _report(tmp_path / name, {"t": df})
    r = cmp.compare_dirs(tmp_path / "ref", tmp_path / "same")["t"]
    assert r["compared"] == r["identical"] == r["in_ci"] == 8 and not r["outside"]
    r = cmp.compare_dirs(tmp_path / "ref", tmp_path / "inside")["t"]
    assert r["in_ci"] == 8 and not r["outside"]  # timings are not compared
    r = cmp.compare_dirs(tmp_path / "ref", tmp_path / "outside")["t"]
    assert {(k, c) for k, c, _, _ in r["outside"]} == {
        (("b", "4"), "MSE"), (("b", "4"), "median std"), (("a", "4"), "rank"),
        (("b", "4"), "rank"), (("a", "4"), "followed")}
    assert cmp.parse("7/19 [0.069, 0.71]") == pytest.approx((7 / 19, 0.069, 0.71))
    assert cmp.main([str(tmp_path / "ref"), str(tmp_path / "outside")]) == 1
    assert cmp.main([str(tmp_path / "ref"), str(tmp_path / "same")]) == 0
    assert cmp.main([str(tmp_path / "ref"), str(tmp_path / "missing")]) == 2
