"""Measure a Vid2Param checkpoint on the test split: ``python -m methods.vid2param.evaluate``.

Reports, on ``--n`` test-split videos (sub-ranges never seen in training; ``--seed`` differs from
the validation seed used during training), video only:

* normalised MSE per parameter after each of ``--lengths`` frames (``r`` also over the videos in
  which the ball rolls, and the mean posterior std of ``r`` where it never rolls);
* 50% and 90% interval coverage after the last length;
* the same errors for ``vid2param-physics`` (the physics fitted to the network's own track) on
  the first ``--physics-n`` cases at ``--physics-lengths``, and for ``lsq`` (frames -> tracking
  -> fit) on the first ``--lsq-n`` cases at ``--lsq-lengths``, with the seconds per
  identification of each;
* with ``--spin`` / ``--dwell``, a robustness study: the same test cases re-simulated with
  ``sysid_bench.core.physics.simulate_perturbed`` (each video its own spin loss ~ U[0, spin] and
  contact dwell ~ U[0, dwell]) and rendered again, scored the same way, plus the RMS position
  error (m) of forecasts of ``--horizon`` frames after ``--forecast-from`` observed frames on
  both the clean and the perturbed videos (first ``--forecast-n`` cases).

The JSON result is printed and, with ``--json``, written atomically.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from methods.vid2param.data import perturb_dataset, rolls_mask
from methods.vid2param.estimator import Vid2Param
from sysid_bench.core._io import atomic_write
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.metrics import central_z
from sysid_bench.core.physics import BOX_WIDTH, PARAMS, PRIOR

_LO = np.array([PRIOR[p][0] for p in PARAMS])
_HI = np.array([PRIOR[p][1] for p in PARAMS])
_Z90, _Z50 = 1.6448536, 0.6744898


#: Rolling frames (2 s) for the second r score: with the 5-frame minimum of ``rolls_mask`` many
#: "rolling" videos show only a few frames of a deceleration of at most 0.7 m/s^2.
LONG_ROLL = 40


def _scores(mu, sd, truth, rolls, long_rolls=None) -> dict:
    """mu, sd, truth normalised (N, 4) -> per-parameter nMSE, r on rolling, coverage."""
    err = (mu - truth) ** 2
    z = np.abs(mu - truth) / np.maximum(sd, 1e-12)
    out = {
        "nmse": {p: float(err[:, i].mean()) for i, p in enumerate(PARAMS)},
        "nmse_r_rolling": float(err[rolls, 3].mean()) if rolls.any() else None,
        "nmse_r_not_rolling": float(err[~rolls, 3].mean()) if (~rolls).any() else None,
        "coverage90": {p: float((z[:, i] <= _Z90).mean()) for i, p in enumerate(PARAMS)},
        "coverage50": {p: float((z[:, i] <= _Z50).mean()) for i, p in enumerate(PARAMS)},
        "mean_std": {p: float(sd[:, i].mean()) for i, p in enumerate(PARAMS)},
    }
    if (~rolls).any():
        out["r_std_not_rolling"] = float(sd[~rolls, 3].mean())
    if rolls.any():
        out["r_std_rolling"] = float(sd[rolls, 3].mean())
        out["coverage90_r_rolling"] = float((z[rolls, 3] <= _Z90).mean())
    if long_rolls is not None and long_rolls.any():
        out[f"nmse_r_rolling_{LONG_ROLL}"] = float(err[long_rolls, 3].mean())
        out[f"n_rolling_{LONG_ROLL}"] = int(long_rolls.sum())
    return out


def forecast_interval(fc, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Central ``level`` interval of a Forecast, (H, 2) each: sample quantiles, else Gaussian
    (as the benchmark's forecasting experiment reads one)."""
    a = (1 - level) / 2
    if fc.samples is not None and len(fc.samples) >= 2:
        return tuple(np.quantile(fc.samples, [a, 1 - a], axis=0))
    z = float(central_z(level))
    return fc.mean - z * fc.std, fc.mean + z * fc.std


def save_figure(fig, path) -> Path:
    """Save ``fig`` as PNG at ``path`` atomically and close it."""
    import matplotlib.pyplot as plt

    try:
        fig.tight_layout()
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    finally:
        plt.close(fig)


