"""Calibrate ``vid2param-physics``'s intervals on train videos: one std factor per parameter.

``vid2param-physics`` fits our physics to the network's whole track; its posterior is the
Laplace one, widened by the residuals' autocorrelation time. That models the track's misreadings
as noise around the true path. The camera network's heights carry an error no such model
holds (a per-video bias of the height scale and the floor, at the percent level: g's 90%
intervals held 44% of the truths on its test split while g's MSE was 3e-4). So, as the
network's own stds are (``train.calibrate``), the fit's stds get one factor per parameter such
that 90% intervals hold 90% of the truths on fresh train-split videos, pooled over 50, 100 and
200 frames (``r`` over the videos that roll), never below 1. The means do not move.

This is the ``physics_calibration`` stage (``methods.vid2param.stages``): ``python -m
methods.vid2param.train --preset camera --export F`` fits it after the network and the stages
before it (the fit's prior is their posterior).
"""

from __future__ import annotations

import time

import numpy as np

from methods.vid2param.inference import HI, LO, physical, unseen_as_nan
from sysid_bench.core.physics import DT, PARAMS

__all__ = ["calibrate_physics_stage", "LENGTHS", "SEED"]

#: Prefix lengths pooled.
LENGTHS = (50, 100, 200)
#: Seed of the calibration videos (train split; the network's calibration uses 424242).
SEED = 424243

_Z90 = 1.6448536269514722


def calibrate_physics_stage(ctx, n: int = 100, seed: int = SEED) -> dict:
    """Fit ``vid2param-physics``'s std factors after the stages of ``ctx`` (an
    ``inference.FitContext``).

    Parameters
    ----------
    n : int
        Train-split videos (rendered as the checkpoint was trained, our physics).
    seed : int

    Returns
    -------
    dict
        The stage's state: ``std_scale`` (``PARAMS`` order) and the 90% coverage per
        parameter before and after, pooled.
    """
    from methods.vid2param.data import rolls_mask
    from methods.vid2param.rollout import fit_track

    t0 = time.perf_counter()
    # (videos shorter than the shortest: their full length)
    lengths = [L for L in LENGTHS if L <= ctx.n_frames] or [ctx.n_frames]
    ds = ctx.split(n, seed)
    theta = np.asarray(ds.theta)
    truth = theta[:, -1] if theta.ndim == 3 else theta
    z = np.empty((len(truth), len(lengths), len(PARAMS)))
    frames = np.asarray(ds.frames)
    floor = ctx.floor_prior()
    for i in range(len(truth)):
        # as Vid2ParamPhysics.identify_prefixes, uncalibrated: the fit's Laplace posterior
        m, s, pos, sd = ctx.parameters(frames[i][None])
        m, s, pos = m[0], s[0], unseen_as_nan(pos[0], sd[0], ctx.net.config.targets)
        for j, L in enumerate(lengths):
            fit = fit_track(pos[:L], *physical(m[L - 1], s[L - 1]), dt=DT, floor=floor)
            std = np.sqrt(np.diag(fit.cov[4:8, 4:8]))
            z[i, j] = (np.clip(fit.theta, LO, HI) - truth[i]) / std
    z = np.abs(z)
    rolls = rolls_mask(ds.states, ds.floor)
    q = np.quantile(z.reshape(-1, len(PARAMS)), 0.9, axis=0, method="higher")  # >= 90% in
    i_r = PARAMS.index("r")
    if rolls.any():  # elsewhere r's interval is prior-wide by design (as stages.calibrate)
        q[i_r] = np.quantile(z[rolls, :, i_r], 0.9, method="higher")
    # only widened: the Laplace posterior is what the track holds if the model were right, and
    # a narrower one on train videos (d: 0.80 on the camera model's) did not hold on test videos
    scale = np.maximum(q / _Z90, 1.0)
    sub = np.where(np.arange(len(PARAMS)) == i_r, 0, 1)  # coverage of r on rolling videos

    def coverage(f):
        inside = z <= _Z90 * f * (1 + 1e-12)  # the quantile itself is inside
        return {p: float(inside[:, :, k].mean() if sub[k] or not rolls.any()
                         else inside[rolls, :, k].mean()) for k, p in enumerate(PARAMS)}

    record = {"std_scale": scale.tolist(), "targets": list(PARAMS), "n": int(n), "seed": int(seed),
              "split": "train", "level": 0.9, "lengths": lengths,
              "coverage90_before": coverage(np.ones(len(PARAMS))),
              "coverage90_after": coverage(scale), "wall_s": time.perf_counter() - t0}
    ctx.log(f"vid2param-physics calibration: factors {dict(zip(PARAMS, np.round(scale, 3)))}, "
            f"coverage {record['coverage90_before']} -> {record['coverage90_after']}")
    return record
