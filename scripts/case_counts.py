"""What each section's case count buys: cases per system and the 95% CI of its headline figure.

For each experiment and system, the cases per (method, input) and, over those groups, the
median half-width of the 95% CI the report shows for the headline metric's mean
(:func:`sysid_bench.bench.experiment.ci_summary`: bootstrap over cases), relative to the mean
(or in absolute units for a share), from a report's ``results.parquet``. Run::

    python scripts/case_counts.py reports/results.parquet
"""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd

from sysid_bench.bench.experiment import ci_summary

#: experiment -> (metric, "rel" for a relative half-width, "abs" for a share's)
HEADLINE = {
    "identification": ("se", "rel"), "forecasting": ("pos_mse", "rel"),
    "calibration": ("hit90_*", "abs"), "changing": ("followed_*", "abs"),
    "online": ("per_frame_s", "rel"), "systems": ("se", "rel"), "foreign": ("se", "rel"),
    "camera": ("se", "rel"), "sensitivity": ("se", "rel"), "interception": ("success", "abs"),
}


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
        by = ["method", "input", "condition"]
        ci = ci_summary(per, by)
        cases = ci.n.to_numpy()
        hw = ((ci.hi - ci.lo) / 2).to_numpy(dtype=float)
        if kind == "rel":
            hw = hw / np.abs(ci["mean"].to_numpy(dtype=float))
            # errors spanning decades: the interval of the mean of log10 (groups all > 0)
            pos = per.groupby(by).value.transform(lambda v: (v > 0).all())
            logs = per[pos.astype(bool)].assign(value=lambda d: np.log10(d.value))
            lci = ci_summary(logs, by) if len(logs) else None
            dec = [] if lci is None else ((lci.hi - lci.lo) / 2).to_numpy(dtype=float)
        else:
            dec = []
        recs.append({"experiment": exp, "system": system, "metric": metric,
                     "cases": int(np.median(cases)),
                     "median CI half-width": (f"{100 * np.nanmedian(hw):.0f}% of the mean"
                                              if kind == "rel" else
                                              f"±{np.nanmedian(hw):.2f} (share)"),
                     "geometric mean's": (f"±{np.nanmedian(dec):.2f} decades"
                                          if len(dec) and np.isfinite(dec).any() else "-")})
    return pd.DataFrame(recs)


if __name__ == "__main__":
    from sysid_bench.core._markdown import markdown_table

    print(markdown_table(main(sys.argv[1] if len(sys.argv) > 1 else "reports/results.parquet")))
