"""Experiment 6: physics that is not ours (the paper's "real videos", from MuJoCo).

Videos come from an independent engine (:mod:`sysid_bench.core.mujoco_scene`: soft contacts with a
finite contact time, friction that spins the ball up at each bounce and lets it roll, MuJoCo's
fluid drag with Magnus lift) for rubber, tennis and ping-pong balls, rendered by MuJoCo's own
renderer in the suite's framing, written as H.264 files and generated once per run directory
(``<run_dir>/foreign_videos``, seeded by the scale's seed). Every method reads them as a user's
file would be read (:func:`sysid_bench.core.footage.read_video`, the ball found by background
subtraction; Vid2Param sees frames re-drawn at the track, position methods the track).

Rows per case and frame count: ``se_<p>`` (squared error against what the engine measurably
did, normalised by the prior range; ``r`` only where the ball rolled), ``se`` (their mean),
``wall_s``, ``hit90_<p>`` (1 when the posterior's central 90% interval holds that measured
value), ``check_ok`` (1 when the posterior's model check passed; methods that return one);
and, the paper's real-video metric, ``last10_rmse`` / ``last10_mse``: the error of the
forecast of the video's last ten positions from the first ``n`` frames (metres RMS, and the
normalised position MSE), for ``n`` growing as the video unrolls.

Skipped (no cells; the report says why) when MuJoCo does not import. Where MuJoCo's renderer
is unavailable the engine's trajectories are drawn by the suite's renderer and the report says
so (the physics is MuJoCo's either way).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from sysid_bench.bench.calibration import (
    COVERAGE_BAND,
    EGD,
    FEW_CASES,
    band_verdict,
    honest_rows,
    share_ci,
)
from sysid_bench.bench.calibration import n_cases as plural_cases
from sysid_bench.bench.experiment import (
    Cell,
    CellOutput,
    Context,
    Experiment,
    ci_summary,
    fmt_ci,
    timed_prefixes,
)
from sysid_bench.core._io import atomic_write
from sysid_bench.core.metrics import GUESS_MSE, normalised_param_se, position_mse
from sysid_bench.core.physics import PARAMS

#: per scale: cases (ball types in turn), frames per video, identification prefixes, forecast
#: prefixes (forecasting the last ten frames); methods of the expensive tier
#: (``Scale.thinned``) get the ``*_expensive`` prefixes, and a method's declared
#: ``scale_cases["foreign"]`` caps its cases
CONFIG = {
    "smoke": {"n": 3, "frames": 120, "lengths": (50, 120), "forecast_after": (40, 100),
              "lengths_expensive": (120,), "forecast_after_expensive": (100,)},
    "quick": {"n": 1, "frames": 200, "lengths": (200,), "forecast_after": (120,),
              "lengths_expensive": (200,), "forecast_after_expensive": (120,)},
    # measured at load 8-12 with 2 workers: ~45 s per vid2param cell (forecasts of up to 180
    # frames with 200 particles), bo ~150 s per case: 7 forecast prefixes, bo / emcee on 2
    "default": {"n": 9, "frames": 200, "lengths": (25, 50, 100, 150, 200),
                "forecast_after": (20, 50, 80, 110, 140, 170, 190),
                "lengths_expensive": (100, 200), "forecast_after_expensive": (50, 120, 190)},
    "paper": {"n": 30, "frames": 200, "lengths": tuple(range(10, 201, 10)),
              "forecast_after": tuple(range(20, 191, 10)),
              "lengths_expensive": (50, 100, 150, 200),
              "forecast_after_expensive": (50, 100, 150, 190)},
}
N_EXAMPLES = 1
LAST = 10


def config(scale) -> dict:
    return CONFIG.get(scale.name, CONFIG["default"])


def video_dir(run_dir) -> Path:
    return Path(run_dir) / "foreign_videos"


@contextlib.contextmanager
def _lock(path: Path):
    """One process generates a case; the others wait and read it from the cache."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: generation may be duplicated
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def case_video(run_dir, scale, case: int):
    """(path, meta) of case ``case``'s MuJoCo video (generated on first use)."""
    from sysid_bench.core.mujoco_scene import make_video

    cfg = config(scale)
    d = video_dir(run_dir)
    with _lock(d / f".case{case}.lock"):
        return make_video(d, case, seed=scale.seed, n_frames=cfg["frames"])


