"""The contenders, behind one ``Estimator`` interface, in a lazy registry.

Entries are ``"module:Class"`` strings resolved on first use, so importing ``methods`` pulls in
neither torch nor JAX; only the method that needs them does.

Adding a method is one file and one ``register("name", "methods.file:Class")`` line below;
everything the harness needs is declared on the class (:mod:`sysid_bench.core.spec`) and read with
:func:`spec`. Reading a declaration imports the method's module (its class holds them): the
declarations live in the one file that defines the method, with their code, instead of in a
second copy on the register line that could drift from it. Only the names (``available``) and
an unknown-name error are answered without importing; the runner, the report and the figures
import the modules they run or draw anyway.

>>> import methods
>>> methods.available()  # doctest: +NORMALIZE_WHITESPACE
['vid2param', 'vid2param-physics', 'vid2param-changing', 'nuts', 'emcee', 'lsq', 'bo',
 'sindy', 'dmd']
>>> methods.references()
['prior']
>>> est = methods.get("lsq", n_samples=500)          # doctest: +SKIP
>>> est = methods.get("nuts", system="pendulum")    # doctest: +SKIP

Every method is one class that runs on each system it declares (``systems``, a tuple of names
or ``"any"``; :mod:`sysid_bench.core.spec`), picked by its ``system`` hyperparameter: on the ball it
runs the ball's machinery (:mod:`methods._simulation`, :mod:`methods._tracks`), on another system
it composes the generic likelihood on the system's tracked points (:mod:`methods._points`; nuts
samples through the system's JAX twin) or, for sindy, the system's feature
library (:mod:`methods._sindy_libraries`), or, for vid2param, the system's network
(:mod:`methods.vid2param._points`; vid2param-physics fits the system's physics to that network's
track). lsq, bo, emcee, nuts, dmd, prior, vid2param and vid2param-physics declare ``"any"`` (a
system a user registers included; nuts answers n/a where the system has no JAX twin, the two
vid2params where no model is shipped or given: ``checkpoint=F``); sindy the ball, the pendulum
and the spring; vid2param-changing the ball. A system a method
does not declare raises :class:`NotAvailable`, and so does a method whose ``check_available()``
finds it cannot run there (:func:`get` calls it).
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
from dataclasses import dataclass

from sysid_bench.core.estimator import Estimator
from sysid_bench.core.spec import MethodSpec

__all__ = ["available", "references", "get", "get_class", "register", "unregister", "spec",
           "commands", "Registration", "MethodSpec", "NotAvailable"]


class NotAvailable(NotImplementedError, ValueError):
    """A method that does not run on the system asked for (the harness records "n/a").

    Both a ``NotImplementedError`` (the suite's "n/a" convention, which the benchmarks record)
    and a ``ValueError`` (a bad ``system`` argument for this method), so either catch holds it.
    """


@dataclass(frozen=True)
class Registration:
    """A registry entry: the name, the ``module:Class`` entry point, the packages it needs (for
    the error message when they are missing) and whether it is a reference helper (run next to
    the contenders, e.g. ``prior``, the score of guessing) rather than a contender."""

    name: str
    entry_point: str
    requires: tuple[str, ...] = ()
    reference: bool = False


_REGISTRY: dict[str, Registration] = {}


def register(name: str, entry_point: str, requires=(), reference: bool = False) -> None:
    """Add a method. ``entry_point`` is ``"package.module:ClassName"``; nothing is imported.

    The class declares the systems it runs on (``systems``).
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty str, got {name!r}")
    if not isinstance(entry_point, str) or entry_point.count(":") != 1:
        raise ValueError(f"entry_point: expected 'module:Class', got {entry_point!r}")
    if name in _REGISTRY:
        raise ValueError(f"name: {name!r} is already registered ({_REGISTRY[name].entry_point})")
    _REGISTRY[name] = Registration(name, entry_point, tuple(requires), bool(reference))


def unregister(name: str) -> None:
    """Remove a method (tests and plugins that registered one temporarily)."""
    if name not in _REGISTRY:
        raise _unknown(name)
    del _REGISTRY[name]


register("vid2param", "methods.vid2param:Vid2Param", requires=("torch",))
register("vid2param-physics", "methods.vid2param:Vid2ParamPhysics", requires=("torch",))
register("vid2param-changing", "methods.vid2param:Vid2ParamChanging", requires=("torch",))
register("nuts", "methods.nuts:NUTS", requires=("jax", "numpyro"))
register("emcee", "methods.ensemble:Emcee", requires=("emcee",))
register("lsq", "methods.lsq:LSQ")
register("bo", "methods.bo:BayesOpt", requires=("skopt",))
register("sindy", "methods.sindy:SINDy", requires=("pysindy",))
register("dmd", "methods.dmd:DMD", requires=("pydmd",))
register("prior", "methods.prior:PriorOnly", reference=True)


#: Commands the methods ship, run by ``sysid-bench NAME ...`` with the rest of the command line:
#: ``name -> ("module:function", help)``; the function takes ``argv`` and returns an exit status.
_COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("methods.vid2param.train:main",
              "train a Vid2Param checkpoint (python -m methods.vid2param.train)"),
    "evaluate": ("methods.vid2param.evaluate:main",
                 "evaluate Vid2Param checkpoints (python -m methods.vid2param.evaluate)"),
}


