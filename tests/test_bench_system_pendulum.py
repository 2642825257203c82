"""Pendulum simulator speed: 2000 trajectories x 200 frames against a loop of its solve_ivp
reference.

Run with ``pytest tests/test_bench_system_pendulum.py --benchmark-only``. The reference loop is
timed on ``N_REF`` trajectories and scaled per trajectory to 2000; the ratio, measured in the
same process on the same cases, is stored in the benchmark's ``extra_info`` and printed. The
design asks >= 1000x; the assertion keeps a 2x margin for a loaded machine (>= 500x).
"""

import time

import numpy as np
import pytest

from sysid_bench.systems import get

B = 2000
N_REF = 10


@pytest.fixture(scope="module")
def cases():
    system = get("pendulum")
    rng = np.random.default_rng(0)
    theta, s0 = system.sample_theta(B, rng), system.sample_state0(B, rng)
    system.simulate(theta[:2], s0[:2], 5)  # compile (or load numba's cache) outside the timing
    return system, theta, s0


@pytest.mark.benchmark(group="system-pendulum")
def test_bench_pendulum_simulate_2000x200(benchmark, cases):
    system, theta, s0 = cases
    out = benchmark.pedantic(system.simulate, args=(theta, s0), rounds=5, iterations=1,
                             warmup_rounds=1)
    assert out.shape == (B, 200, 2)
    t0 = time.perf_counter()
    for i in range(N_REF):
        system.reference(theta[i], s0[i])
    ref_s = (time.perf_counter() - t0) / N_REF * B
    sim_s = benchmark.stats.stats.median
    ratio = ref_s / sim_s
    benchmark.extra_info.update(
        {"reference_loop_s_scaled": ref_s, "simulate_median_s": sim_s, "speedup": ratio}
    )
    print(f"\npendulum simulate {sim_s * 1e3:.1f} ms, solve_ivp loop {ref_s:.0f} s "
          f"(scaled from {N_REF}), speed-up {ratio:.0f}x")
    assert ratio >= 500, f"speed-up {ratio:.0f}x, design target >= 1000x (asserted >= 500x)"
