"""Issue 14, section 3: inputs a hostile user gave that were accepted; each is now a ValueError
naming the argument, at construction."""

import numpy as np
import pytest

import methods
from sysid_bench.core.estimator import BOX_MARGIN, DT_RANGE, MAX_HORIZON, Observation


def _track(n=20):
    t = np.arange(n) * 0.05
    return np.column_stack([2.0 + 3.0 * t, 8.0 - 4.9 * t**2])


@pytest.mark.parametrize("dt", ["0.05", b"0.05", True, None, [0.05], 1e-9, 0.0, -0.05, 1e6,
                                float("nan"), float("inf")])
def test_dt_must_be_a_sensible_number(dt):
    with pytest.raises(ValueError, match="dt"):
        Observation(positions=_track(), dt=dt)


def test_dt_range_ends_are_accepted():
    for dt in DT_RANGE:
        assert Observation(positions=_track(), dt=dt).dt == dt
    assert Observation(positions=_track(), dt=np.float32(0.05)).dt == pytest.approx(0.05)


@pytest.mark.parametrize("shape", [(5, 0, 0), (5, 28, 0), (5, 2, 2)])
def test_empty_or_tiny_frames(shape):
    with pytest.raises(ValueError, match="frames"):
        Observation(frames=np.zeros(shape, np.uint8))


@pytest.mark.parametrize("where, value", [(0, -1.0), (0, 10.0 + BOX_MARGIN + 0.01), (1, -0.5),
                                          (1, 10.3)])
def test_positions_outside_the_box(where, value):
    pos = _track()
    pos[3, where] = value
    with pytest.raises(ValueError, match="positions"):
        Observation(positions=pos, floor=0.0)


def test_positions_within_the_margin_are_accepted_and_moved_onto_the_edge():
    from sysid_bench.core.estimator import observed_positions

    pos = _track()
    pos[0, 0] = -0.01  # a tracked ball touching the wall
    obs = Observation(positions=pos, floor=0.0)
    assert obs.positions[0, 0] == -0.01  # stored as given
    assert observed_positions(obs)[0, 0] == 0.0


def test_unknown_floor_still_bounds_the_height_of_the_track():
    pos = _track()
    pos[3, 1] = pos[:, 1].min() - 11.0
    with pytest.raises(ValueError, match="positions"):
        Observation(positions=pos)
    pos = _track() + [0.0, 100.0]  # a floor 100 m up is fine when the floor is unknown
    Observation(positions=pos)


@pytest.mark.parametrize("state0", [[12.0, 5.0, 1.0, 1.0], [5.0, -1.0, 0.0, 0.0],
                                    [5.0, 10.5 + BOX_MARGIN, 0.0, 0.0]])
def test_state0_outside_the_box(state0):
    with pytest.raises(ValueError, match="state0"):
        Observation(positions=_track(), floor=0.0, state0=state0)


def test_floor_must_be_a_number():
    with pytest.raises(ValueError, match="floor"):
        Observation(positions=_track(), floor="0")


@pytest.mark.parametrize("name", ["prior", "lsq", "sindy", "dmd"])
def test_every_method_refuses_a_huge_horizon(name):
    est = methods.get(name, **methods.spec(name).contract_options)
    obs = Observation(positions=_track(20), floor=0.0)
    with pytest.raises(ValueError, match="horizon"):
        est.forecast(obs, 10**6)
    assert est.forecast(obs, 5).horizon == 5
    assert MAX_HORIZON >= 200


def test_seed_must_be_an_int():
    with pytest.raises(ValueError, match="seed"):
        methods.get("prior", seed="x")

