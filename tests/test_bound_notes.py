"""identify's notes flag a fitted parameter that ends on its search range's bound (issue 38:
tr.mp4 read g = -12.81 at PRIOR's bound with a passing check, an answer that is not a
measurement)."""
import numpy as np
import pytest

from sysid_bench.apps.video import bound_notes


def _track(last):
    m = np.full((5, 4), np.nan)
    m[2] = [0.7, -9.8, 0.01, 0.3]
    m[3] = last  # the last estimate counts; rows after it without one are skipped
    return m


def test_g_on_prior_bound_is_flagged():
    notes = bound_notes(_track([0.69, -12.81, 0.01, 0.3]))
    assert len(notes) == 1 and notes[0].startswith("g = -12.81 sits on its range's lower bound")


def test_inside_held_and_zero_edges_are_not_flagged():
    assert bound_notes(_track([0.69, -9.81, 0.0005, 0.0])) == []  # no drag, no spin: physical
    assert bound_notes(_track([0.69, -12.81, 0.01, 0.3]), known={"g": -12.81}) == []
    # the user's own range replaces PRIOR's
    assert bound_notes(_track([0.69, -12.81, 0.01, 0.3]), prior={"g": (-15.0, -5.0)}) == []
    notes = bound_notes(_track([0.69, -9.0, 0.05, 0.3]))
    assert len(notes) == 1 and "d = 0.05" in notes[0] and "upper" in notes[0]


def test_bad_shape_is_refused():
    with pytest.raises(ValueError, match="mean: expected a"):
        bound_notes(np.zeros((3, 2)))
    assert bound_notes(np.full((3, 4), np.nan)) == []
