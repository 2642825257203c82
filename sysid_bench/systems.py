"""Public alias: ``sysid_bench.systems`` is ``sysid_bench.core.systems`` (the same module object, and its submodules).

The code lives in ``sysid_bench/core/systems/`` (issue #37 §4: the folder tree is the layer map).
"""

# alias written by relayout.py (issue #37 §4)
from sysid_bench._alias import alias

alias(__name__, "sysid_bench.core.systems", package=True)
