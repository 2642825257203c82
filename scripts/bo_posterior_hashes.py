"""Hashes of bo posteriors (mean, std, samples, check, extras less wall-clock) on a few cases.

Run before and after a change to bo's GP code; equal lines mean equal bytes::

    PYTHONPATH=$PWD nice -n 10 python scripts/bo_posterior_hashes.py > before.txt

Cases: three 100-frame ball test videos (positions) at the default options and one at
``contract_options``; three noisy 100-frame cases of each other system at the defaults.
"""

from __future__ import annotations

import hashlib
import pickle
import sys
import time

import numpy as np

import methods
import methods.bo  # noqa: F401  (imported up front: the code measured is the code at start)
from sysid_bench.core import systems
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation


def _digest(post) -> str:
    extras = {k: v for k, v in post.extras.items() if "wall" not in k}
    blob = pickle.dumps((post.mean, post.std, post.samples, post.check, sorted(extras.items())),
                        protocol=5)
    return hashlib.sha256(blob).hexdigest()[:16]


def _system_case(system, seed, n_frames=100, noise=0.01):
    rng = np.random.default_rng([seed, 28])
    theta = system.sample_theta(1, rng, "test")
    try:
        state0 = system.sample_state0(1, rng, theta=theta)
    except TypeError:
        state0 = system.sample_state0(1, rng)
    pts = system.observe(system.simulate(theta, state0, n_frames=n_frames), theta)[0]
    return pts + rng.normal(0.0, noise, pts.shape)


def cases(which=("ball", "pendulum", "spring", "collision")):
    """(label, estimator, observation) of each case."""
    if "ball" in which:
        ds = make_dataset("test", 3, seed=5, n_frames=100)
        for i in range(3):
            yield f"ball{i}", methods.get("bo"), ds.observation(i, positions=True)
        yield ("ball0-contract", methods.get("bo", **methods.bo.BayesOpt.contract_options),
               ds.observation(0, positions=True))
    for name in which:
        if name == "ball":
            continue
        system = systems.get(name)
        for seed in range(3):
            obs = Observation(positions=_system_case(system, seed), system=name)
            yield f"{name}{seed}", methods.get("bo", system=name), obs


if __name__ == "__main__":
    which = tuple(sys.argv[1:]) or ("ball", "pendulum", "spring", "collision")
    for label, est, obs in cases(which):
        t0 = time.process_time()
        post = est.identify(obs)
        print(f"{label:16s} {_digest(post)}  cpu {time.process_time() - t0:6.2f} s", flush=True)
