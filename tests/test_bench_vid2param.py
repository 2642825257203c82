"""Vid2Param speed: one streamed frame on one CPU thread; 100 videos x 200 frames identified at once.

Run with ``pytest tests/test_bench_vid2param.py --benchmark-only``. Targets (issue 4): a ``push``
at most 1 ms on one thread (>= 50x real time at 20 frames/s); batched identification of 100 x 200
frames at most 2 s on 2 cores. Absolute times depend on the machine and its load, so the
targets are only reported (``extra_info``: median, target, ``meets_target``; printed) and the
README's measured tables hold them (issue 14: a slower machine failed 1.37 ms against 1 ms).
What is asserted are ratios measured in the same run: a streamed frame costs at most a tenth of
identifying the 200-frame video from scratch (measured ~90x under load 5), and, on one thread,
batching 100 videos is at least twice as fast per video as identifying one alone (measured
~9x). Nothing asserted depends on how busy the machine is beyond a 2x margin (issue 29).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from methods.vid2param import SHIPPED_CHECKPOINT, SHIPPED_CHECKPOINTS, Vid2Param
from sysid_bench.core.datasets import make_dataset

pytestmark = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")

PUSH_TARGET_S = 1e-3  # reported, not asserted
BATCH_TARGET_S = 2.0  # reported, not asserted
PUSH_VS_IDENTIFY_MIN = 10.0  # identify(200 frames) / push, same run
BATCH_GAIN_MIN = 2.0  # one video alone / per-video time in a batch of 100, same run


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
    """Median seconds of ``push`` over ``rounds`` frames of a warmed-up stream, reported with the
    target; asserted only against identifying the same video from scratch in this run."""
    import time

    from sysid_bench.core.estimator import Observation

    stream = est.stream()
    for f in frames[:20]:  # warm up: first calls allocate
        stream.push(f)
    it = iter(np.concatenate([frames] * (-(-rounds // len(frames)))))
    post = benchmark.pedantic(lambda: stream.push(next(it)), rounds=rounds, iterations=1)
    assert np.isfinite(post.mean).all()
    med = benchmark.stats.stats.median
    whole = []
    for _ in range(3):
        t0 = time.perf_counter()
        est.identify(Observation(frames=frames))
        whole.append(time.perf_counter() - t0)
    ratio = float(np.median(whole)) / med
    benchmark.extra_info.update({"median_s": med, "target_s": PUSH_TARGET_S,
                                 "meets_target": bool(med <= PUSH_TARGET_S),
                                 "x_real_time_at_20fps": 0.05 / med,
                                 "identify_video_s": float(np.median(whole)),
                                 "identify_over_push": ratio})
    print(f"\n{label} median {med * 1e3:.3f} ms = {0.05 / med:.0f}x real time at 20 fps "
          f"(target {PUSH_TARGET_S * 1e3:g} ms: {'met' if med <= PUSH_TARGET_S else 'MISSED'}); "
          f"identifying the {len(frames)}-frame video takes {ratio:.0f}x one push")
    assert ratio >= PUSH_VS_IDENTIFY_MIN, (
        f"{label}: a push costs 1/{ratio:.1f} of identifying the whole video, expected "
        f"<= 1/{PUSH_VS_IDENTIFY_MIN:g}")


@pytest.mark.benchmark(group="vid2param")
@pytest.mark.parametrize("n_threads", [1, 2])
def test_bench_identify_100_videos_200_frames(benchmark, threads, videos, n_threads):
    """Reported against the 2-core target. On this shared machine two OpenMP threads contend
    with other processes (measured 6-9 s vs 1.4-1.7 s with one thread under load 5 with the
    first checkpoint), while on a quiet one two threads win (1.35 s vs 2.24 s with the second
    checkpoint). Asserted on one thread only: batching beats one video at a time, fastest
    rounds against fastest (measured ~9x; bound 2x). The two-thread gain is reported, not
    asserted: other processes on the cores hide it (a fresh clone failed it on a busy machine,
    issue 29)."""
    import time

    threads(n_threads)
    est = Vid2Param(device="cpu", batch=100, n_samples=200)
    posts = benchmark.pedantic(est.identify_batch, args=(videos,), kwargs={"check": False},
                               rounds=3, iterations=1,
                               warmup_rounds=1)
    assert len(posts) == 100
    med = benchmark.stats.stats.median
    alone = []
    for i in range(3):
        t0 = time.perf_counter()
        est.identify_batch(videos[i : i + 1], check=False)
        alone.append(time.perf_counter() - t0)
    # fastest rounds: the least disturbed by other processes (the medians are reported too)
    gain = float(np.min(alone)) / (benchmark.stats.stats.min / 100)
    benchmark.extra_info.update({"median_s": med, "target_s": BATCH_TARGET_S,
                                 "meets_target": bool(med <= BATCH_TARGET_S),
                                 "per_video_s": med / 100, "threads": n_threads,
                                 "one_video_alone_s": float(np.median(alone)),
                                 "batch_gain_per_video": gain,
                                 "gain_asserted": n_threads == 1})
    print(f"\n100 x 200 frames in {med:.3f} s ({med * 10:.1f} ms per video), {n_threads} thread(s) "
          f"(target {BATCH_TARGET_S:g} s: {'met' if med <= BATCH_TARGET_S else 'MISSED'}); "
          f"{gain:.1f}x faster per video than one alone")
    if n_threads == 1:
        assert gain >= BATCH_GAIN_MIN, (
            f"batching gains only {gain:.1f}x per video, expected >= {BATCH_GAIN_MIN:g}x")


@pytest.mark.benchmark(group="vid2param")
@pytest.mark.skipif(not SHIPPED_CHECKPOINTS["camera"].exists(), reason="no camera checkpoint")
def test_bench_push_camera_model_one_thread(benchmark, threads):
    """The 100x50 camera-like model streams too: same 1 ms target (reported) for one push (its keypoint
    channel 0 reads the full 5000-pixel frame, the conv path a 2x pooled one)."""
    from methods.vid2param.checkpoint import load_checkpoint

    threads(1)
    nuis = load_checkpoint(SHIPPED_CHECKPOINTS["camera"])["train"]["nuisance"]
    frames = np.asarray(make_dataset("test", 1, 2024, size=(50, 100), nuisance=nuis).frames[0])
    _bench_push(benchmark, Vid2Param(checkpoint="camera", device="cpu"), frames, 1000,
                "camera push")


@pytest.mark.benchmark(group="vid2param")
@pytest.mark.parametrize("system", ["pendulum", "spring", "collision"])
def test_bench_push_system_model_one_thread(benchmark, threads, system):
    """Another system's shipped model streams on the NumPy path too (issue 39: push <= 0.5 ms
    median on one thread, the two-point collision network included; reported, not asserted).
    Asserted, same run: a NumPy push costs at most half the torch modules' push."""
    import time

    import methods
    from methods.vid2param.data import make_system_split

    threads(1)
    try:
        est = methods.get("vid2param", system=system, device="cpu")
    except methods.NotAvailable as exc:
        pytest.skip(str(exc))
    net = est._model()._net
    frames = np.asarray(make_system_split(system, "test", 1, 2024, 200,
                                          net.config.frame_size).frames[0])
    stream = est.stream()
    assert stream._fast is not None, f"{system}: the stream left the NumPy path"
    slow = est.stream()
    slow._fast, slow._state = None, net.init_state(1)  # the torch modules' push
    for f in frames[:20]:  # warm up: first calls allocate
        stream.push(f)
        slow.push(f)
    it = iter(np.concatenate([frames] * 5))
    post = benchmark.pedantic(lambda: stream.push(next(it)), rounds=1000, iterations=1)
    assert np.isfinite(post.mean).all()
    med = benchmark.stats.stats.median
    torch_s = []
    for f in frames[20:220]:
        t0 = time.perf_counter()
        slow.push(f)
        torch_s.append(time.perf_counter() - t0)
    ratio = float(np.median(torch_s)) / med
    benchmark.extra_info.update({"median_s": med, "target_s": 5e-4,
                                 "meets_target": bool(med <= 5e-4),
                                 "torch_push_s": float(np.median(torch_s)),
                                 "torch_over_numpy": ratio})
    print(f"\n{system} push median {med * 1e3:.3f} ms (target 0.5 ms: "
          f"{'met' if med <= 5e-4 else 'MISSED'}); the torch modules' push "
          f"{np.median(torch_s) * 1e3:.3f} ms ({ratio:.1f}x)")
    assert ratio >= 2.0, f"{system}: the NumPy push is only {ratio:.2f}x the torch push"
