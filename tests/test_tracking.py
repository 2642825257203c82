import numpy as np
import pytest

from sysid_bench.core import physics
from sysid_bench.core.render import render, view_geometry
from sysid_bench.core.tracking import track, track_batch


@pytest.fixture(scope="module")
def states():
    rng = np.random.default_rng(11)
    th = physics.sample_theta(30, rng)
    s0 = physics.sample_state0(30, rng)
    return physics.simulate(th, s0)


@pytest.mark.parametrize("size", [(28, 28), (50, 100)])
def test_clean_frames_within_a_tenth_of_a_metre(states, size):
    pos = track_batch(render(states, size))
    err = np.linalg.norm(pos - states[..., :2], axis=-1)
    assert np.isfinite(err).all()
    # measured: 28x28 max 0.047 m, RMS 0.012 m; 100x50 max 0.016 m, RMS 0.005 m
    assert err.max() <= 0.1
    assert np.sqrt((err**2).mean()) <= 0.03


def test_track_matches_track_batch_and_floor(states):
    fr = render(states[:3], floor=2.0 + np.zeros(3))
    one = track(fr[1], floor=2.0)
    assert one.shape == (200, 2)
    np.testing.assert_array_equal(one, track_batch(fr, 2.0)[1])
    # the same pixels framed on another floor read shifted by it
    np.testing.assert_allclose(track(fr[1], floor=0.0)[:, 1] + 2.0, one[:, 1])
    np.testing.assert_allclose(track(fr[1].astype(float), floor=2.0), one, atol=1e-6)


def test_dropped_and_blacked_out_frames_are_nan(states):
    fr, info = render(states[:5], drop=0.3, seed=2, return_info=True)
    pos = track_batch(fr)
    assert np.isnan(pos[info["dropped"]]).all()
    assert np.isfinite(pos[~info["dropped"]]).all()
    black = fr.copy()
    black[:, 10:20] = 0
    assert np.isnan(track_batch(black)[:, 10:20]).all()


def test_ball_mostly_under_occluder_is_nan():
    g = view_geometry((28, 28))
    s = np.tile([[[5.0, 5.0, 0.0, 0.0]]], (1, 3, 1))
    fr = render(s)[0]
    col, row = g.to_pixels([5.0, 5.0])
    c = int(col)
    fr[1, :, : c + 2] = 0  # covers the left part and the middle of the ball: most of it
    fr[2, :, : c - 2] = 0  # clips only its left edge
    pos = track(fr)
    assert np.isfinite(pos[0]).all()
    assert np.isnan(pos[1]).all()
    assert np.isfinite(pos[2]).all()


def test_occlusion_nuisance_leaves_unoccluded_frames_accurate(states):
    fr, info = render(states[:10], occlusion=0.5, seed=5, return_info=True)
    pos = track_batch(fr)
    err = np.linalg.norm(pos - states[:10, :, :2], axis=-1)
    assert err[~info["occluded"]].max() <= 0.1
    # boxes that cover the ball's centre and most of its disc make the ball unseen
    assert np.isnan(err[info["occluded"]]).any()


def test_noise_and_blur_robust(states):
    fr = render(states[:10], blur=1.0, noise=20.0, seed=1)
    err = np.linalg.norm(track_batch(fr) - states[:10, :, :2], axis=-1)
    assert np.isfinite(err).all()
    assert err.max() <= 0.2


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: track(np.zeros((28, 28))), "frames"),
        (lambda: track(np.full((2, 28, 28), 300.0)), "frames"),
        (lambda: track(np.full((2, 28, 28), np.nan)), "frames"),
        (lambda: track_batch(np.zeros((2, 28, 28), np.uint8)), "frames"),
        (lambda: track(np.zeros((2, 28, 28), np.uint8), floor=np.nan), "floor"),
        (lambda: track_batch(np.zeros((2, 2, 28, 28), np.uint8), floor=np.zeros(3)), "floor"),
        (lambda: track(np.zeros((2, 28, 28), np.uint8), threshold=1.5), "threshold"),
        (lambda: track(np.zeros((2, 28, 28), np.uint8), min_mass=0), "min_mass"),
        (lambda: track(np.zeros((2, 2, 28), np.uint8)), "size"),
    ],
)
def test_bad_input(call, name):
    with pytest.raises(ValueError, match=name):
        call()