def evaluate_vid2param(est, ds, lengths) -> dict:
    """Scores of ``est`` (a Vid2Param) after each length, one pass per batch of videos."""
    frames = np.asarray(ds.frames)
    truth = (np.asarray(ds.theta)[:, -1] - _LO) / (_HI - _LO)
    rolls = rolls_mask(ds.states, ds.floor)
    long_rolls = rolls_mask(ds.states, ds.floor, min_frames=LONG_ROLL)
    t0 = time.perf_counter()
    mu, sd = est.normalised_prefixes(frames, lengths)  # (N, L, 4)
    wall = time.perf_counter() - t0
    res = {str(L): _scores(mu[:, j], sd[:, j], truth, rolls, long_rolls)
           for j, L in enumerate(lengths)}
    return {"by_length": res, "seconds_per_video_all_lengths": wall / len(frames),
            "n": int(len(frames)), "n_rolling": int(rolls.sum())}


def video_observation(ds, i: int):
    """Video ``i`` of ``ds`` as the frame-based baselines should see it.

    With a randomised floor (``nuisance["floor_offset"]``) the camera stays framed on floor 0
    while ``Dataset.floor`` is the true floor, so tracking with ``Observation.floor`` would
    shift every height by the floor (see the README's design notes). There the positions are
    tracked with the camera's own framing and handed over with the true floor.
    """
    obs = ds.observation(i)
    if not (ds.meta.get("nuisance") or {}).get("floor_offset", 0.0):
        return obs
    from sysid_bench.core.estimator import Observation, observed_positions
    from sysid_bench.core.physics import BOX_WIDTH

    # the suite's own tracking path, framed on the camera's floor 0
    pos = observed_positions(Observation(frames=obs.frames, dt=obs.dt, floor=0.0), min_seen=0)
    pos[:, 1] = np.clip(pos[:, 1], obs.floor, obs.floor + BOX_WIDTH)
    return Observation(frames=obs.frames, positions=pos, dt=obs.dt, floor=obs.floor)


def evaluate_lsq(ds, lengths, n: int, seed: int = 0) -> dict:
    """``lsq`` on frames (tracked) for the first ``n`` videos after each length."""
    import methods

    videos = [video_observation(ds, i) for i in range(n)]  # tracked once, cut per length
    return evaluate_identifier(methods.get("lsq", seed=seed), ds, videos, lengths)


def evaluate_physics(checkpoint, ds, lengths, n: int, threads: int = 1) -> dict:
    """``vid2param-physics`` (the physics fitted to the network's track) on the first ``n``
    videos after each length: one network pass and one fit per video and length."""
    import methods

    est = methods.get("vid2param-physics", checkpoint=checkpoint, device="cpu", threads=threads,
                      n_samples=0)
    return evaluate_identifier(est, ds, [ds.observation(i) for i in range(n)], lengths)


def evaluate_identifier(est, ds, videos, lengths) -> dict:
    """Scores of ``est.identify`` on ``videos`` (the first ``len(videos)`` of ``ds``) cut after
    each length, with the median seconds per identification."""
    n = len(videos)
    truth = (np.asarray(ds.theta)[:n, -1] - _LO) / (_HI - _LO)
    rolls = rolls_mask(ds.states[:n], ds.floor[:n])
    long_rolls = rolls_mask(ds.states[:n], ds.floor[:n], min_frames=LONG_ROLL)
    res, secs = {}, {}
    for L in lengths:
        mu, sd, walls = [], [], []
        for i in tqdm(range(n), desc=f"{est.name} @ {L} frames", mininterval=30):
            obs = videos[i].prefix(L)
            t0 = time.perf_counter()
            try:
                post = est.identify(obs)
                m, s = post.mean, post.std
            except ValueError:  # too few tracked frames: answer the prior
                m, s = (_LO + _HI) / 2, (_HI - _LO) / np.sqrt(12)
            walls.append(time.perf_counter() - t0)
            mu.append((np.clip(m, _LO, _HI) - _LO) / (_HI - _LO))
            sd.append(np.asarray(s) / (_HI - _LO))
        res[str(L)] = _scores(np.array(mu), np.array(sd), truth, rolls, long_rolls)
        secs[str(L)] = float(np.median(walls))
    return {"by_length": res, "median_seconds_per_identification": secs, "n": int(n),
            "n_rolling": int(rolls.sum())}


