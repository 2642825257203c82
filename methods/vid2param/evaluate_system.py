"""Evaluate a system's Vid2Param checkpoint on test-split videos.

``python -m methods.vid2param.evaluate_system --system pendulum --checkpoint F --out J``:
``--n`` videos of the system's test split (``--seed``; not the training run's validation seed),
rendered at the model's frame size; per parameter the normalised MSE (errors of parameters
normalised by the prior, ``System.normalise``) and the fraction of truths inside the 90%
interval (mean +- 1.645 std, after the checkpoint's stages) after 50, 100 and 200 frames.
The JSON is written atomically.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from sysid_bench.core._io import atomic_write

__all__ = ["evaluate_system", "main"]

#: Test videos' seed (the training runs validate on seed 1).
TEST_SEED = 20261126


def evaluate_system(est, n: int = 100, seed: int = TEST_SEED, lengths=(50, 100, 200),
                    batch: int = 50) -> dict:
    """Normalised parameter MSE and 90% coverage of ``est`` (a system's network,
    :class:`methods.vid2param._points.PointsModel`) on ``n`` test-split videos, after each of
    ``lengths`` frames.

    Returns
    -------
    dict
        ``nmse`` and ``coverage90``: ``{length: {param: float}}``; ``nmse_mean``
        ``{length: float}`` (averaged over the parameters); ``n``, ``seed``, ``split``,
        ``wall_s``.
    """
    from methods.vid2param.data import make_system_split

    sys_ = est._sys
    cfg = est._net.config
    T = max(int(v) for v in lengths)
    t0 = time.perf_counter()
    ds = make_system_split(sys_.name, "test", int(n), int(seed), T, cfg.frame_size)
    ms, ss = [], []
    for i in range(0, int(n), batch):
        m, s, _, _ = est.posteriors(ds.frames[i:i + batch])
        ms.append(m[..., est._order])
        ss.append(s[..., est._order])
    m, s = np.concatenate(ms), np.concatenate(ss)  # (N, T, P), the system's parameter order
    truth = sys_.normalise(ds.theta)[:, None, :]
    m = np.clip(m, 0.0, 1.0)  # as the posterior mean (clipped to the prior)
    err, z = (m - truth) ** 2, np.abs(m - truth) / s
    out = {"system": sys_.name, "n": int(n), "seed": int(seed), "split": "test",
           "frame_size": list(cfg.frame_size), "nmse": {}, "nmse_mean": {}, "coverage90": {}}
    for L in lengths:
        j = int(L) - 1
        out["nmse"][int(L)] = {p: float(err[:, j, k].mean()) for k, p in enumerate(sys_.params)}
        out["nmse_mean"][int(L)] = float(err[:, j].mean())
        out["coverage90"][int(L)] = {p: float((z[:, j, k] <= 1.6448536).mean())
                                     for k, p in enumerate(sys_.params)}
    out["wall_s"] = time.perf_counter() - t0
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m methods.vid2param.evaluate_system",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--system", required=True)
    p.add_argument("--checkpoint", required=True, help="the system's checkpoint (.pt)")
    p.add_argument("--n", type=int, default=100, help="test videos (default 100)")
    p.add_argument("--seed", type=int, default=TEST_SEED)
    p.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    p.add_argument("--out", required=True, help="JSON to write")
    a = p.parse_args(argv)
    if a.n < 1:
        raise SystemExit(f"--n: expected an int >= 1, got {a.n}")
    import methods

    # the system's network and stages (its normalised posteriors are what is scored)
    est = methods.get("vid2param", system=a.system, checkpoint=a.checkpoint,
                      device=a.device)._model()
    res = evaluate_system(est, a.n, a.seed)
    res["checkpoint"] = Path(a.checkpoint).name
    text = json.dumps(res, indent=1, sort_keys=True)
    atomic_write(a.out, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
