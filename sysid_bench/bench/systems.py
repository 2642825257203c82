"""Experiment 0: every method on every system, one protocol, one table across systems.

Each registered system gets the same protocol, the one of calibration (experiment 5):
``n_cases["systems"]`` test-split cases, 200 frames of the system's own render (the ball's
from the paper's test set), the scene's geometry known (the ball's floor, the pendulum's
pivot); frame methods read the frames, position methods the harness's tracking of them (as in
every other experiment's ``video`` input). The first ``n_cases["calibration"]`` cases are
calibration's (and identification's and forecasting's) cases, byte for byte
(:func:`~sysid_bench.bench.cases.extended_case`), so a method that declares ``pure_fit`` reads
the fits those experiments computed (:mod:`sysid_bench.bench.fitcache`): the reference
posterior (``nuts``) after 200 frames, bo, emcee and lsq after 50, 100 and 200 and their
forecasts after 50 are not computed a second time; cases past those come from an independent
stream of the same test split. Per case and observed-frame count (50, 100, 200) the rows are
``se_<p>`` / ``se`` (squared error normalised by the prior range, and their mean), ``cov90``
(fraction of the parameters whose 90% interval holds the truth), ``check_ok`` (the posterior's
model check passed), ``wall_s`` (the identification's seconds, a shared fit's where it was
computed), ``u_<p>`` (the posterior mean normalised by the prior, for the agreement with the
``nuts`` reference) and the samplers' ``rhat_max`` / ``ess_min``; after 50 frames a 100-frame
forecast adds ``fc_mse`` (position MSE normalised by the view's width).

Until session 23 the section drew its own cases (10 per system from another stream) and gave
position methods the true points with 1 cm Gaussian noise instead of the tracked video, so no
fit was shared with calibration (its NUTS alone ~900 core-seconds of the default run); its
figures are now those of tracked video, on other cases.

A method that does not run on a system (no model shipped for it, no feature library) raises
``NotImplementedError`` with a sentence; the report lists it as ``n/a``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sysid_bench.bench.calibration import reference_method
from sysid_bench.bench.cases import extended_case, system_case
from sysid_bench.bench.experiment import (
    Cell,
    CellOutput,
    Context,
    Experiment,
    ci_summary,
    fmt_ci,
)
from sysid_bench.core.metrics import GUESS_MSE

__all__ = ["Systems", "SYSTEM_LENGTHS", "FORECAST_AFTER", "FORECAST_HORIZON", "INPUT",
           "system_case"]

#: Observed-frame counts of the identification rows.
SYSTEM_LENGTHS = (50, 100, 200)
#: The forecast: ``FORECAST_HORIZON`` frames after the first ``FORECAST_AFTER``.
FORECAST_AFTER = 50
FORECAST_HORIZON = 100
#: every method's input: calibration's (the system's render; position methods track it)
INPUT = "video"
#: the experiment whose first cases section 0's are (the same observations: shared fits)
SHARED_WITH = "calibration"


def _gap_to_reference(df, system: str, method: str, n_frames: int, reference: str | None):
    """Per case: the mean squared distance (normalised units) between ``method``'s and the
    ``reference`` method's posterior means (the one declaring ``reference_posterior``,
    :func:`~sysid_bench.bench.calibration.reference_method`), on the cases both identified after
    ``n_frames`` frames.

    Returns
    -------
    pandas.DataFrame
        ``method``, ``case``, ``value``; empty for the reference itself or no shared case.
    """
    import pandas as pd

    empty = pd.DataFrame({"method": [], "case": [], "value": []})
    if reference is None or method == reference:
        return empty
    sub = df[(df.system == system) & (df.n_frames == n_frames) & df.metric.str.startswith("u_")]
    a = sub[sub.method == method].set_index(["case", "metric"]).value
    b = sub[sub.method == reference].set_index(["case", "metric"]).value
    both = a.index.intersection(b.index)
    if not len(both):
        return empty
    d = ((a[both] - b[both]) ** 2).groupby(level="case").mean()
    return pd.DataFrame({"method": method, "case": d.index, "value": d.to_numpy()})


def _share_bounds(c, per_case, trials: int):
    """``c`` (a :func:`ci_summary` row) with the exact binomial (Clopper-Pearson) 95% interval
    of the pooled trials where every case scored the same share: a bootstrap of identical
    cases has no width (10 cases whose 4 intervals each held 3 truths are not "0.75 [0.75,
    0.75]"). ``trials`` per case: the parameters (coverage) or 1 (the check)."""
    from scipy import stats

    v = np.asarray(per_case, dtype=float)
    v = v[np.isfinite(v)]
    if v.size and np.ptp(v) == 0 and trials >= 1:
        n = v.size * trials
        k = int(round(float(v.sum()) * trials))
        ci = stats.binomtest(k, n).proportion_ci(0.95, method="exact")
        c = c.copy()
        c["lo"] = min(float(c["lo"].iloc[0]), ci.low)
        c["hi"] = max(float(c["hi"].iloc[0]), ci.high)
    return c


