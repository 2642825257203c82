"""Each new system's simulator speed: 2000 trajectories x 200 frames against its solve_ivp loop.

Run with ``pytest tests/test_bench_systems.py --benchmark-only``. The loop of the system's
``solve_ivp`` reference is timed on ``N_REF`` trajectories and scaled per trajectory to 2000; the
ratio, measured in the same process on the same cases, is stored in the benchmark's
``extra_info`` and printed. The design asks >= 1000x; the assertion keeps a 2x margin for a
loaded machine (>= 500x).
"""

import time

import numpy as np
import pytest

from sysid_bench import systems

B = 2000
N_REF = 10
SYSTEMS = ("pendulum", "spring", "collision")


@pytest.mark.parametrize("name", SYSTEMS)
def test_bench_system_simulate_2000x200(benchmark, name):
    benchmark.group = f"system-{name}"
    system = systems.get(name)
    theta, state0 = system.sample_cases(B, np.random.default_rng(0))
    system.simulate(theta[:2], state0[:2], 5)  # numba compile (or cache load) outside the timing
    out = benchmark.pedantic(system.simulate, args=(theta, state0), rounds=7, iterations=1,
                             warmup_rounds=1)
    assert out.shape == (B, 200, system.n_state)
    t0 = time.perf_counter()
    for i in range(N_REF):
        system.reference(theta[i], state0[i])
    ref_s = (time.perf_counter() - t0) / N_REF * B
    sim_s = benchmark.stats.stats.median
    ratio = ref_s / sim_s
    benchmark.extra_info.update(
        {"reference_loop_s_scaled": ref_s, "reference_trajectories_timed": N_REF,
         "simulate_median_s": sim_s, "speedup": ratio}
    )
    print(f"\n{name} simulate {sim_s * 1e3:.1f} ms, solve_ivp loop {ref_s:.1f} s "
          f"(scaled from {N_REF}), speed-up {ratio:.0f}x")
    assert ratio >= 500, f"speed-up {ratio:.0f}x, design target >= 1000x (asserted with 2x margin)"
