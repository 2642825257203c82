"""Public alias: ``sysid_bench.mujoco_scene`` is ``sysid_bench.core.mujoco_scene`` (the same module object).

The code lives in ``sysid_bench/core/mujoco_scene.py`` (issue #37 §4: the folder tree is the layer map).
"""

# alias written by relayout.py (issue #37 §4)
from sysid_bench._alias import alias

alias(__name__, "sysid_bench.core.mujoco_scene", package=False)