#: a sampler's chains converged on a case: worst split R-hat below this and ESS at least
#: :data:`CONVERGED_ESS` (the reference's own rule, ``methods.nuts``)
CONVERGED_RHAT = 1.05
CONVERGED_ESS = 50


def _converged_rows(at):
    """Per case (``method``, ``case``, ``value`` 0/1): whether the sampler's chains converged
    (:data:`CONVERGED_RHAT`, :data:`CONVERGED_ESS`); empty for methods without diagnostics.
    A share over cases has a CI; the worst R-hat of three cases does not (issue 29)."""
    import pandas as pd

    rh = at[at.metric == "rhat_max"].groupby("case").value.max()
    es = at[at.metric == "ess_min"].groupby("case").value.min()
    both = rh.index.intersection(es.index)
    ok = (rh[both] < CONVERGED_RHAT) & (es[both] >= CONVERGED_ESS)
    meth = at.method.iloc[0] if len(at) else ""
    return pd.DataFrame({"method": meth, "case": both, "value": ok.to_numpy(dtype=float)})


def _ci_rank(mean, lo, hi) -> np.ndarray:
    """1 + the number of methods whose whole 95% CI lies below this one's (lower is better):
    methods the intervals cannot separate share a rank, so a rank never rests on a difference
    the CIs do not support (issue 29). NaN where ``mean`` is NaN."""
    mean, lo, hi = (np.asarray(x, dtype=float) for x in (mean, lo, hi))
    ok = np.isfinite(mean)
    lo = np.where(np.isfinite(lo), lo, mean)
    hi = np.where(np.isfinite(hi), hi, mean)
    better = (hi[None, :] < lo[:, None]) & ok[None, :]
    return np.where(ok, 1.0 + better.sum(axis=1), np.nan)


def _scored_point(post, sys_) -> np.ndarray:
    """The posterior's point (P,) in normalised units, as the table scores it.

    A parameter the method itself declares uninformed (``post.extras["uninformed"]``: moving it
    across its whole prior range changes the fitted track by less than the noise, see
    ``methods._simulation.uninformed``) carries the prior as its interval, and its posterior
    mean is then the prior's centre (0.5): the point a search happened to stop at (the ball's r
    after 200 frames without rolling: either end of its range, flipped by the last bits of a
    BLAS kernel) is not an estimate and would make the figure swing between runs (issue 37).
    """
    u = np.array(sys_.normalise(post.mean), dtype=np.float64)
    flat = set(post.extras.get("uninformed") or ())
    for k, p in enumerate(sys_.params):
        if p in flat:
            u[k] = 0.5
    return u


def _interval_holds(post, truth, level=0.9) -> np.ndarray:
    lo, hi = post.interval(level)
    return (truth >= lo) & (truth <= hi)


def _rank_text(best: float, worst: float) -> str:
    """``"2"``, or ``"2-4"`` where the CIs leave the place open; ``"-"`` unranked."""
    if not np.isfinite(best):
        return "-"
    return f"{best:.0f}" if worst <= best else f"{best:.0f}-{worst:.0f}"


