"""The old, public import paths of the modules that moved into ``core/`` and ``apps/``.

Issue #37 §4 made the folder tree the layer map (core < methods < bench < apps). Each old
path (``sysid_bench/physics.py``, ...) is a thin module calling :func:`alias`, which puts the
moved module itself in its place in ``sys.modules``: one module object under two names, so
module state and monkeypatching stay single. For a package (``systems``, ``intercept``) a
finder also maps its submodules, so ``sysid_bench.systems.ball`` is
``sysid_bench.core.systems.ball`` rather than a second copy of ball.py (two ``Ball`` classes).
``python -m sysid_bench.report`` runs the moved module as ``__main__``.
"""

# alias written by relayout.py (issue #37 §4)
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import runpy
import sys

__all__ = ["alias"]


class _Submodule(importlib.abc.Loader):
    """Loads ``old.x`` as the already importable ``new.x`` (the same object)."""

    def __init__(self, target: str) -> None:
        self.target = target
        self._spec = None

    def create_module(self, spec):
        module = importlib.import_module(self.target)
        self._spec = module.__spec__
        return module

    def exec_module(self, module) -> None:
        # the import system set ``__spec__`` to the alias's spec: the module keeps its own
        module.__spec__ = self._spec


class _Finder(importlib.abc.MetaPathFinder):
    """Maps the submodules of aliased packages (old prefix -> new prefix)."""

    def __init__(self) -> None:
        self.prefixes: dict[str, str] = {}

    def find_spec(self, fullname, path=None, target=None):
        for old, new in self.prefixes.items():
            if fullname.startswith(old + "."):
                moved = new + fullname[len(old):]
                found = importlib.util.find_spec(moved)
                if found is None:
                    return None
                return importlib.util.spec_from_loader(
                    fullname, _Submodule(moved),
                    is_package=found.submodule_search_locations is not None)
        return None


_FINDER = _Finder()


def alias(name: str, target: str, *, package: bool = False) -> None:
    """Make the module ``name`` be ``target`` (run it as ``__main__`` under ``python -m``).

    Parameters
    ----------
    name : str
        The old dotted name (the calling module's ``__name__``).
    target : str
        The dotted name of the moved module.
    package : bool
        Whether ``target`` is a package, whose submodules are then aliased too.
    """
    if name == "__main__":
        runpy.run_module(target, run_name="__main__", alter_sys=True)
        return
    if package:
        _FINDER.prefixes[name] = target
        if _FINDER not in sys.meta_path:
            sys.meta_path.insert(0, _FINDER)
    sys.modules[name] = importlib.import_module(target)
