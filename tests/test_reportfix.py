"""What a user reads is true and safe to run (issue 29): the sample clip and identify's default
output folder, intercept's default output folder, the report's store name and provenance, the
interception experiment in the store, and the workers' portable floating point."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from sysid_bench.apps.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
CLIP = ROOT / "docs" / "sample" / "ball.mp4"


def test_sample_clip_is_small_and_identify_writes_under_runs(tmp_path, monkeypatch, capsys):
    import av  # noqa: F401 (a dependency of [test]: missing fails, not skips)
    assert CLIP.is_file() and CLIP.stat().st_size <= 1_000_000
    truth = json.loads(CLIP.with_suffix(".json").read_text())["theta"]
    monkeypatch.chdir(tmp_path)  # the default output folder is relative to where one runs
    assert cli_main(["identify", str(CLIP), "--method", "lsq", "--every", "100",
                     "--no-progress"]) == 0
    out = tmp_path / "runs" / "identify" / "ball_lsq"
    assert {p.name for p in out.iterdir()} >= {"estimates.csv", "estimates.json", "track.png"}
    import pandas as pd

    est = pd.read_csv(out / "estimates.csv")
    assert len(est) == 200
    # a 10 s clip of our own physics: lsq finds g within 0.5 m/s^2
    assert abs(est.g_mean.iloc[-1] - truth["g"]) < 0.5
    assert "wrote runs/identify/ball_lsq/" in capsys.readouterr().out


@pytest.mark.slow
def test_readme_identify_lines_run_as_written(tmp_path, monkeypatch):
    """Each README ``identify`` line on a shipped clip, as written, each into its own folder (the
    camera examples name a user's own files)."""
    import shlex

    import av  # noqa: F401 (a dependency of [test]: missing fails, not skips)

    lines = [ln.split("#")[0].split() for ln in (ROOT / "README.md").read_text().splitlines()
             if ln.startswith("sysid-bench identify docs/sample/")]
    assert len(lines) >= 3
    outs = [ln[ln.index("--out") + 1] for ln in lines]
    assert len(set(outs)) == len(outs) and all(o.startswith("runs/") for o in outs)
    monkeypatch.chdir(ROOT)
    for ln in lines:
        out = ROOT / ln[ln.index("--out") + 1]
        assert cli_main(shlex.split(" ".join(ln[1:]))) == 0, ln
        assert (out / "estimates.csv").is_file()


def test_intercept_default_out_is_under_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["intercept", "--policy", "random-1hz", "--throws", "1",
                     "--no-progress"]) == 0
    assert (tmp_path / "runs" / "intercept" / "tables" / "intercept_random-1hz.json").is_file()
    assert not (tmp_path / "reports").exists()
    capsys.readouterr()


def test_store_label_is_relative(tmp_path, monkeypatch):
    from sysid_bench.apps.report import store_label

    store = tmp_path / "runs" / "default" / "results.sqlite"
    monkeypatch.chdir(tmp_path)
    assert store_label(store) == "runs/default/results.sqlite"
    monkeypatch.chdir(ROOT)  # a store outside the current folder: its run dir and file only
    assert store_label(store) == "default/results.sqlite"
    assert str(tmp_path) not in store_label(store)


def test_provenance_ignores_the_reports_own_outputs():
    """A run's own files under reports/ do not make its commit "uncommitted"."""
    import subprocess

    from sysid_bench.bench.runner import REPORT_OUTPUTS, provenance

    assert "reports" in REPORT_OUTPUTS
    other = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                            ":(exclude)reports"], cwd=ROOT, capture_output=True, text=True)
    if other.returncode != 0:
        pytest.skip("not a git checkout")
    assert provenance()["git_dirty"] == bool(other.stdout.strip())


