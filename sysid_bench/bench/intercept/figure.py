"""The interception experiment's figure and the helpers the app shares with it: names, the
order of policies, traces thinned for storage."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["intercept_figure", "thin_trace", "order_key", "slug"]


def slug(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def thin_trace(trace: dict, n_forecasts: int = 12) -> dict:
    """A throw's trace made small for disk: at most ``n_forecasts`` forecasts, evenly spread
    (first and last kept), numbers rounded to 1 mm / 1 ms."""

    def rnd(v):
        if isinstance(v, float):
            return round(v, 3)
        if isinstance(v, list):
            return [rnd(x) for x in v]
        if isinstance(v, dict):
            return {k: rnd(x) for k, x in v.items()}
        return v

    out = dict(trace)
    fcs = trace.get("forecasts", [])
    if len(fcs) > n_forecasts:
        keep = np.unique(np.linspace(0, len(fcs) - 1, n_forecasts).round().astype(int))
        out["forecasts"] = [fcs[i] for i in keep]
    return rnd(out)


#: Order of the built-in policies in tables and figures, after those of the methods.
_BUILTIN_ORDER = ("kalman", "react", "random-2hz", "random-1hz", "oracle")


def order_key(policy: str) -> tuple:
    """Tables and figures list the methods' policies first, in registry order (names only:
    nothing is imported), then other declared policies by name, then the built-ins; a drawn
    throw prefers the first with a trace."""
    import methods

    reg = methods.available(include_reference=True)
    if policy in reg:
        return (0, reg.index(policy), policy)
    if policy in _BUILTIN_ORDER:
        return (2, _BUILTIN_ORDER.index(policy), policy)
    return (1, 0, policy)


def intercept_figure(results: dict, path, draw: str | None = None) -> Path | None:
    """Success rates with 95% CIs per policy, and one throw drawn (height and x against time).

    Parameters
    ----------
    results : dict
        policy -> the JSON written by :func:`write_results`.
    path : path of the PNG.
    draw : str, optional
        Policy whose recorded throw to draw; default the first in table order with a trace.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sysid_bench.bench.figures import save_figure

    if not results:
        return None
    pols = list(results)
    rates = np.array([results[p]["summary"]["rate"] for p in pols])
    lo = np.array([results[p]["summary"]["ci95_lo"] for p in pols])
    hi = np.array([results[p]["summary"]["ci95_hi"] for p in pols])
    if draw is None:
        draw = next((p for p in pols if p != "oracle" and results[p].get("traces")), None)
    trace = None
    if draw is not None and results.get(draw, {}).get("traces"):
        trace = next(iter(results[draw]["traces"].values()))
    ncol = 3 if trace else 1
    fig, axes = plt.subplots(1, ncol, figsize=(5.0 * ncol, 3.8), squeeze=False)
    ax = axes[0, 0]
    y = np.arange(len(pols))
    ax.barh(y, 100 * rates, color="#4c72b0", alpha=0.8)
    ax.errorbar(100 * rates, y, xerr=[100 * (rates - lo), 100 * (hi - rates)], fmt="none",
                ecolor="k", capsize=3)
    ax.set_yticks(y, [f"{p} (n={results[p]['summary']['throws']})" for p in pols])
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("throws caught, % (95% Wilson CI)")
    ax.axvline(77, color="grey", ls=":", lw=1, label="paper's PR2 (27/35)")
    ax.legend(fontsize=7, loc="lower right")
    if trace:
        sc = results[draw].get("scene") or {}
        bt, bx, by = (np.asarray(trace[k]) for k in ("ball_t", "ball_x", "ball_y"))
        fcs = trace["forecasts"]
        pick = [fcs[i] for i in sorted({int(round(q * (len(fcs) - 1))) for q in (0.0, 0.4, 0.8)})] \
            if fcs else []
        colours = ["#dd8452", "#55a868", "#8172b3"]
        for ax, dim, b in ((axes[0, 1], 1, by), (axes[0, 2], 0, bx)):
            ax.plot(bt, b, color="k", lw=1.5, label="ball (true)")
            for c, f in zip(colours, pick):
                ft, fm, fs = np.asarray(f["times"]), np.asarray(f["mean"]), np.asarray(f["std"])
                ax.plot(ft, fm[:, dim], color=c, lw=1, label=f"forecast at {f['t']:.2f} s")
                ax.fill_between(ft, fm[:, dim] - 2 * fs[:, dim], fm[:, dim] + 2 * fs[:, dim],
                                color=c, alpha=0.2)
            ax.axvline(trace["t_cross"], color="grey", ls="--", lw=1)
            ax.set_xlim(0, trace["t_cross"] + 0.5)
            ax.set_xlabel("t (s)")
        ax = axes[0, 1]
        ax.plot(trace["effector_t"], trace["effector_y"], color="#c44e52", lw=2, label="effector")
        r = sc.get("catch_radius", 0.5)
        ax.errorbar([trace["t_cross"]], [trace["y_cross"]], yerr=[[r], [r]], fmt="o", color="k",
                    capsize=4, ms=4, label="catch window")
        ax.set_ylabel("height y (m)")
        ax.set_title(f"{draw}, throw {trace['throw']}: "
                     f"{'caught' if trace['success'] else 'missed'}", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
        ax = axes[0, 2]
        ax.axhline(sc.get("x_catch", 5.0), color="#c44e52", lw=1.5, label="x_catch")
        ax.set_ylabel("x (m)")
        ax.set_title("across: when the ball reaches the line (bands: mean +- 2 std)", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    return save_figure(fig, path)
