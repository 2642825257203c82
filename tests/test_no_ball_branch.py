"""Issue 37: the ball is a system like the others. No code outside the ball's own files asks
whether it runs on the ball (``== "ball"`` and the like): what differs is declared by the System
(:mod:`sysid_bench.core.systems._base` hooks, :mod:`sysid_bench.core.systems.ball`) or by a method's own
per-system table. And no ``System*`` twin of a class.

The ball's own files are the ball's System and, until issue 37 reaches it (another branch),
``methods/vid2param/``; the ball's experiments (interception, the paper comparisons) have none
today, so none is allowed there either.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BALL_BRANCH = re.compile(r'== "ball"|!= "ball"|_is_ball|"ball" in|is_ball')
TWIN = re.compile(r"^\s*class System[A-Z]\w*", re.M)

#: the ball's own files, where a ball branch is the point
BALL_FILES = ("sysid_bench/core/systems/ball.py", "methods/vid2param/")
#: classes named System* that are no twin of another class
NOT_TWINS = {"sysid_bench/core/_system_checks.py": ["SystemCheckError"]}


def _sources():
    for top in ("sysid_bench", "methods"):
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if not rel.startswith(BALL_FILES):
                yield rel, path.read_text(encoding="utf-8")


def _branches(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() if BALL_BRANCH.search(line)]


def test_no_ball_branch_outside_the_balls_files():
    found = {rel: hits for rel, text in _sources() if (hits := _branches(text))}
    assert not found, ("a ball branch outside the ball's files (declare what differs on the "
                       f"System or in the module's per-system table instead): {found}")


def test_no_system_twin_class():
    found = {rel: [m.group().split()[1] for m in TWIN.finditer(text)]
             for rel, text in _sources()}
    twins = {rel: [c for c in names if c not in NOT_TWINS.get(rel, [])]
             for rel, names in found.items()}
    assert not {rel: c for rel, c in twins.items() if c}, twins


def test_the_grep_sees_a_branch():
    assert _branches('if system == "ball":\n    pass\nx = 1\n') == ['if system == "ball":']
    assert _branches('if "ball" in names or obs._is_ball:\n') != []
    assert _branches('own_machinery = ("ball",)\n') == []
    assert TWIN.search("class SystemFit:\n") and not TWIN.search("class PointsFit:\n")


def test_observation_and_stream_ask_the_system(monkeypatch):
    """The ball's observation checks and its stream's tracking are the ball System's hooks."""
    import numpy as np

    from sysid_bench.core import systems
    from sysid_bench.core.estimator import Observation

    ball = type(systems.get("ball"))
    seen = []
    monkeypatch.setattr(ball, "check_observation", lambda self, obs, default: seen.append(
        (self.name, obs.positions.shape, default)))
    Observation(positions=np.ones((3, 2)))
    assert seen == [("ball", (3, 2), True)]
    # the generic check reads (T, 2) of a one-point system as (T, 1, 2)
    assert Observation(positions=np.zeros((3, 2)), system="pendulum").positions.shape == (3, 1, 2)
