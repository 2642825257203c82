"""Parameter accuracy and interval coverage of the position methods on one system.

Held-out test-split cases (``system.sample_theta(n, rng, "test")``, initial states from the
system's own ranges), ``--frames`` frames, the K tracked points with Gaussian noise of
``--noise`` metres (default the system's ``noise_m``, 1 cm), no initial state given. Per method:
normalised MSE (each parameter's squared error over its prior range squared, averaged over the
parameters and the cases), the 90% interval coverage (fraction of parameter-case pairs whose
central 90% interval holds the truth), per-parameter figures, seconds per identification (wall
and this process's CPU time: on a shared machine the CPU time is the figure that holds), and
for NUTS its worst R-hat, smallest ESS and the cases it converged on (R-hat < 1.05 and
ESS >= 50 on every parameter: ``converged_rhat_ess``).

    OMP_NUM_THREADS=1 python scripts/measure_systems.py --system pendulum --n 20 --methods lsq nuts

prints a table and writes ``<out>/systems_<system>_cases.csv`` (one row per case and method) and
``<out>/systems_<system>_summary.csv`` (one row per method), atomically. ``--options`` takes a
JSON object of per-method options, e.g. ``'{"nuts": {"num_warmup": 100}}'``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

_TARGET_NMSE, _TARGET_COVERAGE = 0.01, 0.75


def _cases(system, n: int, frames: int, noise: float, seed: int):
    """theta (n, P), noisy points (n, T, K, 2) of the test split."""
    rng = np.random.default_rng([seed, 28])
    theta = system.sample_theta(n, rng, "test")
    try:
        state0 = system.sample_state0(n, rng, theta=theta)
    except TypeError:  # systems whose initial state does not depend on theta
        state0 = system.sample_state0(n, rng)
    points = system.observe(system.simulate(theta, state0, n_frames=frames), theta)
    return theta, points + rng.normal(0.0, noise, points.shape)


def _write_csv(path: Path, rows: list[dict]) -> None:
    from sysid_bench.core._io import atomic_write

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write(path, buf.getvalue())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", required=True)
    ap.add_argument("--n", type=int, default=20, help="test cases")
    ap.add_argument("--methods", nargs="+", default=["lsq", "nuts"])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--noise", type=float, default=None, help="metres (default: noise_m)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--options", default="{}", help="JSON: {method: {option: value}}")
    ap.add_argument("--out", default="runs")
    args = ap.parse_args(argv)

    import methods
    from sysid_bench.core import systems
    from sysid_bench.core.estimator import Observation

    system = systems.get(args.system)
    if args.n < 1 or args.frames < 3:
        ap.error(f"--n and --frames: expected >= 1 and >= 3, got {args.n} and {args.frames}")
    opts = json.loads(args.options)
    if not isinstance(opts, dict):
        ap.error(f"--options: expected a JSON object, got {args.options!r}")
    noise = system.noise_m if args.noise is None else float(args.noise)
    theta, noisy = _cases(system, args.n, args.frames, noise, args.seed)
    span = system.prior_hi - system.prior_lo
    rows, summary = [], []
    for m in args.methods:
        est = methods.get(m, system=system.name, **opts.get(m, {}))
        se, cov, walls, cpus, rhat, ess, conv = [], [], [], [], [], [], []
        for i in range(args.n):
            obs = Observation(positions=noisy[i], dt=0.05, system=system.name)
            t0, c0 = time.perf_counter(), time.process_time()
            post = est.identify(obs)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            lo, hi = post.interval(0.9)
            e = ((post.mean - theta[i]) / span) ** 2
            inside = (theta[i] >= lo) & (theta[i] <= hi)
            se.append(e)
            cov.append(inside)
            walls.append(wall)
            cpus.append(cpu)
            row = {"system": system.name, "method": m, "case": i, "nmse": float(e.mean()),
                   "coverage90": float(inside.mean()), "wall_s": wall, "cpu_s": cpu,
                   "check_ok": None if post.check is None else bool(post.check.ok)}
            for j, p in enumerate(system.params):
                row.update({f"{p}_true": theta[i, j], f"{p}_mean": post.mean[j],
                            f"{p}_std": post.std[j], f"{p}_in90": bool(inside[j])})
            if isinstance(post.extras.get("rhat"), dict):
                rhat.append(max(post.extras["rhat"].values()))
                ess.append(min(post.extras["ess"].values()))
                conv.append(bool(rhat[-1] < 1.05 and ess[-1] >= 50))
                row.update(rhat_max=rhat[-1], ess_min=ess[-1], converged_rhat_ess=conv[-1],
                           converged=post.extras.get("converged"))
            rows.append(row)
            print(f"{m:6s} case {i:2d} nmse {e.mean():.2e} cov90 {inside.mean():.2f} "
                  f"{wall:6.1f} s (cpu {cpu:5.1f} s)" + (f" rhat {rhat[-1]:.3f} ess {ess[-1]:.0f}" if rhat else ""),
                  flush=True)
        se, cov = np.array(se), np.array(cov)
        s = {"system": system.name, "method": m, "n": args.n, "frames": args.frames,
             "noise_m": noise, "nmse": float(se.mean()), "coverage90": float(cov.mean()),
             "median_wall_s": float(np.median(walls)), "median_cpu_s": float(np.median(cpus)),
             "mean_cpu_s": float(np.mean(cpus))}
        for j, p in enumerate(system.params):
            s[f"nmse_{p}"] = float(se[:, j].mean())
            s[f"cov90_{p}"] = float(cov[:, j].mean())
        if rhat:
            s.update(rhat_max=float(np.max(rhat)), ess_min=float(np.min(ess)),
                     converged_rhat_ess=int(np.sum(conv)))
        s["meets_targets"] = bool(s["nmse"] <= _TARGET_NMSE and s["coverage90"] >= _TARGET_COVERAGE)
        summary.append(s)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(out / f"systems_{system.name}_cases.csv", rows)
    _write_csv(out / f"systems_{system.name}_summary.csv", summary)
    print(f"\n{system.name}: {args.n} test cases, {args.frames} frames, noise {noise:g} m")
    head = f"{'method':8s} {'nMSE':>9s} {'cov90':>6s} {'s/id':>7s} {'cpu/id':>7s}  " + "  ".join(
        f"{p:>15s}" for p in system.params)
    print(head + "   (per parameter: nMSE / cov90)")
    for s in summary:
        per = "  ".join(f"{s[f'nmse_{p}']:.1e}/{s[f'cov90_{p}']:.2f}".rjust(15)
                        for p in system.params)
        extra = (f"  R-hat max {s['rhat_max']:.3f}, ESS min {s['ess_min']:.0f}, converged "
                 f"{s['converged_rhat_ess']}/{args.n}" if "rhat_max" in s else "")
        print(f"{s['method']:8s} {s['nmse']:9.2e} {s['coverage90']:6.2f} "
              f"{s['median_wall_s']:7.2f} {s['median_cpu_s']:7.2f}  {per}{extra}")
    print(f"targets: nMSE <= {_TARGET_NMSE}, 90% coverage >= {_TARGET_COVERAGE:.0%}; "
          f"written {out}/systems_{system.name}_summary.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
