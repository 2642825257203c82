"""Cost and answer of each method at 20 and 60 frames/s on one simulated clip (issue 38 §2).

    PYTHONPATH=$PWD python scripts/capture_dt_cost.py pendulum lsq,emcee,bo,sindy,nuts

10 s of the system's tracked points (1 cm noise, seeded) at dt = 1/20 and 1/60 s; one
``identify`` each after a warm-up on 40 frames (imports, compilation); prints CPU and wall
seconds, the posterior mean and std.
"""

from __future__ import annotations

import sys
import time

import numpy as np

import methods
from sysid_bench.core import systems
from sysid_bench.core.estimator import Observation


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    sysname, names = argv[0], argv[1].split(",")
    s = systems.get(sysname)
    rng = np.random.default_rng(1)
    lo, hi = (np.array([s.prior[p][i] for p in s.params]) for i in (0, 1))
    th = (lo + (hi - lo) * rng.random(len(lo)))[None]
    s0 = s.sample_state0(1, rng)
    obs = {}
    for fps in (20, 60):
        n = 10 * fps
        pts = s.observe(s.simulate(th, s0, n_frames=n, dt=1.0 / fps), th)[0]
        obs[fps] = Observation(positions=pts + rng.normal(0, 0.01, pts.shape), dt=1.0 / fps,
                               system=sysname, **s.known_geometry())
    print(sysname, "truth", dict(zip(s.params, np.round(th[0], 4).tolist())), flush=True)
    for m in names:
        try:
            methods.get(m, system=sysname).identify(obs[20].prefix(40))
        except (NotImplementedError, ValueError):
            pass
        for fps in (20, 60):
            try:
                est = methods.get(m, system=sysname)
                c0, w0 = time.process_time(), time.perf_counter()
                post = est.identify(obs[fps])
                cpu, wall = time.process_time() - c0, time.perf_counter() - w0
            except (NotImplementedError, ValueError) as exc:
                print(f"{m:8s} {fps} fps: n/a ({exc})", flush=True)
                continue
            print(f"{m:8s} {fps} fps T={obs[fps].n_frames}: cpu {cpu:7.2f} s wall {wall:7.2f} s "
                  f"mean {np.round(post.mean, 4)} std {np.round(post.std, 4)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
