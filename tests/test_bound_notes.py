"""A real clip outside a system's prior: an answer on a range's bound says which option widens it."""

import numpy as np

from sysid_bench.core import systems


def test_bound_notes_name_the_option_that_widens_the_range():
    from sysid_bench.apps.video_systems import bound_notes

    system = systems.get("pendulum")
    mean = np.full((3, 4), np.nan)
    mean[-1] = [-9.81, 0.5, 0.1, 0.1]  # L on the prior's lower bound
    check = np.full((3, 3), np.nan)
    check[-1] = [0.0, 0.2, 0.01]
    notes = bound_notes(system, mean, check, {"g": -9.81}, None)
    assert len(notes) == 1 and "--prior L=0.2:2" in notes[0]
    check[-1, 0] = 1.0  # the fit passes: a bound is an answer, nothing to say
    assert bound_notes(system, mean, check, {"g": -9.81}, None) == []
    check[-1, 0] = 0.0  # a user's range already at the physics' limit: nothing to widen
    assert bound_notes(system, mean, check, {"g": -9.81}, {"L": (0.5, 2.0)}) != []
    mean[-1, 1] = 0.2
    assert bound_notes(system, mean, check, {"g": -9.81}, {"L": (0.2, 2.0)}) == []
