"""Batched identification throughput (issue 11, section 5): >= 170 videos/s on 2 cores.

Run with ``pytest tests/test_bench_vid2param_batch.py --benchmark-only``. Reports (does not
assert: two threads on a busy machine hide it, issue 29) a ratio measured in this run: the
current path (encoder in cache-sized pieces, the keypoint convolution on a channels_last input,
``batch=500``) against the previous one (the encoder over the whole batch at once, the keypoint
convolution in NCHW, ``batch=100``), both with 2 torch threads on the same videos; the videos/s
of each are reported in ``extra_info``.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

import methods.vid2param.fast as fast
import methods.vid2param.parts as parts
from methods.vid2param import SHIPPED_CHECKPOINT, Vid2Param
from sysid_bench.core.datasets import make_dataset

pytestmark = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")

#: Current path over the previous one, same run: reported, not asserted. Chunked encoding alone
#: measured 3.0x when it was written and 1.66-1.82x three days later on the same 2-core machine
#: (the ratio moves with the machine); with the channels_last keypoint convolution 2.23-2.75x
#: (146-192 / 65-70 videos/s, the other core busy training) and 2.97-3.10x idle (282-290 /
#: 94-95). Both paths run two threads, which other processes on a 2-core machine disturb
#: unevenly: under load 17 both ran at 3 videos/s (0.93x) and a bound of 1.1 failed, so no bound
#: on it survives a busy machine (issue 29). ``speedup`` in ``extra_info`` and the printed line
#: carry it; ``meets_expected`` says whether it reached EXPECTED.
EXPECTED = 1.8


@pytest.mark.benchmark(group="vid2param-batch")
def test_bench_identify_batch_two_threads(benchmark, monkeypatch):
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        videos = np.asarray(make_dataset("test", 200, 2024).frames)
        new = Vid2Param(device="cpu")
        new.identify_batch(videos[:4])  # load the checkpoint outside the clock

        def rate(est) -> float:
            t0 = time.perf_counter()
            est.normalised_prefixes(videos, [videos.shape[1]])
            return len(videos) / (time.perf_counter() - t0)

        old = Vid2Param(device="cpu", batch=100)
        old.identify_batch(videos[:4])
        r_new, r_old = [], []
        for _ in range(2):  # interleaved, so both see the same load
            r_new.append(rate(new))
            with monkeypatch.context() as m:
                m.setattr(fast, "ENCODE_CHUNK", 10**9)  # the whole batch at once, as before
                m.setattr(parts, "KEYPOINT_CHANNELS_LAST", False)  # the NCHW keypoint conv
                r_old.append(rate(old))
        posts = benchmark.pedantic(new.identify_batch, args=(videos,), kwargs={"check": False},
                                 rounds=1, iterations=1)
        assert len(posts) == len(videos)
        best_new, best_old = max(r_new), max(r_old)
        ratio = best_new / best_old
        benchmark.extra_info.update({"videos_per_s": best_new, "previous_videos_per_s": best_old,
                                     "speedup": ratio, "expected_speedup": EXPECTED,
                                     "meets_expected": bool(ratio >= EXPECTED), "threads": 2})
        print(f"\n{best_new:.0f} videos/s (previous path {best_old:.0f}), 2 threads, "
              f"{ratio:.2f}x (expected >= {EXPECTED:g}x on a quiet machine: "
              f"{'met' if ratio >= EXPECTED else 'MISSED'})")
    finally:
        torch.set_num_threads(before)
