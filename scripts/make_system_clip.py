"""Write a seeded sample clip of a system (its own render, H.264) and its true parameters.

    python scripts/make_system_clip.py --system pendulum --out docs/sample/pendulum.mp4
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sysid_bench.core import systems
from sysid_bench.core._io import atomic_write
from sysid_bench.core.footage import write_video


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--system", default="pendulum")
    p.add_argument("--out", default=None)
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    sys_ = systems.get(a.system)
    out = Path(a.out or f"docs/sample/{sys_.name}.mp4")
    theta, state0 = sys_.sample_cases(1, np.random.default_rng(a.seed), "test")
    frames = sys_.render(sys_.simulate(theta, state0, a.frames), theta)[0]
    out.parent.mkdir(parents=True, exist_ok=True)
    write_video(out, frames)
    meta = {"system": sys_.name, "seed": a.seed, "frames": a.frames, "fps": 20,
            "theta": dict(zip(sys_.params, theta[0].tolist())),
            "state0": dict(zip(sys_.state, state0[0].tolist())),
            "made_by": f"python scripts/make_system_clip.py --system {sys_.name} --seed {a.seed}"}
    atomic_write(out.with_suffix(".json"), json.dumps(meta, indent=1))
    print(out, out.stat().st_size, "bytes", meta["theta"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
