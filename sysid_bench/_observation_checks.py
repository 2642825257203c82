"""Public alias: ``sysid_bench._observation_checks`` is ``sysid_bench.core._observation_checks`` (the same module object).

The code lives in ``sysid_bench/core/_observation_checks.py`` (issue #37 §4: the folder tree is the layer map).
"""

# alias written by relayout.py (issue #37 §4)
from sysid_bench._alias import alias

alias(__name__, "sysid_bench.core._observation_checks", package=False)
