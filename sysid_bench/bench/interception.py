"""Experiment 8: interception, the paper's robot experiment, simulated (the ball's task).

A slow end effector must meet a bouncing ball whose physics it does not know, from a camera-like
video seen one frame at a time (:mod:`sysid_bench.bench.intercept`; the task in full in
:mod:`sysid_bench.apps.intercept`, the ``sysid-bench intercept`` app). Every policy of the run is
scored on the same seeded throws: the built-in ones (``oracle``, random targets at 1 and 2 Hz,
``react``, ``kalman``), those the run's online methods declare (``policies``) and the run's
forecasting methods of declared cost at most :data:`MAX_COST` (re-identifying every few frames).

A cell is one policy on :data:`CHUNK` consecutive throws (throw ``i`` depends only on the seed
and ``i``); its rows, per throw: ``success``, ``miss_m``, ``decision_s``, ``settled_s``,
``step_ms``, ``step_mean_ms``, ``skipped_steps``, ``t_cross_s``, ``y_cross_m``, ``reachable``,
``n_bounces``, ``failed`` (the policy raised). The cell's method is the registered method
behind the policy, or the policy's own name for a built-in one (no method: its cells'
fingerprint is the experiment's code); the condition is the policy.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sysid_bench.bench.experiment import Cell, CellOutput, Context, Experiment

__all__ = ["Interception", "policies", "MAX_COST", "CHUNK", "SEED"]

#: Throws per cell.
CHUNK = 10
#: The throws' seed: that of ``sysid-bench intercept``'s default, so its figures compare.
SEED = 0
#: A forecasting method re-identifies every few frames as a policy only when its declared cost
#: is at most this (bo, emcee, nuts would take minutes per throw).
MAX_COST = 8
#: The paper's PR2 caught 27 of 35 throws; its random policies at 1 Hz and 2 Hz 8 and 10.
PAPER = {"robot": (27, 35), "random-1hz": (8, 35), "random-2hz": (10, 35)}

_METRICS = ("success", "miss_m", "decision_s", "settled_s", "step_ms", "step_mean_ms",
            "skipped_steps", "t_cross_s", "y_cross_m", "reachable", "n_bounces")


def policies(methods=None) -> list[str]:
    """The policies of a run: the built-in ones, those the run's online methods declare
    (``policies``), and the run's forecasting methods of declared cost at most
    :data:`MAX_COST`."""
    import methods as registry
    from sysid_bench.bench.intercept.registry import POLICIES, _stream_policies

    def wanted(m):
        return methods is None or m in methods

    out = list(POLICIES)
    out += [p for p, (m, _) in _stream_policies().items() if wanted(m) and p not in out]
    for m in registry.available():
        if not wanted(m) or m in out:
            continue
        try:
            sp = registry.spec(m)
        except ImportError:  # a method whose packages are not installed
            continue
        if sp.forecasts and not sp.online and sp.cost <= MAX_COST:
            out.append(m)
    return out


def _backing(policy: str) -> str:
    """The registered method behind ``policy`` (the policy's name for a built-in one)."""
    from sysid_bench.bench.intercept.registry import _stream_policies

    return _stream_policies().get(policy, (policy, None))[0]


class Interception(Experiment):
    name = "interception"
    title = "8. Interception (the paper's robot experiment, simulated)"
    systems = ("ball",)  # the paper's task: a ball thrown at a robot
    #: the bench modules whose code decides the rows (part of the cells' fingerprint)
    depends_on = ("sysid_bench.bench.intercept.scene", "sysid_bench.bench.intercept.policies",
                  "sysid_bench.bench.intercept.kalman", "sysid_bench.bench.intercept.registry",
                  "sysid_bench.bench.intercept.evaluation")

    @property
    def description(self) -> str:
        from sysid_bench.bench.intercept.scene import Scene

        sc = Scene().as_dict()
        nuis = ", ".join(f"{k} {v:g}" for k, v in sorted((sc.get("nuisance") or {}).items()))
        return (
            f"A ball drawn from the test sub-ranges, filmed at 20 Hz with camera nuisances "
            f"({nuis}), must be met by an effector moving only vertically on x = "
            f"{sc['x_catch']:g} m at most {sc['speed']:g} m/s from {sc['effector_start']:g} m, "
            f"within {sc['catch_radius']:g} m of the ball's centre at its first crossing after "
            f"{sc['t_min']:g} s (always after a bounce). Models are reset at every throw; every "
            f"policy sees the same throws (seed {SEED}). Rates with 95% Wilson intervals; the "
            "paper's PR2 caught 27/35 (77%), its random policies 8/35 and 10/35. See "
            "`docs/intercept.md`.")

    def cells(self, scale, methods, system="ball"):
        n = scale.n_for(self.name, system)
        return [Cell(self.name, _backing(p), "video", p, k, system)
                for p in policies(methods) for k in range(-(-n // CHUNK))]

    def run(self, cell: Cell, ctx: Context) -> CellOutput:
        from sysid_bench.bench.intercept.evaluation import evaluate
        from sysid_bench.bench.intercept.figure import thin_trace

        n = ctx.scale.n_for(self.name, cell.system)
        first = int(cell.case) * CHUNK
        last = min(n, first + CHUNK)
        df = evaluate(cell.condition, n_throws=last, seed=SEED, first=first,
                      record=[0] if first == 0 else [])
        out = CellOutput()
        for r in df.itertuples():
            for m in _METRICS:
                out.add(r.throw, 0, m, float(getattr(r, m)))
            out.add(r.throw, 0, "failed", float(bool(r.error)))
        traces = df.attrs.get("traces") or {}
        if 0 in traces:  # the figure's drawn throw, as JSON bytes (artifacts are arrays)
            blob = json.dumps(thin_trace(traces[0]), default=float).encode()
            out.artifacts["trace"] = np.frombuffer(blob, dtype=np.uint8)
        return out

    # -- report -----------------------------------------------------------------------------
    def summary(self, df):
        """One row per policy: throws, caught, rate and its 95% Wilson interval, medians of
        miss, lead, settled lead and control-step time, errors; in the app's policy order."""
        import pandas as pd

        from sysid_bench.bench.intercept.evaluation import wilson_interval
        from sysid_bench.bench.intercept.figure import order_key

        recs = []
        for pol, g in df.groupby("condition"):
            # (NaN values are stored as NULL: pivot keeps them, and every metric's column)
            w = (g.pivot(index="case", columns="metric", values="value")
                 .reindex(columns=[*_METRICS, "failed"]).astype(float))
            n = len(w)
            k = int(w.success.sum())
            lo, hi = wilson_interval(k, n)
            ok = w[w.failed == 0]
            recs.append({
                "policy": pol, "throws": n, "caught": k, "rate %": 100 * k / n if n else np.nan,
                "95% CI %": f"{100 * lo:.1f}-{100 * hi:.1f}", "_lo": lo, "_hi": hi,
                "median miss m": float(ok.miss_m.median()) if len(ok) else np.nan,
                "median lead s": float((ok.t_cross_s - ok.decision_s).median())
                if len(ok) else np.nan,
                "median settled lead s": float((ok.t_cross_s - ok.settled_s).fillna(0.0).median())
                if len(ok) else np.nan,
                "median step ms": float(w.step_ms.median()),
                "mean step ms": float(w.step_mean_ms.mean()),
                "errors": int(w.failed.sum()),
            })
        t = pd.DataFrame(recs)
        if t.empty:
            return t
        t["_k"] = t.policy.map(order_key)
        return t.sort_values("_k").drop(columns="_k").reset_index(drop=True)

    def tables(self, df):
        t = self.summary(df)
        if t.empty:
            return {}
        return {"intercept_summary": t.drop(columns=["_lo", "_hi"])}

    def figures(self, df, store, outdir: Path):
        from sysid_bench.bench.intercept.figure import intercept_figure
        from sysid_bench.bench.intercept.scene import Scene

        t = self.summary(df)
        if t.empty:
            return {}
        system = str(df.system.iloc[0]) if "system" in df.columns else "ball"
        arts = store.artifacts(f"{system}/{self.name}|%|0")
        traces = {}
        for (cid, name), a in arts.items():
            if name == "trace":
                pol = cid.split("|")[3]
                traces[pol] = {"0": json.loads(a.tobytes().decode())}
        results = {r.policy: {"summary": {"rate": r["rate %"] / 100, "ci95_lo": r._lo,
                                          "ci95_hi": r._hi, "throws": r.throws},
                              "scene": Scene().as_dict(), "traces": traces.get(r.policy, {})}
                   for _, r in t.iterrows()}
        path = intercept_figure(results, Path(outdir) / "intercept.png")
        if path is None:
            return {}
        return {"Interception: success rates with 95% CIs; one throw of the first forecasting "
                "policy drawn: the ball, its forecast (mean +- 2 std) at three instants, the "
                "effector and the catch window at the crossing": path}

    def reading(self, df):
        t = self.summary(df)
        if t.empty:
            return []
        from sysid_bench.bench.intercept.registry import POLICIES

        pk, pn = PAPER["robot"]
        out = []
        for _, r in t[~t.policy.isin(list(POLICIES))].iterrows():  # the methods' policies
            verdict = ("above" if r._lo > pk / pn else "below" if r._hi < pk / pn
                       else "not separable from")
            out.append(f"{r.policy} caught {r.caught}/{r.throws} ({r['rate %']:.0f}%, 95% CI "
                       f"{r['95% CI %']}%): {verdict} the paper's PR2 ({pk}/{pn}, "
                       f"{100 * pk / pn:.0f}%).")
        return out
