"""Videos/s of ``Vid2Param.identify_batch`` with and without its model checks, and of
``methods._check_batch.check_batch`` alone, on the ball's test videos (issue 39, section 1).

One torch thread (two threads fight a loaded machine: ``docs/vid2param-speed.md``); the model
and numba kernels are warmed before the clock. Compare two checkouts by running this from each
in turn, several rounds, on the same machine (ratios of one session, not absolute figures)::

    cd CHECKOUT && PYTHONPATH=$PWD python scripts/measure_identify_batch.py --n 200

Prints one JSON line: ``net`` (no checks), ``with_checks`` and ``checks`` (videos/s).
"""

from __future__ import annotations

import argparse
import copy
import json
import time

import numpy as np


def time_batch(est, videos, call=None):
    """Warm ``est`` up, then time its ``identify_batch`` on ``videos`` (N, T, H, W) without and
    with the checks (``tests/test_bench_vid2param_checks.py`` times it so too).

    The warm-up loads the checkpoint and numba's kernels and runs a video no trajectory explains,
    so a failed check's lazy imports (scipy.stats in ``Check.bound``: ~half of the checks' time
    on 200 videos, py-spy) are not timed as if they were per-video work. ``call(fn, videos)``
    runs the checked batch (a benchmark's ``pedantic``); default a plain call.

    Returns
    -------
    posts, t_net, checked, t_all
        The unchecked posteriors and their seconds, the checked ones and theirs.
    """
    call = call or (lambda fn, v: fn(v))
    jumps = videos[1:2, np.arange(videos.shape[1]) % 2 * 60]
    est.identify_batch(np.concatenate([videos[:3], jumps]))
    t0 = time.perf_counter()
    posts = est.identify_batch(videos, check=False)
    t_net = time.perf_counter() - t0
    t0 = time.perf_counter()
    checked = call(est.identify_batch, videos)
    t_all = time.perf_counter() - t0
    return posts, t_net, checked, t_all


def main(n: int, seed: int) -> dict:
    import torch

    from methods._check_batch import check_batch
    from methods.vid2param import Vid2Param
    from methods.vid2param.estimator import DEFAULT_SIGMA
    from sysid_bench.core.datasets import make_dataset

    torch.set_num_threads(1)
    videos = np.asarray(make_dataset("test", n, seed).frames)
    posts, t_net, _, t_all = time_batch(Vid2Param(device="cpu"), videos)
    fresh = [copy.deepcopy(p) for p in posts]
    t0 = time.perf_counter()
    check_batch(fresh, videos, DEFAULT_SIGMA)
    t_chk = time.perf_counter() - t0
    return {"n": n, "net": n / t_net, "with_checks": n / t_all, "checks": n / t_chk}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200, help="test videos (default 200)")
    ap.add_argument("--seed", type=int, default=2024, help="test split's seed (default 2024)")
    a = ap.parse_args()
    if a.n < 4:
        ap.error(f"--n: expected at least 4 videos, got {a.n}")
    print(json.dumps(main(a.n, a.seed)))
