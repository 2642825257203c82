"""sindy's intervals on tracked video (issue 29 (c): a posterior that fails the model check).

On the report's 20 test videos sindy's own 90% intervals missed e in 10 of 40 posteriors
(5-frame cubics at each bounce read ratios from 0.1 to 4.6, and one bounce got a fixed 0.02
std), and g after 200 frames was pulled toward 0 by floor-sliding runs taken for flight. The
tests use another seed's videos than the report's.
"""

import numpy as np
import pytest

from methods._tracks import segment_track
from methods.sindy import SINDy, _segment_jackknife, bounce_ratios, free_flight, pool_ratios
from sysid_bench.core import physics
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation


@pytest.fixture(scope="module")
def videos():
    return make_dataset("test", n=8, seed=5)


def _video(ds, i, n=200):
    return Observation(frames=np.asarray(ds.frames[i])[:n], dt=float(ds.meta["dt"]),
                       floor=float(ds.floor[i]))


def test_restitution_from_video_is_accurate_and_its_interval_honest(videos):
    z, err = [], []
    for i in range(len(videos.theta)):
        post, _, _ = SINDy()._fit(_video(videos, i))
        e = videos.theta[i, 0, 0]
        assert post.extras["informed"][0]
        err.append(post.mean[0] - e)
        z.append((post.mean[0] - e) / post.std[0])
    err, z = np.abs(err), np.abs(z)
    # before: bounce ratios from 5-frame cubics, errors up to 0.3 and |z| up to 16
    assert err.max() < 0.05, err
    assert z.max() < 3.0, z


def test_bounce_ratios_on_a_clean_track_give_e_with_a_small_error():
    theta = np.array([[0.8, -9.81, 0.01, 0.3]])
    s0 = np.array([[2.0, 6.0, 2.5, 0.0]])
    states = physics.simulate(theta, s0, n_frames=120)
    pos = states[0, :, :2]
    rng = np.random.default_rng(0)
    noisy = pos + rng.normal(0.0, 0.01, pos.shape)
    seg = segment_track(noisy, physics.DT, floor=0.0)
    ratios, se = bounce_ratios(noisy, physics.DT, seg, 0.01)
    assert ratios.size >= 2
    m, s, used = pool_ratios(ratios, se)
    assert abs(m - 0.8) < 3 * s
    assert s < 0.05


def test_pool_drops_a_ratio_far_from_the_others_and_widens_on_scatter():
    r = np.array([0.80, 0.81, 0.79, 0.80, 1.40])
    m, s, used = pool_ratios(r, np.full(5, 0.01))
    assert used.tolist() == [True, True, True, True, False]
    assert m == pytest.approx(0.80, abs=1e-3)
    # scatter 10x the stated errors: the std follows the scatter, not the errors
    r2 = np.array([0.70, 0.90, 0.75, 0.85])
    _, s2, _ = pool_ratios(r2, np.full(4, 0.01))
    assert s2 > 0.04


def test_free_flight_keeps_a_parabola_and_drops_a_floor_slide():
    dt = physics.DT
    t = np.arange(30) * dt
    pos = np.zeros((60, 2))
    pos[:30, 1] = 3.0 + 4.0 * t - 0.5 * 9.81 * t**2
    pos[30:, 1] = 0.05 + 0.002 * np.sin(np.arange(30))  # sliding, tracked with a wobble
    kept = free_flight([(0, 30), (30, 60)], pos, dt, 0.005)
    assert kept == [(0, 30)]


def test_segment_jackknife_sees_segments_that_disagree():
    rng = np.random.default_rng(1)
    theta = np.column_stack([np.ones(60), rng.normal(size=60), rng.normal(size=60)])
    coef = np.array([[0.0, -0.02, 0.0], [-9.8, 0.0, -0.02]])
    acc = (theta @ coef.T)
    same = _segment_jackknife(coef, theta, acc, [20, 20, 20])
    assert np.allclose(same, 0.0, atol=1e-9)
    acc2 = acc.copy()
    acc2[20:40, 1] += 1.0  # one segment falls 1 m/s^2 faster
    differ = _segment_jackknife(coef, theta, acc2, [20, 20, 20])
    assert differ[0] > 0.3
    assert _segment_jackknife(coef, theta, acc, [30, 30]) is None


def test_clean_positions_keep_the_short_unbiased_fit_at_bounces():
    """On clean positions the fits over 15 frames read e 0.005 low (drag's curvature; nothing to
    average away); the 5 frames nearest each contact do not."""
    ds = make_dataset("test", n=10, seed=5)
    err_default, err_long = [], []
    for i in range(10):
        pos = ds.states[i, :, :2]
        seg = segment_track(pos, physics.DT, floor=float(ds.floor[i]))
        e = ds.theta[i, 0, 0]
        for k, out in ((None, err_default), (15, err_long)):
            r, se = bounce_ratios(pos, physics.DT, seg, 1e-4, k=k)
            out.append(pool_ratios(r, se)[0] - e)
    assert np.mean(np.abs(err_default)) < 0.002, err_default
    assert np.mean(np.abs(err_long)) > 2 * np.mean(np.abs(err_default))
