"""sindy and one wild position (issue 14): a confident posterior must also be a right one."""

import numpy as np
import pytest

from methods.sindy import SINDy, reject_outliers
from sysid_bench.core import physics
from sysid_bench.core.estimator import Observation


@pytest.fixture(scope="module")
def track():
    rng = np.random.default_rng(5)
    theta = physics.sample_theta(1, rng)
    states = physics.simulate(theta, physics.sample_state0(1, rng), n_frames=200)
    return theta[0], states[0, :, :2]


@pytest.mark.parametrize("frame", [0, 1, 77, 198, 199])
@pytest.mark.parametrize("value", [1000.0, -1000.0, 5.0])
def test_one_outlier_gives_an_honest_posterior(track, frame, value):
    theta, pos = track
    pos = pos.copy()
    pos[frame, 1] = value
    try:
        post = SINDy().identify(Observation(frames=None, positions=pos))
    except ValueError as exc:  # refusing the input, naming it, is honest too
        assert "positions" in str(exc)
        return
    z = np.abs(post.mean - theta) / post.std
    assert (z[:3] < 4.0).all(), f"e, g, d off by {z[:3].round(1)} std: mean {post.mean}, std {post.std}"
    if abs(value) > 100:  # a 5 m error near a bounce can be within reach of a real ball
        assert post.extras["n_outliers"] == 1


def test_reject_outliers_keeps_real_tracks_whole():
    rng = np.random.default_rng(0)
    th, s0 = physics.sample_theta(30, rng), physics.sample_state0(30, rng)
    s0[:, 2:] *= 1.5  # faster than the prior's balls, to stress the speed bound
    states = physics.simulate(th, s0)
    for b in range(30):
        pos = states[b, :, :2] + rng.normal(0.0, 0.01, (200, 2))
        pos[rng.random(200) < 0.2] = np.nan  # gaps
        assert not reject_outliers(pos, physics.DT).any()


def test_reject_outliers_finds_two_neighbouring_outliers():
    t = np.arange(50) * 0.05
    pos = np.column_stack([1.0 + 2.0 * t, 5.0 + 3.0 * t - 4.9 * t**2])
    pos[[20, 21], 1] += 4.0
    np.testing.assert_array_equal(np.flatnonzero(reject_outliers(pos, 0.05)), [20, 21])
