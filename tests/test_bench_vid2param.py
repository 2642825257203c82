"""Vid2Param speed: one streamed frame on one CPU thread; 100 videos x 200 frames identified at once.

Run with ``pytest tests/test_bench_vid2param.py --benchmark-only``. Targets (issue 4): a ``push``
at most 1 ms on one thread (>= 50x real time at 20 frames/s); batched identification of 100 x 200
frames at most 2 s on 2 cores (asserted with one thread, see below). The median is compared with
the target and reported in ``extra_info``; a miss fails the benchmark.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from methods.vid2param import SHIPPED_CHECKPOINT, SHIPPED_CHECKPOINTS, Vid2Param  # noqa: E402
from sysid_bench.datasets import make_dataset  # noqa: E402

pytestmark = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")

PUSH_TARGET_S = 1e-3
BATCH_TARGET_S = 2.0


@pytest.fixture
def threads():
    """Run under a chosen torch thread count, restoring the previous one afterwards."""
    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def videos():
    return np.asarray(make_dataset("test", 100, 2024).frames)


@pytest.mark.benchmark(group="vid2param")
def test_bench_push_one_thread(benchmark, threads, videos):
    threads(1)
    _bench_push(benchmark, Vid2Param(device="cpu"), videos[0], 2000, "push")


def _bench_push(benchmark, est, frames, rounds: int, label: str) -> None:
    """Median seconds of ``push`` over ``rounds`` frames of a warmed-up stream, against the target."""
    stream = est.stream()
    for f in frames[:20]:  # warm up: first calls allocate
        stream.push(f)
    it = iter(np.concatenate([frames] * (-(-rounds // len(frames)))))
    post = benchmark.pedantic(lambda: stream.push(next(it)), rounds=rounds, iterations=1)
    assert np.isfinite(post.mean).all()
    med = benchmark.stats.stats.median
    benchmark.extra_info.update({"median_s": med, "target_s": PUSH_TARGET_S,
                                 "x_real_time_at_20fps": 0.05 / med})
    print(f"\n{label} median {med * 1e3:.3f} ms = {0.05 / med:.0f}x real time at 20 fps")
    assert med <= PUSH_TARGET_S


_BATCH_MEDIANS: dict[int, float] = {}


@pytest.mark.benchmark(group="vid2param")
@pytest.mark.parametrize("n_threads", [1, 2])
def test_bench_identify_100_videos_200_frames(benchmark, threads, videos, n_threads):
    """The target is for the 2-core machine, and the better of 1 and 2 threads must meet it:
    on this shared machine two OpenMP threads contend with other processes (measured 6-9 s vs
    1.4-1.7 s with one thread under load 5 with the first checkpoint), while on a quiet one
    two threads win (1.35 s vs 2.24 s with the second checkpoint, read_cell widens the heads)."""
    threads(n_threads)
    est = Vid2Param(device="cpu", batch=100, n_samples=200)
    posts = benchmark.pedantic(est.identify_batch, args=(videos,), rounds=3, iterations=1,
                               warmup_rounds=1)
    assert len(posts) == 100
    med = benchmark.stats.stats.median
    benchmark.extra_info.update({"median_s": med, "target_s": BATCH_TARGET_S,
                                 "per_video_s": med / 100, "threads": n_threads})
    print(f"\n100 x 200 frames in {med:.3f} s ({med * 10:.1f} ms per video), {n_threads} thread(s)")
    _BATCH_MEDIANS[n_threads] = med
    if n_threads == 2:
        assert min(_BATCH_MEDIANS.values()) <= BATCH_TARGET_S, _BATCH_MEDIANS


@pytest.mark.benchmark(group="vid2param")
@pytest.mark.skipif(not SHIPPED_CHECKPOINTS["camera"].exists(), reason="no camera checkpoint")
def test_bench_push_camera_model_one_thread(benchmark, threads):
    """The 100x50 camera-like model streams too: same 1 ms target for one push (its keypoint
    channel 0 reads the full 5000-pixel frame, the conv path a 2x pooled one)."""
    from methods.vid2param.checkpoint import load_checkpoint

    threads(1)
    nuis = load_checkpoint(SHIPPED_CHECKPOINTS["camera"])["train"]["nuisance"]
    frames = np.asarray(make_dataset("test", 1, 2024, size=(50, 100), nuisance=nuis).frames[0])
    _bench_push(benchmark, Vid2Param(checkpoint="camera", device="cpu"), frames, 1000,
                "camera push")
