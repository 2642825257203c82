"""Public alias: ``sysid_bench.video_systems`` is ``sysid_bench.apps.video_systems`` (the same module object).

The code lives in ``sysid_bench/apps/video_systems.py`` (issue #37 §4: the folder tree is the layer map).
"""

# alias written by relayout.py (issue #37 §4)
from sysid_bench._alias import alias

alias(__name__, "sysid_bench.apps.video_systems", package=False)