def test_portable_float_env_in_workers():
    from sysid_bench.bench.runner import _cpu_flags, _thread_env, portable_float_env

    env = _thread_env(1)
    port = portable_float_env()
    if {"avx2", "fma"} <= _cpu_flags():
        assert port["OPENBLAS_CORETYPE"] == "Haswell"
        assert "--xla_cpu_max_isa=AVX2" in env["XLA_FLAGS"]
    assert {k: env[k] for k in port} == port and env["OPENBLAS_NUM_THREADS"] == "1"


def test_interception_is_an_experiment_of_the_store_and_rendered(tmp_path, monkeypatch):
    """Section 8 runs through the runner and the store like the others (issue 37: not a side
    path of the report): a built-in policy's cells have no method, a rerun keeps them, and the
    ball's page shows their table; the provenance names the store, not a machine path."""
    from sysid_bench.apps.report import render
    from sysid_bench.bench import interception
    from sysid_bench.bench.runner import STORE_NAME, run

    monkeypatch.setattr(interception, "policies", lambda methods=None: ["oracle", "random-1hz"])
    run_dir = tmp_path / "run"
    kw = dict(scale="smoke", methods=["prior"], experiments=["interception"], run_dir=run_dir,
              workers=0, progress=False)
    res = run(**kw)
    assert res["ok"] == res["cells"] == 2 and res["errors"] == 0
    assert run(**kw)["ran"] == 0  # kept, not measured again
    text = render(res["store"], tmp_path / "rep").read_text()
    page = (tmp_path / "rep" / "ball.md").read_text()
    sec = page.split("## 8. Interception")[1]
    assert "| oracle | 3 | 3 |" in sec and "| random-1hz | 3 |" in sec
    assert (tmp_path / "rep" / "tables" / "ball" / "intercept_summary.csv").is_file()
    assert (tmp_path / "rep" / "figures" / "ball" / "intercept.png").stat().st_size > 10_000
    assert str(tmp_path) not in text.split("## Run")[0]
    assert f"run/{STORE_NAME}" in text.split("## Run")[0]
    assert re.search(r"git commit `[0-9a-f]+`", text)


# -- readings: a verdict only where the 95% CIs separate ------------------------------------------
def _forecast_rows(spec):
    """``spec``: method -> list of per-case position MSEs (the same after each prefix)."""
    rows = []
    for m, vals in spec.items():
        for case, v in enumerate(vals):
            for n in (20, 50, 100):
                rows += [(m, "video", case, n, "pos_mse", v), (m, "video", case, n, "cov90", 0.9),
                         (m, "video", case, n, "width90_m", 1.0 / n)]
    import pandas as pd

    return pd.DataFrame(rows, columns=["method", "input", "case", "n_frames", "metric", "value"])


def test_forecast_reading_says_not_separable_when_cis_overlap():
    from sysid_bench.bench import EXPERIMENTS

    spread = [0.001, 0.01, 0.02, 0.05]  # emcee's 4 cases: mean 0.020, CI wide
    v2p = [0.02, 0.025, 0.03, 0.022, 0.028, 0.024, 0.026, 0.021]  # mean 0.0245
    text = " ".join(EXPERIMENTS["forecasting"].reading(_forecast_rows(
        {"vid2param": v2p, "emcee": spread})))
    assert "Not here" not in text
    assert "holds here in that none of emcee" in text
    assert "Not separable (95% CIs overlap): emcee (video) after 20, 50, 100" in text


def test_forecast_reading_says_not_here_when_cis_separate():
    from sysid_bench.bench import EXPERIMENTS

    v2p = [0.02, 0.025, 0.03, 0.022, 0.028, 0.024, 0.026, 0.021]
    text = " ".join(EXPERIMENTS["forecasting"].reading(_forecast_rows(
        {"vid2param": v2p, "emcee": [0.001, 0.0012, 0.0011, 0.0013]})))
    assert "Not here: a lower position MSE than vid2param (video), 95% CIs disjoint, for emcee " \
           "(video) after 20, 50, 100 of 3 prefixes" in text
    assert "Not separable" not in text


