"""Rewrite the README's two tables from the committed report's tables.

    python scripts/readme_headline.py [--check]

The headline table: every figure is a cell of ``reports/tables/summary.csv`` (the report's
Summary section, the paper's system, video input) under the same column name, printed as the
report prints it (3 significant digits). The "Across systems" table: every cell is the
parameter MSE, 90% coverage and seconds per identification of ``reports/tables/
systems_summary.csv`` (section 0), per method and system. Run it after the report is
regenerated; ``--check`` exits 1 when the README differs from the report instead of writing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from sysid_bench.core._io import atomic_write

ROOT = Path(__file__).resolve().parents[1]
#: the README's rows, in its order (``prior``: always answering the prior mean)
ROWS = ("vid2param", "vid2param-physics", "emcee", "lsq", "sindy", "bo", "prior")
#: the summary's columns the README shows; the best (lowest) of each but the last is bold
COLUMNS = ("e, g, d MSE @ 200", "r MSE @ 200", "forecast MSE after 50", "s / identification @ 200")
START = "| method (video input) |"


def headline_table(summary: pd.DataFrame) -> str:
    """The README's table (markdown) from the report's summary table."""
    missing = [c for c in COLUMNS if c not in summary.columns]
    if missing:
        raise ValueError(f"summary: expected the columns {list(COLUMNS)}, missing {missing} "
                         "(regenerate the report)")
    if "system" in summary.columns:  # the paper's system (the ball) heads the README
        from sysid_bench.core import systems

        paper = [s for s in summary.system.unique() if s in systems.available()
                 and systems.get(s).paper]
        summary = summary[summary.system.isin(paper[:1])]
    video = summary[summary.input == "video"].set_index("method")
    rows = [m for m in ROWS if m in video.index]
    best = {c: video.loc[[m for m in rows if m != "prior"], c].min() for c in COLUMNS[:-1]}
    lines = [START + " " + " | ".join(COLUMNS) + " |", "| --- |" + " --- |" * len(COLUMNS)]
    for m in rows:
        cells = []
        for c in COLUMNS:
            v = video.loc[m, c]
            text = "-" if not np.isfinite(v) or (m == "prior" and c == COLUMNS[-1]) else f"{v:.3g}"
            cells.append(f"**{text}**" if c in best and v == best[c] else text)
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


#: the first line of the README's "Across systems" table
SYSTEMS_START = "| method (section 0) |"


def _lead(text) -> float:
    """The figure before a CI (``"0.012 [0.01, 0.015]"`` -> 0.012); NaN for ``-``."""
    try:
        return float(str(text).split()[0])
    except ValueError:
        return float("nan")


def systems_table(summary: pd.DataFrame) -> str:
    """The README's "Across systems" table (markdown) from section 0's table: per method and
    system ``MSE / coverage / s``, the lowest MSE of each system in bold, ``n/a`` where the
    method has no row there (it does not run on the system)."""
    want = ("system", "method", "param MSE @ 200", "coverage 90%", "s / identification")
    missing = [c for c in want if c not in summary.columns]
    if missing:
        raise ValueError(f"systems_summary: expected the columns {list(want)}, missing {missing}")
    from sysid_bench.core import systems

    known = systems.available()
    names = [x for x in known if x in set(summary.system)]
    names += sorted(set(summary.system) - set(names))
    mse = summary.assign(v=summary["param MSE @ 200"].map(_lead))
    best = mse[np.isfinite(mse.v)].groupby("system").v.min()
    def rank(m):  # the most systems first, then the smallest mean log-ratio to each best
        ok = mse[(mse.method == m) & np.isfinite(mse.v)]
        ratios = [np.log(r.v / best[r.system]) for r in ok.itertuples() if best[r.system] > 0]
        return (-len(ok), float(np.mean(ratios)) if ratios else np.inf, m)

    # forecast-only methods (no parameter figure anywhere) have no place in this table
    methods = [m for m in dict.fromkeys(summary.method)
               if np.isfinite(mse[mse.method == m].v).any()]
    order = sorted(methods, key=rank)
    lines = [SYSTEMS_START + " " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
    for m in order:
        cells = []
        for sysname in names:
            r = mse[(mse.method == m) & (mse.system == sysname)]
            if r.empty:
                cells.append("n/a")
                continue
            r = r.iloc[0]
            v = "-" if not np.isfinite(r.v) else f"{r.v:.2g}"
            if np.isfinite(r.v) and r.v == best.get(sysname):
                v = f"**{v}**"
            cov = _lead(r["coverage 90%"])
            sec = _lead(r["s / identification"])
            cells.append(f"{v} / {'-' if not np.isfinite(cov) else f'{cov:.2f}'} / "
                         f"{'-' if not np.isfinite(sec) else f'{sec:.2g}'}")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _replace(lines: list[str], start: str, table: str) -> list[str]:
    i = next(k for k, ln in enumerate(lines) if ln.startswith(start))
    j = next((k for k in range(i, len(lines)) if not lines[k].startswith("|")), len(lines))
    return [*lines[:i], table, *lines[j:]]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true")
    a = p.parse_args(argv)
    table = headline_table(pd.read_csv(ROOT / "reports" / "tables" / "summary.csv"))
    readme = (ROOT / "README.md").read_text()
    lines = _replace(readme.splitlines(), START, table)
    across = ROOT / "reports" / "tables" / "systems_summary.csv"
    if any(ln.startswith(SYSTEMS_START) for ln in lines):
        lines = _replace(lines, SYSTEMS_START, systems_table(pd.read_csv(across)))
    new = "\n".join(lines) + "\n"
    if a.check:
        if new != readme:
            print("README.md: a table differs from reports/tables/summary.csv or "
                  "systems_summary.csv (run scripts/readme_headline.py)", file=sys.stderr)
            return 1
        return 0
    atomic_write(ROOT / "README.md", new)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
