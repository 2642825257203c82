"""Streams and sindy-on-the-systems at their public boundary (issue 37, "Bad input", methods part).

The default stream of a non-streaming method (``LoopStream``) must read valid frames of every
system as that system's; every stream refuses a bad frame before touching its state, and a bad
``floor`` or a call before any push with a ``ValueError`` naming it; sindy on the systems checks
its posterior against the system's simulator and never shows a precise answer the data do not
support (a frozen spring's ``k3 = 0 +- 0``, a wrong ``dt``).
"""

from __future__ import annotations

import numpy as np
import pytest

import methods
from sysid_bench.core import systems
from sysid_bench.core.estimator import (
    POSITION_NOW,
    Estimator,
    Forecast,
    LoopStream,
    Observation,
    Posterior,
    Stream,
    check_frame,
    prior_posterior,
)

#: lsq budgets small enough for a push of a few frames to take a fraction of a second
TINY = {"n_samples": 60, "search_rounds": 2, "n_starts": 1, "max_opt_evals": 5}


def _clip(name: str, n_frames: int = 5, seed: int = 0):
    """theta (1, P) and rendered frames (n_frames, H, W) uint8 of one test case of ``name``."""
    sys_ = systems.get(name)
    rng = np.random.default_rng([seed, 37])
    theta = sys_.sample_theta(1, rng, "test")
    try:
        state0 = sys_.sample_state0(1, rng, theta=theta)
    except TypeError:
        state0 = sys_.sample_state0(1, rng)
    states = sys_.simulate(theta, state0, n_frames=n_frames)
    return theta, sys_.render(states, theta)[0]


# ------------------------------------------------------------------------------------------
# 1. LoopStream builds the observation of the estimator's own system
@pytest.mark.parametrize("name", systems.available())
def test_lsq_stream_reads_every_systems_frames_as_its_own(name):
    sys_ = systems.get(name)
    est = (methods.get("lsq", n_samples=60) if name == "ball"
           else methods.get("lsq", system=name, **TINY))
    _, frames = _clip(name, 4)
    stream = est.stream()
    assert isinstance(stream, LoopStream) and stream.system == name
    first = stream.push(frames[0])  # before min_frames: the system's prior, not the ball's
    assert first.system == name and first.mean.shape == (sys_.n_params,)
    if name != "ball":
        np.testing.assert_allclose(first.mean, 0.5 * (sys_.prior_lo + sys_.prior_hi))
    for fr in frames[1:]:
        post = stream.push(fr)
    assert stream.n_frames == len(frames)
    assert isinstance(post, Posterior) and post.system == name
    assert np.isfinite(post.mean).all() and post.extras["n_simulations"] > 0
    assert stream.check() is post
    pos = stream.position()
    assert pos.shape == (2,) and np.isfinite(pos).all()
    fc = stream.forecast(3, floor=0.5)
    shape = (3, 2) if sys_.n_points == 1 else (3, sys_.n_points, 2)
    assert isinstance(fc, Forecast) and fc.mean.shape == shape
    np.testing.assert_allclose(fc.extras[POSITION_NOW], pos + [0.0, 0.5])


# ------------------------------------------------------------------------------------------
# 2. frames, floor and order of calls
class _Recorder(Estimator):
    """Answers the prior and keeps the frames of every observation it was given."""

    name = "recorder"
    forecasts = True

    def __init__(self, *, seed: int = 0):
        self.seed = seed
        self.seen = []

    def identify(self, obs):
        self.seen.append(obs.frames.copy())
        return prior_posterior()

    def forecast(self, obs, horizon):
        return Forecast(mean=np.full((horizon, 2), 5.0), std=np.ones((horizon, 2)))


def _frame(value=0.0, shape=(28, 28)):
    return np.full(shape, value)


BAD_FRAMES = {
    "NaN": (_frame(np.nan), "NaN"),
    "inf": (_frame(np.inf), "inf"),
    "strings": (np.full((28, 28), "a"), "dtype"),
    "bool": (np.zeros((28, 28), bool), "dtype"),
    "complex": (np.zeros((28, 28), complex), "dtype"),
    "object": (np.full((28, 28), None, dtype=object), "dtype"),
    "float 300": (_frame(300.0), r"\[0, 255\]"),
    "negative": (_frame(-1.0), r"\[0, 255\]"),
    "2x2": (_frame(0.0, (2, 2)), "at least 4x4"),
    "3-D": (np.zeros((3, 28, 28)), r"\(H, W\)"),
    "scalar": (np.float64(3.0), r"\(H, W\)"),
    "ragged": ([[0.0, 1.0], [2.0]], "frame"),
}