def case_observation(path: Path, size):
    """:func:`sysid_bench.core.footage.observe` of a case's file; the track is cached beside it.

    Every method reads the same file, so the ball is found once per case (the tracker is
    deterministic; the cache is keyed by the file's size and the tracker's source).
    """
    import hashlib
    import inspect

    from sysid_bench.core import footage as video
    from sysid_bench.core.estimator import Observation

    key = hashlib.sha256(inspect.getsource(video).encode()
                         + str(path.stat().st_size).encode()).hexdigest()[:12]
    cache = path.with_name(f"{path.stem}.track-{key}.npz")
    if cache.is_file():
        with np.load(cache) as z:
            pix, radius, shape = z["pixels"], float(z["radius"]), tuple(z["shape"])
        trk = video.BallTrack(pix, radius, np.isfinite(pix).all(axis=1))
        geo = video.geometry_from_options(shape[1:])
        pos = geo.to_metres(pix)
        if size is not None:
            obs = Observation(frames=video.model_frames(pos, size), floor=0.0)
        else:
            obs = Observation(positions=np.clip(pos, 0.0, 10.0), floor=0.0)
        return obs, pos, trk
    clip = video.read_video(path)
    obs, pos, trk, _ = video.observe(clip.frames, size, dt=1.0 / clip.fps)
    atomic_write(cache, lambda tmp: np.savez(tmp, pixels=trk.pixels, radius=trk.radius,
                                             shape=np.array(clip.frames.shape)))
    return obs, pos, trk


