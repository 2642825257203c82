"""Experiment 1: identification against the number of observed frames (paper, Fig. "sysID").

On every registered system, every method identifies the system's parameters of each test case
after 10, 20, ..., 200 frames, once from video only (the system's render; position methods
track it) and once from the true positions and initial state (the paper's privileged
baselines; methods that read pixels get video only). Rows per case and frame count:
``se_<p>`` (squared error of parameter p normalised by its prior range), ``se`` (their mean),
``wall_s`` (seconds for that identification) and ``n_simulations`` when the method reports it.

Cases: the ball's are the paper's test videos (:mod:`sysid_bench.core.datasets`, 20 at the default
scale); every other system's are its test split (:func:`~sysid_bench.bench.cases.system_cases`),
fewer at the default scale (``n_cases["identification"]["*"]``): the position methods there
reach 1e-4 to 1e-2 within a few cases (section 0's CIs), so 4 cases show the curves and their
order, not a figure to three digits.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sysid_bench.bench.cases import bench_case, inputs_for
from sysid_bench.bench.experiment import (
    Cell,
    CellOutput,
    Context,
    Experiment,
    ci_summary,
    fmt_ci,
    paper_methods,
    timed_prefixes,
)
from sysid_bench.core.metrics import GUESS_MSE


def method_inputs(method: str, wanted) -> list[str]:
    """Input kinds ``method`` runs on, from its declared ``input_kind`` (no instantiation)."""
    import methods

    return inputs_for(methods.spec(method).input_kind, wanted)


def case_cells(experiment: str, scale, methods: list[str], wanted,
               system: str = "ball") -> list[Cell]:
    """One cell per (method, input kind it runs on, test case) of ``system``, in that nesting
    order."""
    return [
        Cell(experiment, m, inp, "", i, system)
        for m in methods
        for inp in method_inputs(m, wanted)
        for i in range(scale.cases(experiment, m, system))
    ]


def system_params(df) -> tuple[str, ...]:
    """The parameter names of the system whose rows ``df`` holds (the report hands each
    experiment one system's rows)."""
    from sysid_bench.core import systems

    name = str(df.system.iloc[0]) if "system" in df.columns and len(df) else "ball"
    return tuple(systems.get(name).params)


def paper_system(df) -> bool:
    """Whether ``df``'s system is the one of the paper whose claims the readings check."""
    from sysid_bench.core import systems

    name = str(df.system.iloc[0]) if "system" in df.columns and len(df) else "ball"
    return bool(systems.get(name).paper)


def normalised_se(system: str, truth, mean) -> np.ndarray:
    """Squared error (P,) of each parameter normalised by ``system``'s prior range."""
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    span = np.asarray(sys_.prior_hi, float) - np.asarray(sys_.prior_lo, float)
    return ((np.asarray(mean, float) - np.asarray(truth, float)) / span) ** 2


class Identification(Experiment):
    name = "identification"
    title = "1. Identification vs observed frames"
    description = (
        "Normalised parameter MSE (each parameter scaled to [0, 1] by its prior range; always "
        f"answering the prior mean scores {GUESS_MSE:.3f}) after 10, 20, ..., 200 observed frames, "
        "and seconds per identification. `video`: frames (and the floor height) only, position "
        "methods track the ball; `privileged`: true positions and initial state, floor known, as the "
        "paper's lsq/bo baselines had. Seconds are wall-clock time of one identification in "
        "a single-threaded worker while the other workers run other cells: ratios between "
        "methods of one run compare, absolute values depend on the machine's load."
    )

    def cells(self, scale, methods, system="ball"):
        return case_cells(self.name, scale, methods, ("video", "privileged"), system)

    def run(self, cell: Cell, ctx: Context) -> CellOutput:
        from sysid_bench.core import systems

        sc = ctx.scale
        i = int(cell.case)
        obs, truth, _ = bench_case(cell.system, i, sc.n_for(self.name, cell.system), sc.seed,
                                   cell.input)
        lengths = [n for n in sc.lengths_for(cell.method) if n <= obs.n_frames]
        # the fits forecasting and calibration ask for on these cases are these (fitcache)
        est = ctx.estimator(cell.method, system=cell.system, share_fits=True)
        params = systems.get(cell.system).params
        out = CellOutput()
        for n, post, wall in timed_prefixes(est, obs, lengths, out, case=i):
            se = normalised_se(cell.system, truth, post.mean)
            for p, v in zip(params, se):
                out.add(i, n, f"se_{p}", v)
            out.add(i, n, "se", se.mean())
            out.add(i, n, "wall_s", wall)
            nsim = post.extras.get("n_simulations")
            if nsim is not None:
                out.add(i, n, "n_simulations", nsim)
        return out

    # -- report -----------------------------------------------------------------------------
    def _summary(self, df, metric):
        return ci_summary(df[df.metric == metric], ["method", "input", "n_frames"])

    def tables(self, df):
        import pandas as pd

        if df.empty:
            return {}
        s = self._summary(df, "se")
        frames = sorted(s.n_frames.unique())
        show = [n for n in (10, 20, 50, 100, 150, 200) if n in frames] or frames
        wide = {}
        for (m, inp), g in s.groupby(["method", "input"]):
            g = g.set_index("n_frames")
            rec = {"method": m, "input": inp, "cases": int(g.n.max())}
            for n in show:
                rec[f"{n} frames"] = fmt_ci(*g.loc[n, ["mean", "lo", "hi"]]) if n in g.index else "-"
            wide[(m, inp)] = rec
        mse = pd.DataFrame(list(wide.values()))

        last = max(frames)
        per = []
        for (m, inp), g in df[df.n_frames == last].groupby(["method", "input"]):
            rec = {"method": m, "input": inp}
            for p in system_params(df):
                s_p = ci_summary(g[g.metric == f"se_{p}"], ["method"]).iloc[0]
                rec[p] = fmt_ci(s_p["mean"], s_p["lo"], s_p["hi"])
            per.append(rec)
        params = pd.DataFrame(per)

        w = df[df.metric == "wall_s"]
        med = w.groupby(["method", "input", "n_frames"]).value.median().unstack("n_frames")
        sp = []
        # speeds relative to the paper's method (the first that declares ``claims``), from video
        head = next(iter(paper_methods(df.method.unique())), None)
        ref = med.loc[(head, "video"), last] if (head, "video") in med.index else None
        for (m, inp), row in med.iterrows():
            rec = {"method": m, "input": inp}
            for n in [n for n in (20, 50, 100, 200) if n in med.columns]:
                rec[f"s @ {n}"] = _g(row[n])
            rec[f"s/frame @ {last}"] = _g(row[last] / last)
            if ref:
                rec[f"x {head} @ {last}"] = _g(row[last] / ref)
            sp.append(rec)
        speed = pd.DataFrame(sp)
        return {
            "identification_mse": mse,
            f"identification_params_at_{last}": params,
            "identification_speed": speed,
        }

    def figures(self, df, store, outdir: Path):
        import matplotlib.pyplot as plt

        if df.empty:
            return {}
        figs = {}
        s = self._summary(df, "se")
        inputs = [i for i in ("video", "privileged") if i in set(s.input)]
        fig, axes = plt.subplots(1, len(inputs), figsize=(6 * len(inputs), 4), squeeze=False,
                                 sharey=True)
        # the plotted range follows the means: a band reaching far below every mean (emcee's
        # lower CI over 4 cases, down to 1e-9) would squash every other line; it is clipped
        pos = s["mean"][s["mean"] > 0]
        bottom = 10 ** np.floor(np.log10(pos.min() / 3)) if len(pos) else None
        for ax, inp in zip(axes[0], inputs):
            for m, g in s[s.input == inp].groupby("method"):
                ax.plot(g.n_frames, g["mean"], marker="o", ms=3, label=m, color=method_color(m))
                ax.fill_between(g.n_frames, g.lo, g.hi, alpha=0.2, color=method_color(m))
            ax.axhline(GUESS_MSE, color="k", ls=":", lw=1, label="prior mean")
            ax.set(title=f"input: {inp}", xlabel="observed frames", ylabel="normalised param MSE",
                   yscale="log")
            if bottom is not None:
                ax.set_ylim(bottom=bottom)
        # one legend for both panels (a method may be in one only), outside: no data hidden
        seen = {}
        for ax in axes[0]:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                seen.setdefault(lab, h)
        axes[0, -1].legend(seen.values(), seen.keys(), fontsize=7, loc="upper left",
                           bbox_to_anchor=(1.01, 1.0))
        figs["Accuracy vs observed frames (95% bootstrap CI bands, clipped at the plotted "
             "range)"] = _save(fig, outdir / "identification_accuracy.png")

        params = system_params(df)
        fig, axes = plt.subplots(1, len(params), figsize=(4 * len(params), 3.6), sharey=True,
                                 squeeze=False)
        axes = axes[0]
        for ax, p in zip(axes, params):
            sp = self._summary(df, f"se_{p}")
            for (m, inp), g in sp.groupby(["method", "input"]):
                ax.plot(g.n_frames, g["mean"], ls="-" if inp == "video" else "--",
                        label=f"{m} ({inp})", color=method_color(m))
            ax.axhline(GUESS_MSE, color="k", ls=":", lw=1)
            ax.set(title=p, xlabel="observed frames", yscale="log")
        axes[0].set_ylabel("normalised MSE")
        axes[-1].legend(fontsize=6)
        figs["Per-parameter accuracy (solid: video, dashed: privileged)"] = _save(
            fig, outdir / "identification_params.png")

        w = df[df.metric == "wall_s"].groupby(["method", "input", "n_frames"]).value.median()
        fig, ax = plt.subplots(figsize=(6, 4))
        for (m, inp), g in w.groupby(level=[0, 1]):
            g = g.droplevel([0, 1])
            ax.plot(g.index, g.values, ls="-" if inp == "video" else "--", marker="o", ms=3,
                    label=f"{m} ({inp})", color=method_color(m))
        ax.set(xlabel="observed frames", ylabel="seconds per identification (median)",
               yscale="log", title="Speed vs observed frames")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: no data hidden
        figs["Speed vs observed frames"] = _save(fig, outdir / "identification_speed.png")
        return figs

    def reading(self, df):
        if df.empty:
            return []
        out = []
        s = self._summary(df, "se").set_index(["method", "input", "n_frames"])
        last = int(df.n_frames.max())
        # the paper's method (the first that declares ``claims``), from video
        head = next(iter(paper_methods(df.method.unique())), None)
        v2p = (head, "video")
        if (*v2p, last) in s.index:
            a = s.loc[(*v2p, last)]
            if a["hi"] >= GUESS_MSE:
                out.append(
                    f"{head} (video) does not beat guessing the prior mean: "
                    f"{fmt_ci(a['mean'], a['lo'], a['hi'])} at {last} frames vs {GUESS_MSE:.3f}; "
                    "every comparison with it below reflects the model this run used "
                    "(see its model card).")
        import methods as registry

        # the paper's baselines (declared ``paper_baseline``) are compared on the paper's system
        bases = [m for m in sorted(df.method.unique()) if paper_system(df)
                 and m in registry.available(include_reference=True)
                 and registry.spec(m).paper_baseline]
        for base in bases:
            if (*v2p, last) in s.index and (base, "privileged", last) in s.index:
                a, b = s.loc[(*v2p, last)], s.loc[(base, "privileged", last)]
                frames = sorted({n for (m, i, n) in s.index if (m, i) == v2p})
                wins = sum(
                    s.loc[(*v2p, n), "mean"] <= s.loc[(base, "privileged", n), "hi"]
                    for n in frames if (base, "privileged", n) in s.index
                )
                # "similar or better" fails only where the CIs separate with Vid2Param's above
                if a["lo"] > b["hi"]:
                    verdict = "does NOT hold (95% CIs disjoint)"
                elif a["hi"] < b["lo"]:
                    verdict = "holds (better, 95% CIs disjoint)"
                else:
                    verdict = "holds (not separable: the 95% CIs overlap)"
                if a["lo"] <= GUESS_MSE <= a["hi"] and b["lo"] <= GUESS_MSE <= b["hi"]:
                    verdict += f" only in that both are at the guessing level ({GUESS_MSE:.3f})"
                out.append(
                    f"Paper: Vid2Param from video is similar to or better than {base} with true "
                    f"positions and initial state. Here at {last} frames {head} (video) scores "
                    f"{fmt_ci(a['mean'], a['lo'], a['hi'])} vs {base} (privileged) "
                    f"{fmt_ci(b['mean'], b['lo'], b['hi'])}: the claim {verdict}; {head}'s mean "
                    f"is within or below {base}'s CI at {wins} of {len(frames)} frame counts."
                )
        w = df[(df.metric == "wall_s") & (df.n_frames == last)].groupby(["method", "input"]).value.median()
        if v2p in w.index:
            # (a method of cost 0 answers without computing: no speed to compare)
            slower = [f"{m} ({i}) {w[(m, i)] / w[v2p]:.3g}x" for (m, i) in w.index
                      if (m, i) != v2p and not _free(m)]
            if slower:
                out.append(
                    f"Speed at {last} frames, median seconds per identification relative to "
                    f"{head} ({w[v2p]:.3g} s): " + ", ".join(slower) + "."
                )
        if (*v2p, last) in s.index and paper_system(df):
            params = system_params(df)
            se = {p: self._summary(df, f"se_{p}").set_index(["method", "input", "n_frames"])
                  for p in params}
            parts = []
            for p in params:
                t = se[p]
                early = [n for n in (20, 50) if (*v2p, n) in t.index]
                vals = ", ".join(f"{t.loc[(*v2p, n), 'mean']:.3g} @ {n}" for n in [*early, last])
                parts.append(f"{p}: {vals}")
            out.append(
                "Paper: g and d are inferred after a few frames, e after the first bounce, r has "
                f"the highest error until late. {head} per-parameter MSE here (guess = "
                f"{GUESS_MSE:.3f}): " + "; ".join(parts) + "."
            )
        return out


def _free(method: str) -> bool:
    """A method that declares cost 0 (the prior: it computes nothing)."""
    import methods as registry

    try:
        return registry.spec(method).cost == 0
    except (ValueError, ImportError):
        return False


def _g(x: float) -> str:
    """3 significant digits, ``-`` for missing."""
    return "-" if x is None or not np.isfinite(x) else f"{x:.3g}"


def _save(fig, path: Path) -> Path:
    from sysid_bench.bench.figures import save_figure

    return save_figure(fig, path)


def method_color(method: str) -> str:
    from sysid_bench.bench.figures import method_color as mc

    return mc(method)