@pytest.mark.parametrize("what", sorted(BAD_FRAMES))
def test_push_refuses_a_bad_frame_and_keeps_its_state(what):
    bad, match = BAD_FRAMES[what]
    est = _Recorder()
    stream = est.stream()
    good = np.zeros((28, 28), np.uint8)
    good[10:14, 10:14] = 255
    stream.push(good)
    with pytest.raises(ValueError, match=match) as info:
        stream.push(bad)
    assert str(info.value).startswith("frame:")
    assert stream.n_frames == 1
    stream.push(good)  # a valid push after a refused one works, on the frames kept
    assert stream.n_frames == 2
    assert est.seen[-1].shape == (2, 28, 28) and np.isfinite(est.seen[-1]).all()


def test_a_bad_first_frame_is_refused_and_a_frame_must_match_the_first():
    stream = _Recorder().stream()
    with pytest.raises(ValueError, match="frame: expected a frame of at least 4x4"):
        stream.push(np.zeros((2, 2), np.uint8))
    assert stream.n_frames == 0
    stream.push(np.zeros((28, 28), np.uint8))
    with pytest.raises(ValueError, match=r"frame: expected shape \(28, 28\) like the earlier"):
        stream.push(np.zeros((28, 30), np.uint8))
    assert stream.n_frames == 1


def test_check_and_forecast_before_any_push_name_push():
    stream = _Recorder().stream()
    with pytest.raises(ValueError, match="check: push at least one frame"):
        stream.check()
    with pytest.raises(ValueError, match="forecast: push at least one frame"):
        stream.forecast(5)
    stream.push(np.zeros((28, 28), np.uint8))
    stream.reset()
    with pytest.raises(ValueError, match="check: push"):
        stream.check()
    assert np.isnan(stream.position()).all()


@pytest.mark.parametrize("floor", ["x", "0.5", float("nan"), float("inf"), 1e300, -1e4, True,
                                   [1.0], None])
def test_forecast_floor_is_checked(floor):
    stream = _Recorder().stream()
    stream.push(np.zeros((28, 28), np.uint8))
    if floor is None:
        assert stream.forecast(4, floor=floor).mean.shape == (4, 2)
        return
    with pytest.raises(ValueError, match="^floor: expected"):
        stream.forecast(4, floor=floor)


@pytest.mark.parametrize("horizon", [0, -1, 2.5, "3", 10**6])
def test_forecast_horizon_is_checked(horizon):
    stream = _Recorder().stream()
    stream.push(np.zeros((28, 28), np.uint8))
    with pytest.raises(ValueError, match="^horizon: expected"):
        stream.forecast(horizon)


def test_every_stream_gets_the_base_checks():
    """A stream's own ``push`` and ``forecast`` (Vid2Param's are theirs) see only checked input."""

    class Own(Stream):
        def __init__(self):
            self.pushed = []

        def reset(self):
            self.pushed = []

        def push(self, frame):
            self.pushed.append(frame)
            return prior_posterior()

        def forecast(self, horizon, floor=None):
            off = 0.0 if floor is None else floor
            return Forecast(mean=np.full((horizon, 2), off), std=np.ones((horizon, 2)))

    s = Own()
    for bad, _ in BAD_FRAMES.values():
        with pytest.raises(ValueError, match="^frame: "):
            s.push(bad)
    assert s.pushed == []
    fr = np.arange(28 * 28, dtype=np.float32).reshape(28, 28) % 256
    s.push(fr)
    assert s.pushed[0].dtype == np.float32 and np.array_equal(s.pushed[0], fr)  # as given
    with pytest.raises(ValueError, match="^floor: "):
        s.forecast(3, floor=1e300)
    with pytest.raises(ValueError, match="^horizon: "):
        s.forecast(0)
    assert s.forecast(3, floor=2).mean[0, 0] == 2.0


def test_check_frame_passes_valid_frames_through_unchanged():
    u8 = np.zeros((5, 7), np.uint8)
    assert check_frame(u8) is u8
    f = np.full((5, 7), 255.0)
    assert check_frame(f) is f


def test_loop_stream_arguments_are_checked():
    est = _Recorder()
    with pytest.raises(ValueError, match="^dt: "):
        LoopStream(est, dt=0.0)
    with pytest.raises(ValueError, match="^floor: "):
        LoopStream(est, floor=float("nan"))
    with pytest.raises(ValueError, match="^estimator: "):
        LoopStream("lsq")


