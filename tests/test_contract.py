"""One contract, every registered method (like scikit-learn's ``check_estimator``).

Each class may declare ``_contract_options``: cheap hyperparameters so the contract runs fast;
they change budgets, never the code path.
"""

import inspect

import numpy as np
import pytest

import methods
from sysid_bench.estimator import Estimator, Forecast, Observation, Posterior
from sysid_bench.physics import PARAMS, PRIOR

NAMES = methods.available(include_reference=True)
N_OBS = 60


def _make(name, **extra):
    cls = methods.get_class(name)
    opts = dict(getattr(cls, "_contract_options", {}))
    opts.update(extra)
    return methods.get(name, **opts)


def _maybe(fn, *args):
    """Run ``fn``; a NotImplementedError must explain itself in a sentence."""
    try:
        return fn(*args)
    except NotImplementedError as exc:
        msg = str(exc)
        assert len(msg.split()) >= 4, f"NotImplementedError without a reason: {msg!r}"
        return None


@pytest.fixture(scope="module")
def obs(ball_case):
    return Observation(
        frames=ball_case["frames"][:N_OBS],
        positions=ball_case["states"][:N_OBS, :2],
        floor=0.0,
        state0=ball_case["state0"],
    )


def _check_posterior(post):
    assert isinstance(post, Posterior)
    assert post.mean.shape == (4,) and post.std.shape == (4,)
    assert np.isfinite(post.mean).all()
    assert (post.std >= 0).all()
    # physical units, PARAMS order: means stay near the prior box
    for i, p in enumerate(PARAMS):
        lo, hi = PRIOR[p]
        span = hi - lo
        assert lo - span <= post.mean[i] <= hi + span, f"{p} = {post.mean[i]} not in physical units?"
    if post.samples is not None:
        assert post.samples.ndim == 2 and post.samples.shape[1] == 4
    assert isinstance(post.extras.get("n_simulations"), (int, np.integer))
    assert post.extras["n_simulations"] >= 0
    assert float(post.extras.get("wall_s", -1)) >= 0


@pytest.mark.parametrize("name", NAMES)
def test_constructor_only_stores_keyword_hyperparameters(name):
    cls = methods.get_class(name)
    assert issubclass(cls, Estimator)
    assert cls.name == name
    sig = inspect.signature(cls.__init__)
    for p in list(sig.parameters.values())[1:]:
        assert p.kind is p.KEYWORD_ONLY, f"{name}: hyperparameter {p.name} must be keyword-only"
        assert p.default is not p.empty, f"{name}: hyperparameter {p.name} needs a default"
    est = cls()
    params = est.get_params()
    for k, p in list(sig.parameters.items())[1:]:
        assert params[k] is p.default or params[k] == p.default, f"{name}: {k} not stored verbatim"
    assert "seed" in params, f"{name}: every method takes a seed"
    # no fitted state before fit/identify
    assert not [a for a in vars(est) if a.endswith("_") and not a.startswith("_")]


@pytest.mark.parametrize("name", NAMES)
def test_identify_forecast_and_seeds(name, obs):
    est = _make(name, seed=11)
    assert est.fit(None) is est
    post = _maybe(est.identify, obs)
    if post is not None:
        _check_posterior(post)
        again = _make(name, seed=11).identify(obs)
        np.testing.assert_array_equal(post.mean, again.mean, err_msg=f"{name}: same seed, other answer")
        np.testing.assert_array_equal(post.std, again.std)
    fc = _maybe(est.forecast, obs, 10)
    if fc is not None:
        assert isinstance(fc, Forecast)
        assert fc.mean.shape == (10, 2) and fc.std.shape == (10, 2)
        assert np.isfinite(fc.mean).all()
        if fc.samples is not None:
            assert fc.samples.shape[1:] == (10, 2)
        again = _make(name, seed=11).forecast(obs, 10)
        np.testing.assert_array_equal(fc.mean, again.mean, err_msg=f"{name}: same seed, other forecast")
    assert post is not None or fc is not None, f"{name} neither identifies nor forecasts"


@pytest.mark.parametrize("name", NAMES)
def test_prefixes_and_stream(name, obs):
    est = _make(name)
    posts = _maybe(est.identify_prefixes, obs, [20, N_OBS])
    if posts is None:
        return
    assert len(posts) == 2
    for p in posts:
        _check_posterior(p)
    stream = est.stream()
    stream.reset()
    last = None
    for frame in obs.frames[:5]:
        last = stream.push(frame)
    _check_posterior(last)


@pytest.mark.parametrize("name", NAMES)
def test_frames_only_input(name, ball_case):
    est = _make(name)
    obs = Observation(frames=ball_case["frames"][:N_OBS])
    post = _maybe(est.identify, obs)
    if post is not None:
        _check_posterior(post)
