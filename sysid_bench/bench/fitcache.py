"""Fits computed once per run and reused by the experiments that ask for the same one.

Identification (experiment 1), forecasting (2) and calibration on our physics (5) draw the
same test cases (:func:`~sysid_bench.bench.cases.bench_case`, the same ``n``), and a
simulation-based method's ``identify`` and ``forecast`` both start from one ``_fit`` of the
prefix (``_fit_points`` on a system other than the ball): identification after 20, 50, 100 and
200 frames computed every fit forecasting (20, 50, 100) and calibration (200) computed again.
A method whose class declares ``pure_fit = True`` (its fit is a pure function of its
hyperparameters and the observation: every random stream seeded from ``seed`` per call, no
state kept between calls; ``tests/test_fitcache.py`` checks it) gets its fits stored under the
run directory, keyed by

* the method's fingerprint (its code, weights and declarations: a changed method never reads an
  old fit) and the bytes of every source under ``sysid_bench/core`` and ``methods`` (tracking,
  rendering and the rest a fit runs through but a method's fingerprint does not hash),
* its hyperparameters as the cell built them (scale options, system, threads),
* which fit (``_fit`` or ``_fit_points``) and the observation's bytes (frames or positions,
  dt, floor, state0, scene, known values),

and a later cell of any experiment, in any worker, reads the fit instead of computing it: the
same computation, so the same bytes as computing it again. Written atomically (a partial file
is never read); two workers computing the same fit at once both write the same bytes.

Seconds: a reused fit took no time here, but the tables report what an identification costs.
:func:`clock` is ``perf_counter`` plus the seconds the reused fits took when they were
computed, so a cell timing ``clock() - t0`` around ``identify`` reports the fit's own cost.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import time
from functools import lru_cache
from pathlib import Path

import numpy as np

__all__ = ["FOLDER", "clock", "observation_digest", "share_fits", "stats"]

#: the run directory's folder of stored fits
FOLDER = "fits"
#: bump when the stored format changes
_FORMAT = 1
#: the fitting functions a method may have (the ball's machinery, another system's points)
_FIT_FUNCTIONS = ("_fit", "_fit_points")

_CREDIT = [0.0]  # seconds of reused fits, this process
_STATS = {"hits": 0, "misses": 0}


def clock() -> float:
    """``time.perf_counter()`` plus the seconds every reused fit of this process took to
    compute (see the module): intervals of it time a cell's identifications as if computed."""
    return time.perf_counter() + _CREDIT[0]


def stats() -> dict:
    """Hits and misses of this process (tests and measurements)."""
    return dict(_STATS)


def _digest_array(h, a) -> None:
    a = np.ascontiguousarray(a)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())


def observation_digest(obs) -> str:
    """SHA-256 of everything an :class:`~sysid_bench.core.estimator.Observation` holds
    (frames, positions, dt, floor, state0, system, scene, known), hex."""
    h = hashlib.sha256()
    for name in ("frames", "positions", "state0"):
        v = getattr(obs, name, None)
        h.update(name.encode())
        if v is None:
            h.update(b"None")
        else:
            _digest_array(h, v)
    for name in ("dt", "floor", "system", "scene", "known"):
        h.update(name.encode())
        h.update(repr(getattr(obs, name, None)).encode())
    return h.hexdigest()


@lru_cache(maxsize=64)
def _fingerprint(method: str) -> str:
    from sysid_bench.bench.fingerprint import method_fingerprint

    return method_fingerprint(method)


@lru_cache(maxsize=1)
def _sources() -> str:
    """SHA-256 of the layer-1 and layer-2 sources (``sysid_bench/core``, ``methods``)."""
    root = Path(__file__).resolve().parents[2]
    h = hashlib.sha256()
    for sub in ("sysid_bench/core", "methods"):
        for f in sorted((root / sub).rglob("*.py")):
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def _key(method: str, options: dict, fn: str, obs) -> str:
    ident = json.dumps([_FORMAT, method, _fingerprint(method), _sources(), options, fn,
                        observation_digest(obs)], sort_keys=True, default=repr)
    return hashlib.sha256(ident.encode()).hexdigest()


def _read(path: Path):
    try:
        with open(path, "rb") as f:
            return pickle.load(f)
    except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError):
        return None  # absent, or unreadable: compute it


def _write(path: Path, record) -> None:
    """Atomically (:func:`sysid_bench.core._io.atomic_write`: a temporary file, then rename)."""
    from sysid_bench.core._io import atomic_write

    atomic_write(path, pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL))


class _suppress:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return exc[0] is not None and issubclass(exc[0], OSError)


def share_fits(est, method: str, options: dict, run_dir, lengths=None) -> bool:
    """Make ``est`` (a fresh estimator of ``method`` built with ``options``) read and store its
    fits under ``run_dir/fits`` when its class declares ``pure_fit``; returns whether it does.
    ``lengths``: only observations of these frame counts (the ones another experiment asks
    for; None: every one), so the folder holds no fit nobody reads.

    The instance's fitting functions are wrapped (its class is untouched): a call whose key
    (see the module) is stored returns the stored fit, a copy, and credits its seconds to
    :func:`clock`; else it fits and stores the result. A fit that raises is not stored.
    """
    if not getattr(type(est), "pure_fit", False):
        return False
    folder = Path(run_dir) / FOLDER
    for fn in _FIT_FUNCTIONS:
        inner = getattr(est, fn, None)
        if callable(inner):
            setattr(est, fn, _wrapped(inner, method, options, fn, folder, lengths))
    return True


def _wrapped(inner, method, options, fn, folder, lengths):
    lengths = None if lengths is None else frozenset(int(n) for n in lengths)

    def fit(obs, *args):
        if lengths is not None and obs.n_frames not in lengths:
            return inner(obs, *args)
        path = folder / f"{_key(method, options, fn, obs)}.pkl"
        rec = _read(path)
        if rec is not None:
            _STATS["hits"] += 1
            _CREDIT[0] += rec["seconds"]
            return rec["fit"]
        _STATS["misses"] += 1
        t0 = time.perf_counter()
        out = inner(obs, *args)
        seconds = time.perf_counter() - t0
        try:
            _write(path, {"fit": out, "seconds": seconds})
        except (OSError, pickle.PicklingError, TypeError, AttributeError):
            pass  # a fit that cannot be stored is computed again where asked: slower, not wrong
        return out

    fit.__wrapped__ = inner
    return fit
