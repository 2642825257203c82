"""Rewrite the README's headline table from the committed report's summary table.

    python scripts/readme_headline.py [--check]

Every figure of the table is a cell of ``reports/tables/summary.csv`` (the report's Summary
section, video input) under the same column name, printed as the report prints it (3
significant digits). Run it after the report is regenerated; ``--check`` exits 1 when the
README differs from the report instead of writing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from sysid_bench._io import atomic_write

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
        from sysid_bench import systems

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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true")
    a = p.parse_args(argv)
    table = headline_table(pd.read_csv(ROOT / "reports" / "tables" / "summary.csv"))
    readme = (ROOT / "README.md").read_text()
    lines = readme.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(START))
    j = next(k for k in range(i, len(lines)) if not lines[k].startswith("|"))
    new = "\n".join([*lines[:i], table, *lines[j:]]) + "\n"
    if a.check:
        if new != readme:
            print("README.md: the headline table differs from reports/tables/summary.csv",
                  file=sys.stderr)
            return 1
        return 0
    atomic_write(ROOT / "README.md", new)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
