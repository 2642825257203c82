"""What each section's case count buys: cases per system and the 95% CI of its headline figure.

For each experiment and system, the cases per (method, input) and, over those groups, the
median half-width of the 95% t-interval of the headline metric's mean relative to the mean
(or in absolute units for a share), from a report's ``results.parquet``. Run::

    python scripts/case_counts.py reports/results.parquet
"""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd
from scipy import stats

#: experiment -> (metric, "rel" for a relative half-width, "abs" for a share's)
HEADLINE = {
    "identification": ("se", "rel"), "forecasting": ("pos_mse", "rel"),
    "calibration": ("hit90_*", "abs"), "changing": ("followed_*", "abs"),
    "online": ("per_frame_s", "rel"), "systems": ("se", "rel"), "foreign": ("se", "rel"),
    "camera": ("se", "rel"), "sensitivity": ("se", "rel"), "interception": ("success", "abs"),
}


def half_width(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan")
    return float(stats.t.ppf(0.975, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size))


def main(path: str) -> pd.DataFrame:
    df = pd.read_parquet(path)
    df = df[df.status == "ok"]
    recs = []
    for (exp, system), g in df.groupby(["experiment", "system"]):
        if exp not in HEADLINE:
            continue
        metric, kind = HEADLINE[exp]
        m = g[g.metric.str.fullmatch(metric.replace("*", ".+"))] if "*" in metric \
            else g[g.metric == metric]
        if m.empty:
            continue
        # one value per case: the mean over parameters / frame counts of that case
        per = m.groupby(["method", "input", "condition", "case"]).value.mean().reset_index()
        hw, dec, cases = [], [], []
        for _, h in per.groupby(["method", "input", "condition"]):
            v = h.value.to_numpy(dtype=float)
            cases.append(len(v))
            w = half_width(v)
            if kind == "rel":
                mu = float(np.mean(v))
                w = w / abs(mu) if mu else float("nan")
                pos = v[v > 0]  # errors spanning decades: the geometric mean's interval
                dec.append(half_width(np.log10(pos)) if pos.size == v.size else np.nan)
            hw.append(w)
        recs.append({"experiment": exp, "system": system, "metric": metric,
                     "cases": int(np.median(cases)),
                     "median CI half-width": (f"{100 * np.nanmedian(hw):.0f}% of the mean"
                                              if kind == "rel" else
                                              f"±{np.nanmedian(hw):.2f} (share)"),
                     "geometric mean's": (f"±{np.nanmedian(dec):.2f} decades"
                                          if kind == "rel" and np.isfinite(dec).any() else "-")})
    return pd.DataFrame(recs)


if __name__ == "__main__":
    from sysid_bench.core._markdown import markdown_table

    print(markdown_table(main(sys.argv[1] if len(sys.argv) > 1 else "reports/results.parquet")))
