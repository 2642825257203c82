"""Why the ball's camera footage misses |g|: each stage of the pipeline against the truth.

Films ``--n`` clips of the ball with the camera section's own generator (the default scale's
shots: ``camera_footage.shots("ball", n, seed)`` at 640x360, seeds 2024...; cached in
``--out``), then, clip by clip, runs what ``footage.observe_clip`` runs (decode with the
clip's ``--start``/``--fps``, turn upright, :func:`find_object`, :func:`camera_for` with
``--object-size-m``) and compares with the truth of each kept frame:

- the apparent radius (px) against the true one (``0.035 m * f / depth``), hence the scale;
- the tracked centre against the true pixel (col, row);
- the positions in metres against the true ones (x up to a constant: no walls are in view);
- the fitted parameters (``--methods``, each identifying once after the whole clip, the scale's
  uncertainty added as the camera section adds it): |g| error, 90% coverage of g, e error,
  the model check, confident wrong (a miss by more than 3 std with the check passing).

``--oracle`` adds fits on the true positions (what the method gets from a perfect camera).

    PYTHONPATH=. python scripts/measure_ball_camera.py --n 10 --out runs/ball_camera
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

Z90 = 1.6449


def clip_truth(out: Path, seed: int, k: int, n: int):
    from sysid_bench.core.camera_footage import shots, write_clip

    shot = shots("ball", n, seed, size=(360, 640))[k]
    name = f"ball_{k}"
    j = out / f"{name}.json"
    if not j.is_file():
        write_clip(shot, out, name)
    truth = json.loads(j.read_text())
    return out / truth["file"], truth


def observe(video: Path, truth: dict):
    """The section's pipeline, keeping the intermediate track, camera and frame indices."""
    from sysid_bench.core import footage
    from sysid_bench.core.estimator import Observation

    opts = footage.clip_options(truth["options"])
    clip = footage.read_video(video, start=opts.get("start"), capture_fps=opts.get("capture_fps"))
    frames = footage.rotate_frames(clip.frames, int(opts.get("rotate", 0)))
    trk = footage.find_object(frames)
    cam = footage.camera_for("ball", trk, frames.shape[1:], object_size_m=opts["object_size_m"],
                             rotate=int(opts.get("rotate", 0)))
    pos = cam.to_metres(trk.pixels)
    obs = Observation(positions=pos[:, None, :], dt=1.0 / clip.fps, system="ball", floor=0.0)
    fps = float(truth["fps"])
    i0 = int(np.ceil(float(opts.get("start") or 0.0) * fps - 1e-6))
    idx = i0 + np.rint(clip.times * fps).astype(int)
    return obs, trk, cam, idx


def true_scale(truth: dict, idx) -> np.ndarray:
    c = truth["camera"]
    t = np.asarray(idx) / float(truth["fps"])
    z = c["distance_m"] + c["depth_speed_m_s"] * np.maximum(t - truth["release_s"], 0.0)
    return c["f_px"] / z


