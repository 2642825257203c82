"""Does another run's report reproduce the committed one?  Table by table, figure by figure.

    python scripts/compare_reports.py reports OTHER/ [--out docs/cross_machine.md]

``reports`` (the committed report) is the reference: each of its figures written
``"x [lo, hi]"`` (a value with its 95% CI) is matched when the other run's value ``x'`` lies in
``[lo, hi]`` (issue 29: "every figure a fresh run prints on another machine must lie within the
committed figure's shown 95% CI"); a figure without a CI is matched when it is equal to the
shown digits, a rank range ("2-4") when the two ranges overlap. Rows are paired by their label columns (the text columns: method, input, physics,
...); timing columns (seconds, milliseconds, speed ratios) are not compared, as timings move
with the machine. Prints a summary per table and every figure outside its CI; exits 1 if any.
"""
from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

import pandas as pd

#: a figure with its CI, "0.0539 [0.0297, 0.0853]"
_CI = re.compile(r"^\s*(\S+)\s*\[\s*(\S+)\s*,\s*(\S+)\s*\]\s*$")
#: columns that are timings (compared by nobody: they move with the machine)
_TIMING = re.compile(r"(^s |s / |s/|^s @|train s|_ms\b|\bms\b|step|wall|total_s|cpu_s|"
                     r"per_frame|ratio|s_per_id|x vid2param|decision_s|settled_s|lead s|"
                     r"online)", re.I)
#: tables not compared: per-throw logs (their summary is), and the report's opening summary,
#: whose figures are the sections' means (compared there, with their CIs)
_SKIP_TABLES = re.compile(r"^(intercept_(?!summary)|summary$)")
#: a place the CIs leave open, "2-4" (systems_summary's rank)
_RANGE = re.compile(r"^\s*(\d+)-(\d+)\s*$")


