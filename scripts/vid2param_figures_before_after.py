"""Vid2Param's rows of every committed report table, before (a commit) and now, figure by figure.

Reads ``reports/tables/*.csv`` at ``--before`` (``git show``) and in the working tree, keeps the
rows of ``vid2param``, ``vid2param-physics`` and ``vid2param-changing`` (the ``method`` or
``policy`` column), and prints one markdown table per report table: each figure before and
after, better / same / worse (by the figure's sense: an error or a time lower, a coverage
nearer its nominal level, a count of followed changes higher; band widths and stds only
"wider" / "narrower"), and whether the change lies within the figures' 95% CIs. Runs nothing
of the benchmark. The notes on why figures changed are written by hand in the doc this feeds
(``docs/vid2param-figures-before-after.md``)::

    python scripts/vid2param_figures_before_after.py --before 0878870 > tables.md
"""

from __future__ import annotations

import argparse
import io
import math
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
METHODS = ("vid2param", "vid2param-physics", "vid2param-changing")
#: columns that say which row a figure belongs to, not a figure
KEYS = ("method", "policy", "input", "system", "condition", "parameter",
        "distance above training range", "frames", "mode")
#: columns that are not figures at all
SKIP = ("seed", "note", "95% CI %")
CELL = re.compile(r"^\s*(-?[\d.eE+-]+)\s*\[\s*(-?[\d.eE+-]+)\s*,\s*(-?[\d.eE+-]+)\s*\]\s*$")


def parse(cell) -> tuple[float, float | None, float | None, str]:
    """``(value, lo, hi, text)`` of a cell: ``"0.1 [0.05, 0.2]"``, a number, ``"3/15"``."""
    text = "" if cell is None or (isinstance(cell, float) and math.isnan(cell)) else str(cell)
    m = CELL.match(text)
    if m:
        return float(m[1]), float(m[2]), float(m[3]), text
    frac = re.fullmatch(r"\s*(\d+)/(\d+)\s*", text)
    if frac:
        return int(frac[1]) / int(frac[2]), None, None, text
    try:
        return float(text), None, None, text
    except ValueError:
        return math.nan, None, None, text


def sense(column: str) -> str:
    """How a figure of ``column`` improves: "lower", "higher", "nominal:<p>", "width", "count"
    or "timing" (lower, but a measured time: compared only on the same load)."""
    c = column.lower()
    if c in ("cases", "throws", "posteriors", "first_frame", "caught"):
        return "count"
    if "shift" in c:
        return "lower"
    if c.startswith("coverage") or c.startswith("cov90") or c in ("90% coverage", "coverage90"):
        nominal = 0.5 if "50%" in c else 0.9
        return f"nominal:{nominal}"
    if "band" in c or "std" in c:
        return "width"
    if c.startswith("s ") or c.startswith("s/") or "s/frame" in c or "s / " in c or \
            c.endswith("_s") or "ms" in c.split() or "step ms" in c or c == "train s" \
            or c.startswith("median s") or c.startswith("s_per") or "lead s" in c:
        return "higher" if "lead" in c else "timing"
    if c in ("ratio", "ratio_cpu") or c.startswith("x vid2param"):
        return "timing"
    if "followed" in c or c in ("caught", "rate %", "check_pass"):
        return "higher"
    return "lower"  # errors: MSE, W1, shifts, RMSE, NLL, misses, failing checks, frames to follow


def _short(text: str) -> str:
    """A plain number printed to 4 significant digits (the tables' own cells keep theirs)."""
    try:
        v = float(text)
    except ValueError:
        return text
    return f"{v:.4g}" if len(text) > 8 else text


def _digits(text: str) -> int:
    m = re.match(r"\s*-?(\d*)\.?(\d*)", text)
    return len((m[1] + m[2]).lstrip("0")) if m else 0


def compare(col: str, before, after) -> tuple[str, str, str, str]:
    """``(before, after, verdict, within CI)`` of one figure."""
    b, a = parse(before), parse(after)
    bt, at = _short(b[3]) or "-", _short(a[3]) or "-"
    if bt == at:
        return bt, at, "same", ""
    if math.isnan(b[0]) or math.isnan(a[0]):
        return bt, at, "-" if math.isnan(b[0]) and math.isnan(a[0]) else "new" \
            if math.isnan(b[0]) else "gone", ""
    # the same to the digits the coarser of the two prints: "same"
    d = min(_digits(bt.split("[")[0]) or 6, _digits(at.split("[")[0]) or 6)
    if b[0] == a[0] or (d and float(f"{b[0]:.{d}g}") == float(f"{a[0]:.{d}g}")):
        verdict = "same"
    else:
        s = sense(col)
        if s == "count":
            verdict = "changed"
        elif s == "width":
            verdict = "wider" if a[0] > b[0] else "narrower"
        elif s.startswith("nominal:"):
            p = float(s.split(":")[1])
            db, da = abs(b[0] - p), abs(a[0] - p)
            verdict = "same" if math.isclose(da, db, abs_tol=1e-12) else \
                ("better" if da < db else "worse") + f" (nominal {p:g})"
        else:
            up = a[0] > b[0]
            better = up if s == "higher" else not up
            verdict = ("better" if better else "worse") + (" (timing)" if s == "timing" else "")
    ci = ""
    if b[1] is not None and a[1] is not None:
        overlap = a[1] <= b[2] and b[1] <= a[2]
        ci = "CIs overlap" if overlap else "**CIs disjoint**"
        if overlap and b[1] <= a[0] <= b[2]:
            ci = "inside before's CI"
    elif a[1] is not None:
        ci = "before inside after's CI" if a[1] <= b[0] <= a[2] else "**before outside after's CI**"
    elif b[1] is not None:
        ci = "inside before's CI" if b[1] <= a[0] <= b[2] else "**outside before's CI**"
    elif verdict != "same":
        ci = "no CI"
    return bt, at, verdict, ci


