"""Vid2Param's preset records: one per system, looked up by name, a user's system derived."""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path

import pytest
import torch  # noqa: F401 (a dependency of [test]: missing fails, not skips)

from methods.vid2param import presets  # noqa: E402
from methods.vid2param.model import V2PConfig, system_targets  # noqa: E402
from methods.vid2param.train import _parse, _stages, _train_config  # noqa: E402
from sysid_bench.core import systems  # noqa: E402


@pytest.fixture
def decay(tmp_path, monkeypatch):
    """The toy system of docs/adding-a-system.md, registered as a user would."""
    doc = Path(__file__).resolve().parents[1] / "docs" / "adding-a-system.md"
    module = re.findall(r"```python\n(.*?)```", doc.read_text(), flags=re.S)[0]
    (tmp_path / "toy_decay_presets.py").write_text(module)
    monkeypatch.syspath_prepend(str(tmp_path))
    systems.register("decay", "toy_decay_presets:Decay")
    yield "decay"
    systems.unregister("decay")
    sys.modules.pop("toy_decay_presets", None)


def test_every_preset_is_one_frozen_record_looked_up_by_its_or_its_systems_name():
    assert set(presets.PRESETS) == {"28x28", "camera", "pendulum", "spring", "collision"}
    assert presets.get("ball") is presets.get("28x28")
    for name, p in presets.PRESETS.items():
        assert presets.get(name) is p and p.name == name
        assert p.space == (presets.BOX if p.system == "ball" else presets.VIEW)
        with pytest.raises(dataclasses.FrozenInstanceError):
            p.system = "x"
        with pytest.raises(TypeError):
            p.train["steps"] = 1  # read-only: a caller cannot change a preset for everyone
    assert presets.get("pendulum").train["chunk_epochs"] == 8
    assert dict(presets.get("camera").net)["roll_stat"] == "fit"
    assert V2PConfig.preset("camera") == V2PConfig(**presets.get("camera").net)
    with pytest.raises(ValueError, match=r"preset: expected a preset \(28x28, camera, .*registered "
                                         r"system \(ball, .*got 'sprung'"):
        presets.get("sprung")
    with pytest.raises(TypeError, match="preset: expected a preset or system name"):
        presets.get(3)
    with pytest.raises(ValueError, match="space"):
        presets.Preset("p", "pendulum", "pixels")


def test_a_users_system_gets_a_derived_preset_and_its_network(decay):
    p = presets.get(decay)
    assert (p.name, p.system, p.space) == ("decay", "decay", presets.VIEW)
    # the generic recipe of a shipped system (the shipped systems' presets add their chunk
    # sizes and the points curriculum, which needs fixed keypoint channels), its stages
    coll = presets.get("collision")
    assert dict(p.train) == dict(presets._VIEW_TRAIN)
    assert "points_steps" not in p.train
    assert all(presets.get(s).train["points_steps"] > 0 for s in ("spring", "pendulum", "collision"))
    # the shipped systems' stages less their weak form (a user's system has none)
    assert p.stages == tuple(st for st in coll.stages if st[0] != "weak_evidence")
    assert [n for n, _ in coll.stages] == ["weak_evidence", "std_scale"]
    c = V2PConfig.preset(decay)
    s = systems.get(decay)
    assert c.system == "decay" and c.targets == system_targets(decay)
    assert c.frame_size == tuple(s.size) and c.n_points == s.n_points
    assert not c.roll_features and not c.physics_prior
    # its recurrence's difference scales measured from its own simulated data
    assert c.diff_scales == presets.diff_scales(decay) == dict(p.net)["diff_scales"]
    assert all(v > 0 for v in c.diff_scales) and c.diff_scales != V2PConfig().diff_scales
    # the training command's recipe and stages for it (``--system decay``)
    a = _parse(["--out", "x", "--system", decay])
    assert a.run.preset == decay
    assert _train_config(a, c).steps == p.train["steps"]
    assert [n for n, _ in _stages(a)] == ["std_scale"]


@pytest.mark.parametrize("system", ["pendulum", "spring", "collision"])
def test_measured_difference_scales_are_the_probes_that_set_the_shipped_presets(system):
    # the shipped systems' scales came from the probe's measurement (variant b); the derived
    # presets' measurement finds them within 15% (another sample of trajectories and noise)
    want = presets._DIFF_SCALES[system]
    got = presets.diff_scales(system)
    assert got == presets.diff_scales(system)  # measured once, the same numbers
    for g, w in zip(got, want):
        assert abs(g / w - 1) < 0.15, (system, got, want)
