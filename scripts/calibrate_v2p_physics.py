"""Calibrate, or evaluate, ``vid2param-physics`` on a system with a Vid2Param network.

    python scripts/calibrate_v2p_physics.py --system pendulum              # fit the factors
    python scripts/calibrate_v2p_physics.py --system pendulum --evaluate   # test split figures

Calibration (train split, seed 424243, ``--n`` videos of 200 frames, prefixes 50/100/200): one
std factor per parameter, the smallest >= 1 with which the 90% intervals hold at least 90% of
the truths, pooled over the prefixes (as the ball's ``physics_calibration`` stage); written
atomically beside the checkpoint (``methods.vid2param._points.physics_calibration_path``) with
the checkpoint's sha256, so a retrained network is not read with another's factors.

Evaluation (test split, seed 2024): normalised MSE (each parameter scaled by its prior range)
and 90% coverage per parameter and prefix, for ``vid2param-physics`` and the network alone
(``vid2param``), printed and written to ``<stem>_physics_test.json`` beside the checkpoint.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

LENGTHS = (50, 100, 200)
CAL_SEED, TEST_SEED = 424243, 2024
Z90 = 1.6448536269514722


def _run(system: str, split: str, n: int, seed: int, with_network: bool):
    """Means, stds (N, L, P) of vid2param-physics (calibrated only when evaluating, i.e. with
    ``with_network``) and of the network, and the truths (N, P)."""
    from tqdm import tqdm

    import methods
    from methods.vid2param.data import make_system_split
    from sysid_bench.core.estimator import Observation

    est = methods.get("vid2param-physics", system=system)
    model = est._model()
    ds = make_system_split(system, split, n, seed, max(LENGTHS), model.frame_size)
    mean, std, nmean, nstd = [], [], [], []
    for i in tqdm(range(n), desc=f"{system} {split}", file=sys.stderr):
        obs = Observation(frames=np.asarray(ds.frames[i]), system=system)
        ps = model.physics_prefixes(obs, LENGTHS, calibrated=with_network)
        mean.append([p.mean for p in ps])
        std.append([p.std for p in ps])
        if with_network:
            qs = model.identify_prefixes(obs, LENGTHS)
            nmean.append([q.mean for q in qs])
            nstd.append([q.std for q in qs])
    return (np.array(mean), np.array(std), np.array(nmean), np.array(nstd),
            np.asarray(ds.theta, dtype=np.float64), model)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", required=True)
    ap.add_argument("--n", type=int, default=60, help="videos (default 60)")
    ap.add_argument("--evaluate", action="store_true", help="test-split figures instead")
    a = ap.parse_args(argv)
    if a.n < 10:
        ap.error(f"--n: expected at least 10 videos, got {a.n}")
    from sysid_bench.core import systems
    from sysid_bench.core._io import atomic_write

    sys_ = systems.get(a.system)
    names, span = list(sys_.params), sys_.prior_hi - sys_.prior_lo
    t0 = time.perf_counter()
    split, seed = ("test", TEST_SEED) if a.evaluate else ("train", CAL_SEED)
    # the factors are fitted on the uncalibrated spread
    mean, std, nmean, nstd, theta, model = _run(a.system, split, a.n, seed, a.evaluate)
    z = np.abs(mean - theta[:, None]) / np.maximum(std, 1e-300)

    def coverage(zz, f=1.0):
        return {q: float(np.mean(zz[..., j] <= Z90 * (f if np.isscalar(f) else f[j])
                                 * (1 + 1e-12))) for j, q in enumerate(names)}

    ck = Path(model.path)
    if a.evaluate:
        rec = {"system": a.system, "checkpoint": ck.name, "split": split, "seed": seed, "n": a.n,
               "wall_s": time.perf_counter() - t0, "physics_calibration": model.physics_scale()[1]}
        for label, m, s in (("vid2param-physics", mean, std), ("vid2param", nmean, nstd)):
            zz = np.abs(m - theta[:, None]) / np.maximum(s, 1e-300)
            err = ((m - theta[:, None]) / span) ** 2
            rec[label] = {str(L): {"nmse": dict(zip(names, err[:, k].mean(0).tolist())),
                                   "nmse_mean": float(err[:, k].mean()),
                                   "coverage90": coverage(zz[:, k])}
                          for k, L in enumerate(LENGTHS)}
        out = ck.with_name(ck.stem + "_physics_test.json")
    else:
        q = np.quantile(z.reshape(-1, len(names)), 0.9, axis=0, method="higher")
        f = np.maximum(1.0, q / Z90)
        rec = {"system": a.system, "checkpoint": ck.name,
               "checkpoint_sha256": hashlib.sha256(ck.read_bytes()).hexdigest(),
               "std_scale": dict(zip(names, f.tolist())), "split": split, "seed": seed,
               "n": a.n, "lengths": list(LENGTHS), "coverage90_before": coverage(z),
               "coverage90_after": coverage(z, f), "wall_s": time.perf_counter() - t0,
               "command": f"python scripts/calibrate_v2p_physics.py --system {a.system} "
                          f"--n {a.n}"}
        from methods.vid2param._points import physics_calibration_path

        out = physics_calibration_path(ck)
    atomic_write(out, json.dumps(rec, indent=1, sort_keys=True) + "\n")
    print(json.dumps(rec, indent=1, sort_keys=True))
    print(f"-> {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
