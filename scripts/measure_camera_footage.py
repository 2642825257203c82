"""What ``sysid-bench identify`` gets on camera-like clips of the four systems (issue 38, 5).

Films ``--n`` clips per system with :mod:`sysid_bench.core.camera_footage` (cached: a clip whose
JSON exists is not filmed again), runs ``python -m sysid_bench identify CLIP <the options a user
would give, from the clip's JSON> --every 100000 --no-progress --out DIR`` on each (one estimate,
after the whole clip), and compares the answer with the truth: each parameter's error, whether
its 90% interval (mean +- 1.645 std) holds the truth, by how many of its stds it misses, the
model check's verdict, and the frames (at identify's 20 frames/s) where the tracker did not see
the object. Writes ``--out``/results.json and prints a Markdown table.

    PYTHONPATH=. python scripts/measure_camera_footage.py --n 5 --out runs/camera_footage
    PYTHONPATH=. python scripts/measure_camera_footage.py --n 5 --system collision \
        --method emcee --out runs/camera_footage        # another method: results_emcee.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

Z90 = 1.6449


def _identify(video: Path, options: list[str], out: Path) -> dict:
    cmd = [sys.executable, "-m", "sysid_bench", "identify", str(video), *options,
           "--every", "100000", "--no-progress", "--out", str(out)]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ})
    wall = time.perf_counter() - t0
    res = {"cmd": " ".join(["sysid-bench", "identify", video.name, *options]), "rc": p.returncode,
           "wall_s": round(wall, 1), "stderr": p.stderr.strip().splitlines()[-3:]}
    if p.returncode == 0:
        res["estimates"] = json.loads((out / "estimates.json").read_text())
    return res


def _score(truth: dict, res: dict) -> dict:
    row = {"clip": truth["file"], "system": truth["system"], "cmd": res["cmd"], "rc": res["rc"],
           "wall_s": res["wall_s"], "fps": truth["fps"], "size": truth["size_filmed"],
           "rotate": truth["rotate"], "tilt_deg": truth["tilt_deg"]}
    if res["rc"] != 0:
        row["error"] = res["stderr"][-1] if res["stderr"] else ""
        return row
    est = res["estimates"]
    rows = est["estimates"]
    params = truth["params"]
    last = [r for r in rows if r.get(f"{params[0]}_mean") is not None][-1]
    checks = [r["check_ok"] for r in rows if r.get("check_ok") is not None]
    xkey = "x_m" if "x_m" in rows[0] else "x1_m"
    row["frames"] = len(rows)
    row["lost"] = sum(1 for r in rows if r.get(xkey) is None)
    row["check_ok"] = bool(checks[-1]) if checks else None
    held = (est.get("knowledge") or {}).get("held")
    row["known_held"] = held
    for p in params:
        m, s, t = last[f"{p}_mean"], last[f"{p}_std"], truth["theta"][p]
        row[p] = {"truth": t, "mean": m, "std": s, "err": m - t,
                  "rel_err": (m - t) / abs(t) if t else None,
                  "in90": bool(abs(m - t) <= Z90 * s) if s is not None else None,
                  "z": abs(m - t) / s if s else None}
    return row


def _fmt(v, rel=False):
    if v is None:
        return "-"
    return f"{100 * v:+.1f}%" if rel else f"{v:.4g}"


def table(results: list[dict]) -> str:
    """The Markdown table of ``results`` (one row per clip) and a per-system summary."""
    lines = ["| clip | fps, size, rotate, tilt | answer vs truth (mean ± std; error) | 90% holds | "
             "check | frames not seen | wall |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        how = f"{r['fps']}, {r['size'][1]}x{r['size'][0]}, {r['rotate']}, {r['tilt_deg']:g}"
        if r["rc"] != 0:
            why = r.get("error", "").split(".mp4: ", 1)[-1]  # the line without the command and path
            lines.append(f"| {r['clip']} | {how} | exit {r['rc']}: {why} "
                         f"| - | - | - | {r['wall_s']} s |")
            continue
        ps = [k for k in r if isinstance(r[k], dict) and "truth" in r[k]]
        ans = "; ".join(f"{p} {r[p]['mean']:.4g} ± {r[p]['std']:.2g} (truth {r[p]['truth']:.4g})"
                        for p in ps)
        held = " ".join(f"{p}:{'y' if r[p]['in90'] else 'n'}" for p in ps)
        chk = {True: "pass", False: "fail", None: "-"}[r["check_ok"]]
        lines.append(f"| {r['clip']} | {how} | {ans} | {held} | {chk} | {r['lost']} of "
                     f"{r['frames']} | {r['wall_s']} s |")
    lines += ["", "| system | clips answered | per parameter: median abs error (relative where the truth "
              "is not 0), 90% interval holds | check passes | confident wrong (a miss > 3 std, "
              "check passing) | frames not seen |", "| --- | --- | --- | --- | --- | --- |"]
    for system in dict.fromkeys(r["system"] for r in results):
        rs = [r for r in results if r["system"] == system]
        ok = [r for r in rs if r["rc"] == 0]
        if not ok:
            lines.append(f"| {system} | 0 of {len(rs)} | - | - | - | - |")
            continue
        ps = [k for k in ok[0] if isinstance(ok[0][k], dict) and "truth" in ok[0][k]]
        per = []
        for p in ps:
            rel = [abs(r[p]["rel_err"]) for r in ok if r[p]["rel_err"] is not None]
            err = np.median(rel) if len(rel) == len(ok) else np.median([abs(r[p]["err"])
                                                                         for r in ok])
            unit = "%" if len(rel) == len(ok) else ""
            val = f"{100 * err:.1f}%" if unit else f"{err:.3g}"
            per.append(f"{p} {val}, {sum(r[p]['in90'] for r in ok)}/{len(ok)}")
        passed = sum(bool(r["check_ok"]) for r in ok)
        wrong = sum(bool(r["check_ok"]) and any((r[p]["z"] or 0) > 3 for p in ps) for r in ok)
        lost = sum(r["lost"] for r in ok), sum(r["frames"] for r in ok)
        lines.append(f"| {system} | {len(ok)} of {len(rs)} | {'; '.join(per)} | {passed}/{len(ok)} "
                     f"| {wrong} | {lost[0]} of {lost[1]} ({100 * lost[0] / lost[1]:.0f}%) |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from sysid_bench.core._io import atomic_write
    from sysid_bench.core.camera_footage import SYSTEMS, shots, write_clip

    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="runs/camera_footage")
    ap.add_argument("--system", action="append", choices=SYSTEMS, default=None)
    ap.add_argument("--table", action="store_true", help="print the table of --out's results")
    ap.add_argument("--method", default=None,
                    help="identify with this method instead of the clip's (lsq); results go to "
                         "results_<method>.json")
    args = ap.parse_args(argv)
    out = Path(args.out)
    res_name = "results.json" if args.method is None else f"results_{args.method}.json"
    if args.table:
        print(table(json.loads((out / res_name).read_text())))
        return 0
    results = []
    for system in args.system or SYSTEMS:
        for shot in shots(system, args.n, args.seed):
            name = f"{shot.system}_s{shot.seed}_{shot.fps}fps"
            jpath = out / f"{name}.json"
            t0 = time.perf_counter()
            if not jpath.is_file():
                write_clip(shot, out, name)
            film_s = time.perf_counter() - t0
            truth = json.loads(jpath.read_text())
            opts = list(truth["options"])
            if args.method is not None:
                opts[opts.index("--method") + 1] = args.method
            suffix = "" if args.method is None else f"_{args.method}"
            res = _identify(out / truth["file"], opts, out / f"{name}_identify{suffix}")
            row = _score(truth, res)
            row["film_s"] = round(film_s, 1)
            results.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "cmd"}), flush=True)
            atomic_write(out / res_name, json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
