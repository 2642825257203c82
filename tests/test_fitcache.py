"""Fits shared between cells (sysid_bench.bench.fitcache): keyed correctly, same numbers."""

from __future__ import annotations

import numpy as np
import pytest

import methods
from sysid_bench.bench import fitcache
from sysid_bench.core.estimator import Observation

OPTS = {"n_samples": 200, "search_rounds": 1, "n_starts": 1, "max_opt_evals": 20}


def _obs(seed=0, n=40):
    rng = np.random.default_rng(seed)
    from sysid_bench.core import physics

    theta = physics.sample_theta(1, rng)
    s0 = np.array([[2.0, 5.0, 1.5, 0.0]])
    pos = physics.simulate(theta, s0, n_frames=n, dt=0.05)[0, :, :2]
    return Observation(positions=pos + rng.normal(0, 0.01, pos.shape), dt=0.05, floor=0.0)


def _est(tmp_path, **opts):
    est = methods.get("lsq", **{**OPTS, **opts})
    assert fitcache.share_fits(est, "lsq", {**OPTS, **opts}, tmp_path)
    return est


def test_reused_fit_gives_the_same_numbers(tmp_path):
    obs = _obs()
    fresh = methods.get("lsq", **OPTS).identify(obs)
    h0 = fitcache.stats()["hits"]
    a = _est(tmp_path).identify(obs)  # computes and stores
    b = _est(tmp_path).identify(obs)  # reads
    assert fitcache.stats()["hits"] == h0 + 1
    assert len(list((tmp_path / fitcache.FOLDER).glob("*.pkl"))) == 1
    for p in (a, b):
        np.testing.assert_array_equal(p.mean, fresh.mean)
        np.testing.assert_array_equal(p.std, fresh.std)
        np.testing.assert_array_equal(p.samples, fresh.samples)
    # a forecast starts from the same fit: reused, it equals a fresh one
    f1 = methods.get("lsq", **OPTS).forecast(obs, 10)
    f2 = _est(tmp_path).forecast(obs, 10)
    np.testing.assert_array_equal(f1.samples, f2.samples)


def test_key_changes_with_options_observation_and_prefix(tmp_path):
    obs = _obs()
    _est(tmp_path).identify(obs)
    h0 = fitcache.stats()["hits"]
    _est(tmp_path, seed=1).identify(obs)  # another option: computed, not reused
    _est(tmp_path).identify(_obs(seed=1))  # another observation
    _est(tmp_path).identify(obs.prefix(30))  # another prefix
    assert fitcache.stats()["hits"] == h0
    assert len(list((tmp_path / fitcache.FOLDER).glob("*.pkl"))) == 4


def test_digest_sees_every_field():
    obs = _obs()
    d = fitcache.observation_digest(obs)
    assert d == fitcache.observation_digest(_obs())
    moved = Observation(positions=obs.positions, dt=obs.dt, floor=0.01)
    assert fitcache.observation_digest(moved) != d
    pos = np.array(obs.positions)
    pos[5, 0] += 1e-12
    assert fitcache.observation_digest(Observation(positions=pos, dt=0.05, floor=0.0)) != d


def test_unreadable_file_is_computed_again(tmp_path):
    obs = _obs()
    _est(tmp_path).identify(obs)
    (f,) = (tmp_path / fitcache.FOLDER).glob("*.pkl")
    f.write_bytes(b"not a pickle")
    h0 = fitcache.stats()["hits"]
    p = _est(tmp_path).identify(obs)
    assert fitcache.stats()["hits"] == h0
    np.testing.assert_array_equal(p.mean, methods.get("lsq", **OPTS).identify(obs).mean)


def test_clock_credits_a_reused_fit(tmp_path):
    obs = _obs()
    _est(tmp_path).identify(obs)
    t0 = fitcache.clock()
    _est(tmp_path).identify(obs)
    (f,) = (tmp_path / fitcache.FOLDER).glob("*.pkl")
    import pickle

    assert fitcache.clock() - t0 >= pickle.loads(f.read_bytes())["seconds"]


def test_method_without_declaration_is_not_shared(tmp_path):
    est = methods.get("prior")
    assert not fitcache.share_fits(est, "prior", {}, tmp_path)


@pytest.mark.parametrize("name", ["lsq", pytest.param("bo", marks=pytest.mark.slow), "emcee",
                                  pytest.param("nuts", marks=pytest.mark.slow)])
def test_declared_pure_fit_is_pure(name):
    """The declaration's contract: a used estimator fits a prefix as a fresh one does."""
    opts = {"lsq": OPTS, "bo": {"n_calls": 6, "n_initial_points": 3, "n_surrogate": 64},
            "emcee": methods.spec("emcee").contract_options,
            "nuts": methods.spec("nuts").contract_options}[name]
    assert getattr(methods.get_class(name), "pure_fit", False)
    obs = _obs(n=30)
    used = methods.get(name, **opts)
    used.identify(_obs(seed=3, n=30))
    a = used.identify(obs)
    b = methods.get(name, **opts).identify(obs)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.samples, b.samples)


def test_only_the_asked_lengths_are_stored(tmp_path):
    est = methods.get("lsq", **OPTS)
    fitcache.share_fits(est, "lsq", OPTS, tmp_path, lengths=[30])
    obs = _obs()
    est.identify(obs)  # 40 frames: not stored
    assert not (tmp_path / fitcache.FOLDER).exists()
    est.identify(obs.prefix(30))
    assert len(list((tmp_path / fitcache.FOLDER).glob("*.pkl"))) == 1


_NUTS_DIGEST = """
import hashlib, sys
import numpy as np
import methods
from sysid_bench.bench.cases import bench_case
obs = bench_case(sys.argv[1], 0, 2, 7, "privileged")[0].prefix(40)
p = methods.get("nuts", system=sys.argv[1], **methods.spec("nuts").contract_options).identify(obs)
print(hashlib.sha256(np.ascontiguousarray(p.samples).tobytes()).hexdigest())
"""


@pytest.mark.slow
@pytest.mark.parametrize("system", ["ball", "pendulum"])
def test_nuts_fit_is_the_same_in_another_process(tmp_path, system):
    """NUTS declares ``pure_fit``: its fit in a fresh process (the workers', with JAX's
    persistent compilation cache) has the bytes of this process's, and it is stored and read
    back (section 0 reads calibration's reference posteriors)."""
    import hashlib
    import os
    import subprocess
    import sys

    from sysid_bench.bench.cases import bench_case

    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "jax_cache")}
    theirs = subprocess.run([sys.executable, "-c", _NUTS_DIGEST, system], env=env, check=True,
                            capture_output=True, text=True, timeout=900).stdout.split()[-1]
    obs = bench_case(system, 0, 2, 7, "privileged")[0].prefix(40)
    opts = {**methods.spec("nuts").contract_options, "system": system}
    est = methods.get("nuts", **opts)
    assert fitcache.share_fits(est, "nuts", opts, tmp_path)
    mine = est.identify(obs)
    assert hashlib.sha256(np.ascontiguousarray(mine.samples).tobytes()).hexdigest() == theirs
    h0 = fitcache.stats()["hits"]
    est = methods.get("nuts", **opts)
    fitcache.share_fits(est, "nuts", opts, tmp_path)
    again = est.identify(obs)
    assert fitcache.stats()["hits"] == h0 + 1
    np.testing.assert_array_equal(again.samples, mine.samples)