def fit(method: str, obs, rel: float, truth: dict) -> dict:
    import methods
    from sysid_bench.core import footage

    est = methods.get(method, system="ball")
    t0 = time.perf_counter()
    post = est.identify(obs)
    wall = time.perf_counter() - t0
    mean, std = np.asarray(post.mean, float), np.asarray(post.std, float)
    if rel > 0:
        std = footage.widen_for_scale("ball", ("e", "g", "d", "r"), mean, std, rel)
    th = np.array([truth["theta"][p] for p in ("e", "g", "d", "r")])
    z = np.abs(mean - th) / np.where(std > 0, std, np.nan)
    ok = None if post.check is None else bool(post.check.ok)
    return {"mean": mean.tolist(), "std": std.tolist(), "g_rel": float(mean[1] / th[1] - 1),
            "g_in90": bool(abs(mean[1] - th[1]) <= Z90 * std[1]),
            "e_err": float(mean[0] - th[0]), "z": np.nan_to_num(z, nan=np.inf).tolist(),
            "check": ok, "check_rms": None if post.check is None else post.check.rms_m,
            "check_noise": None if post.check is None else post.check.noise_m,
            "confident_wrong": bool(ok and np.any(z > 3.0)), "wall_s": wall}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--n", type=int, default=10)
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--out", default="runs/ball_camera")
    p.add_argument("--methods", default="lsq,emcee")
    p.add_argument("--oracle", action="store_true")
    p.add_argument("--json", default=None, help="write the per-clip figures here")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for k in range(a.n):
        video, truth = clip_truth(out, a.seed, k, a.n)
        obs, trk, cam, idx = observe(video, truth)
        trk_size = (truth["size_filmed"][0], truth["size_filmed"][1])
        seen = trk.found
        s_true = true_scale(truth, idx)
        s_read = cam.scales(len(idx))
        r_true = 0.5 * truth["object_size_m"] * s_true
        pix_true = np.asarray(truth["pixels"])[idx, 0]  # (T, 2) upright px
        d_pix = trk.pixels - pix_true
        pos_true = np.asarray(truth["positions_m"])[idx, 0]
        pos = np.asarray(obs.positions).reshape(len(idx), -1, 2)[:, 0]
        dx = (pos[:, 0] - pos_true[:, 0])
        dx = dx - np.nanmedian(dx)
        dy = pos[:, 1] - pos_true[:, 1]
        row = {
            "clip": k, "fps": truth["fps"], "rotate": truth["rotate"], "tilt": truth["tilt_deg"],
            "frames": int(len(idx)), "seen": int(seen.sum()),
            "r_true_px": float(np.median(r_true)),
            "radius_bias_px": float(np.nanmedian(trk.radii[seen] - r_true[seen])),
            "radius_rms_px": float(np.sqrt(np.nanmean((trk.radii[seen] - r_true[seen]) ** 2))),
            "scale_err_med": float(np.nanmedian(s_read[seen] / s_true[seen] - 1)),
            "scale_err_min": float(np.nanmin(s_read[seen] / s_true[seen] - 1)),
            "scale_err_max": float(np.nanmax(s_read[seen] / s_true[seen] - 1)),
            "scale_change": float(s_true[seen].max() / s_true[seen].min() - 1),
            "scale_rel_std": float(cam.scale_rel_std),
            "col_bias_px": float(np.nanmedian(d_pix[seen, 0])),
            "row_bias_px": float(np.nanmedian(d_pix[seen, 1])),
            "centre_rms_px": float(np.sqrt(np.nanmean((d_pix[seen] ** 2).sum(axis=1)))),
            "y_bias_m": float(np.nanmedian(dy[seen])),
            "y_rms_m": float(np.sqrt(np.nanmean(dy[seen] ** 2))),
            "y_drift_m": float(np.polyfit(np.flatnonzero(seen) * obs.dt, dy[seen], 1)[0]),
            "x_rms_m": float(np.sqrt(np.nanmean(dx[seen] ** 2))),
            "fits": {},
        }
        for m in [s for s in a.methods.split(",") if s]:
            row["fits"][m] = fit(m, obs, cam.scale_rel_std, truth)
            if a.oracle:
                from sysid_bench.core.estimator import Observation

                pt = pos_true + [5.0 - float(np.mean(pos_true[:, 0])), 0.0]  # mid-box, as camera_for
                o2 = Observation(positions=np.where(seen[:, None], pt, np.nan)[:, None],
                                 dt=obs.dt, system="ball", floor=0.0)
                row["fits"][m + "@truth"] = fit(m, o2, 0.0, truth)
                # the tracked centres at the true scale of each frame, scaled about the image
                # centre (the pinhole's principal point), the true offset: the track's own error
                h, w = trk_size
                m_xy = np.stack([(trk.pixels[:, 0] - w / 2) / s_true,
                                 (h / 2 - trk.pixels[:, 1]) / s_true], axis=1)
                off = np.nanmedian(pt - m_xy, axis=0)
                o3 = Observation(positions=(m_xy + off)[:, None], dt=obs.dt, system="ball",
                                 floor=0.0)
                row["fits"][m + "@track+true-scale"] = fit(m, o3, 0.0, truth)
        rows.append(row)
        f = row["fits"]
        print(f"clip {k} {truth['fps']}fps rot{truth['rotate']} tilt{truth['tilt_deg']:g}: "
              f"seen {row['seen']}/{row['frames']} r {row['r_true_px']:.1f}px "
              f"r-bias {row['radius_bias_px']:+.2f}px scale {100 * row['scale_err_med']:+.1f}% "
              f"[{100 * row['scale_err_min']:+.1f}, {100 * row['scale_err_max']:+.1f}] "
              f"(true change {100 * row['scale_change']:.1f}%, rel_std "
              f"{100 * row['scale_rel_std']:.1f}%) centre bias ({row['col_bias_px']:+.2f}, "
              f"{row['row_bias_px']:+.2f})px rms {row['centre_rms_px']:.2f}px; y bias "
              f"{100 * row['y_bias_m']:+.1f}cm rms {100 * row['y_rms_m']:.1f}cm drift "
              f"{100 * row['y_drift_m']:+.1f}cm/s; "
              + "; ".join(f"{m}: g {100 * v['g_rel']:+.1f}% {'in' if v['g_in90'] else 'OUT'} "
                          f"(std {v['std'][1]:.2g}) e {v['e_err']:+.3f} check "
                          f"{'pass' if v['check'] else 'fail'} rms {1000 * (v['check_rms'] or 0):.1f}mm"
                          f"{' CONFIDENT-WRONG' if v['confident_wrong'] else ''}"
                          for m, v in f.items()), flush=True)
    print()
    for m in sorted({m for r in rows for m in r["fits"]}):
        fs = [r["fits"][m] for r in rows if m in r["fits"]]
        g3 = sum(abs(v["g_rel"]) <= 0.03 for v in fs)
        cov = sum(v["g_in90"] for v in fs)
        e5 = sum(abs(v["e_err"]) <= 0.05 for v in fs)
        cw = sum(v["confident_wrong"] for v in fs)
        ck = sum(bool(v["check"]) for v in fs)
        med = float(np.median([abs(v["g_rel"]) for v in fs]))
        print(f"{m}: |g| within 3% {g3}/{len(fs)} (median |err| {100 * med:.1f}%), g 90% holds "
              f"{cov}/{len(fs)}, e within 0.05 {e5}/{len(fs)}, check passes {ck}/{len(fs)}, "
              f"confident wrong {cw}/{len(fs)}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