@pytest.mark.parametrize("hits, verdict", [
    ((0.5, 0.9), "consistent with calibration"),
    ((0.2, 0.6), "over-confident"),
])
def test_calibration_verdict_rests_on_the_cis(hits, verdict):
    """A coverage a few cases away from nominal is not called miscalibrated; a clear miss is."""
    import pandas as pd

    from sysid_bench.bench import EXPERIMENTS

    rng = np.random.default_rng(0)
    rows = []
    for case in range(12):
        for lev, h in zip(("50", "90"), hits):
            for p in "egdr":
                rows.append(("lsq", "video", case, 200, f"hit{lev}_{p}", float(rng.random() < h)))
    df = pd.DataFrame(rows, columns=["method", "input", "case", "n_frames", "metric", "value"])
    text = " ".join(EXPERIMENTS["calibration"].reading(df))
    assert verdict in text and "95% CIs over cases" in text


# -- the README's headline figures are the report's summary cells ---------------------------------
def _headline():
    from scripts_loader import load_script

    return load_script("readme_headline")


def test_readme_headline_table_is_the_summary_under_its_names():
    import pandas as pd

    from sysid_bench.apps.report import summary_table

    rows = []
    for m, se in (("vid2param", 0.01), ("lsq", 0.03), ("prior", 0.075)):
        for case in range(3):
            for p, v in zip("egdr", (se, se, se, 4 * se)):
                rows.append((m, "video", case, 200, f"se_{p}", v, "identification", "ok"))
            rows += [(m, "video", case, 200, "se", 1.75 * se, "identification", "ok"),
                     (m, "video", case, 200, "wall_s", 0.5, "identification", "ok"),
                     (m, "video", case, 50, "pos_mse", se / 10, "forecasting", "ok")]
    df = pd.DataFrame(rows, columns=["method", "input", "case", "n_frames", "metric", "value",
                                     "experiment", "status"])
    summ = summary_table(df)
    table = _headline().headline_table(summ).splitlines()
    head = [c.strip() for c in table[0].strip("|").split("|")][1:]
    assert head == list(_headline().COLUMNS) and set(head) <= set(summ.columns)
    assert table[2] == "| vid2param | **0.01** | **0.04** | **0.001** | 0.5 |"
    assert table[4] == "| prior | 0.075 | 0.3 | 0.0075 | - |"


def test_readme_headline_matches_the_committed_report():
    import pandas as pd

    summ = pd.read_csv(ROOT / "reports" / "tables" / "summary.csv")
    if "e, g, d MSE @ 200" not in summ.columns:
        pytest.skip("the committed report predates the summary's headline columns: regenerate "
                    "it, then run scripts/readme_headline.py")
    assert _headline().main(["--check"]) == 0, "run scripts/readme_headline.py"


def test_readme_systems_table_is_section_0_per_method_and_system():
    """The README's "Across systems" table is section 0's table, one source of truth: each cell
    the MSE / coverage / seconds figures of systems_summary, the lowest MSE per system bold,
    n/a where a method has no row, forecast-only methods left out."""
    import pandas as pd

    rows = [("ball", "lsq", "0.02 [0.01, 0.03]", "0.9 [0.8, 1]", "0.1"),
            ("ball", "emcee", "0.01 [0.005, 0.02]", "0.95 [0.9, 1]", "0.3"),
            ("pendulum", "lsq", "8e-05 [5e-05, 1e-04]", "0.9 [0.8, 1]", "0.35"),
            ("ball", "dmd", "-", "-", "-")]
    summ = pd.DataFrame(rows, columns=["system", "method", "param MSE @ 200", "coverage 90%",
                                       "s / identification"])
    table = _headline().systems_table(summ).splitlines()
    assert table[0] == "| method (section 0) | ball | pendulum |"
    assert table[2] == "| lsq | 0.02 / 0.90 / 0.1 | **8e-05** / 0.90 / 0.35 |"
    assert table[3] == "| emcee | **0.01** / 0.95 / 0.3 | n/a |"
    assert len(table) == 4  # dmd identifies nothing: no row
