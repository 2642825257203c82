"""Write the sample clip the README's ``identify`` lines run on: ``docs/sample/ball.mp4``.

One simulated episode (test-split parameters, seeded), rendered at 128 x 128 by the suite's
renderer and written as H.264 at 20 frames/s with :func:`sysid_bench.core.footage.write_video`:

    python scripts/make_sample_clip.py [--out docs/sample/ball.mp4] [--seed 2026]

The clip's true parameters are printed and written beside it (``ball.json``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sysid_bench.core._io import atomic_write
from sysid_bench.core.datasets import SUBRANGES_TEST
from sysid_bench.core.footage import write_video
from sysid_bench.core.physics import N_FRAMES, PARAMS, sample_state0, sample_theta, simulate
from sysid_bench.core.render import render


def make_clip(out, seed: int = 2026, size: int = 128) -> tuple[Path, dict]:
    """Simulate, render and write one episode.

    Returns
    -------
    Path
        The video file.
    dict
        ``seed``, ``theta`` (e, g, d, r), ``state0`` (x, y, vx, vy), ``size``, ``fps``.
    """
    rng = np.random.default_rng(seed)
    theta = sample_theta(1, rng, subranges=SUBRANGES_TEST)
    s0 = sample_state0(1, rng)
    states = simulate(theta, s0, n_frames=N_FRAMES)
    frames = render(states, size=(size, size))[0]
    path = write_video(out, frames, fps=20)
    info = {"seed": int(seed), "theta": dict(zip(PARAMS, map(float, theta[0]))),
            "state0": [float(v) for v in s0[0]], "size": [size, size], "fps": 20,
            "command": f"python scripts/make_sample_clip.py --seed {seed}"}
    return path, info


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="docs/sample/ball.mp4")
    p.add_argument("--seed", type=int, default=2026)
    a = p.parse_args(argv)
    path, info = make_clip(a.out, a.seed)
    atomic_write(Path(a.out).with_suffix(".json"), json.dumps(info, indent=1) + "\n")
    print(f"{path}: {path.stat().st_size} bytes; {info['theta']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
