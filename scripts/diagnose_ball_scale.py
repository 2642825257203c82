"""Why a camera clip of the ball misses |g|: its size, scale, floor and centres against the truth.

For each ``ball_*.json`` clip of ``camera_footage`` in ``--clips`` (``measure_camera_footage.py``
films them), follows the ball as ``sysid-bench identify`` does (decode with the clip's options,
in colour, turned upright, :func:`footage.find_object`, :func:`footage.camera_for` with
``--object-size-m``) and prints, against the truth the generator knows (the camera's focal
length and the ball's depth frame by frame):

- the ball's apparent diameter read against the true one (median error over the frames), and
  the scale the camera used (median error);
- lsq's |g| error (one estimate after the whole clip, as identify's last) with the track as
  read (``read``), the tracked centres at each frame's true scale (``true-scale``), the same
  with the true floor height (``true-floor``), and the true centres at the true scale
  (``true-centres``; the floor still estimated): which stage carries the error.

    PYTHONPATH=. python scripts/diagnose_ball_scale.py --clips runs/ball20
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np


def _g_error(cam, pix, fps, truth) -> float:
    import methods
    from sysid_bench.core.estimator import Observation
    from sysid_bench.core.physics import BOX_WIDTH

    pos = cam.to_metres(pix)
    obs = Observation(positions=np.clip(pos, 0.0, BOX_WIDTH), dt=1.0 / fps, floor=0.0)
    post = methods.get("lsq", seed=0).identify(obs)
    return float(post.mean[1] / truth["theta"]["g"] - 1)  # + : |g| read too large


def diagnose(jpath: Path) -> dict:
    from sysid_bench.core import footage

    truth = json.loads(jpath.read_text())
    opts = footage.clip_options(truth["options"])
    clip = footage.read_video(jpath.parent / truth["file"], None, start=opts.get("start"),
                              capture_fps=opts.get("capture_fps"), colour=True)
    rot = int(opts.get("rotate", 0))
    frames = footage.rotate_frames(clip.frames, rot)
    trk = footage.find_object(frames, colour=footage.rotate_frames(clip.colour_frames, rot),
                              chroma_px=footage.turned_chroma(clip.chroma_px, rot))
    fps = float(truth["fps"])
    # each kept frame's index in the clip (the window starts at the first frame >= --start)
    idx = int(np.ceil(float(opts.get("start") or 0.0) * fps - 1e-6)) + np.rint(
        clip.times * fps).astype(int)
    k0 = trk.first_seen()
    trk, idx = trk.from_frame(k0), idx[k0:]  # as identify: from the first frame seen
    c = truth["camera"]
    z = c["distance_m"] + c["depth_speed_m_s"] * np.maximum(idx / fps - truth["release_s"], 0)
    s_true = c["f_px"] / z
    d_true = float(opts["object_size_m"]) * s_true
    size = frames.shape[1:]
    cam = footage.camera_for("ball", trk, size, object_size_m=opts["object_size_m"])
    # the same camera code given the true sizes: the true scale, frame by frame
    exact = dataclasses.replace(trk, radii=np.where(trk.found, d_true / 2, np.nan))
    cam_t = footage.camera_for("ball", exact, size, object_size_m=opts["object_size_m"])
    cam_f = dataclasses.replace(cam_t, offset=(cam_t.offset[0], c["looks_at_m"][1]))
    pix_true = np.asarray(truth["pixels"])[idx, 0]
    true_c = dataclasses.replace(exact, pixels=np.where(trk.found[:, None], pix_true, np.nan))
    cam_c = footage.camera_for("ball", true_c, size, object_size_m=opts["object_size_m"])
    seen = trk.found
    return {
        "clip": truth["file"], "fps": truth["fps"], "size": truth["size_filmed"],
        "tilt_deg": truth["tilt_deg"],
        "diameter_px": [float(d_true.min()), float(d_true.max())],
        "diameter_err": float(np.nanmedian(2 * trk.radii[seen] / d_true[seen] - 1)),
        "scale_err": float(np.median(cam.scales(len(idx))[seen] / s_true[seen] - 1)),
        "centre_row_err_px": float(np.nanmedian(trk.pixels[seen, 1] - pix_true[seen, 1])),
        "g": {"read": _g_error(cam, trk.pixels, fps, truth),
              "true-scale": _g_error(cam_t, trk.pixels, fps, truth),
              "true-floor": _g_error(cam_f, trk.pixels, fps, truth),
              "true-centres": _g_error(cam_c, true_c.pixels, fps, truth)},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clips", default="runs/ball20")
    ap.add_argument("--json", default=None, help="write the rows here too")
    a = ap.parse_args(argv)
    paths = sorted(Path(a.clips).glob("ball_s*fps.json"),
                   key=lambda p: int(p.name.split("_s")[1].split("_")[0]))
    rows = []
    print("| clip | fps, size, tilt | true diameter px | diameter read | scale read | |g| error: "
          "read / true scale / + true floor / true centres |")
    print("|---|---|---|---|---|---|")
    for p in paths:
        r = diagnose(p)
        rows.append(r)
        g = r["g"]
        print(f"| {p.stem} | {r['fps']}, {r['size'][1]}x{r['size'][0]}, {r['tilt_deg']:g} | "
              f"{r['diameter_px'][0]:.1f}-{r['diameter_px'][1]:.1f} | "
              f"{100 * r['diameter_err']:+.1f}% | {100 * r['scale_err']:+.1f}% | "
              + " / ".join(f"{100 * g[k]:+.1f}%" for k in g) + " |", flush=True)
    for k in rows[0]["g"] if rows else ():
        n3 = sum(abs(r["g"][k]) <= 0.03 for r in rows)
        print(f"{k}: |g| within 3% in {n3} of {len(rows)}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
