"""sindy's raw intervals and model checks on tracked video (issue 29 (c); docs/reliability.md).

For each video, after 50 and 200 frames: the raw (pre-check) posterior's z-scores
``(mean - truth) / std`` for e, g, d, and whether ``identify``'s model check passes. Prints
per length the share failing, the raw 90% coverage and the RMS z, and one line per failure.

Usage::

    python scripts/measure_sindy_intervals.py --split train --seed 777 --n 30
    python scripts/measure_sindy_intervals.py --split test --seed 2024 --n 20   # the report's
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def main(argv=None) -> None:
    from methods.sindy import SINDy
    from sysid_bench.core.datasets import make_dataset
    from sysid_bench.core.estimator import Observation

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", default="train", choices=("train", "test"))
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--lengths", default="50,200")
    a = ap.parse_args(argv)
    lengths = [int(x) for x in a.lengths.split(",")]
    ds = make_dataset(a.split, a.n, a.seed)
    est = SINDy()
    rows = {L: [] for L in lengths}
    for i in range(a.n):
        obs = Observation(frames=np.asarray(ds.frames[i]), dt=float(ds.meta["dt"]),
                          floor=float(ds.floor[i]))
        for L in lengths:
            o = dataclasses.replace(obs, frames=obs.frames[:L])
            raw, _, _ = est._fit(o)
            ok = est.identify(o).check.ok
            z = (raw.mean - ds.theta[i, 0]) / raw.std
            if not ok:
                print(f"failing: video {i}, {L} frames, raw z (e, g, d, r) {np.round(z, 2)}")
            rows[L].append((ok, *(np.abs(z[:3]) <= 1.645), *z[:3]))
    for L, r in rows.items():
        r = np.asarray(r, dtype=float)
        print(f"{a.split} seed {a.seed}, {L} frames, {len(r)} videos: failing "
              f"{1 - r[:, 0].mean():.3f}; raw 90% coverage e, g, d {np.round(r[:, 1:4].mean(0), 2)}; "
              f"RMS z {np.round(np.sqrt((r[:, 4:7] ** 2).mean(0)), 2)}")


if __name__ == "__main__":
    main()