class Foreign(Experiment):
    name = "foreign"
    systems = ("ball",)  # MuJoCo's ball against ours: a paper comparison of the ball's
    title = "6. Physics that is not ours (MuJoCo videos)"
    _description = (
        "Videos of rubber, tennis and ping-pong balls simulated by MuJoCo (soft contacts, "
        "spin-up and rolling by friction, the engine's fluid drag with Magnus lift), rendered by "
        "MuJoCo's renderer in the suite's framing and read back from H.264 files as a user's "
        "recording would be (`sysid_bench.video`: ball found by background subtraction; "
        "Vid2Param sees frames re-drawn at the track, position methods the track, floor known). "
        "Identification: normalised squared error against what the engine measurably did "
        "(e from its bounces, d fitted to its flight, r from its rolling, g exact; guessing "
        f"scores {GUESS_MSE:.3f}); coverage: share of e, g, d whose measured value the "
        "posterior's central 90% interval holds, and honest: the interval holds it or the "
        "method's model check fails (issue 29 asks 80-97% and at least 80%). Forecast: RMS "
        "error (m) of the last ten positions of the video predicted from the first n frames, as "
        "the video unrolls (the paper's real-video metric). The reference posterior (nuts) "
        "identifies after the whole clip only, on the first videos, for its coverage."
    )

    @property
    def description(self) -> str:
        from sysid_bench.core.mujoco_scene import mujoco_available

        why = mujoco_available()
        return self._description + (f" **Skipped on this machine: {why}**" if why else "")

    def cells(self, scale, methods, system="ball"):
        from sysid_bench.core.mujoco_scene import mujoco_available

        if mujoco_available() is not None:
            return []
        cfg = config(scale)
        out = []
        import methods as registry

        for m in methods:
            spec = registry.spec(m)
            cap = spec.cases_cap(scale.key_for(spec.scale_cases), self.name)
            n = cfg["n"] if cap is None else min(cfg["n"], cap)
            out += [Cell(self.name, m, "video", "", i) for i in range(n)]
        return out

    def run(self, cell: Cell, ctx: Context) -> CellOutput:
        import methods

        sc = ctx.scale
        cfg = config(sc)
        i = int(cell.case)
        path, meta = case_video(ctx.run_dir, sc, i)
        est = ctx.estimator(cell.method)
        frames_model = getattr(methods.get_class(cell.method), "input_kind", "positions") == "frames"
        size = tuple(est.frame_size) if frames_model else None
        obs, pos, trk = case_observation(path, size)
        if not frames_model and trk.n_found < 3:
            raise ValueError(f"the ball was found in {trk.n_found} frames of {path.name}")
        truth_states = np.asarray(meta["states"])
        t_n = min(obs.n_frames, len(truth_states))
        measured = np.array([np.nan if v is None else v for v in meta["measured"]])
        expensive = sc.thinned(cell.method)
        lengths = [n for n in cfg["lengths_expensive" if expensive else "lengths"] if n <= t_n]
        # the reference posterior (nuts, ~40 s a run) is here for its coverage off our physics
        # (issue 29): one posterior after the whole clip, no forecasts
        reference = methods.spec(cell.method).reference_posterior
        if reference:
            lengths = lengths[-1:]
        out = CellOutput()
        try:
            posts = timed_prefixes(est, obs, lengths, out, case=i)
        except NotImplementedError as exc:  # DMD: no parameters, but it forecasts
            posts, no_ident = [], exc
        else:
            no_ident = None
        for n, post, wall in posts:
            se = normalised_param_se(np.nan_to_num(measured, nan=0.5), post.mean)
            se = np.where(np.isfinite(measured), se, np.nan)
            for p, v in zip(PARAMS, se):
                if np.isfinite(v):
                    out.add(i, n, f"se_{p}", v)
            out.add(i, n, "se", np.nanmean(se))
            out.add(i, n, "wall_s", wall)
            # issue 29: do the 90% intervals hold what the engine measurably did?
            lo, hi = post.interval(0.9)
            for p, t, a, b in zip(PARAMS, measured, lo, hi):
                if np.isfinite(t):
                    out.add(i, n, f"hit90_{p}", float(a <= t <= b))
            if post.check is not None:
                out.add(i, n, "check_ok", float(post.check.ok))
        truth_last = truth_states[t_n - LAST : t_n, :2]
        for n in () if reference else cfg["forecast_after_expensive" if expensive
                                           else "forecast_after"]:
            if n > t_n - LAST:
                continue
            try:
                fc = est.forecast(obs.prefix(n), t_n - n)
            except NotImplementedError:
                if no_ident is not None:
                    raise  # neither identifies nor forecasts: n/a
                break  # identifies but does not forecast: keep the identification rows
            except Exception as exc:
                out.fail(n, exc, i)
                continue
            pred = fc.mean[-LAST:]
            out.add(i, n, "last10_rmse", float(np.sqrt(np.mean((pred - truth_last) ** 2))))
            out.add(i, n, "last10_mse", position_mse(truth_last, pred))
            if i < N_EXAMPLES:
                out.artifacts[f"fc_{n}"] = fc.mean
        if i < N_EXAMPLES:
            out.artifacts["tracked"] = pos
            out.artifacts["truth"] = truth_states[:, :2]
        out.add(i, 0, "mujoco_rendered", float(str(meta["renderer"]).startswith("mujoco")))
        out.add(i, 0, "found_frac", trk.n_found / max(1, len(trk.found)))
        out.add(i, 0, "track_rmse_m", float(np.sqrt(np.nanmean(
            (pos[:t_n] - truth_states[:t_n, :2]) ** 2))))
        return out

    # -- report -----------------------------------------------------------------------------
    def tables(self, df):
        import pandas as pd

        if df.empty:
            return {}
        tabs = {}
        ident = df[df.metric.str.startswith("se")]
        if len(ident):
            last = ident.groupby("method").n_frames.max()
            recs = []
            for m, n in last.items():
                g = ident[(ident.method == m) & (ident.n_frames == n)]
                rec = {"method": m, "frames": int(n), "cases": int(g.case.nunique())}
                for metric, lab in (("se", "mean"), *((f"se_{p}", p) for p in PARAMS)):
                    s = ci_summary(g[g.metric == metric], ["method"])
                    rec[lab] = fmt_ci(*s.iloc[0][["mean", "lo", "hi"]]) if len(s) and s.n.iloc[0] else "-"
                rec["fails (mean > guessing)"] = "yes" if g[g.metric == "se"].value.mean() > GUESS_MSE else "no"
                gm = df[(df.method == m) & (df.n_frames == n)]
                for lab, s in (("coverage 90% (e, g, d)", _coverage(gm)),
                               ("honest (e, g, d)", _honest(gm))):
                    rec[lab] = fmt_ci(s["mean"], s["lo"], s["hi"], 2) if s is not None else "-"
                recs.append(rec)
            tabs["foreign_identification"] = pd.DataFrame(recs)
        fc = df[df.metric == "last10_rmse"]
        if len(fc):
            s = ci_summary(fc, ["method", "n_frames"])
            wide = s.assign(v=[fmt_ci(a, b, c) for a, b, c in zip(s["mean"], s.lo, s.hi)]).pivot(
                index="method", columns="n_frames", values="v")
            wide.columns = [f"after {c}" for c in wide.columns]
            tabs["foreign_last10_rmse_m"] = wide.reset_index().fillna("-")
        tr = df[df.metric == "track_rmse_m"]
        if len(tr):
            per = tr.drop_duplicates("case").value
            tabs["foreign_tracking"] = pd.DataFrame([{
                "cases": len(per), "tracking RMS error (m), mean": f"{per.mean():.4f}",
                "worst case": f"{per.max():.4f}",
                "ball found (fraction of frames)": f"{df[df.metric == 'found_frac'].value.mean():.3f}"}])
        return tabs

    def figures(self, df, store, outdir: Path):
        import matplotlib.pyplot as plt

        from sysid_bench.bench.identification import _save, method_color

        figs = {}
        fc = df[df.metric == "last10_rmse"]
        if len(fc):
            s = ci_summary(fc, ["method", "n_frames"])
            fig, ax = plt.subplots(figsize=(7, 4))
            # methods that agree draw one line over another: each its own marker and dash, and
            # later lines thinner and on top, so a line under another still shows
            styles = [("o", "-"), ("s", "--"), ("^", "-."), ("D", ":"), ("v", "-"), ("P", "--"),
                      ("X", "-."), ("*", ":")]
            for k, (m, g) in enumerate(s.groupby("method")):
                mk, ls = styles[k % len(styles)]
                ax.plot(g.n_frames, g["mean"], marker=mk, ls=ls, ms=6 - 0.5 * (k % 4),
                        lw=2.2 - 0.3 * (k % 4), mfc="none", label=m, color=method_color(m),
                        zorder=3 + k)
                ax.fill_between(g.n_frames, g.lo, g.hi, alpha=0.15, color=method_color(m))
            ax.set(yscale="log", xlabel="frames observed",
                   ylabel="RMS error of the last 10 positions (m)",
                   title="MuJoCo videos: forecast of the last ten frames as the video unrolls")
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
            figs["Forecast of the last ten frames vs frames observed (MuJoCo videos; 95% CI)"] = \
                _save(fig, outdir / "foreign_convergence.png")
        ident = df[df.metric.str.startswith("se_")]
        if len(ident):
            last = ident.groupby("method").n_frames.transform("max")
            g = ident[ident.n_frames == last]
            s = ci_summary(g, ["method", "metric"])
            meths = sorted(s.method.unique())
            fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(meths)), 3.8))
            width = 0.8 / len(PARAMS)
            for k, p in enumerate(PARAMS):
                sp = s[s.metric == f"se_{p}"].set_index("method")
                ys = [sp.loc[m, "mean"] if m in sp.index else np.nan for m in meths]
                ax.bar(np.arange(len(meths)) + k * width, ys, width, label=p)
            ax.axhline(GUESS_MSE, color="k", ls="--", lw=0.8, label="guessing")
            ax.set_xticks(np.arange(len(meths)) + width * 1.5)
            ax.set_xticklabels(meths, fontsize=8)
            ax.set(yscale="log", ylabel="normalised squared error",
                   title="MuJoCo videos: error against the engine's measured parameters, all frames")
            ax.legend(fontsize=7, ncol=5)
            figs["Identification error against the engine's measured e, g, d, r"] = \
                _save(fig, outdir / "foreign_identification.png")
        arts = store.artifacts(f"%/{self.name}|%|0")
        meths = sorted({c.split("|")[1] for c, _ in arts})
        truth = next((v for (c, n), v in arts.items() if n == "truth"), None)
        if meths and truth is not None:
            fig, ax = plt.subplots(figsize=(7, 3.5))
            t = np.arange(len(truth))
            ax.plot(t, truth[:, 1], color="k", lw=1.5, label="MuJoCo (truth)")
            tracked = next((v for (c, n), v in arts.items() if n == "tracked"), None)
            if tracked is not None:
                ax.plot(t[: len(tracked)], tracked[:, 1], ".", ms=2, color="grey", label="tracked")
            for m in meths:
                keys = sorted((int(n.split("_")[1]), v) for (c, n), v in arts.items()
                              if c.split("|")[1] == m and n.startswith("fc_"))
                if keys:
                    n0, mean = keys[len(keys) // 2]
                    ax.plot(n0 + np.arange(len(mean)), mean[:, 1], lw=1, color=method_color(m),
                            label=f"{m} after {n0}")
            ax.set(xlabel="frame", ylabel="y (m)", title="MuJoCo case 0: forecasts of height")
            ax.legend(fontsize=6, ncol=2)
            figs["Example: MuJoCo case 0, forecasts of height"] = \
                _save(fig, outdir / "foreign_example.png")
        return figs

    def reading(self, df):
        if df.empty:
            return []
        out = []
        rend = df[df.metric == "mujoco_rendered"].drop_duplicates("case").value
        if len(rend) and rend.mean() < 1:
            out.append(f"{int((rend < 1).sum())} of {len(rend)} MuJoCo videos were drawn by the "
                       "suite's renderer (MuJoCo's offscreen renderer was unavailable); their "
                       "physics is MuJoCo's.")
        ident = df[df.metric == "se"]
        if len(ident):
            last = ident[ident.n_frames == ident.groupby("method").n_frames.transform("max")]
            m = ci_summary(last, ["method"]).sort_values("mean").set_index("method")
            # "worse than guessing" only where the whole 95% CI lies above it
            bad = [k for k, r in m.iterrows() if r["lo"] > GUESS_MSE]
            out.append("On MuJoCo videos (physics that is not ours) the identification error "
                       "after the last frame (95% CIs; ordered by mean, neighbours whose CIs "
                       "overlap are not separable): "
                       + ", ".join(f"{k} {fmt_ci(r['mean'], r['lo'], r['hi'])}"
                                   for k, r in m.iterrows())
                       + f" (guessing {GUESS_MSE:.3f})"
                       + (f"; worse than guessing, failing visibly: {', '.join(bad)}." if bad else "."))
        out += self._coverage_reading(df)
        fc = df[df.metric == "last10_rmse"]
        if len(fc):
            s = fc.groupby(["method", "n_frames"]).value.mean()
            lines = []
            for meth in s.index.get_level_values(0).unique():
                v = s.loc[meth]
                lines.append(f"{meth} {v.iloc[0]:.2f} m after {v.index[0]} -> {v.iloc[-1]:.2f} m "
                             f"after {v.index[-1]}")
            out.append("Paper (real videos): Vid2Param's forecast of the last ten frames "
                       "converges as frames come in. Here (RMS of the last ten positions): "
                       + "; ".join(lines) + ".")
        return out

    @staticmethod
    def _coverage_reading(df) -> list[str]:
        """One sentence: each method's 90% coverage of e, g, d and honest share after its last
        frame count, against issue 29's band; verdicts only where the whole 95% CI is outside."""
        hits = df[df.metric.isin([f"hit90_{p}" for p in EGD])]
        if hits.empty:
            return []
        last = hits.groupby("method").n_frames.max()
        lo_b, hi_b = COVERAGE_BAND
        parts, below, above = [], [], []
        for m, last_n in last.items():
            gm = df[(df.method == m) & (df.n_frames == last_n)]
            c, h = _coverage(gm), _honest(gm)
            n = gm[gm.metric.isin([f"hit90_{p}" for p in EGD])].case.nunique()
            few = n < FEW_CASES
            parts.append(f"{m} {fmt_ci(c['mean'], c['lo'], c['hi'], 2)}"
                         + (f" (honest {fmt_ci(h['mean'], h['lo'], h['hi'], 2)})" if h is not None
                            else "") + f", {plural_cases(n)}"
                         + (", too few to tell" if few else ""))
            if few:
                continue
            if c["hi"] < lo_b:
                below.append(m)
            elif c["lo"] > hi_b:
                above.append(m)
        return ["On MuJoCo videos the 90% intervals after the last frame hold the engine's "
                "measured e, g, d in (95% CIs over cases; honest: the interval holds it or the "
                "model check fails): " + "; ".join(parts)
                + band_verdict(below, above, lo_b, hi_b)]


def _coverage(g):
    """Mean and 95% CI over cases (:func:`~.calibration.share_ci`) of the 90% intervals' hits on
    e, g, d in rows ``g``, or None without hits."""
    h = g[g.metric.isin([f"hit90_{p}" for p in EGD])]
    return None if h.empty else share_ci(h)


def _honest(g):
    """As :func:`_coverage` for the honest share (:func:`~.calibration.honest_rows`), or None
    where the method gives no model check."""
    h = honest_rows(g)
    return None if h.empty else share_ci(h)
