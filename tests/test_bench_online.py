"""Online cost and the streamed frame: ratios measured in one run, never absolute times.

Run with ``pytest tests/test_bench_online.py --benchmark-only``. Targets (issue 11, section 5):

- a posterior after every frame of a 200-frame video is >= 100x cheaper with Vid2Param's stream
  than with ``lsq`` re-run on every prefix of the same video (lsq from video: it tracks the
  ball itself, from its ``min_frames`` on);
- ``push`` <= 0.5 ms on one thread, where the torch path took ~0.8 ms on an idle machine: the
  NumPy path must be >= 1.6x faster than the torch modules on the same frames, same process.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from methods.vid2param import SHIPPED_CHECKPOINT, Vid2Param
from sysid_bench.bench.online import online_cost, online_cost_markdown
from sysid_bench.core.datasets import make_dataset

pytestmark = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")

ONLINE_RATIO = 100.0  # the target: reported (extra_info, printed)
#: Asserted: half the ratios measured (162x; 121x with every posterior's samples drawn), so a busy
#: machine cannot fail them (issue 29) while losing the stream's advantage still does.
ONLINE_RATIO_MIN = 80.0
ONLINE_RATIO_SAMPLES_MIN = 60.0
PUSH_SPEEDUP = 0.8 / 0.5  # the torch path's idle-machine median over the 0.5 ms target
#: (measured 3.5-5.7x, CPU time of interleaved blocks: more than a 2x margin)


@pytest.mark.slow
@pytest.mark.benchmark(group="vid2param-online")
def test_bench_online_cost_vs_lsq(benchmark, one_thread):
    """One video (lsq on 198 prefixes takes ~10 s of CPU); the ratio is of process CPU time,
    which the other processes on a loaded machine disturb less than wall-clock time."""
    df = benchmark.pedantic(online_cost, args=(["vid2param", "lsq"], 1, 0),
                            kwargs={"samples": True}, rounds=1, iterations=1)
    print("\n" + online_cost_markdown(df))
    row = df.set_index("method")
    ratio_cpu = float(row.loc["lsq", "ratio_cpu"])
    ratio_wall = float(row.loc["lsq", "ratio"])
    ratio_samples = float(row.loc["lsq", "cpu_s"] / row.loc["vid2param+samples", "cpu_s"])
    benchmark.extra_info.update({"lsq_over_vid2param_cpu": ratio_cpu,
                                 "lsq_over_vid2param_wall": ratio_wall,
                                 "lsq_over_vid2param_samples_cpu": ratio_samples,
                                 "target_ratio": ONLINE_RATIO,
                                 "meets_target": bool(ratio_cpu >= ONLINE_RATIO),
                                 "vid2param_s": float(row.loc["vid2param", "total_s"]),
                                 "lsq_s": float(row.loc["lsq", "total_s"])})
    print(f"lsq / vid2param CPU: {ratio_cpu:.0f}x (target {ONLINE_RATIO:g}x: "
          f"{'met' if ratio_cpu >= ONLINE_RATIO else 'MISSED'}), {ratio_samples:.0f}x with samples")
    assert row.loc["lsq", "posteriors"] == 198 and row.loc["vid2param", "posteriors"] == 200
    assert ratio_cpu >= ONLINE_RATIO_MIN, df.to_string()
    # with every posterior's 200 samples drawn as well
    assert ratio_samples >= ONLINE_RATIO_SAMPLES_MIN, df.to_string()


def _push_times(stream, frames, rounds: int) -> np.ndarray:
    out = np.empty(rounds)
    for i in range(rounds):
        f = frames[i % len(frames)]
        t0 = time.thread_time()
        stream.push(f)
        out[i] = time.thread_time() - t0
    return out


@pytest.mark.benchmark(group="vid2param-online")
def test_bench_push_numpy_vs_torch_path(benchmark, one_thread):
    """Median CPU time of a push on the NumPy path and on the torch modules, interleaved in
    blocks of one video so that both see the same load."""
    frames = np.asarray(make_dataset("test", 1, 2024).frames[0])
    est = Vid2Param(device="cpu")
    fast = est.stream()
    assert fast._fast is not None
    slow = est.stream()
    slow._fast, slow._state = None, est.net_.init_state(1)
    t_fast, t_slow = [], []
    for _ in range(3):
        fast.reset()
        slow.reset()
        slow._fast, slow._state = None, est.net_.init_state(1)
        t_fast.append(_push_times(fast, frames, len(frames)))
        t_slow.append(_push_times(slow, frames, len(frames)))
    fast.reset()
    it = iter(np.concatenate([frames] * 5))
    benchmark.pedantic(lambda: fast.push(next(it)), rounds=len(frames) * 5, iterations=1)
    m_fast, m_slow = np.median(np.concatenate(t_fast)), np.median(np.concatenate(t_slow))
    benchmark.extra_info.update({"numpy_median_cpu_s": m_fast, "torch_median_cpu_s": m_slow,
                                 "speedup": m_slow / m_fast})
    print(f"\npush median CPU: NumPy {m_fast * 1e3:.3f} ms, torch {m_slow * 1e3:.3f} ms, "
          f"{m_slow / m_fast:.1f}x")
    assert m_slow / m_fast >= PUSH_SPEEDUP
