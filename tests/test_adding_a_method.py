"""A toy method in one new file plus one register line: it passes ``check_estimator``, runs in
the smoke benchmark and shows in the report, with nothing else touched.

The file is the code block of ``docs/adding-a-method.md``, executed as it stands (so the page
cannot rot), written as a module into a temporary directory and registered with the page's one
line (pointed at that module).
"""

import re
import sys
from pathlib import Path

import pandas as pd
import pytest

import methods
from sysid_bench.core.testing import check_estimator

DOC = Path(__file__).resolve().parents[1] / "docs" / "adding-a-method.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", DOC.read_text(), flags=re.S)


@pytest.fixture
def toy(tmp_path, monkeypatch):
    module = _blocks("python")[0]
    (tmp_path / "toy_parabola.py").write_text(module)
    monkeypatch.syspath_prepend(str(tmp_path))
    line = _blocks("text")[0].strip()
    assert line == 'register("parabola", "methods.parabola:Parabola")'
    methods.register("parabola", "toy_parabola:Parabola")
    yield "parabola"
    methods.unregister("parabola")
    sys.modules.pop("toy_parabola", None)


def test_the_toy_of_the_doc_passes_check_estimator(toy):
    est = methods.get(toy)
    check_estimator(est)
    # the doc's own check block runs as written
    exec(_blocks("python")[1], {"Parabola": type(est)})
    spec = methods.spec(toy)
    assert spec.capabilities == ("identifies",) and spec.cost == 10 and not spec.expensive


def test_the_toy_runs_in_the_smoke_benchmark_and_shows_in_the_report(toy, tmp_path):
    from sysid_bench.apps.report import render
    from sysid_bench.bench.runner import run

    # in-process (workers=0): the toy's temporary module is registered in this process only;
    # a real method's register line is in methods/__init__.py, which workers import too
    out = run(scale="smoke", methods=[toy, "prior"], run_dir=tmp_path / "run", workers=0,
              progress=False)
    assert out["errors"] == 0, out
    report = render(out["store"], tmp_path / "reports")
    text = report.read_text()
    assert "parabola" in text
    summary = pd.read_csv(tmp_path / "reports" / "tables" / "summary.csv")
    assert toy in set(summary.method)
    ident = pd.read_csv(tmp_path / "reports" / "tables" / "ball" / "identification_mse.csv")
    assert toy in set(ident.method)
    # the toy does not forecast: its forecasting cells are n/a, not errors
    assert out["na"] > 0
