"""Calibration of the sampling baselines: do their 90% intervals hold the truth 80-100% of the time?

50 test-split cases (sub-ranges 1, 3, 5, 7, 9), 200 frames. The positions get independent
Gaussian noise of the likelihood's own ``sigma`` (:data:`sysid_bench.core.simulator.DEFAULT_SIGMA`), so the
model is well specified and a correct sampler covers ~90%; the initial state and floor are given,
as to the paper's baselines. Noisy positions a wall or the floor would put outside the box are
moved onto its edge (the suite rejects positions outside the box; this touches a few frames).

Run with ``pytest tests/test_bench_calibration.py --benchmark-only`` (emcee: about 7 minutes on
2 cores). ``METHODS`` lists the samplers checked; nuts joins when its module lands.
"""

import numpy as np
import pytest
from tqdm import tqdm

import methods
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation
from sysid_bench.core.metrics import interval_coverage
from sysid_bench.core.physics import BOX_WIDTH
from sysid_bench.core.simulator import DEFAULT_SIGMA

METHODS = ["emcee", "nuts"]  # nuts: about 6 minutes on 2 cores (50 x ~6 s + compile)
N_CASES = 50
SEED = 17
LEVEL = 0.9


def calibration_cases(n: int = N_CASES, seed: int = SEED):
    """The test-split cases with noisy positions: (true theta (n, 4), list of Observation)."""
    ds = make_dataset("test", n=n, seed=seed)
    rng = np.random.default_rng(seed)
    pos = ds.states[:, :, :2] + rng.normal(0.0, DEFAULT_SIGMA, size=ds.states[:, :, :2].shape)
    pos[..., 0] = np.clip(pos[..., 0], 0.0, BOX_WIDTH)
    fl = ds.floor[:, None]
    pos[..., 1] = np.clip(pos[..., 1], fl, fl + BOX_WIDTH)
    obs = [
        Observation(positions=pos[i], floor=float(ds.floor[i]), state0=ds.states[i, 0])
        for i in range(n)
    ]
    return ds.theta[:, 0], obs


def run_calibration(est, theta, observations, progress: bool = True) -> dict:
    """Identify every case; coverage of the ``LEVEL`` intervals per parameter, and diagnostics."""
    lo, hi, conv = [], [], []
    for o in tqdm(observations, desc=f"calibration {est.name}", disable=not progress):
        post = est.identify(o)
        a, b = post.interval(LEVEL)
        lo.append(a)
        hi.append(b)
        conv.append(bool(post.extras.get("converged", True)))
    cover = interval_coverage(theta, np.array(lo), np.array(hi))
    return {"coverage": cover, "converged": float(np.mean(conv))}


@pytest.fixture(scope="module")
def cases():
    return calibration_cases()


@pytest.mark.benchmark(group="calibration")
@pytest.mark.parametrize("name", METHODS)
def test_bench_calibration_90(benchmark, cases, name):
    theta, observations = cases
    est = methods.get(name)
    out = benchmark.pedantic(run_calibration, args=(est, theta, observations), rounds=1, iterations=1)
    cover = out["coverage"]
    benchmark.extra_info.update(
        {"coverage_e_g_d_r": cover.tolist(), "converged_fraction": out["converged"], "n_cases": len(observations)}
    )
    print(f"\n{name}: 90% coverage e={cover[0]:.2f} g={cover[1]:.2f} d={cover[2]:.2f} r={cover[3]:.2f}; "
          f"converged {out['converged']:.0%}")
    assert ((cover[:3] >= 0.8) & (cover[:3] <= 1.0)).all(), f"{name}: coverage {cover[:3]}"
