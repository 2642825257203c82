"""The systems the suite identifies, in a lazy registry.

A system is one module holding a :class:`System` subclass and one ``register`` line below
(``"module:Class"``, imported on first use, as methods are). ``get(name)`` returns the system's
one shared instance.

>>> from sysid_bench import systems
>>> systems.available()
['ball', 'collision', 'pendulum', 'spring']
>>> systems.get("pendulum").params
('g', 'L', 'b', 'mu')
"""

from __future__ import annotations

import difflib
import importlib

from sysid_bench.core.systems._base import SUBRANGES_TEST, SUBRANGES_TRAIN, System
from sysid_bench.core.systems._scene import (
    BallScene,
    CollisionScene,
    PendulumScene,
    Scene,
    SpringScene,
)

__all__ = ["System", "Scene", "BallScene", "PendulumScene", "SpringScene", "CollisionScene",
           "available", "get", "register", "unregister", "SUBRANGES_TRAIN", "SUBRANGES_TEST"]

_REGISTRY: dict[str, str] = {}
_INSTANCES: dict[str, System] = {}


def register(name: str, entry_point: str) -> None:
    """Add a system: ``entry_point`` is ``"package.module:ClassName"``; nothing is imported."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty str, got {name!r}")
    if not isinstance(entry_point, str) or entry_point.count(":") != 1:
        raise ValueError(f"entry_point: expected 'module:Class', got {entry_point!r}")
    if name in _REGISTRY:
        raise ValueError(f"name: system {name!r} is already registered ({_REGISTRY[name]})")
    _REGISTRY[name] = entry_point


def unregister(name: str) -> None:
    """Remove a system (tests and plugins that registered one temporarily)."""
    if name not in _REGISTRY:
        raise _unknown(name)
    del _REGISTRY[name]
    _INSTANCES.pop(name, None)


register("ball", "sysid_bench.core.systems.ball:Ball")
register("collision", "sysid_bench.core.systems.collision:Collision")
register("pendulum", "sysid_bench.core.systems.pendulum:Pendulum")
register("spring", "sysid_bench.core.systems.spring:Spring")


def available() -> list[str]:
    """Names of the registered systems, sorted."""
    return sorted(_REGISTRY)


def _unknown(name) -> ValueError:
    known = available()
    close = difflib.get_close_matches(str(name), known, n=1)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    return ValueError(f"system: unknown system {name!r}; known systems: {', '.join(known)}.{hint}")


def get(name) -> System:
    """The registered system ``name`` (one shared instance; systems hold no state)."""
    if isinstance(name, System):
        return name
    if not isinstance(name, str) or name not in _REGISTRY:
        raise _unknown(name)
    if name not in _INSTANCES:
        entry = _REGISTRY[name]
        module_name, cls_name = entry.split(":")
        try:
            module = importlib.import_module(module_name)
        except Exception as exc:  # missing, or raising on import: say which entry and why
            raise ValueError(
                f"system: could not import {module_name!r} for the system {name!r} (entry point "
                f"{entry!r}): {type(exc).__name__}: {exc}"
            ) from exc
        cls = getattr(module, cls_name, None)
        if cls is None:
            raise ValueError(f"system: module {module_name!r} has no {cls_name!r} for the system "
                             f"{name!r} (entry point {entry!r})")
        if not (isinstance(cls, type) and issubclass(cls, System)):
            raise TypeError(f"{entry} is not a System subclass")
        if cls.name != name:
            raise ValueError(f"name: {_REGISTRY[name]} declares name {cls.name!r}, registered as {name!r}")
        _INSTANCES[name] = cls()
    return _INSTANCES[name]
