"""Time one Vid2Param training step of the pendulum preset (docs/vid2param-training-speed.md).

    python scripts/measure_train_step.py --threads 2 --batch 64          # step times
    python scripts/measure_train_step.py --threads 1 --batch 8 --profile # + torch.profiler table
    python scripts/measure_train_step.py --batch 64 --flop               # + FLOP per step

The batch is 64 pendulum training videos (seed 123, 200 frames, the preset's frame size), drawn
once and cached in ``--cache`` (an .npz); the step is forward, backward, gradient clipping and
Adam, timed after one warm-up step.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from methods.vid2param.data import make_system_split, targets_from_dataset
from methods.vid2param.model import V2PConfig, Vid2ParamNet


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=64, help="videos per step (at most 64)")
    ap.add_argument("--cache", default="runs/train_step_batch.npz")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--flop", action="store_true")
    a = ap.parse_args()
    if not 1 <= a.batch <= 64:
        ap.error(f"--batch: expected 1..64, got {a.batch}")
    mc = V2PConfig.preset("pendulum")
    cache = Path(a.cache)
    if not cache.is_file():
        t = time.time()
        ds = make_system_split("pendulum", "train", 64, 123, 200, mc.frame_size, None, workers=1)
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, frames=np.asarray(ds.frames), targets=targets_from_dataset(ds, mc.targets))
        print(f"drew 64 videos in {time.time() - t:.1f} s -> {cache}")
    torch.set_num_threads(a.threads)
    d = np.load(cache)
    fr, tg = torch.as_tensor(d["frames"][:a.batch]), torch.as_tensor(d["targets"][:a.batch])
    torch.manual_seed(0)
    net = Vid2ParamNet(mc)
    opt = torch.optim.Adam(net.parameters(), 1e-3)

    def step(loss_key: str = "loss") -> None:
        g = torch.Generator().manual_seed(1)
        out = net(fr, tg, n_obs=200, rec_frac=0.25, generator=g, aux_grad=0.01)
        opt.zero_grad(set_to_none=True)
        out[loss_key].backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()

    step()  # warm-up
    for k in ("loss", "loss_nll", "loss"):
        t, c = time.perf_counter(), time.process_time()
        step(k)
        print(f"{k}: wall {time.perf_counter() - t:.3f} s, cpu {time.process_time() - c:.3f} s",
              flush=True)
    if a.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as p:
            step()
        print(p.key_averages().table(sort_by="self_cpu_time_total", row_limit=30))
    if a.flop:
        from torch.utils.flop_counter import FlopCounterMode

        with FlopCounterMode(display=False) as fc:
            step()
        print(f"GFLOP per step: {fc.get_total_flops() / 1e9:.2f}")


if __name__ == "__main__":
    main()
