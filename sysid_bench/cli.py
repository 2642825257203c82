"""Public alias: ``sysid_bench.cli`` is ``sysid_bench.apps.cli`` (the same module object).

The code lives in ``sysid_bench/apps/cli.py`` (issue #37 §4: the folder tree is the layer map).
"""

# alias written by relayout.py (issue #37 §4)
from sysid_bench._alias import alias

alias(__name__, "sysid_bench.apps.cli", package=False)
