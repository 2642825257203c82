"""On the other systems an answer on a range's bound whose fit fails names the --prior that
widens it (a 0.26 m pendulum against the prior's 0.5-2 m)."""

import numpy as np

from sysid_bench.apps.video import bound_notes
from sysid_bench.core import systems


def test_bound_notes_name_the_option_that_widens_the_range():
    system = systems.get("pendulum")
    mean = np.full((3, 4), np.nan)
    mean[-1] = [-9.81, 0.5, 0.1, 0.1]  # L on the prior's lower bound
    check = np.full((3, 3), np.nan)
    check[-1] = [0.0, 0.2, 0.01]

    def notes(known, prior):
        return bound_notes(mean, known, prior, 0.01, system=system, check=check)

    assert len(notes({"g": -9.81}, None)) == 1 and "--prior L=0.2:2" in notes({"g": -9.81}, None)[0]
    check[-1, 0] = 1.0  # the fit passes: a bound is an answer, nothing to say
    assert notes({"g": -9.81}, None) == []
    check[-1, 0] = 0.0  # a user's range already at the physics' limit: nothing to widen
    assert notes({"g": -9.81}, {"L": (0.5, 2.0)}) != []
    mean[-1, 1] = 0.2
    assert notes({"g": -9.81}, {"L": (0.2, 2.0)}) == []
