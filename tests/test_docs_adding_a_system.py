"""A toy system in one new file plus one register line passes ``check_system``, with nothing
else touched.

The file is the first Python block of ``docs/adding-a-system.md``, executed as it stands (so the
page cannot rot): written as a module into a temporary directory and registered with the page's
one line (pointed at that module); then the page's second Python block runs as written.
"""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from sysid_bench.core import systems
from sysid_bench.core.testing import SystemCheckError, system_checks

DOC = Path(__file__).resolve().parents[1] / "docs" / "adding-a-system.md"
LINE = 'register("decay", "sysid_bench.core.systems.decay:Decay")'


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", DOC.read_text(), flags=re.S)


@pytest.fixture
def decay(tmp_path, monkeypatch):
    module = _blocks("python")[0]
    (tmp_path / "toy_decay.py").write_text(module.replace("sysid_bench.core.systems.decay:",
                                                          "toy_decay:"))
    monkeypatch.syspath_prepend(str(tmp_path))
    assert _blocks("text")[0].strip() == LINE
    systems.register("decay", "toy_decay:Decay")
    yield "decay"
    systems.unregister("decay")
    sys.modules.pop("toy_decay", None)


def test_the_page_has_the_module_the_line_and_the_check():
    assert len(_blocks("python")) == 2 and len(_blocks("text")) == 1
    assert "class Decay(System):" in _blocks("python")[0]
    assert 'check_system("decay")' in _blocks("python")[1]


def test_the_doc_system_passes_every_check_and_its_usage_block_runs(decay):
    assert decay in systems.available()
    exec(_blocks("python")[1], {})  # check_system("decay") first: raises naming a failed check


def test_the_doc_system_is_what_the_page_says(decay):
    toy = systems.get(decay)
    mod = sys.modules["toy_decay"]
    # the simulator agrees with the closed form of the damped oscillator
    w2, c, y0, v0 = 16.0, 0.1, 0.8, -0.5
    states = toy.simulate(np.array([[w2, c]]), np.array([[y0, v0]]))[0]
    t = np.arange(200) * 0.05
    wd = np.sqrt(w2 - c * c / 4)
    exact = np.exp(-c * t / 2) * (y0 * np.cos(wd * t) + (v0 + c * y0 / 2) / wd * np.sin(wd * t))
    assert np.abs(states[:, 0] - exact).max() <= 1e-6
    # SUBSTEPS's comment: 6e-8 m at the stiffest prior case
    err = np.abs(states[:, 0] - toy.reference([w2, c], [y0, v0])[:, 0]).max()
    assert 3e-8 < err < 1e-7 and mod.SUBSTEPS == 8
    # a frame without the bob gives NaN
    frames = np.stack([np.zeros((28, 28)), np.full((28, 28), 255.0)]).astype(np.uint8)
    assert np.isnan(toy.track(frames)).all()


def test_a_broken_doc_system_fails_check_system(decay, monkeypatch):
    # the check can fail: with too few RK4 steps per frame the simulator misses the reference
    systems.get(decay)  # imports the module
    monkeypatch.setattr(sys.modules["toy_decay"], "SUBSTEPS", 2)
    checks = dict(system_checks(decay))
    with pytest.raises(SystemCheckError, match="reference"):
        checks["check_system_reference"]()
