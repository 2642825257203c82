"""Issue 38: choose the camera check's factor from clips with truth.

Reads a ``scripts/measure_ball_camera.py`` results file (per clip: each method's check RMS, its
verdict and its misses ``z`` in stds) and the clips beside it, follows each clip once with
:func:`sysid_bench.core.footage.observe_clip` (the clip's own options) to get the track's noise
(:func:`track_noise`), and counts, for a few factors, confident-wrong answers (a miss by more
than 3 std with the check passing) and false alarms (the check failing while every 90%
interval holds the truth).

    PYTHONPATH=. python scripts/measure_camera_check.py runs/ball_camera/after.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from sysid_bench.core import footage
from sysid_bench.core.estimator import Check


def main(argv=None) -> int:
    res = Path((argv or sys.argv[1:])[0])
    rows = json.loads(res.read_text())
    noise = {}
    for r in rows:
        truth = json.loads((res.parent / f"ball_{r['clip']}.json").read_text())
        opts = [o for o in truth["options"]]
        drop = {"--system", "--method"}
        keep, i = [], 0
        while i < len(opts):
            if opts[i] in drop:
                i += 2
                continue
            keep.append(opts[i])
            i += 1
        cc = footage.observe_clip(res.parent / truth["file"], "ball", keep, fps=footage.MODEL_FPS)
        noise[r["clip"]] = footage.track_noise(np.asarray(cc.observation.positions))
        print(f"clip {r['clip']}: track noise {noise[r['clip']]:.4g} m", flush=True)
    print("\n| method | k | check passes | confident wrong | false alarms |")
    print("|---|---|---|---|---|")
    for m in ("lsq", "emcee"):
        for k in (None, 1.5, 2.0, 3.0, 4.0):
            ok_n = cw = fa = 0
            for r in rows:
                f = r["fits"][m]
                z = np.abs(np.asarray(f["z"], dtype=float))
                chk = Check(float(f["check_rms"]), float(f["check_noise"]), bool(f["check"]),
                            n=2 * int(r["seen"]))
                if k is not None:
                    chk = footage.camera_check(chk, noise[r["clip"]], k)
                ok_n += chk.ok
                cw += chk.ok and bool(np.any(z > 3))
                fa += (not chk.ok) and bool(np.all(z <= 1.6449))
            print(f"| {m} | {'none' if k is None else k} | {ok_n}/{len(rows)} | {cw} | {fa} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
