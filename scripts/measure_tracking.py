"""Tracker figures: detection and error on rendered videos, "no ball" on meaningless frames,
and the centre of a shaded, lit ball.

    OMP_NUM_THREADS=1 PYTHONPATH=.:tests python scripts/measure_tracking.py

Rendered videos: test-split-like balls (``physics.sample_theta``/``sample_state0``), clean and
with the camera nuisances (blur 0.5, occlusion 0.05, drop 0.05, noise 8), at 28x28 and 50x100.
``tracking.track_batch`` and ``video.find_ball`` (background subtraction over each clip) are run
on every video; a frame counts as "visible" when it is not dropped. Meaningless frames: white,
black, uniform grey, uniform random noise, Gaussian noise around mid-grey, and a frozen
background (the same textured scene in every frame, no ball). "clear": neither dropped nor
occluded. Shaded ball: ``shaded_ball`` (tests/shaded_ball.py), a Lambertian sphere lit from
above-left on a wall a little brighter than its lit top, radii 3-12 px.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from sysid_bench.apps.video import find_ball
from sysid_bench.core import physics
from sysid_bench.core.render import render, view_geometry
from sysid_bench.core.tracking import track_batch

NUIS = {"blur": 0.5, "occlusion": 0.05, "drop": 0.05, "noise": 8.0}


def rendered(n_videos: int, n_frames: int) -> dict:
    rng = np.random.default_rng(2029)
    st = physics.simulate(physics.sample_theta(n_videos, rng), physics.sample_state0(n_videos, rng),
                          n_frames=n_frames)
    out = {}
    for size in ((28, 28), (50, 100)):
        geo = view_geometry(size)
        for name, kw in (("clean", {}), ("nuisances", NUIS)):
            fr, info = render(st, size, seed=7, return_info=True, **kw)
            vis = ~info["dropped"]
            clear = vis & ~info["occluded"]
            row = {"frames": int(fr.shape[0] * fr.shape[1]), "visible": int(vis.sum()),
                   "clear": int(clear.sum())}
            pos = track_batch(fr)
            seen = np.isfinite(pos).all(axis=-1)
            row["track"] = _score(pos, st[..., :2], seen, vis, clear, geo)
            pix = np.stack([find_ball(v).pixels for v in fr])
            pos = geo.to_metres(pix)
            seen = np.isfinite(pos).all(axis=-1)
            row["find_ball"] = _score(pos, st[..., :2], seen, vis, clear, geo)
            out[f"{size[0]}x{size[1]} {name}"] = row
    return out


def _score(pos, truth, seen, vis, clear, geo) -> dict:
    err = np.linalg.norm(pos - truth, axis=-1)
    sx, sy = geo.px_per_m
    err_px = np.hypot((pos[..., 0] - truth[..., 0]) * sx, (pos[..., 1] - truth[..., 1]) * sy)
    ok = seen & vis
    return {"detected_of_visible": round(float(ok.sum() / vis.sum()), 4),
            "detected_of_clear": round(float((seen & clear).sum() / clear.sum()), 4),
            "rms_px_clear": round(float(np.sqrt(np.mean(err_px[seen & clear] ** 2))), 4),
            "detected_of_dropped": int((seen & ~vis).sum()),
            "rms_m": round(float(np.sqrt(np.mean(err[ok] ** 2))), 5),
            "rms_px": round(float(np.sqrt(np.mean(err_px[ok] ** 2))), 4),
            "max_m": round(float(err[ok].max()), 4)}


def meaningless(n_frames: int, size=(28, 28)) -> dict:
    rng = np.random.default_rng(5)
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    scene = np.clip(60 + 120 * xx / w + 25 * np.sin(yy / 3.0) + rng.normal(0, 4, (h, w)), 0, 255)
    kinds = {
        "white": np.full((n_frames, h, w), 255, np.uint8),
        "black": np.zeros((n_frames, h, w), np.uint8),
        "grey": np.full((n_frames, h, w), 128, np.uint8),
        "uniform noise": rng.integers(0, 256, (n_frames, h, w)).astype(np.uint8),
        "gaussian noise": np.clip(rng.normal(128, 40, (n_frames, h, w)), 0, 255).astype(np.uint8),
        "frozen background": np.broadcast_to(scene.astype(np.uint8), (n_frames, h, w)).copy(),
    }
    out = {}
    for name, fr in kinds.items():
        out[name] = {"track": round(float(np.isfinite(track_batch(fr[None])[0]).all(-1).mean()), 3),
                     "find_ball": round(float(find_ball(fr).found.mean()), 3)}
    return out


def shaded(n_frames: int) -> dict:
    from shaded_ball import path, shaded_frames

    out = {}
    size = (72, 96)
    for radius in (3.0, 5.0, 8.0, 12.0):
        truth = path(n_frames, radius, size, seed=int(radius))
        fr = shaded_frames(truth, radius, size, seed=int(radius))
        pix = find_ball(fr).pixels
        d = pix - truth
        ok = np.isfinite(d).all(axis=1)
        out[f"r={radius:g}"] = {"found": round(float(ok.mean()), 3),
                                "bias_col_px": round(float(d[ok, 0].mean()), 3),
                                "bias_row_px": round(float(d[ok, 1].mean()), 3),
                                "max_err_px": round(float(np.hypot(*d[ok].T).max()), 3)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--videos", type=int, default=10)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    res = {"rendered": rendered(a.videos, a.frames), "meaningless": meaningless(a.frames),
           "shaded": shaded(a.frames)}
    text = json.dumps(res, indent=1)
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
