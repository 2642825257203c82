"""Batch identification with its model checks (issue 39, section 1): videos/s with and without.

Run with ``pytest tests/test_bench_vid2param_checks.py --benchmark-only``. ``identify_batch``
checks every posterior by default; its checks ran one scipy ``least_squares`` fit per video
(18 videos/s with them against 216 without, quiet, at 93ab25a) and now run for the whole batch
at once (:func:`methods._check_batch.check_batch`). Reported in ``extra_info``: the batch's
videos/s with and without the checks, and the checks alone by the batched path and by the
per-video one (``check_prefixes``) on the same videos in the same run. Asserted, loosely, only
ratios measured in this run (the machine is shared): the batched checks at least 2x the
per-video ones (measured 3.8-6.8x on a loaded 2-core machine).
"""

from __future__ import annotations

import copy
import time

import numpy as np
import pytest
import torch
from scripts_loader import load_script

from methods._check_batch import check_batch
from methods._simulation import check_prefixes
from methods.vid2param import SHIPPED_CHECKPOINT, Vid2Param
from methods.vid2param.estimator import DEFAULT_SIGMA
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation

pytestmark = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")

#: videos the per-video checks are timed on (the slow path: ~0.1-0.25 s a video)
N_SEQUENTIAL = 40
#: the least speedup of the checks asserted (measured 4-5x under load)
MIN_SPEEDUP = 2.0


@pytest.mark.benchmark(group="vid2param-checks")
def test_bench_identify_batch_with_checks(benchmark):
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        videos = np.asarray(make_dataset("test", 200, 2024).frames)
        est = Vid2Param(device="cpu")
        # warmed up (checkpoint, kernels, a failed check's lazy imports), then timed without
        # and with the checks, as scripts/measure_identify_batch.py measures them
        posts, t_net, checked, t_all = load_script("measure_identify_batch").time_batch(
            est, videos,
            lambda fn, v: benchmark.pedantic(fn, args=(v,), rounds=1, iterations=1))
        assert all(p.check is not None for p in checked)
        # the checks alone, batched and per video, on the same videos and posteriors
        sub, vs = posts[:N_SEQUENTIAL], videos[:N_SEQUENTIAL]
        t0 = time.perf_counter()
        new = check_batch([copy.deepcopy(p) for p in sub], vs, DEFAULT_SIGMA)
        t_new = time.perf_counter() - t0
        t0 = time.perf_counter()
        old = [check_prefixes([copy.deepcopy(p)], Observation(frames=v), [v.shape[0]],
                              DEFAULT_SIGMA)[0] for p, v in zip(sub, vs)]
        t_old = time.perf_counter() - t0
        n = len(videos)
        speedup = t_old / t_new
        agree = sum(a.check.ok == b.check.ok for a, b in zip(old, new))
        benchmark.extra_info.update({
            "videos_per_s_without_checks": n / t_net, "videos_per_s_with_checks": n / t_all,
            "checks_videos_per_s": N_SEQUENTIAL / t_new,
            "previous_checks_videos_per_s": N_SEQUENTIAL / t_old, "checks_speedup": speedup,
            "verdicts_agree": f"{agree}/{N_SEQUENTIAL}", "threads": 2})
        print(f"\nidentify_batch {n / t_all:.0f} videos/s with checks, {n / t_net:.0f} without; "
              f"checks alone {N_SEQUENTIAL / t_new:.0f} videos/s batched against "
              f"{N_SEQUENTIAL / t_old:.1f} per video ({speedup:.1f}x), verdicts agree on "
              f"{agree}/{N_SEQUENTIAL}")
        assert speedup >= MIN_SPEEDUP
    finally:
        torch.set_num_threads(before)
