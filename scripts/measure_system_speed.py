"""Each system's simulator against its solve_ivp reference: speed ratio and position error.

    python scripts/measure_system_speed.py                       # speed, 3 back-to-back rounds
    python scripts/measure_system_speed.py --rounds 5 --n-ref 20 pendulum spring
    python scripts/measure_system_speed.py --accuracy --substeps 6 7 8   # pendulum error vs steps

Speed (issue #37 section 6, design.md "Systems"): ``simulate`` on 2000 prior cases x 200 frames
(seed 0), best of ``--best`` calls after a warm-up, and the loop of the system's event-driven
``solve_ivp`` reference (DOP853, rtol = atol = 1e-12) on the first ``--n-ref`` of those cases,
scaled per trajectory to 2000; the two are timed back to back in one process, ``--rounds``
times, so a ratio is measured under one load (printed with the load average). The design asks
>= 1000x. The ball's ``reference`` is its own kernel, so its ratio is measured by
``tests/test_bench_physics.py`` (against ``tests/physics_reference.py``) instead.

Accuracy (``--accuracy``): the largest error of the tracked points (metres, over 200 frames at
dt = 0.05) against the reference on the prior's fastest corner (every sign of the initial state),
corners with Coulomb friction (events, sticks) and ``--n-acc`` random prior cases. For the
pendulum ``--substeps`` runs its kernel with other step counts per frame (the spring's is a
compile-time constant and is measured as it is). The design asks <= 1e-6 m.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from sysid_bench.core import systems

B = 2000


def _load() -> str:
    return "load average " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def speed(name: str, rounds: int, best: int, n_ref: int) -> list[float]:
    """Print and return the speed ratio of ``rounds`` back-to-back measurements."""
    system = systems.get(name)
    theta, state0 = system.sample_cases(B, np.random.default_rng(0))
    system.simulate(theta, state0)  # compile (or load the cache) and warm up
    ratios = []
    for r in range(rounds):
        times = []
        for _ in range(best):
            t0 = time.perf_counter()
            system.simulate(theta, state0)
            times.append(time.perf_counter() - t0)
        sim_s = min(times)
        t0 = time.perf_counter()
        for i in range(n_ref):
            system.reference(theta[i], state0[i])
        ref_s = (time.perf_counter() - t0) / n_ref * B
        ratios.append(ref_s / sim_s)
        print(f"{name:9s} round {r}: simulate {sim_s * 1e3:6.1f} ms (best of {best}, median "
              f"{np.median(times) * 1e3:6.1f}), solve_ivp loop {ref_s:6.1f} s (from {n_ref}), "
              f"{ratios[-1]:5.0f}x  [{_load()}]", flush=True)
    return ratios


def _cases(name: str, n_acc: int):
    """(theta, state0) rows: the fastest corner, friction corners and random prior cases."""
    system = systems.get(name)
    rows = []
    if name == "pendulum":
        for mu in (0.0, 0.2, 0.5):
            for th0 in (2.5, -2.5):
                for om0 in (1.0, -1.0):
                    rows.append(([-12.81, 0.5, 0.0, mu], [th0, om0]))
        rows.append(([-6.81, 2.0, 0.1, 0.5], [0.9, -0.2]))  # sticks
        rows.append(([-9.81, 1.0, 0.05, 0.15], [1.5, 0.5]))  # many turnarounds
        rows.append(([-6.81, 2.0, 0.05, 0.05], [0.0, 5.0]))  # over the top
    elif name == "spring":
        for sign in (1.0, -1.0):
            for v0 in (0.5, -0.5):
                rows.append(([25.0, 20.0, 0.0, 1.5], [1.5 + sign * 0.6, v0]))
    theta = np.array([r[0] for r in rows]).reshape(-1, len(system.params))
    state0 = np.array([r[1] for r in rows]).reshape(-1, system.n_state)
    rt, rs = system.sample_cases(n_acc, np.random.default_rng(7))
    return np.concatenate([theta, rt]), np.concatenate([state0, rs]), len(rows)


def accuracy(name: str, n_acc: int, substeps: list[int]) -> None:
    """Print the largest point error against the reference, corners and random cases apart."""
    system = systems.get(name)
    theta, state0, n_corner = _cases(name, n_acc)
    ref = np.stack([system.reference(theta[i], state0[i]) for i in range(len(theta))])
    pts_ref = system.observe(ref, theta)
    runs = {"as shipped": system.simulate(theta, state0)}
    if name == "pendulum":
        from sysid_bench.core.systems import pendulum as P

        for n in substeps:
            out = np.empty((len(theta), 200, 2))
            P._kernel(np.ascontiguousarray(theta[:, None, :]), state0, 0.05, n, out)
            runs[f"{n} steps/frame"] = out
    for label, out in runs.items():
        err = np.abs(system.observe(out, theta) - pts_ref).max(axis=(1, 2, 3))
        corners = f"{err[:n_corner].max():.2e} m" if n_corner else "(none listed)"
        print(f"{name:9s} {label:14s}: max point error corners {corners}, "
              f"{n_acc} random prior cases {err[n_corner:].max():.2e} m "
              f"(worst case {int(np.argmax(err))})", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("systems", nargs="*", default=["pendulum", "spring", "collision"])
    ap.add_argument("--rounds", type=int, default=3, help="back-to-back speed measurements")
    ap.add_argument("--best", type=int, default=5, help="simulate calls per round (best taken)")
    ap.add_argument("--n-ref", type=int, default=10, help="reference trajectories timed")
    ap.add_argument("--accuracy", action="store_true", help="measure errors instead of speed")
    ap.add_argument("--n-acc", type=int, default=100, help="random prior cases for --accuracy")
    ap.add_argument("--substeps", type=int, nargs="*", default=[],
                    help="pendulum: also these RK4 steps per frame")
    a = ap.parse_args()
    if "ball" in a.systems and not a.accuracy:
        ap.error("systems: the ball's reference is its own kernel; time it with "
                 "tests/test_bench_physics.py")
    for name in a.systems:
        if a.accuracy:
            accuracy(name, a.n_acc, a.substeps)
        else:
            speed(name, a.rounds, a.best, a.n_ref)


if __name__ == "__main__":
    main()
