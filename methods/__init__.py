"""The contenders, behind one ``Estimator`` interface, in a lazy registry.

Entries are ``"module:Class"`` strings resolved on first use, so importing ``methods`` pulls in
neither torch nor JAX; only the method that needs them does.

>>> import methods
>>> methods.available()
['vid2param', 'nuts', 'emcee', 'lsq', 'bo', 'sindy', 'dmd']
>>> est = methods.get("lsq", n_samples=500)          # doctest: +SKIP
"""

from __future__ import annotations

import difflib
import importlib
from dataclasses import dataclass

from sysid_bench.estimator import Estimator

__all__ = ["available", "get", "get_class", "register", "MethodSpec"]


@dataclass(frozen=True)
class MethodSpec:
    """A registered method: its name, its ``module:Class`` entry point and what it needs."""

    name: str
    entry_point: str
    requires: tuple[str, ...] = ()
    reference: bool = False  # test/reference helpers, not contenders


_REGISTRY: dict[str, MethodSpec] = {}


def register(name: str, entry_point: str, requires=(), reference: bool = False) -> None:
    """Add a method. ``entry_point`` is ``"package.module:ClassName"``."""
    if ":" not in entry_point:
        raise ValueError(f"entry_point: expected 'module:Class', got {entry_point!r}")
    if name in _REGISTRY:
        raise ValueError(f"name: {name!r} is already registered ({_REGISTRY[name].entry_point})")
    _REGISTRY[name] = MethodSpec(name, entry_point, tuple(requires), reference)


register("vid2param", "methods.vid2param:Vid2Param", requires=("torch",))
register("nuts", "methods.nuts:NUTS", requires=("jax", "numpyro"))
register("emcee", "methods.ensemble:Emcee", requires=("emcee",))
register("lsq", "methods.lsq:LSQ")
register("bo", "methods.bo:BayesOpt", requires=("skopt",))
register("sindy", "methods.sindy:SINDy", requires=("pysindy",))
register("dmd", "methods.dmd:DMD", requires=("pydmd",))
register("prior", "methods.prior:PriorOnly", reference=True)


def available(include_reference: bool = False) -> list[str]:
    """Names of the registered methods (contenders; add the reference helpers on request)."""
    return [n for n, s in _REGISTRY.items() if include_reference or not s.reference]


def _unknown(name) -> ValueError:
    known = list(_REGISTRY)
    close = difflib.get_close_matches(str(name), known, n=1)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    return ValueError(f"name: unknown method {name!r}; known methods: {', '.join(known)}.{hint}")


def get_class(name: str) -> type[Estimator]:
    """Import and return the class registered under ``name``."""
    if name not in _REGISTRY:
        raise _unknown(name)
    spec = _REGISTRY[name]
    module_name, cls_name = spec.entry_point.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        need = ", ".join(spec.requires) or "its dependencies"
        raise ImportError(
            f"method {name!r} needs {need}; install with `pip install -e .[all]` ({exc})"
        ) from exc
    cls = getattr(module, cls_name)
    if not (isinstance(cls, type) and issubclass(cls, Estimator)):
        raise TypeError(f"{spec.entry_point} is not an Estimator subclass")
    return cls


def get(name: str, **options) -> Estimator:
    """A ready-to-use estimator; ``options`` are its keyword hyperparameters."""
    cls = get_class(name)
    try:
        return cls(**options)
    except TypeError as exc:
        params = cls._param_names()
        raise ValueError(
            f"options: {name!r} takes keyword hyperparameters {params}, got {sorted(options)} ({exc})"
        ) from exc
