"""One Vid2Param training step of the pendulum preset (issue 39, section 1).

Run with ``pytest tests/test_bench_train_step.py --benchmark-only``. One optimiser step
(forward, backward, gradient clip, Adam) of the pendulum preset's network (64x64 frames pooled
to 32x32, ~550k parameters) on ``B`` rendered pendulum videos of ``T`` frames. The preset's step
is 64 x 200 (48.2 GFLOP, torch's ``FlopCounterMode``); the benchmark runs 4 x 50 so that it
stays under a minute on two busy cores (the step's cost is about linear in B x T, so 1/64 of
the preset's; ``extra_info`` gives both).

Reported in ``extra_info`` and printed: the step's seconds, its FLOP (counted on this step),
GFLOP/s and the ratio to the cores' fp32 peak (``PEAK_GFLOPS_PER_CORE`` times the threads).
Also timed in the same run, interleaved, and reported (not asserted): the step with the
preset's 4 threads (what ``train`` used before ``train_threads`` capped them at the usable
cores) and with 1 thread. A bound on those ratios does not survive a shared machine: on the
2-core machine under load ~11 (8 engineers' jobs), 2 threads were slower than 4 in one run and a
B=8 step took 69-98 s with 2 threads against 4.5-5.2 s with 1 (OpenMP threads waiting for a
descheduled sibling at each of the step's ~10^4 small operations;
docs/vid2param-training-speed.md). Asserted: the FLOP count of this step is linear in the batch
(a ratio measured in this run; it fails if a batch-independent cost or a per-video Python path
enters the counted step).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from methods.vid2param.data import make_system_split, targets_from_dataset
from methods.vid2param.model import V2PConfig, Vid2ParamNet
from methods.vid2param.train import PRESET_TRAIN, train_threads, usable_cores

#: fp32 peak of one core (GFLOP/s): the issue's 190 GFLOP/s for two AVX-512 cores of the CI
#: machine (2 FMA x 16 lanes x 2 FLOP at ~3 GHz); another CPU has another peak.
PEAK_GFLOPS_PER_CORE = 95.0
B, T = 4, 50
PRESET_B, PRESET_T = 64, 200


def _step(net, opt, frames, targets):
    g = torch.Generator().manual_seed(1)
    out = net(frames, targets, n_obs=frames.shape[1], rec_frac=0.25, generator=g,
              aux_grad=0.01)
    opt.zero_grad(set_to_none=True)
    out["loss"].backward()
    torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
    opt.step()


def _flop(net, opt, frames, targets) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc:
        _step(net, opt, frames, targets)
    return float(fc.get_total_flops())


@pytest.mark.slow
@pytest.mark.benchmark(group="vid2param-train-step")
def test_bench_pendulum_training_step(benchmark):
    before = torch.get_num_threads()
    mc = V2PConfig.preset("pendulum")
    ds = make_system_split("pendulum", "train", B, 5, T, mc.frame_size)
    frames = torch.as_tensor(np.asarray(ds.frames))
    targets = torch.as_tensor(targets_from_dataset(ds, mc.targets))
    torch.manual_seed(0)
    net = Vid2ParamNet(mc)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    asked = int(PRESET_TRAIN["pendulum"]["threads"])
    used = train_threads(asked)
    try:
        flop = _flop(net, opt, frames, targets)
        flop_half = _flop(net, opt, frames[: B // 2], targets[: B // 2])

        def timed(threads: int) -> float:
            torch.set_num_threads(threads)
            t0 = time.perf_counter()
            _step(net, opt, frames, targets)
            return time.perf_counter() - t0

        timed(used)  # warm-up
        t_used, t_asked, t_one = [], [], []
        for _ in range(2):  # interleaved, so all see the same load
            t_used.append(timed(used))
            t_asked.append(timed(asked))
            t_one.append(timed(1))
        torch.set_num_threads(used)
        benchmark.pedantic(_step, args=(net, opt, frames, targets), rounds=1, iterations=1)
    finally:
        torch.set_num_threads(before)
    step_s, ref_s, one_s = min(t_used), min(t_asked), min(t_one)
    gflops = flop / step_s / 1e9
    peak = PEAK_GFLOPS_PER_CORE * used
    info = {"batch": B, "frames": T, "threads": used, "threads_asked": asked,
            "usable_cores": usable_cores(), "step_s": step_s, "step_s_threads_asked": ref_s,
            "speedup_vs_threads_asked": ref_s / step_s, "step_s_one_thread": one_s,
            "flop_per_step": flop,
            "gflop_per_s": gflops, "peak_gflop_per_s": peak, "ratio_to_peak": gflops / peak,
            "preset_flop_per_step_est": flop * (PRESET_B * PRESET_T) / (B * T),
            "preset_step_s_est": step_s * (PRESET_B * PRESET_T) / (B * T)}
    benchmark.extra_info.update(info)
    print(f"\npendulum step {B}x{T}: {step_s:.3f} s with {used} threads ({asked} threads: "
          f"{ref_s:.3f} s, 1 thread: {one_s:.3f} s), {flop / 1e9:.2f} GFLOP, {gflops:.1f} GFLOP/s = "
          f"{100 * gflops / peak:.1f}% of {peak:.0f}; the preset's 64x200 step ~"
          f"{info['preset_step_s_est']:.1f} s")
    assert flop == pytest.approx(2 * flop_half, rel=0.02), info