def forecast_errors(est, ds, n: int, n_obs: int, horizon: int) -> dict:
    """Errors of ``est.forecast`` after ``n_obs`` frames over the first ``n`` videos of ``ds``.

    Returns the RMS position error (m) per horizon step and overall, the normalised position
    MSE (as the benchmark's forecast experiment: squared error / (10 m)^2, mean over x, y and
    steps), the share of coordinates inside the 90% band and the band's mean width (m).
    """
    sq, cov, width = [], [], []
    for i in tqdm(range(n), desc=f"{est.name} forecasts", mininterval=30):
        obs = video_observation(ds, i).prefix(n_obs)
        truth = np.asarray(ds.states)[i, n_obs : n_obs + horizon, :2]
        try:
            fc = est.forecast(obs, horizon)
        except ValueError:
            continue
        lo, hi = forecast_interval(fc, 0.9)
        sq.append((fc.mean - truth) ** 2)
        cov.append((truth >= lo) & (truth <= hi))
        width.append(float(np.mean(hi - lo)))
    sq, cov = np.array(sq), np.array(cov)
    return {"rmse_m_by_step": np.sqrt(sq.sum(-1).mean(0)).round(4).tolist(),
            "rmse_m": float(np.sqrt(sq.sum(-1).mean())),
            "pos_mse_norm": float(sq.mean() / BOX_WIDTH**2), "coverage90": float(cov.mean()),
            "band90_m": float(np.mean(width)), "n": int(len(sq)), "n_obs": int(n_obs),
            "horizon": int(horizon)}


