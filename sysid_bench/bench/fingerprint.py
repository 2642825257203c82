"""A method's fingerprint: the hash of what decides its numbers (code, weights, declarations).

Its own module, below the runner and the experiments that both need it (the sensitivity
experiment keys its trained models by it), so neither imports the other for it.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["method_fingerprint"]

#: harness files the baselines are built on: a change to one changes their fingerprints
_SHARED_SOURCES = ("sysid_bench/simulator.py", "methods/_tracks.py", "methods/_weights.py",
                   "methods/_simulation.py")


def method_fingerprint(name: str) -> str:
    """Hash of what decides a method's numbers: its module (or package, with its checkpoint
    files), the shared harness modules the baselines are built on, and its declarations
    (options and caps per scale, tier).

    A store's cells of a method whose fingerprint changed are computed again by the next run,
    so a retrained checkpoint or a fixed method never mixes with its old results.
    """
    import hashlib
    import importlib.util

    import methods

    spec = methods.spec(name)
    mod = spec.entry_point.split(":")[0]
    found = importlib.util.find_spec(mod)
    files: list[Path] = []
    if found is not None and found.origin:
        origin = Path(found.origin)
        if found.submodule_search_locations:  # a package: all its sources and weights
            root = origin.parent
            files = sorted(p for p in root.rglob("*")
                           if p.is_file() and p.suffix in (".py", ".pt", ".json", ".npz")
                           and "__pycache__" not in p.parts and not p.name.endswith("_test.json"))
        else:
            files = [origin]
    for shared in _SHARED_SOURCES:
        f = Path(__file__).resolve().parents[2] / shared
        if f.is_file():
            files.append(f)
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    h.update(spec.to_json().encode())
    return h.hexdigest()[:16]