def commands() -> dict[str, tuple[str, str]]:
    """The command-line tools the methods ship, ``name -> ("module:function", help)`` (nothing
    is imported)."""
    return dict(_COMMANDS)


def available(include_reference: bool = False) -> list[str]:
    """Names of the registered methods (contenders; add the reference helpers on request)."""
    return [n for n, s in _REGISTRY.items() if include_reference or not s.reference]


def references() -> list[str]:
    """Names of the reference helpers (run by default next to the contenders)."""
    return [n for n, s in _REGISTRY.items() if s.reference]


def spec(name: str) -> MethodSpec:
    """The declarations of the method registered as ``name`` (imports its module)."""
    reg = _REGISTRY.get(name)
    if reg is None:
        raise _unknown(name)
    return dataclasses.replace(get_class(name).spec(), entry_point=reg.entry_point)


def _unknown(name) -> ValueError:
    known = list(_REGISTRY)
    close = difflib.get_close_matches(str(name), known, n=1)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    return ValueError(f"name: unknown method {name!r}; known methods: {', '.join(known)}.{hint}")


def _import_class(spec: Registration, entry_point: str) -> type[Estimator]:
    module_name, cls_name = entry_point.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        missing = getattr(exc, "name", None) or ""
        if missing and (module_name == missing or module_name.startswith(missing + ".")):
            # the registered module itself is not there: a wrong entry point, not a dependency
            raise ValueError(
                f"entry_point: method {spec.name!r} is registered as {entry_point!r}, but there "
                f"is no module {missing!r}"
            ) from exc
        need = ", ".join(spec.requires) or "its dependencies"
        raise ImportError(
            f"method {spec.name!r} needs {need}; install with `pip install -e .[all]` ({exc})"
        ) from exc
    cls = getattr(module, cls_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Estimator)):
        raise ValueError(f"entry_point: {entry_point!r} (method {spec.name!r}) is not an "
                         "Estimator subclass")
    if cls.name != spec.name:
        raise ValueError(f"name: {entry_point} declares name {cls.name!r}, registered as {spec.name!r}")
    return cls


def get_class(name: str, system: str = "ball") -> type[Estimator]:
    """Import and return the class registered under ``name`` that runs on ``system``.

    Raises
    ------
    ValueError
        An unknown method or system, or a method that does not run on ``system``
        (:class:`NotAvailable`, n/a: the class does not declare it).
    """
    if name not in _REGISTRY:
        raise _unknown(name)
    reg = _REGISTRY[name]
    from sysid_bench.core import systems

    sys_name = systems.get(system).name  # ValueError listing the known systems
    cls = _import_class(reg, reg.entry_point)
    declared = cls.spec().systems
    if declared == "any" or sys_name in declared:
        return cls
    reason = getattr(cls, "na_reason", None)
    if callable(reason):
        raise NotAvailable(reason(sys_name))
    only = " only" if len(declared) == 1 else ""
    raise NotAvailable(f"system: {name!r} is n/a on the {sys_name} system: it runs on the "
                       f"{', '.join(declared)} system{'s' if len(declared) > 1 else ''}{only}")


def get(name: str, system: str = "ball", **options) -> Estimator:
    """A ready-to-use estimator for ``system``; ``options`` are its keyword hyperparameters.

    ``system`` is a registered system name (:func:`sysid_bench.core.systems.available`): the method's
    one class, built with ``system=`` where it takes that hyperparameter. A system
    the method does not declare (``systems``) raises :class:`NotAvailable` (a ``ValueError``
    and a ``NotImplementedError``, so recorded as n/a); so does a declared one where the
    estimator's ``check_available()``, if it has one, finds it cannot run with these options
    (Vid2Param without a model for the system). ``known``/``prior`` (what the user knows,
    issue 38 §4) given to a method that does not take them raise ``ValueError`` naming the
    option, the method and its ``knowledge_refused`` reason.
    """
    cls = get_class(name, system)
    given = sorted(k for k in ("known", "prior") if options.get(k))
    if not {"known", "prior"} <= set(cls._param_names()):
        # nothing known (None, {}) asks nothing of the method; anything else is never silently
        # dropped (issue 38 §4): the method says why not
        options = {k: v for k, v in options.items() if k not in ("known", "prior") or v}
    if given and not {"known", "prior"} <= set(cls._param_names()):
        why = getattr(cls, "knowledge_refused", "it does not take known values or prior ranges")
        raise ValueError(f"{'/'.join(given)}: {name} cannot honour known values or prior ranges "
                         f"({why}); got " + ", ".join(f"{k}={options[k]!r}" for k in given))
    if "system" in cls._param_names():
        from sysid_bench.core import systems

        options = {**options, "system": systems.get(system).name}
    try:
        est = cls(**options)
    except TypeError as exc:
        params = cls._param_names()
        raise ValueError(
            f"options: {name!r} takes keyword hyperparameters {params}, got {sorted(options)} ({exc})"
        ) from exc
    # a method that must load something to know whether it runs here (a network per system)
    ready = getattr(est, "check_available", None)
    if callable(ready):
        ready()
    return est