# ------------------------------------------------------------------------------------------
# 3. sindy on the systems: a model check, and no precision the data do not support
def _track(name, n_frames=200, seed=0, noise=0.01):
    sys_ = systems.get(name)
    rng = np.random.default_rng([seed, 37])
    theta = sys_.sample_theta(1, rng, "test")
    try:
        state0 = sys_.sample_state0(1, rng, theta=theta)
    except TypeError:
        state0 = sys_.sample_state0(1, rng)
    pts = sys_.observe(sys_.simulate(theta, state0, n_frames=n_frames), theta)[0]
    return theta[0], pts + rng.normal(0.0, noise, pts.shape)


def _prior_std(name):
    sys_ = systems.get(name)
    return (sys_.prior_hi - sys_.prior_lo) / np.sqrt(12.0)


@pytest.mark.parametrize("name", ["pendulum", "spring"])
def test_sindy_checks_a_valid_track_and_passes(name):
    truth, pts = _track(name)
    post = methods.get("sindy", system=name).identify(Observation(positions=pts, system=name))
    assert post.check is not None and post.check.ok and post.check.n == pts.size
    assert "widened" not in post.extras and "uninformed" not in post.extras
    assert (post.std[:3] < _prior_std(name)[:3]).all()
    assert post.extras["check_simulations"] > 0
    lo, hi = post.interval(0.9)
    assert ((truth >= lo) & (truth <= hi)).mean() >= 0.75


def test_sindy_frozen_spring_is_never_precise():
    """The block frozen mid-view: sindy's regression answered ``k3 = 0 +- 0``."""
    _, pts = _track("spring")
    frozen = np.repeat(pts[:1], 100, axis=0)
    post = methods.get("sindy", system="spring").identify(
        Observation(positions=frozen, system="spring"))
    assert post.check is not None and not post.check.ok
    assert post.extras["widened"] == "prior"
    assert (post.std >= _prior_std("spring") - 1e-12).all()


def test_sindy_spring_at_rest_is_never_precise_about_stiffness_or_damping():
    """A block resting where it stays says nothing of stiffness or damping: whether the check
    fails (widened) or passes (those parameters uninformed), their spread is the prior's."""
    rest = np.zeros((100, 1, 2))
    rest[:, 0, 0] = 1.5
    post = methods.get("sindy", system="spring").identify(
        Observation(positions=rest, system="spring"))
    assert post.check is not None
    if post.check.ok:
        assert set(post.extras["uninformed"]) >= {"w2", "k3", "c"}
    flat = [systems.get("spring").params.index(p) for p in ("w2", "k3", "c")]
    assert (post.std[flat] >= _prior_std("spring")[flat] - 1e-12).all()


def test_sindy_never_shows_a_zero_std():
    """STLSQ prunes a small coefficient to exactly 0, whose regression standard error is 0: the
    posterior said ``k3 = 0 +- 0``; now the pruned parameter gets at least the prior's spread."""
    _, pts = _track("spring")
    obs = Observation(positions=pts, system="spring")
    post = methods.get("sindy", system="spring", threshold=1.0).identify(obs)
    pruned = np.asarray(post.extras["coefficients"])[1] == 0  # (s, s^3, v): w2, k3, c
    assert pruned.any() and not pruned.all()
    assert (post.std > 0).all()
    assert (post.std[:3][pruned] >= _prior_std("spring")[:3][pruned] - 1e-12).all()


@pytest.mark.parametrize("name", ["pendulum", "spring"])
def test_sindy_wrong_dt_fails_its_check_and_is_widened(name):
    """A 0.05 s track read at 0.5 s: confident answers from garbage before the check."""
    for seed in range(6):
        _, pts = _track(name, seed=seed)
        obs = Observation(positions=pts, dt=0.5, system=name)
        try:
            post = methods.get("sindy", system=name).identify(obs)
        except ValueError as exc:  # a pendulum too slow to regress on at this dt: refused
            assert "positions:" in str(exc)
            continue
        assert not post.check.ok and post.extras["widened"] == "prior"
        assert (post.std >= _prior_std(name) - 1e-12).all()
        return
    pytest.fail(f"no {name} track was answered at dt = 0.5 s")


def test_sindy_forecast_still_runs_from_a_checked_fit():
    _, pts = _track("spring", n_frames=60)
    fc = methods.get("sindy", system="spring", n_forecast=8).forecast(
        Observation(positions=pts, system="spring"), 5)
    assert fc.mean.shape == (5, 2) and np.isfinite(fc.mean).all()
