"""Online cost on each new system: Vid2Param's stream (one push per frame) against lsq re-run
on every prefix, on the same test cases, one thread.

    python scripts/measure_system_online.py --checkpoints runs/gpu_init --n 2

``--checkpoints DIR`` holds ``v2p_<system>.pt`` (a system's network; its cost per push does not
depend on how well it is trained, so an unshipped export measures the code's cost). lsq's
every-prefix total is timed on one prefix in ``--stride`` (and the last) and interpolated in the
prefix length (as the report's online-cost table at the default scale). Prints one line per
system and writes ``--out`` (JSON) atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoints", required=True, help="folder with v2p_<system>.pt")
    p.add_argument("--systems", nargs="+", default=["pendulum", "spring", "collision"])
    p.add_argument("--n", type=int, default=2, help="test cases per system")
    p.add_argument("--stride", type=int, default=10, help="lsq: time one prefix in STRIDE")
    p.add_argument("--out", default="runs/system_online.json")
    a = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    import methods
    from sysid_bench.bench.online import _timed_prefixes
    from sysid_bench.bench.systems import system_case
    from sysid_bench.core._io import atomic_write

    res = {}
    for s in a.systems:
        ck = Path(a.checkpoints) / f"v2p_{s}.pt"
        v2p = methods.get("vid2param", system=s, checkpoint=str(ck))
        lsq = methods.get("lsq", system=s)
        push, stream_tot, lsq_tot = [], [], []
        for i in range(a.n):
            video, _, _ = system_case(s, i, a.n, 2024, "video")
            pos, _, _ = system_case(s, i, a.n, 2024, "positions")
            st = v2p.stream()
            st.push(video.frames[0])  # first call: allocations, not the online cost
            st.reset()
            t0 = time.perf_counter()
            for f in video.frames:
                q = time.perf_counter()
                st.push(f)
                push.append(time.perf_counter() - q)
            stream_tot.append(time.perf_counter() - t0)
            T = len(pos.positions)
            lengths = _timed_prefixes(3, T, a.stride)
            walls = []
            for n in lengths:
                q = time.perf_counter()
                lsq.identify(pos.prefix(n))
                walls.append(time.perf_counter() - q)
            lsq_tot.append(float(np.interp(np.arange(3, T + 1), lengths, walls).sum()))
        r = {"push_ms_median": 1e3 * float(np.median(push)),
             "stream_s_per_video": float(np.median(stream_tot)),
             "lsq_every_prefix_s_per_video": float(np.median(lsq_tot)),
             "ratio": float(np.median(lsq_tot) / np.median(stream_tot)), "videos": a.n,
             "frames": int(len(video.frames)), "checkpoint": ck.name}
        res[s] = r
        print(f"{s}: push {r['push_ms_median']:.3f} ms median, stream "
              f"{r['stream_s_per_video']:.3f} s/video, lsq every prefix "
              f"{r['lsq_every_prefix_s_per_video']:.1f} s/video, ratio {r['ratio']:.0f}x",
              flush=True)
    atomic_write(a.out, json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