def parse(value) -> tuple[float, float, float] | float | None:
    """A table cell as ``(x, lo, hi)``, a float, or None (text, empty or "-")."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    s = str(value).strip()
    m = _CI.match(s)
    if m:
        x = parse(m.group(1))  # "0.05 [..]" or a count "7/19 [..]"
        try:
            return (float(x), float(m.group(2)), float(m.group(3)))
        except (TypeError, ValueError):
            return None
    try:
        return float(s)
    except ValueError:
        pass
    m = re.match(r"^\s*(\d+)\s*/\s*(\d+)\s*$", s)  # "7/19": a count of events
    if m and int(m.group(2)) > 0:
        return int(m.group(1)) / int(m.group(2))
    return None


def _label_columns(df: pd.DataFrame) -> list[str]:
    """Columns that name a row: the leading columns holding text, not figures (and the case
    count, which says what a row is computed over)."""
    labels = []
    for c in df.columns:
        vals = [parse(v) for v in df[c]]
        ranked = any(_RANGE.match(str(v)) for v in df[c])
        if (all(v is None for v in vals) and not ranked) or c in ("cases", "frames", "throw", "parameter",
                                                  "distance above training range"):
            labels.append(c)
    return labels


def _same_digits(a: float, b: float) -> bool:
    """``b`` equals ``a`` to the digits ``a`` is shown with (3 significant, as the report)."""
    if a == b:
        return True
    if not (math.isfinite(a) and math.isfinite(b)):
        return False
    return f"{a:.3g}" == f"{b:.3g}"


def compare_table(ref: pd.DataFrame, other: pd.DataFrame) -> dict:
    """Figures of ``other`` against ``ref``'s: counts and the misses.

    Returns ``{"compared", "identical", "in_ci", "outside", "missing_rows"}``: ``outside`` lists
    ``(row label, column, ref cell, other cell)`` of figures outside the reference's CI (or,
    without a CI, differing in the shown digits)."""
    labels = [c for c in _label_columns(ref) if c in other.columns]
    out = {"compared": 0, "identical": 0, "in_ci": 0, "outside": [], "missing_rows": 0}
    key = (lambda r: tuple(str(r[c]) for c in labels)) if labels else (lambda r: r.name)
    others = {key(r): r for _, r in other.iterrows()}
    for _, r in ref.iterrows():
        o = others.get(key(r))
        if o is None:
            out["missing_rows"] += 1
            continue
        for c in ref.columns:
            if c in labels or c not in other.columns or _TIMING.search(str(c)):
                continue
            ra, rb = (_RANGE.match(str(x)) or _RANGE.match(f"{x}-{x}") for x in (r[c], o[c]))
            if ra and rb:  # ranks: the places the two runs' CIs allow must overlap
                out["compared"] += 1
                (a0, a1), (b0, b1) = (tuple(map(int, m.groups())) for m in (ra, rb))
                if str(r[c]).strip() == str(o[c]).strip():
                    out["identical"] += 1
                if max(a0, b0) <= min(a1, b1):
                    out["in_ci"] += 1
                else:
                    out["outside"].append((key(r), c, r[c], o[c]))
                continue
            a, b = parse(r[c]), parse(o[c])
            if a is None:
                continue
            out["compared"] += 1
            bx = b[0] if isinstance(b, tuple) else b
            if str(r[c]).strip() == str(o[c]).strip():
                out["identical"] += 1
                out["in_ci"] += 1
            elif bx is None:
                out["outside"].append((key(r), c, r[c], o[c]))
            elif isinstance(a, tuple):
                if a[1] <= bx <= a[2]:
                    out["in_ci"] += 1
                else:
                    out["outside"].append((key(r), c, r[c], o[c]))
            elif _same_digits(a, bx):
                out["in_ci"] += 1
            else:
                out["outside"].append((key(r), c, r[c], o[c]))
    return out


def compare_dirs(ref_dir: Path, other_dir: Path) -> dict[str, dict]:
    """:func:`compare_table` for every ``tables/*.csv`` the two reports share."""
    ref_t, other_t = Path(ref_dir) / "tables", Path(other_dir) / "tables"
    for d, name in ((ref_t, "reference"), (other_t, "other")):
        if not d.is_dir():
            raise ValueError(f"{name}: expected a report folder holding tables/, got {d.parent}")
    res = {}
    for f in sorted(ref_t.glob("*.csv")):
        if _SKIP_TABLES.match(f.stem) or not (other_t / f.name).exists():
            continue
        res[f.stem] = compare_table(pd.read_csv(f), pd.read_csv(other_t / f.name))
    return res


def render(res: dict[str, dict]) -> str:
    lines = ["| table | figures compared | identical | inside the committed CI (or equal digits) "
             "| outside | rows missing in the other run |", "|---|---|---|---|---|---|"]
    tot = [0, 0, 0, 0]
    for name, r in res.items():
        lines.append(f"| {name} | {r['compared']} | {r['identical']} | {r['in_ci']} | "
                     f"{len(r['outside'])} | {r['missing_rows']} |")
        tot = [tot[0] + r["compared"], tot[1] + r["identical"], tot[2] + r["in_ci"],
               tot[3] + len(r["outside"])]
    lines.append(f"| all | {tot[0]} | {tot[1]} | {tot[2]} | {tot[3]} | |")
    misses = [(n, *m) for n, r in res.items() for m in r["outside"]]
    if misses:
        lines += ["", "Outside the committed CI:", "",
                  "| table | row | column | committed | other run |", "|---|---|---|---|---|"]
        lines += [f"| {n} | {', '.join(map(str, k)) if isinstance(k, tuple) else k} | {c} | "
                  f"{a} | {b} |" for n, k, c, a, b in misses]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reference", type=Path, help="the committed report folder (reports)")
    ap.add_argument("other", type=Path, help="another run's report folder")
    args = ap.parse_args(argv)
    try:
        res = compare_dirs(args.reference, args.other)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(render(res), end="")
    return 1 if any(r["outside"] for r in res.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
