"""Measure a Vid2Param checkpoint on the test split: ``python -m methods.vid2param.evaluate``.

Reports, on ``--n`` test-split videos (sub-ranges never seen in training; ``--seed`` differs from
the validation seed used during training), video only:

* normalised MSE per parameter after each of ``--lengths`` frames (``r`` also over the videos in
  which the ball rolls, and the mean posterior std of ``r`` where it never rolls);
* 50% and 90% interval coverage after the last length;
* the same errors for ``lsq`` (frames -> tracking -> fit) on the first ``--lsq-n`` cases, at
  ``--lsq-lengths``, with the seconds per identification of both methods.

The JSON result is printed and, with ``--json``, written atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from methods.vid2param.data import rolls_mask
from sysid_bench.datasets import make_dataset
from sysid_bench.physics import PARAMS, PRIOR

_LO = np.array([PRIOR[p][0] for p in PARAMS])
_HI = np.array([PRIOR[p][1] for p in PARAMS])
_Z90, _Z50 = 1.6448536, 0.6744898


def _scores(mu, sd, truth, rolls) -> dict:
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
    return out


def evaluate_vid2param(est, ds, lengths) -> dict:
    """Scores of ``est`` (a Vid2Param) after each length, one pass per batch of videos."""
    frames = np.asarray(ds.frames)
    truth = (np.asarray(ds.theta)[:, -1] - _LO) / (_HI - _LO)
    rolls = rolls_mask(ds.states, ds.floor)
    t0 = time.perf_counter()
    mu, sd = est.normalised_prefixes(frames, lengths)  # (N, L, 4)
    wall = time.perf_counter() - t0
    res = {str(L): _scores(mu[:, j], sd[:, j], truth, rolls) for j, L in enumerate(lengths)}
    return {"by_length": res, "seconds_per_video_all_lengths": wall / len(frames),
            "n": int(len(frames)), "n_rolling": int(rolls.sum())}


def evaluate_lsq(ds, lengths, n: int, seed: int = 0) -> dict:
    """``lsq`` on frames (tracked) for the first ``n`` videos after each length."""
    import methods

    est = methods.get("lsq", seed=seed)
    truth = (np.asarray(ds.theta)[:n, -1] - _LO) / (_HI - _LO)
    rolls = rolls_mask(ds.states[:n], ds.floor[:n])
    res, secs = {}, {}
    for L in lengths:
        mu, sd, walls = [], [], []
        for i in tqdm(range(n), desc=f"lsq @ {L} frames", mininterval=30):
            obs = ds.observation(i).prefix(L)
            t0 = time.perf_counter()
            try:
                post = est.identify(obs)
                m, s = post.mean, post.std
            except ValueError:  # too few tracked frames: answer the prior
                m, s = (_LO + _HI) / 2, (_HI - _LO) / np.sqrt(12)
            walls.append(time.perf_counter() - t0)
            mu.append((np.clip(m, _LO, _HI) - _LO) / (_HI - _LO))
            sd.append(np.asarray(s) / (_HI - _LO))
        res[str(L)] = _scores(np.array(mu), np.array(sd), truth, rolls)
        secs[str(L)] = float(np.median(walls))
    return {"by_length": res, "median_seconds_per_identification": secs, "n": int(n),
            "n_rolling": int(rolls.sum())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m methods.vid2param.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="default: the shipped 28x28 checkpoint")
    p.add_argument("--n", type=int, default=200)
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--variant", default="interleaved")
    p.add_argument("--nuisance", type=json.loads, default=None)
    p.add_argument("--lengths", type=int, nargs="+", default=[10, 25, 50, 100, 150, 200])
    p.add_argument("--lsq-n", type=int, default=0)
    p.add_argument("--lsq-lengths", type=int, nargs="+", default=[50, 200])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)

    from methods.vid2param import Vid2Param

    est = Vid2Param(checkpoint=a.checkpoint, device="cpu", threads=a.threads, n_samples=0)
    size = est.frame_size
    ds = make_dataset("test", a.n, a.seed, variant=a.variant, size=size, nuisance=a.nuisance)
    out = {"checkpoint": str(est.checkpoint_info_["path"]), "split": "test", "n": a.n,
           "seed": a.seed, "variant": a.variant, "nuisance": a.nuisance, "size": list(size),
           "vid2param": evaluate_vid2param(est, ds, a.lengths)}
    if a.lsq_n > 0:
        out["lsq"] = evaluate_lsq(ds, a.lsq_lengths, min(a.lsq_n, a.n), seed=0)
    text = json.dumps(out, indent=1)
    print(text)
    if a.json:
        path = Path(a.json)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "w") as fh:
            fh.write(text + "\n")
        os.replace(tmp, path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
