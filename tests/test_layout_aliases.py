"""The public aliases at the old paths (issue #37 §4): one module object per name, one class
object per system, ``python -m`` through an alias (written by relayout.py).
"""

# alias written by relayout.py (issue #37 §4)

import importlib
import subprocess
import sys

import pytest

MOVED = {'_io': 'sysid_bench.core._io', '_markdown': 'sysid_bench.core._markdown', '_observation_checks': 'sysid_bench.core._observation_checks', '_system_checks': 'sysid_bench.core._system_checks', '_validate': 'sysid_bench.core._validate', 'camera_footage': 'sysid_bench.core.camera_footage', 'datasets': 'sysid_bench.core.datasets', 'estimator': 'sysid_bench.core.estimator', 'footage': 'sysid_bench.core.footage', 'metrics': 'sysid_bench.core.metrics', 'mujoco_scene': 'sysid_bench.core.mujoco_scene', 'physics': 'sysid_bench.core.physics', 'physics_jax': 'sysid_bench.core.physics_jax', 'render': 'sysid_bench.core.render', 'simulator': 'sysid_bench.core.simulator', 'spec': 'sysid_bench.core.spec', 'systems': 'sysid_bench.core.systems', 'testing': 'sysid_bench.core.testing', 'tracking': 'sysid_bench.core.tracking', 'video': 'sysid_bench.apps.video', 'video_systems': 'sysid_bench.apps.video_systems', 'intercept': 'sysid_bench.apps.intercept', 'report': 'sysid_bench.apps.report', 'cli': 'sysid_bench.apps.cli'}


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_path_is_the_moved_module(old):
    assert importlib.import_module(f"sysid_bench.{old}") is importlib.import_module(MOVED[old])


def test_one_class_object_per_system():
    import sysid_bench.systems.ball as old

    import sysid_bench.core.systems.ball as new
    from sysid_bench import systems

    assert old is new
    assert old.__spec__.name == "sysid_bench.core.systems.ball"
    assert systems.get("ball") is systems.get("ball")
    assert type(systems.get("ball")).__module__ == "sysid_bench.core.systems.ball"
    assert sys.modules["sysid_bench.systems.ball"] is sys.modules["sysid_bench.core.systems.ball"]


def test_monkeypatch_through_the_old_name_reaches_the_moved_module(monkeypatch):
    import sysid_bench.core.physics as physics

    monkeypatch.setattr("sysid_bench.physics.__doc__", "patched")
    assert physics.__doc__ == "patched"


def test_python_dash_m_through_an_alias():
    r = subprocess.run([sys.executable, "-m", "sysid_bench.cli", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage" in r.stdout.lower()
