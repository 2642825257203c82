"""A method's fingerprint: the hash of what decides its numbers (code, weights, declarations).

Its own module, below the runner and the experiments that both need it (the sensitivity
experiment keys its trained models by it), so neither imports the other for it.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["method_fingerprint", "fingerprint_files"]

#: harness files the methods are built on: a change to one changes their fingerprints (globs
#: from the repository root; every private ``methods/_*.py`` module is shared by several
#: methods, and the physics and systems decide what every method simulates)
_SHARED_SOURCES = ("sysid_bench/core/simulator.py", "sysid_bench/core/physics.py",
                   "sysid_bench/core/physics_jax.py", "sysid_bench/core/systems/*.py", "methods/_*.py")


def fingerprint_files(name: str) -> list[Path]:
    """The files whose bytes a method's fingerprint hashes (its module or package, then the
    shared harness sources)."""
    import importlib.util

    import methods

    mod = methods.spec(name).entry_point.split(":")[0]
    found = importlib.util.find_spec(mod)
    files: list[Path] = []
    if found is not None and found.origin:
        origin = Path(found.origin)
        if found.submodule_search_locations:  # a package: all its sources and weights
            pkg = origin.parent
            files = sorted(p for p in pkg.rglob("*")
                           if p.is_file() and p.suffix in (".py", ".pt", ".json", ".npz")
                           and "__pycache__" not in p.parts and not p.name.endswith("_test.json"))
        else:
            files = [origin]
    root = Path(__file__).resolve().parents[2]
    for pattern in _SHARED_SOURCES:
        files.extend(sorted(f for f in root.glob(pattern) if f.is_file() and f not in files))
    return files


def method_fingerprint(name: str) -> str:
    """Hash of what decides a method's numbers: its module (or package, with its checkpoint
    files), the shared harness modules the baselines are built on, and its declarations
    (options and caps per scale, tier).

    A store's cells of a method whose fingerprint changed are computed again by the next run,
    so a retrained checkpoint or a fixed method never mixes with its old results.
    """
    import hashlib

    import methods

    spec = methods.spec(name)
    files = fingerprint_files(name)
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    h.update(spec.to_json().encode())
    return h.hexdigest()[:16]
