"""Experiment 5 (beyond the paper): calibration of posteriors and agreement with ``nuts``.

Every identifying method's posterior after 50, 100 and 200 frames of the same test videos.
Rows per case, frame count and parameter ``p`` (all normalised to [0, 1] by the prior):
``hit50_<p>`` / ``hit90_<p>`` (1 when the truth lies in the central 50 / 90% interval),
``nll_<p>`` (Gaussian NLL of the truth under N(mean, std)), ``mean_<p>``, ``std_<p>`` and the
posterior quantiles ``q<k>_<p>`` at levels :data:`QUANTILES` (from samples when the method gives
samples, else Gaussian); per case and frame count ``check_ok`` (1 when the posterior's model
check passed, 0 when it failed) and ``check_rms_m``, for methods that return a check.
Agreement with the NUTS reference is computed in the report from the
quantiles: the 1-Wasserstein distance between marginals (mean absolute difference of quantile
functions) and the shift of the mean in units of the NUTS std.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.special import ndtri

from sysid_bench.bench.cases import observation
from sysid_bench.bench.experiment import (
    SPAN,
    Cell,
    CellOutput,
    Context,
    Experiment,
    ci_summary,
    fmt_ci,
    normalise,
    timed_prefixes,
)
from sysid_bench.bench.identification import _save, case_cells, method_color
from sysid_bench.metrics import gaussian_nll
from sysid_bench.physics import PARAMS


def _verdict_ci(ci50: tuple[float, float], ci90: tuple[float, float]) -> str:
    """Words for the 95% CIs ``(lo, hi)`` of the empirical coverages of nominal 50% and 90%
    intervals: a level is missed only where its CI excludes it."""
    side = []
    for (lo, hi), nominal in ((ci50, 0.5), (ci90, 0.9)):
        side.append(-1 if hi < nominal else (1 if lo > nominal else 0))
    if side == [0, 0]:
        return "consistent with calibration (the 95% CIs hold 50% and 90%)"
    if max(side) <= 0:
        return "over-confident (intervals too narrow; CI below the nominal level)"
    if min(side) >= 0:
        return "under-confident (intervals too wide; CI above the nominal level)"
    return ("too narrow at 50% but too wide at 90% (heavy tails)" if side[0] < 0
            else "too wide at 50% but too narrow at 90%")


QUANTILES = tuple(np.round(np.arange(0.05, 1.0, 0.1), 2))  # 0.05, 0.15, ..., 0.95


def reference_method(names) -> str | None:
    """The method among ``names`` that declares ``reference_posterior`` (None if none does).

    Methods that are no longer registered or importable are skipped (a store may outlive them).
    """
    import methods

    for m in sorted(set(names)):
        try:
            if methods.spec(m).reference_posterior:
                return m
        except (ValueError, ImportError):
            continue
    return None


def posterior_quantiles(post) -> np.ndarray:
    """Quantiles (len(QUANTILES), 4) of a Posterior in physical units."""
    q = np.asarray(QUANTILES)
    if post.samples is not None and len(post.samples) >= 2:
        return np.quantile(post.samples, q, axis=0)
    return post.mean[None, :] + ndtri(q)[:, None] * post.std[None, :]


class Calibration(Experiment):
    name = "calibration"
    title = "5. Calibration and agreement with NUTS (beyond the paper)"
    description = (
        "Is each posterior honest? Coverage: share of (case, parameter, frame count) whose true "
        "value lies in the posterior's central 50% / 90% interval (ideal: 0.50 / 0.90). NLL: "
        "Gaussian negative log-likelihood of the truth under N(mean, std) in normalised units "
        "(median, as point-estimate methods give infinite values). Agreement: 1-Wasserstein "
        "distance between each method's marginals and the NUTS reference posterior on the same "
        "case and input (normalised units; 0 = identical), and |mean - nuts mean| / nuts std."
    )

    def cells(self, scale, methods):
        return case_cells(self.name, scale, methods, scale.calibration_inputs)

    def run(self, cell: Cell, ctx: Context) -> CellOutput:
        sc = ctx.scale
        ds = ctx.test_set("interleaved", sc.n_cases[self.name])
        i = int(cell.case)
        obs = observation(ds, i, cell.input)
        truth = np.asarray(ds.theta[i, 0])
        tn = normalise(truth)
        est = ctx.estimator(cell.method)
        out = CellOutput()
        lengths = [n for n in sc.calibration_lengths_for(cell.method) if n <= obs.n_frames]
        for n, post, _ in timed_prefixes(est, obs, lengths, out, case=i):
            hits = {}
            for level in (0.5, 0.9):
                lo, hi = post.interval(level)
                hits[level] = (truth >= lo) & (truth <= hi)
            nll = gaussian_nll(truth, post.mean, post.std)
            qs = normalise(posterior_quantiles(post))
            mn, sd = normalise(post.mean), post.std / SPAN
            for j, p in enumerate(PARAMS):
                out.add(i, n, f"hit50_{p}", hits[0.5][j])
                out.add(i, n, f"hit90_{p}", hits[0.9][j])
                out.add(i, n, f"nll_{p}", nll[j])
                out.add(i, n, f"mean_{p}", mn[j])
                out.add(i, n, f"std_{p}", sd[j])
                out.add(i, n, f"err_{p}", mn[j] - tn[j])
                for q, v in zip(QUANTILES, qs[:, j]):
                    out.add(i, n, f"q{int(round(q * 100)):02d}_{p}", v)
            if post.check is not None:
                out.add(i, n, "check_ok", float(post.check.ok))
                out.add(i, n, "check_rms_m", float(post.check.rms_m))
        return out

    # -- report -----------------------------------------------------------------------------
    @staticmethod
    def _pooled(df, prefix):
        """Rows of metrics ``<prefix>_<p>`` pooled over parameters."""
        return df[df.metric.str.startswith(prefix + "_")]

    def agreement(self, df):
        """Per (method, input, case, n_frames, param): W1 and mean shift vs the reference."""
        import pandas as pd

        ref_name = reference_method(df.method.unique())
        if ref_name is None:
            return pd.DataFrame()
        q = df[df.metric.str.match(r"q\d\d_")].copy()
        q["param"] = q.metric.str.split("_").str[1]
        q["level"] = q.metric.str.split("_").str[0]
        key = ["input", "case", "n_frames", "param"]
        wide = q.pivot_table(index=["method", *key], columns="level", values="value")
        ref = wide.xs(ref_name, level="method")
        ms = df[df.metric.str.match(r"(mean|std)_")].copy()
        ms["param"] = ms.metric.str.split("_").str[1]
        ms["kind"] = ms.metric.str.split("_").str[0]
        msw = ms.pivot_table(index=["method", *key], columns="kind", values="value")
        msref = msw.xs(ref_name, level="method")
        recs = []
        for m in sorted(set(df.method) - {ref_name}):
            if m not in wide.index.get_level_values("method"):
                continue
            mine = wide.xs(m, level="method")
            common = mine.index.intersection(ref.index)
            if not len(common):
                continue
            w1 = (mine.loc[common] - ref.loc[common]).abs().mean(axis=1)
            shift = ((msw.xs(m, level="method").loc[common, "mean"] - msref.loc[common, "mean"]).abs()
                     / msref.loc[common, "std"].clip(lower=1e-9))
            part = pd.DataFrame({"w1": w1, "shift": shift}).reset_index()
            part.insert(0, "method", m)
            recs.append(part)
        return pd.concat(recs, ignore_index=True) if recs else pd.DataFrame()

    @staticmethod
    def model_check(df):
        """Per method and input: posteriors whose model check failed (issue 29's target on our
        own test cases: at most 5%), with a 95% CI over cases, and the median residual RMS."""
        import pandas as pd

        ok = df[df.metric == "check_ok"]
        rms = df[df.metric == "check_rms_m"]
        rows = []
        for (m, inp), g in ok.groupby(["method", "input"]):
            per_case = (1.0 - g.groupby("case").value.mean()).reset_index().assign(k=0)
            s = ci_summary(per_case, ["k"]).iloc[0]
            r = rms[(rms.method == m) & (rms.input == inp)].value
            rows.append({"method": m, "input": inp, "cases": g.case.nunique(),
                         "posteriors": len(g),
                         "failing the check": fmt_ci(s["mean"], s["lo"], s["hi"], 2),
                         "median residual RMS (m)": f"{np.nanmedian(r):.3g}" if len(r) else "-"})
        return pd.DataFrame(rows)

    def tables(self, df):
        import pandas as pd

        if df.empty:
            return {}
        recs = []
        for (m, inp), g in df.groupby(["method", "input"]):
            rec = {"method": m, "input": inp, "cases": g.case.nunique()}
            for lev in ("50", "90"):
                h = self._pooled(g, f"hit{lev}")
                # resample cases: average each case's hits first
                per_case = h.groupby("case").value.mean().reset_index().assign(k=0)
                s = ci_summary(per_case, ["k"]).iloc[0]
                rec[f"coverage {lev}%"] = fmt_ci(s["mean"], s["lo"], s["hi"], 2)
            nll = self._pooled(g, "nll").value
            rec["median NLL"] = f"{np.median(nll):.3g}" if len(nll) else "-"
            sd = self._pooled(g, "std").value
            rec["median std"] = f"{np.median(sd):.3g}" if len(sd) else "-"
            recs.append(rec)
        out = {"calibration": pd.DataFrame(recs)}
        chk = self.model_check(df)
        if len(chk):
            out["model_check"] = chk
        ag = self.agreement(df)
        if len(ag):
            ref = reference_method(df.method.unique())
            rows = []
            for (m, inp), g in ag.groupby(["method", "input"]):
                per_case = g.groupby("case")[["w1", "shift"]].mean().reset_index().assign(k=0)
                s = ci_summary(per_case, ["k"], value="w1").iloc[0]
                rows.append({"method": m, "input": inp, "cases": g.case.nunique(),
                             f"W1 to {ref}": fmt_ci(s["mean"], s["lo"], s["hi"]),
                             f"median |mean shift| / {ref} std": f"{g['shift'].median():.3g}"})
            out[f"agreement_with_{ref}"] = pd.DataFrame(rows)
        return out

    def figures(self, df, store, outdir: Path):
        import matplotlib.pyplot as plt

        if df.empty:
            return {}
        fig, axes = plt.subplots(1, 2, figsize=(13, 4.4))
        ax = axes[0]
        ax.plot([0, 1], [0, 1], "k:", lw=1)
        groups = list(df.groupby(["method", "input"]))
        for j, ((m, inp), g) in enumerate(groups):
            ys, los, his = [], [], []
            for lev in ("50", "90"):
                per_case = self._pooled(g, f"hit{lev}").groupby("case").value.mean().reset_index().assign(k=0)
                s = ci_summary(per_case, ["k"]).iloc[0]
                ys.append(s["mean"])
                los.append(s["mean"] - s["lo"])
                his.append(s["hi"] - s["mean"])
            # methods side by side about each level, so their CI bars do not cover each other
            dx = 0.006 * (j - (len(groups) - 1) / 2)
            ax.errorbar([0.5 + dx, 0.9 + dx], ys, yerr=[los, his], marker="o", capsize=3,
                        label=f"{m} ({inp})", color=method_color(m),
                        ls="-" if inp == "video" else "--")
        ax.set(xlabel="nominal interval level", ylabel="empirical coverage", xlim=(0.4, 1.0),
               ylim=(0, 1.02), title="Calibration of posteriors (95% CI)")
        ax.legend(fontsize=7, loc="lower right")
        ag = self.agreement(df)
        ax = axes[1]
        if len(ag):
            s = ci_summary(ag.groupby(["method", "input", "case"]).w1.mean().reset_index(),
                           ["method", "input"], value="w1")
            # horizontal bars: long method names as y labels never overlap
            lab = [f"{m} ({i})" for m, i in zip(s.method, s.input)]
            y = np.arange(len(lab))
            ax.barh(y, s["mean"], xerr=[s["mean"] - s.lo, s.hi - s["mean"]], capsize=3,
                    color=[method_color(m) for m in s.method])
            ax.set_yticks(y, lab, fontsize=8)
            ax.invert_yaxis()
            ref = reference_method(df.method.unique())
            ax.set(xlabel=f"W1 to the {ref} posterior (normalised)", title=f"Agreement with {ref.upper()}")
        else:
            ax.set_axis_off()
            ax.text(0.5, 0.5, "no reference-posterior (nuts) results in this run", ha="center")
        return {"Calibration and agreement with NUTS": _save(fig, outdir / "calibration.png")}

    def reading(self, df):
        if df.empty:
            return []
        out = []
        parts = []
        for (m, inp), g in df.groupby(["method", "input"]):
            c90 = self._pooled(g, "hit90").value.mean()
            c50 = self._pooled(g, "hit50").value.mean()
            # CIs over cases (a case's coverage pooled over parameters), as in the figure
            ci = [ci_summary(self._pooled(g, f"hit{lev}").groupby("case").value.mean()
                             .reset_index().assign(k=0), ["k"]).iloc[0] for lev in ("50", "90")]
            verdict = _verdict_ci(*[(c["lo"], c["hi"]) for c in ci])
            n = g.case.nunique()
            few = ", too few cases to tell" if n < 5 else ""
            parts.append(f"{m} ({inp}, {n} cases) {c50:.2f} [{ci[0]['lo']:.2f}, "
                         f"{ci[0]['hi']:.2f}]/{c90:.2f} [{ci[1]['lo']:.2f}, {ci[1]['hi']:.2f}], "
                         f"{verdict}{few}")
        out.append("Not in the paper. Coverage of the 50%/90% intervals (95% CIs over cases): "
                   + "; ".join(parts) + ".")
        ag = self.agreement(df)
        if len(ag):
            s = ag.groupby(["method", "input"]).w1.mean()
            ref = reference_method(df.method.unique())
            out.append(f"Mean W1 distance to the {ref.upper()} posterior (normalised units): "
                       + ", ".join(f"{m} ({i}) {v:.3g}" for (m, i), v in s.items()) + ".")
        return out
