"""How close are estimates from video files to the truth, against the same episodes as arrays?

Simulated test-split episodes are written as H.264 files at 20 fps (PyAV, crf 18) at 256x256
(clean) and at a camera-like 200x100 (W x H) with the camera model's nuisances (blur 0.5,
occlusion 0.05, drop 0.05, noise 8; no floor offset: the file's geometry puts the floor at the
bottom edge). Each file goes through the identify pipeline (read, find the ball, re-draw or
track); the same episode "as arrays" is what the benchmark feeds: 28x28 frames (clean) or 50x100
frames with the same nuisances, floor known. Normalised squared error after all 200 frames.

    PYTHONPATH=. python scripts/video_measure.py --n 20 --out docs/video_measure.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

import methods
from sysid_bench.apps.video import observe, read_video, write_video
from sysid_bench.core._io import atomic_write
from sysid_bench.core.estimator import Observation
from sysid_bench.core.metrics import normalised_param_se
from sysid_bench.core.physics import sample_state0, sample_theta, simulate
from sysid_bench.core.render import render

NUIS = {"blur": 0.5, "occlusion": 0.05, "drop": 0.05, "noise": 8.0}
SETUPS = {
    # name: (file size HxW, file nuisances, array size, array nuisances, vid2param checkpoint)
    "256x256 clean": ((256, 256), {}, (28, 28), {}, "28x28"),
    "camera 200x100": ((100, 200), NUIS, (50, 100), NUIS, "camera"),
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--n", type=int, default=20)
    p.add_argument("--seed", type=int, default=5)
    p.add_argument("--methods", nargs="+", default=["vid2param", "lsq", "sindy"])
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    theta = sample_theta(a.n, rng, subranges=(1, 3, 5, 7, 9))
    states = simulate(theta, sample_state0(a.n, rng))
    recs = []
    with tempfile.TemporaryDirectory() as tmp:
        for setup, (fsize, fnuis, asize, anuis, ckpt) in SETUPS.items():
            files = render(states, size=fsize, seed=a.seed, **fnuis)
            arrays = render(states, size=asize, seed=a.seed, **anuis)
            ests = {m: methods.get(m, checkpoint=ckpt) if m == "vid2param" else methods.get(m)
                    for m in a.methods}
            for i in range(a.n):
                path = write_video(Path(tmp) / f"{i}.mp4", files[i], fps=20)
                t0 = time.perf_counter()
                clip = read_video(path)
                t_read = time.perf_counter() - t0
                rolls = bool(np.any((np.abs(states[i, :, 1]) < 1e-9) & (np.abs(states[i, :, 2]) > 0.05)))
                for m, est in ests.items():
                    size = tuple(est.frame_size) if m == "vid2param" else None
                    t0 = time.perf_counter()
                    obs, pos, trk, _ = observe(clip.frames, size)
                    post = est.identify(obs)
                    t_file = time.perf_counter() - t0 + t_read
                    arr = Observation(frames=arrays[i], floor=0.0)
                    post_a = est.identify(arr)
                    se_f = normalised_param_se(theta[i], post.mean)
                    se_a = normalised_param_se(theta[i], post_a.mean)
                    err = np.linalg.norm(pos - states[i, :, :2], axis=1)
                    recs.append({"setup": setup, "case": i, "method": m, "rolls": rolls,
                                 "se_file": se_f.tolist(), "se_array": se_a.tolist(),
                                 "track_rmse_m": float(np.sqrt(np.nanmean(err**2))),
                                 "found": int(trk.n_found), "file_s": t_file})
                print(setup, i, flush=True)
    print("| video | method | e, g, d nMSE from the file | as arrays | r nMSE (rolling) file / arrays | tracking RMS (m) | ball found |")
    print("|---|---|---|---|---|---|---|")
    for setup in SETUPS:
        for m in a.methods:
            rs = [r for r in recs if r["setup"] == setup and r["method"] == m]
            f = np.array([r["se_file"] for r in rs])
            ar = np.array([r["se_array"] for r in rs])
            roll = np.array([r["rolls"] for r in rs])
            rr = (f"{f[roll, 3].mean():.3g} / {ar[roll, 3].mean():.3g} ({roll.sum()})" if roll.any() else "-")
            print(f"| {setup} | {m} | {f[:, :3].mean():.4f} ({' / '.join(f'{v:.4f}' for v in f[:, :3].mean(0))}) "
                  f"| {ar[:, :3].mean():.4f} ({' / '.join(f'{v:.4f}' for v in ar[:, :3].mean(0))}) | {rr} "
                  f"| {np.mean([r['track_rmse_m'] for r in rs]):.4f} "
                  f"| {np.mean([r['found'] for r in rs]) / 200:.3f} |")
    if a.out:
        atomic_write(a.out, json.dumps({"seed": a.seed, "n": a.n, "records": recs}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