def figures(out: dict, ds, fest, outdir, name: str, n_examples: int = 3) -> list[Path]:
    """PNG figures of an evaluation: error against frames seen, forecast examples, frames.

    Parameters
    ----------
    out : dict
        The evaluation's result (``main``'s JSON).
    ds : Dataset
        The evaluated videos.
    fest : Vid2Param
        The estimator whose forecasts are drawn (with samples, see ``Vid2Param.forecast``).
    outdir : path
    name : str
        File-name prefix.

    Returns
    -------
    list of Path
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import methods
    outdir = Path(outdir)
    paths = []
    # 1. normalised MSE against frames seen, Vid2Param's curve and lsq's points
    v = out["vid2param"]["by_length"]
    lengths = [int(L) for L in v]
    fig, axes = plt.subplots(1, 4, figsize=(13, 3.2), sharey=True)
    for ax, p in zip(axes, PARAMS):
        key = (lambda r: r["nmse_r_rolling"]) if p == "r" else (lambda r, p=p: r["nmse"][p])
        ax.plot(lengths, [key(v[str(L)]) for L in lengths], "o-", label="Vid2Param")
        for other, mark in (("vid2param-physics", "D"), ("lsq", "s")):
            if other in out:
                ll = out[other]["by_length"]
                ax.plot([int(L) for L in ll], [key(ll[L]) for L in ll], mark, ms=8, label=other)
        ax.axhline(1 / 12, color="grey", ls=":", label="prior guess")
        ax.axhline(0.03 if p == "r" else 0.01, color="k", ls="--", lw=0.8, label="target")
        ax.set_yscale("log")
        ax.set_xlabel("frames seen")
        ax.set_title(f"{p} (rolling videos)" if p == "r" else p)
    axes[0].set_ylabel("normalised MSE")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{name}: test split, {out['n']} videos")
    paths.append(save_figure(fig, outdir / f"{name}_nmse.png"))
    # 2. forecasts after n_obs frames: truth, Vid2Param mean and 90% band, lsq mean
    n_obs, horizon = 100, 50
    lsq = methods.get("lsq", seed=0)
    fig, axes = plt.subplots(2, n_examples, figsize=(4 * n_examples, 5), sharex=True)
    t = np.arange(n_obs + horizon) * ds.meta.get("dt", 0.05)
    for k in range(n_examples):
        obs = video_observation(ds, k).prefix(n_obs)
        fv = fest.forecast(ds.observation(k).prefix(n_obs), horizon)
        try:
            fl = lsq.forecast(obs, horizon).mean
        except ValueError:
            fl = None
        for j, lab in enumerate(("x (m)", "y (m)")):
            ax = axes[j, k]
            ax.plot(t, ds.states[k, : n_obs + horizon, j], "k-", lw=1, label="truth")
            tf = t[n_obs:]
            ax.plot(tf, fv.mean[:, j], "C0-", label="Vid2Param")
            ax.fill_between(tf, fv.mean[:, j] - 1.645 * fv.std[:, j],
                            fv.mean[:, j] + 1.645 * fv.std[:, j], color="C0", alpha=0.25)
            if fl is not None:
                ax.plot(tf, fl[:, j], "C1--", label="lsq")
            ax.axvline(t[n_obs - 1], color="grey", lw=0.8)
            ax.set_ylabel(lab)
        axes[1, k].set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{name}: forecasts of {horizon} frames after {n_obs} observed (90% band)")
    paths.append(save_figure(fig, outdir / f"{name}_forecast.png"))
    # 3. what the network sees: a strip of frames of the first video
    idx = np.linspace(0, ds.frames.shape[1] - 1, 8).astype(int)
    h, w = ds.frames.shape[-2:]
    fig, axes = plt.subplots(1, len(idx), figsize=(1.6 * len(idx) * w / max(h, w) + 1, 2))
    for ax, i in zip(axes, idx):
        ax.imshow(ds.frames[0, i], cmap="gray", vmin=0, vmax=255)
        ax.set_title(f"frame {i}", fontsize=8)
        ax.axis("off")
    paths.append(save_figure(fig, outdir / f"{name}_frames.png"))
    return paths


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m methods.vid2param.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None,
                   help="a path or a shipped name (28x28, camera); default: the 28x28 one")
    p.add_argument("--n", type=int, default=200)
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--variant", default="interleaved")
    p.add_argument("--nuisance", type=json.loads, default=None,
                   help="renderer nuisances as JSON; default: those the checkpoint was trained on")
    p.add_argument("--lengths", type=int, nargs="+", default=[10, 25, 50, 100, 150, 200])
    p.add_argument("--lsq-n", type=int, default=0)
    p.add_argument("--lsq-lengths", type=int, nargs="+", default=[50, 200])
    p.add_argument("--physics-n", type=int, default=50,
                   help="videos identified by vid2param-physics (network track + physics fit)")
    p.add_argument("--physics-lengths", type=int, nargs="+", default=[50, 200])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--spin", type=float, default=0.0, help="robustness study: max spin loss")
    p.add_argument("--dwell", type=float, default=0.0, help="robustness study: max dwell (s)")
    p.add_argument("--forecast-n", type=int, default=50)
    p.add_argument("--forecast-from", type=int, nargs="+", default=[50, 100])
    p.add_argument("--horizon", type=int, default=100)
    p.add_argument("--json", default=None)
    p.add_argument("--figures", default=None, help="write PNG figures into this folder")
    p.add_argument("--name", default=None, help="figure file prefix; default: checkpoint stem")
    a = p.parse_args(argv)

    est = Vid2Param(checkpoint=a.checkpoint, device="cpu", threads=a.threads, n_samples=0)  # no samples: faster
    size = est.frame_size
    if a.nuisance is None:
        a.nuisance = (est.checkpoint_info_.get("train") or {}).get("nuisance")
    ds = make_dataset("test", a.n, a.seed, variant=a.variant, size=size, nuisance=a.nuisance)
    # the checkpoint as named (a shipped name, or the path given): no machine path in records
    out = {"checkpoint": str(a.checkpoint or Vid2Param.default_checkpoint), "split": "test", "n": a.n,
           "seed": a.seed, "variant": a.variant, "nuisance": a.nuisance, "size": list(size),
           "vid2param": evaluate_vid2param(est, ds, a.lengths)}
    if a.lsq_n > 0:
        out["lsq"] = evaluate_lsq(ds, a.lsq_lengths, min(a.lsq_n, a.n), seed=0)
    if a.physics_n > 0:
        out["vid2param-physics"] = evaluate_physics(a.checkpoint, ds, a.physics_lengths,
                                                    min(a.physics_n, a.n), a.threads)
    # forecasting needs samples: one estimator for the robustness study and the figures
    fest = Vid2Param(checkpoint=a.checkpoint, device="cpu", threads=a.threads)
    if a.spin > 0 or a.dwell > 0:
        import methods

        pds = perturb_dataset(ds, a.spin, a.dwell, seed=a.seed)
        rob = {"spin_max": a.spin, "dwell_max": a.dwell,
               "vid2param": evaluate_vid2param(est, pds, a.lengths)}
        if a.lsq_n > 0:
            rob["lsq"] = evaluate_lsq(pds, a.lsq_lengths, min(a.lsq_n, a.n), seed=0)
        nf = min(a.forecast_n, a.n)
        if nf > 0:  # --forecast-n 0: identification only
            lsq = methods.get("lsq", seed=0)
            fphys = Vid2Param(checkpoint=a.checkpoint, device="cpu", threads=a.threads,
                              forecast="physics")
            rob["forecast"] = {
                name: {kind: {str(t0): forecast_errors(e, d, nf, t0, a.horizon)
                              for t0 in a.forecast_from}
                       for kind, d in (("clean", ds), ("perturbed", pds))}
                for name, e in (("vid2param", fest), ("vid2param-physics", fphys), ("lsq", lsq))
            }
        out["robustness"] = rob
    if a.figures:
        name = a.name or Path(str(est.checkpoint_info_["path"])).stem
        out["figures"] = [str(q) for q in figures(out, ds, fest, a.figures, name)]
    text = json.dumps(out, indent=1)
    print(text)
    if a.json:
        atomic_write(a.json, text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
