"""Report rendering from a results store, the CLI, and the report's derived numbers."""

import numpy as np
import pandas as pd
import pytest

import methods
from sysid_bench.apps.cli import main as cli_main
from sysid_bench.apps.report import main as report_main
from sysid_bench.apps.report import markdown_table, render
from sysid_bench.bench import EXPERIMENTS
from sysid_bench.bench.calibration import QUANTILES, Calibration
from sysid_bench.bench.changing import frames_to_follow
from sysid_bench.bench.runner import STORE_NAME, run
from sysid_bench.bench.store import Store

try:
    methods.get_class("lsq")
    FAST = ["prior", "lsq"]
except (ImportError, ValueError):
    FAST = ["prior"]


@pytest.fixture(scope="module")
def store_path(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    # the ball (the paper's comparisons) and one other system (its own page)
    run(scale="smoke", methods=FAST, experiments=["identification", "forecasting", "changing",
                                                  "calibration"],
        systems=["ball", "spring"], run_dir=d, workers=0, progress=False)
    return d / STORE_NAME


def test_markdown_table():
    df = pd.DataFrame({"method": ["a|b", "c"], "x": [0.123456, np.nan], "n": [1, 2]})
    md = markdown_table(df).splitlines()
    assert md[0] == "| method | x | n |"
    assert md[1] == "|---|---|---|"
    assert md[2] == "| a\\|b | 0.1235 | 1 |"
    assert md[3] == "| c | - | 2 |"


def test_render_from_store(store_path, tmp_path):
    out = tmp_path / "reports"
    path = render(store_path, out)
    index = path.read_text()
    assert "git commit `" in index and "scale `smoke`" in index
    assert "[ball](ball.md)" in index  # the index links each system's page
    text = (out / "ball.md").read_text()
    for e in EXPERIMENTS.values():  # each experiment on the page of the system it ran on
        assert f"## {e.title}" in (index if e.cross_system else text)
    # tables name the input each method saw, and every method appears
    t = pd.read_csv(out / "tables" / "ball" / "identification_mse.csv")
    assert {"method", "input"} <= set(t.columns)
    assert set(t.method) == set(FAST) and set(t.input) == {"video", "privileged"}
    assert (out / "tables" / "ball" / "forecast_mse.parquet").is_file()
    band = pd.read_csv(out / "tables" / "ball" / "forecast_band.csv")  # smoke: prefixes 20, 50
    assert list(band.columns[2:]) == [f"{k} on frames 50-end, after {t}"
                                      for k in ("band (m)", "cov90") for t in (20, 50)]
    # each cell "mean [lo, hi]" (95% CI over cases)
    lead = band.iloc[:, 2:].map(lambda v: float(str(v).split()[0]))
    assert (lead.iloc[:, :2].to_numpy() > 0).all()
    assert ((lead.iloc[:, 2:] >= 0) & (lead.iloc[:, 2:] <= 1)).all().all()
    assert band.iloc[:, 2:].map(lambda v: "[" in str(v)).all().all()
    for png in ("identification_accuracy", "identification_speed", "forecast_accuracy",
                "forecast_examples", "forecast_uncertainty", "changing_example", "calibration"):
        data = (out / "figures" / "ball" / f"{png}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
        assert f"figures/ball/{png}.png" in text
    # the whole run is exported long-format
    res = pd.read_parquet(out / "results.parquet")
    with Store(store_path) as s:
        assert len(res) == len(s.results())
    assert "No results in the store" in text  # sensitivity: no trainable method in this run


def test_perturbed_physics_rows_come_from_the_stored_cells(store_path):
    """Section 5's perturbed-physics rows (issue 29): each method's coverage of e, g, d is the
    stored hits' per-case mean, apart from its rows on our physics."""
    with Store(store_path) as s:
        res = s.results("calibration")
    tabs = Calibration().tables(res[res.status == "ok"])
    cal = tabs["calibration"]
    assert set(zip(cal.method, cal.physics)) == {(m, ph) for m in FAST for ph in ("ours", "perturbed")}
    for m in FAST:
        hits = res[(res.method == m) & (res.condition == "perturbed")
                   & res.metric.isin(["hit90_e", "hit90_g", "hit90_d"])]
        want = hits.groupby("case").value.mean().mean()
        got = cal[(cal.method == m) & (cal.physics == "perturbed")]["coverage 90% (e, g, d)"]
        assert float(got.iloc[0].split()[0]) == pytest.approx(want, abs=0.006)
    if "lsq" in FAST:
        chk = tabs["model_check"]
        row = chk[(chk.method == "lsq") & (chk.physics == "perturbed")]
        assert len(row) == 1 and row["honest (e, g, d)"].iloc[0] != "-"


def test_report_cli_from_store_and_bad_names(store_path, tmp_path, capsys):
    # one experiment, pages drawn in this process (--workers 0): the CLI's from-store path and
    # its options, without drawing again every figure test_render_from_store draws
    assert report_main(["--from-store", str(store_path.parent), "--out", str(tmp_path / "r"),
                        "--experiments", "identification", "--workers", "0"]) == 0
    assert (tmp_path / "r" / "REPORT.md").is_file()
    page = (tmp_path / "r" / "ball.md").read_text()
    assert f"## {EXPERIMENTS['identification'].title}" in page
    assert f"## {EXPERIMENTS['forecasting'].title}" not in page  # --experiments is honoured
    assert report_main(["--from-store", str(store_path), "--out", str(tmp_path / "r2"),
                        "--experiments", "calibratoin"]) == 2
    assert "Did you mean 'calibration'" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="no results store"):
        report_main(["--from-store", str(tmp_path / "nothing")])


def test_cli_list_and_run(tmp_path, capsys):
    from sysid_bench.core import systems

    assert cli_main(["list"]) == 0
    out = capsys.readouterr().out
    assert "identification" in out and "smoke" in out and "lsq" in out
    assert cli_main(["run", "--scale", "smoke", "--methods", "prior", "--experiments",
                     "identification", "--run-dir", str(tmp_path), "--workers", "0",
                     "--no-progress"]) == 0
    # every registered system: 2 inputs x 2 cases each
    n = 4 * len(systems.available())
    assert f"{n} computed ({n} ok, 0 errors, 0 n/a)" in capsys.readouterr().out
    assert cli_main(["run", "--scale", "smoke", "--methods", "prio"]) == 2
    assert "Did you mean 'prior'" in capsys.readouterr().err


def test_agreement_with_nuts_is_the_quantile_distance():
    """A posterior equal to the reference shifted by 0.1 is at W1 = 0.1, shift = 0.1 / std."""
    rows = []
    for m, shift in (("nuts", 0.0), ("other", 0.1)):
        for case in (0, 1):
            for j, p in enumerate("egdr"):
                base = 0.2 + 0.1 * j
                for q in QUANTILES:
                    rows.append((m, "video", case, 50, f"q{int(round(q * 100)):02d}_{p}",
                                 base + shift + 0.05 * (q - 0.5)))
                rows.append((m, "video", case, 50, f"mean_{p}", base + shift))
                rows.append((m, "video", case, 50, f"std_{p}", 0.05))
    df = pd.DataFrame(rows, columns=["method", "input", "case", "n_frames", "metric", "value"])
    ag = Calibration().agreement(df)
    assert set(ag.method) == {"other"} and len(ag) == 2 * 4
    np.testing.assert_allclose(ag.w1, 0.1)
    np.testing.assert_allclose(ag["shift"], 2.0)


def test_frames_to_follow():
    n = np.arange(10, 201, 10)
    est = np.where(n <= 70, 0.2, 0.8)  # jumps to the new value 20 frames after the change at 50
    assert frames_to_follow(n, est, 0.2, 0.8, 50, 50) == 30  # first estimate within half the jump
    ramp = np.where(n <= 50, 0.2, np.minimum(0.2 + 0.01 * (n - 50), 0.8))
    assert frames_to_follow(n, ramp, 0.2, 0.8, 50, 50) == 40  # 0.2 + 0.4 > 0.8 - 0.3
    assert np.isnan(frames_to_follow(n, np.full(n.shape, 0.2), 0.2, 0.8, 50, 50))
    # a constant guess near the new value before the change does not count as following it
    assert frames_to_follow(n, np.full(n.shape, 0.75), 0.2, 0.8, 50, 50) == -1


@pytest.mark.slow
def test_full_smoke_run_of_every_method_renders(tmp_path):
    """Every registered method through every experiment at the smoke scale, then the report."""
    res = run(scale="smoke", run_dir=tmp_path / "run", progress=False)
    with Store(res["store"]) as s:
        cells = s.cells()
    bad = cells[cells.status == "error"]
    assert bad.empty, bad[["cell_id", "error"]].to_string()
    from sysid_bench.bench.intercept.registry import POLICIES

    ran = set(cells.method)
    # the interception section's own policies (oracle, kalman, ...) run beside the methods
    assert ran - set(POLICIES) == set(methods.available()) | {"prior"} - set(res["skipped_methods"])
    text = render(res["store"], tmp_path / "rep").read_text()
    for m in ran - set(POLICIES):
        assert f"| {m} |" in text


def _ident_rows(method, inp, se, wall):
    rows = []
    for case in range(5):
        for n in (20, 50, 200):
            for p in "egdr":
                rows.append((method, inp, case, n, f"se_{p}", se * (1 + 0.1 * case)))
            rows.append((method, inp, case, n, "se", se * (1 + 0.1 * case)))
            rows.append((method, inp, case, n, "wall_s", wall))
    return rows


@pytest.mark.parametrize("v2p_se, verdict", [(0.01, "the claim holds"), (0.05, "does NOT hold")])
def test_identification_reading_checks_the_paper_claim(v2p_se, verdict):
    rows = _ident_rows("vid2param", "video", v2p_se, 0.01) + _ident_rows("lsq", "privileged", 0.02, 0.5)
    df = pd.DataFrame(rows, columns=["method", "input", "case", "n_frames", "metric", "value"])
    text = " ".join(EXPERIMENTS["identification"].reading(df))
    assert verdict in text
    assert "lsq (privileged) 50x" in text  # speed ratio to vid2param


@pytest.mark.parametrize("cov, verdict", [(0.9, "(within 80-95%)"), (0.97, "(outside 80-95% somewhere)")])
def test_forecast_reading_states_the_band_calibration(cov, verdict):
    rows = []
    for case in range(4):
        for n in (20, 50, 100):
            for m, c in (("vid2param", cov), ("lsq", 0.9)):
                rows += [(m, "video", case, n, "pos_mse", 0.01), (m, "video", case, n, "cov90", c),
                         (m, "video", case, n, "width90_m", 1.0 / n)]
    df = pd.DataFrame(rows, columns=["method", "input", "case", "n_frames", "metric", "value"])
    text = " ".join(EXPERIMENTS["forecasting"].reading(df))
    assert f"vid2param {cov:.0%} after 20" in text and verdict in text
    assert "vid2param's mean 90% band narrows" in text


@pytest.mark.parametrize("late, verdict", [((0.9, 0.5, 0.3), "narrows"),
                                           ((0.9, 0.2, 0.3), "does not narrow monotonically")])
def test_forecast_certainty_is_judged_on_the_frames_every_prefix_forecasts(late, verdict):
    # the band over each prefix's next frames widens (other frames); the verdict follows the
    # common frames' band
    rows = []
    for case in range(3):
        for n, w_next, w_common in zip((20, 50, 100), (0.2, 0.3, 0.4), late):
            rows += [("vid2param", "video", case, n, "pos_mse", 0.01),
                     ("vid2param", "video", case, n, "width90_m", w_next),
                     ("vid2param", "video", case, n, "width90_common_m", w_common),
                     ("vid2param", "video", case, n, "cov90_common", 0.9)]
    df = pd.DataFrame(rows, columns=["method", "input", "case", "n_frames", "metric", "value"])
    text = " ".join(EXPERIMENTS["forecasting"].reading(df))
    assert (f"On the frames every prefix forecasts (100 to the end), vid2param's mean 90% band "
            f"{verdict}: {late[0]:.2f} m after 20") in text
    assert "(it holds 90%, 90%, 90% of the true positions)" in text
    assert "(other frames each time) it does not narrow monotonically: 0.20 m after 20" in text
    band = EXPERIMENTS["forecasting"].tables(df)["forecast_band"]
    assert band.loc[0, "band (m) on frames 100-end, after 50"].startswith(f"{late[1]:.3g} [")
    assert band.loc[0, "cov90 on frames 100-end, after 20"] == "0.9 [0.9, 0.9]"