def table(name: str, before: str) -> str:
    new_path = ROOT / "reports" / "tables" / name
    new = pd.read_csv(new_path, dtype=str, keep_default_na=False)
    r = subprocess.run(["git", "show", f"{before}:reports/tables/{name}"], cwd=ROOT,
                       capture_output=True, text=True)
    old = pd.read_csv(io.StringIO(r.stdout), dtype=str, keep_default_na=False) \
        if r.returncode == 0 else None
    who = "policy" if "policy" in new.columns else "method"
    if who not in new.columns:
        return f"### {name}\n\nNo method column: no Vid2Param row.\n"
    for df in (new, old):
        if df is not None and "95% CI %" in df.columns:  # the rate's CI, as the others write it
            lo_hi = df["95% CI %"].str.split("-", n=1, expand=True)
            df["rate %"] = df["rate %"] + " [" + lo_hi[0] + ", " + lo_hi[1] + "]"

    def ours(df):
        return df[df[who].str.startswith(METHODS[0])]

    new = ours(new)
    if new.empty and (old is None or ours(old).empty):
        return f"### {name}\n\nNo Vid2Param row.\n"
    keys = [k for k in KEYS if k in new.columns]
    if old is None:
        head = f"### {name}\n\nNew since {before} (no before).\n\n"
        from sysid_bench.core._markdown import markdown_table

        return head + markdown_table(new.map(_short)) + "\n"
    old = ours(old)
    extra = ""
    if "physics" in new.columns and "physics" not in old.columns:
        # rows on physics that is not ours are new (section 5's perturbed rows): listed apart
        from sysid_bench.core._markdown import markdown_table

        added = new[new["physics"] != "ours"]
        if len(added):
            extra = ("\nNew rows (physics not ours, none before):\n\n"
                     + markdown_table(added.map(_short)) + "\n")
        new = new[new["physics"] == "ours"].drop(columns="physics")
    keys = [k for k in keys if k in old.columns and k in new.columns]
    new = new.drop(columns=[k for k in KEYS if k in new.columns and k not in keys
                            and new[k].nunique() <= 1])
    merged = new.merge(old, on=keys, how="outer", suffixes=(" (after)", " (before)"),
                       indicator=True)
    cols = [c for c in new.columns if c not in keys and c not in SKIP]
    cols += [c for c in old.columns if c not in keys and c not in SKIP and c not in cols]
    lines = ["| row | figure | before | after | verdict | within CI |", "|---|---|---|---|---|---|"]
    counts: dict[str, int] = {}
    for _, row in merged.iterrows():
        label = " / ".join(str(row[k]) for k in keys if str(row[k]) not in ("", "video"))
        for c in cols:
            b = row.get(f"{c} (before)", row.get(c)) if c in old.columns else None
            a = row.get(f"{c} (after)", row.get(c)) if c in new.columns else None
            if row["_merge"] == "left_only":
                b = None
            if row["_merge"] == "right_only":
                a = None
            bt, at, verdict, ci = compare(c, b, a)
            if bt == at == "-" or (bt in ("-", "nan") and at in ("-", "nan")):
                continue
            key = verdict.split(" (")[0]
            counts[key] = counts.get(key, 0) + 1
            cells = (label, c, bt, at, verdict, ci)
            lines.append("| " + " | ".join(s.replace("|", "\\|") for s in cells) + " |")
    tally = ", ".join(f"{v} {k}" for k, v in sorted(counts.items()))
    return f"### {name}\n\n{tally}.\n\n" + "\n".join(lines) + "\n" + extra


def same_throws(policy: str, before: str) -> str:
    """The throws both interception tables of ``policy`` hold, throw by throw."""
    name = f"intercept_{policy}.csv"
    new = pd.read_csv(ROOT / "reports" / "tables" / name)
    r = subprocess.run(["git", "show", f"{before}:reports/tables/{name}"], cwd=ROOT,
                       capture_output=True, text=True, check=True)
    old = pd.read_csv(io.StringIO(r.stdout))
    m = new.merge(old, on="throw", suffixes=("_after", "_before"))
    same = int((m.success_after == m.success_before).sum())
    dmiss = float((m.miss_m_after - m.miss_m_before).abs().max())
    med = {c: (m[f"{c}_before"].median(), m[f"{c}_after"].median())
           for c in ("miss_m", "decision_s", "settled_s")}
    return (f"| {policy} | {len(old)} / {len(new)} | {len(m)} | {int(m.success_before.sum())} / "
            f"{int(m.success_after.sum())} | {same} of {len(m)} | {dmiss:.2g} | "
            + " | ".join(f"{b:.4g} / {a:.4g}" for b, a in med.values()) + " |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", default="0878870", help="the commit to compare with")
    a = ap.parse_args(argv)
    names = sorted(p.name for p in (ROOT / "reports" / "tables").glob("*.csv")
                   if not (p.name.startswith("intercept_") and p.name != "intercept_summary.csv"))
    sys.stdout.write("\n".join(table(n, a.before) for n in names))
    sys.stdout.write("\n### interception on the throws both runs hold\n\n"
                     "| policy | throws before / after | shared | caught before / after | "
                     "same outcome | max abs miss change (m) | median miss m | "
                     "median decision s | median settled s |\n|---|---|---|---|---|---|---|---|---|\n")
    for policy in ("vid2param", "vid2param-physics"):
        sys.stdout.write(same_throws(policy, a.before) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