class Systems(Experiment):
    name = "systems"
    cross_system = True
    title = "0. Across systems"
    description = (
        "Every method on every registered system with one protocol, calibration's: held-out "
        "test-split cases (the first ones calibration's, the ball's from the paper's test set), "
        "200 frames of the system's own render, no initial state (the scene's geometry known: "
        "the ball's floor, the pendulum's pivot); frame methods read the frames, position "
        "methods the harness's tracking of them. Parameter "
        "MSE is normalised by each prior range (guessing the prior mean scores "
        f"{GUESS_MSE:.3f}; a parameter a method declares uninformed, its interval the prior's, "
        "is scored at the prior's centre, not at the point its search stopped at); coverage is "
        "the fraction of parameters whose 90% interval holds the "
        "truth; forecast MSE is over positions scaled by the view's width, 100 frames after 50; "
        "`check passes` is the share of posteriors whose model check passed; `gap to nuts` the "
        "mean squared distance of the posterior means from the reference's; `chains converged` "
        f"the share of cases whose sampler chains converged (split R-hat < {CONVERGED_RHAT}, "
        f"ESS >= {CONVERGED_ESS}). Figures carry 95% CIs over cases. Rank: the places the "
        "parameter-MSE CIs allow, from 1 + the methods whose whole CI lies below to the last "
        "place but those whose whole CI lies above (`2-4`: not separable from its neighbours); "
        "forecast-only methods unranked."
    )

    def cells(self, scale, methods, system="ball"):
        out = []
        for m in methods:
            n = scale.cases(self.name, m, system)
            out += [Cell(self.name, m, INPUT, "", i, system) for i in range(n)]
        return out

    def run(self, cell: Cell, ctx: Context) -> CellOutput:
        sc = ctx.scale
        system, i = cell.system, int(cell.case)
        # calibration's cases (the same bytes), then further ones: its fits are read, not redone
        obs, truth, points = extended_case(system, i, sc.n_for(self.name, system),
                                           sc.n_for(SHARED_WITH, system), sc.seed, cell.input)
        est = ctx.estimator(cell.method, system=system, share_fits=True)
        spec = est.spec()
        out = CellOutput()
        from sysid_bench.core import systems

        sys_ = systems.get(system)
        u_true = sys_.normalise(truth)
        # the expensive tier (samplers, BO) identifies after all 200 frames only at thinned scales
        lengths = SYSTEM_LENGTHS[-1:] if sc.thinned(cell.method) else SYSTEM_LENGTHS
        if spec.identifies:
            from sysid_bench.bench.fitcache import clock

            for n in lengths:
                t0 = clock()  # a fit another cell computed counts its own seconds
                try:
                    post = est.identify(obs.prefix(n))
                except NotImplementedError:
                    raise
                except Exception as exc:  # one frame count failing is a result, not a crash
                    out.fail(n, exc, i)
                    continue
                wall = clock() - t0
                u_post = _scored_point(post, sys_)
                se = (u_post - u_true) ** 2
                for p, v in zip(sys_.params, se):
                    out.add(i, n, f"se_{p}", v)
                out.add(i, n, "se", se.mean())
                out.add(i, n, "cov90", _interval_holds(post, truth).mean())
                out.add(i, n, "wall_s", wall)
                if post.check is not None:
                    out.add(i, n, "check_ok", float(post.check.ok))
                # the samplers' convergence diagnostics (NUTS is the reference posterior)
                for key, metric in (("rhat", "rhat_max"), ("ess", "ess_min")):
                    d = post.extras.get(key)
                    if isinstance(d, dict) and d:
                        v = np.asarray(list(d.values()), dtype=float)
                        out.add(i, n, metric, v.max() if key == "rhat" else v.min())
                # the posterior mean (normalised) for the agreement with the reference
                for p, v in zip(sys_.params, u_post):
                    out.add(i, n, f"u_{p}", v)
        if spec.forecasts:
            try:
                fc = est.forecast(obs.prefix(FORECAST_AFTER), FORECAST_HORIZON)
            except NotImplementedError:
                if not spec.identifies:
                    raise
                return out
            except Exception as exc:
                out.fail(FORECAST_AFTER, exc, i)
                return out
            k = sys_.n_points
            mean = np.asarray(fc.mean).reshape(FORECAST_HORIZON, k, 2)
            want = points[FORECAST_AFTER : FORECAST_AFTER + FORECAST_HORIZON]
            width = sys_.extent[1] - sys_.extent[0]
            out.add(i, FORECAST_AFTER, "fc_mse", float(np.mean(((mean - want) / width) ** 2)))
        return out

    # -- report -----------------------------------------------------------------------------
    def summary(self, df):
        """``systems_summary``: one row per (system, method, input), numbers with 95% CIs over
        cases (``<figure>_lo``, ``<figure>_hi``) and the CI rank (:func:`_ci_rank`)."""
        import pandas as pd

        last = max(SYSTEM_LENGTHS)
        reference = reference_method(df.method.unique())
        recs = []
        for (s, m, inp), g in df.groupby(["system", "method", "input"], sort=True):
            at = g[g.n_frames == last]
            rec = {"system": s, "method": m, "input": inp, "cases": int(g.case.nunique())}
            n_params = g.metric[g.metric.str.startswith("se_")].nunique()  # trials per case
            for name, rows in ((f"param_mse@{last}", at[at.metric == "se"]),
                               ("forecast_mse@50", g[(g.n_frames == FORECAST_AFTER)
                                                     & (g.metric == "fc_mse")]),
                               ("coverage90", at[at.metric == "cov90"]),
                               ("check_pass", at[at.metric == "check_ok"]),
                               ("ref_gap", _gap_to_reference(df, s, m, last, reference)),
                               ("converged", _converged_rows(at))):
                c = ci_summary(rows, ["method"]) if len(rows) else None
                if c is not None and name in ("coverage90", "check_pass", "converged"):
                    c = _share_bounds(c, rows.value, n_params if name == "coverage90" else 1)
                base = name.split("@")[0]
                rec[name] = float(c["mean"].iloc[0]) if c is not None else np.nan
                rec[f"{base}_lo"] = float(c["lo"].iloc[0]) if c is not None else np.nan
                rec[f"{base}_hi"] = float(c["hi"].iloc[0]) if c is not None else np.nan
            rec["rhat_max"] = (float(at[at.metric == "rhat_max"].value.max())
                               if (at.metric == "rhat_max").any() else np.nan)
            rec["ess_min"] = (float(at[at.metric == "ess_min"].value.min())
                              if (at.metric == "ess_min").any() else np.nan)
            rec["s_per_id"] = (float(at[at.metric == "wall_s"].value.median())
                               if (at.metric == "wall_s").any() else np.nan)
            recs.append(rec)
        t = pd.DataFrame(recs)
        if t.empty:
            return t
        key = f"param_mse@{last}"
        t["rank"] = np.nan
        t["rank_worst"] = np.nan
        for _, idx in t.groupby("system").groups.items():
            sub = t.loc[idx]
            t.loc[idx, "rank"] = _ci_rank(sub[key], sub.param_mse_lo, sub.param_mse_hi)
            # worst: ranked methods minus those whose whole CI lies above this one's
            worse = _ci_rank(-sub[key], -sub.param_mse_hi, -sub.param_mse_lo)
            t.loc[idx, "rank_worst"] = np.isfinite(sub[key]).sum() + 1 - worse
        # rows in a fixed order (system, method, input), not by a noisy figure: a rerun whose
        # figures move within their CIs must not reorder the table (the rank column ranks)
        return t.sort_values(["system", "method", "input"]).reset_index(drop=True)

    def tables(self, df):
        """The summary as the report shows it: each figure with its 95% CI over cases."""
        import pandas as pd

        if df.empty:
            return {}
        t = self.summary(df)
        last = max(SYSTEM_LENGTHS)
        reference = reference_method(df.method.unique())

        def ci(r, name, digits=3):
            base = name.split("@")[0]
            return fmt_ci(r[name], r[f"{base}_lo"], r[f"{base}_hi"], digits)

        def num(x, fmt):
            return format(x, fmt) if np.isfinite(x) else "-"

        rows = [{"system": r.system, "method": r.method, "input": r.input, "cases": r.cases,
                 f"param MSE @ {last}": ci(r, f"param_mse@{last}"),
                 "forecast MSE @ 50": ci(r, "forecast_mse@50"),
                 "coverage 90%": ci(r, "coverage90", 2),
                 "check passes": ci(r, "check_pass", 2),
                 "chains converged": ci(r, "converged", 2),
                 f"gap to {reference}": ci(r, "ref_gap"),
                 "s / identification": num(r.s_per_id, ".3g"),
                 "rank": _rank_text(r["rank"], r["rank_worst"])} for _, r in t.iterrows()]
        return {"systems_summary": pd.DataFrame(rows)}

    def figures(self, df, store, outdir: Path):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from sysid_bench.bench.figures import method_color

        if df.empty:
            return {}
        t = self.summary(df)
        last = max(SYSTEM_LENGTHS)
        systems_ = sorted(t.system.unique())
        meths = sorted(t.method.unique())
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
        width = 0.8 / max(len(meths), 1)
        for j, m in enumerate(meths):
            g = t[t.method == m].set_index("system")
            xs = np.arange(len(systems_)) + (j - (len(meths) - 1) / 2) * width
            for ax, col in zip(axes, (f"param_mse@{last}", "forecast_mse@50")):
                ys = [g[col].get(s, np.nan) if s in g.index else np.nan for s in systems_]
                ax.bar(xs, ys, width=width, label=m, color=method_color(m))
        for ax, col, lab in zip(axes, (f"param_mse@{last}", "forecast_mse@50"),
                                (f"parameter MSE after {last} frames", "forecast MSE (100 after 50)")):
            ax.set_xticks(np.arange(len(systems_)), systems_)
            vals = t[col].to_numpy(dtype=float)
            if np.any(np.isfinite(vals) & (vals > 0)):
                ax.set_yscale("log")
            else:  # e.g. a method that does not forecast: nothing to draw on a log axis
                ax.text(0.5, 0.5, "no method answered", transform=ax.transAxes, ha="center")
            ax.set_ylabel(lab)
        axes[0].axhline(GUESS_MSE, color="k", ls=":", lw=1)
        axes[1].legend(fontsize=7, ncol=2, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        fig.tight_layout()
        outdir.mkdir(parents=True, exist_ok=True)
        path = outdir / "systems_summary.png"
        from sysid_bench.bench.figures import save_figure

        save_figure(fig, path)
        plt.close(fig)
        return {"Every method on every system: parameter MSE after 200 frames (dotted: guessing) "
                "and forecast MSE": path}

    def reading(self, df):
        if df.empty:
            return []
        t = self.summary(df)
        last = max(SYSTEM_LENGTHS)
        key = f"param_mse@{last}"
        out = []
        for s, g in t.groupby("system"):
            g = g[np.isfinite(g[key])].sort_values(key)
            if g.empty:
                continue
            win = g.iloc[0]
            ties = g[g.param_mse_lo <= win.param_mse_hi].method.tolist()
            tie = (f" (not separable from {', '.join(x for x in ties if x != win.method)} by "
                   "the 95% CIs)") if len(ties) > 1 else ""
            sent = (f"{s}: {win.method} identifies best ({win[key]:.3g} after {last} frames){tie}")
            f = g[np.isfinite(g["forecast_mse@50"])].sort_values("forecast_mse@50")
            if len(f):
                sent += f"; best forecast {f.iloc[0].method} ({f.iloc[0]['forecast_mse@50']:.3g})"
            out.append(sent + ".")
        return out
