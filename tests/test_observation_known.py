"""``Observation.known`` (design.md): what the user knows travels with the observation; a method
that holds knowledge answers as if built with it, one that cannot refuses with its reason."""

import numpy as np
import pytest

import methods
from sysid_bench.bench.cases import bench_case
from sysid_bench.core.estimator import Observation


@pytest.fixture(scope="module")
def pendulum():
    obs, truth, _ = bench_case("pendulum", 0, 4, 2024, "positions")
    return obs, truth


def test_known_on_the_observation_equals_known_on_the_method(pendulum):
    obs, truth = pendulum
    L = float(truth[1])
    held = Observation(positions=obs.positions, system="pendulum", known={"L": L})
    a = methods.get("lsq", system="pendulum").identify(held)
    b = methods.get("lsq", system="pendulum", known={"L": L}).identify(obs)
    assert np.array_equal(a.mean, b.mean) and np.array_equal(a.std, b.std)
    assert a.mean[1] == L and a.std[1] == 0 and a.extras["known"] == {"L": L}
    assert held.prefix(20).known == {"L": L}


def test_a_method_that_cannot_hold_it_refuses_and_a_contradiction_is_refused(pendulum):
    obs, truth = pendulum
    held = Observation(positions=obs.positions, system="pendulum", known={"L": float(truth[1])})
    with pytest.raises(ValueError, match="obs.known: sindy cannot hold known values"):
        methods.get("sindy", system="pendulum").identify(held)
    with pytest.raises(ValueError, match="contradicts the estimator's known values"):
        methods.get("lsq", system="pendulum", known={"L": 0.5}).identify(held)


@pytest.mark.parametrize("bad, match", [({"x": 1.0}, "known: expected parameters of the pendulum"),
                                        ({"g": float("nan")}, "known: expected a finite number"),
                                        (["g"], "known: expected a dict")])
def test_bad_known_is_named(pendulum, bad, match):
    with pytest.raises(ValueError, match=match):
        Observation(positions=pendulum[0].positions, system="pendulum", known=bad)


def test_the_prior_answers_the_held_value_on_the_ball():
    post = methods.get("prior").identify(Observation(positions=np.full((10, 2), 5.0),
                                                     known={"g": -9.81}))
    assert post.mean[1] == -9.81 and post.std[1] == 0
