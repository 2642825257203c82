"""A system's streamed push after the NumPy filter: the posterior head on Python floats
(``methods.vid2param._points._StreamHead``) and ``LazyPosterior.from_floats`` give the array
path's bytes and refuse what the ``Posterior`` constructor refuses, with its message."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import methods
from methods.vid2param._points import SYSTEM_CHECKPOINTS, _StreamHead
from methods.vid2param.fast import LazyPosterior
from sysid_bench.core import systems

SYSTEMS = [pytest.param(s, marks=pytest.mark.skipif(not p.is_file(), reason=f"no {s} model"))
           for s, p in SYSTEM_CHECKPOINTS.items()]


def _bounds(name: str):
    sys_ = systems.get(name)
    return sys_, [tuple(map(float, b)) for b in sys_._mean_bounds()]


def _same(a, b) -> None:
    """Two posteriors hold the same bytes and fields (samples drawn on both)."""
    assert type(a) is type(b)
    assert a.mean.tobytes() == b.mean.tobytes() and a.std.tobytes() == b.std.tobytes()
    assert a.mean.dtype == b.mean.dtype == np.float64 and a.std.dtype == np.float64
    assert a.system == b.system and a.check is b.check is None
    assert list(a.extras) == list(b.extras)
    assert list(a.__dict__) == list(b.__dict__)
    sa, sb = a.samples, b.samples
    assert (sa is None) == (sb is None)
    if sa is not None:
        assert sa.tobytes() == sb.tobytes()


def test_from_floats_is_the_constructor():
    sys_, mb = _bounds("pendulum")
    lo, hi = sys_.prior_lo, sys_.prior_hi
    mean = ((lo + hi) / 2).tolist()
    std = ((hi - lo) / 7).tolist()
    kw = dict(seed=(4, 9), n_samples=30, bounds=(lo, hi), system="pendulum")
    fast = LazyPosterior.from_floats(mean, std, {"n_simulations": 0, "n_frames": 9},
                                     mean_bounds=mb, **kw)
    m = np.array(mean)
    ref = LazyPosterior(m, np.array(std), {"n_simulations": 0, "n_frames": 9}, loc=m, **kw)
    assert [k for k in fast.__dict__] == [k for k in ref.__dict__]
    assert fast.__dict__["_draw"][0] is fast.mean  # the loc is the mean, as in _params
    _same(fast, ref)
    _same(pickle.loads(pickle.dumps(fast)), ref)
    # without the system's bounds: the constructor itself
    _same(LazyPosterior.from_floats(mean, std, {"n_simulations": 0, "n_frames": 9}, **kw), ref)


@pytest.mark.parametrize("bad", ["nan_mean", "inf_mean", "far_mean", "neg_std", "nan_std",
                                 "short_std"])
def test_from_floats_refuses_as_the_constructor(bad):
    sys_, mb = _bounds("spring")
    lo, hi = sys_.prior_lo, sys_.prior_hi
    mean, std = ((lo + hi) / 2).tolist(), ((hi - lo) / 7).tolist()
    lo_env, hi_env = mb[1]
    change = {"nan_mean": ("m", float("nan")), "inf_mean": ("m", float("inf")),
              "far_mean": ("m", hi_env + 10 * (hi_env - lo_env)), "neg_std": ("s", -1e-3),
              "nan_std": ("s", float("nan"))}
    if bad == "short_std":
        std = std[:-1]
    else:
        which, v = change[bad]
        (mean if which == "m" else std)[1] = v
    kw = dict(seed=(0, 1), n_samples=10, bounds=None, system="spring")
    with pytest.raises(ValueError) as want:
        LazyPosterior(np.array(mean), np.array(std), {}, loc=np.array(mean), **kw)
    with pytest.raises(ValueError) as got:
        LazyPosterior.from_floats(mean, std, {}, mean_bounds=mb, **kw)
    assert str(got.value) == str(want.value)


@pytest.mark.parametrize("system", SYSTEMS)
@pytest.mark.parametrize("clip", [True, False])
def test_push_head_gives_the_array_paths_bytes(system, clip):
    from methods.vid2param.data import make_system_split

    est = methods.get("vid2param", system=system, device="cpu", clip=clip, n_samples=40,
                      seed=3)
    model = est._model()
    frames = np.asarray(make_system_split(system, "test", 1, 7, 60,
                                          model._net.config.frame_size).frames[0])
    fast = est.stream()
    assert fast._head is not None  # std_scale only: the shipped models take the head
    ref = est.stream()
    ref._head = None  # the array path (PointsModel._points, Pipeline.step, _params)
    for k, f in enumerate(frames):
        a = fast.push(f)
        b = ref.push(f)
        assert a.extras["n_frames"] == b.extras["n_frames"] == k + 1
        _same(a, b)
        assert fast.position().tobytes() == ref.position().tobytes()
    # no samples asked: the array path answers, as before
    est.n_samples = 0
    post = fast.push(frames[0])
    assert post.samples is None and post.extras["n_frames"] == len(frames) + 1
    # the torch modules after a reset (as the benchmark's reference stream): the head is
    # not used without the NumPy filter
    slow = est.stream()
    slow._fast, slow._state = None, model._net.init_state(1)
    assert slow._head is not None and slow.push(frames[0]).extras["n_frames"] == 1
    # a reset builds the head again from the same stages
    factors = fast._head.factors
    fast.reset()
    assert fast._head is not None and fast._head.factors == factors


@pytest.mark.parametrize("system", SYSTEMS)
def test_head_only_for_stages_it_knows(system):
    from methods.vid2param.stages import Stage

    model = methods.get("vid2param", system=system, device="cpu")._model()

    class PassThrough(Stage):
        name = "test_pass"

    class Changes(Stage):
        name = "test_changes"

        def step(self, carry, mu, sd, pos):
            return mu, sd * 2.0

    stages = list(model._pipeline.stages)
    try:
        model._pipeline.stages = stages + [PassThrough({})]
        head = _StreamHead.of(model)
        assert head is not None and head.factors == _StreamHead.of(model).factors
        assert head.factors and all(len(f) == 1 for f in head.factors)  # one std_scale
        model._pipeline.stages = stages + [Changes({})]
        assert _StreamHead.of(model) is None
        stream = model.stream()  # the array path runs the stage
        assert stream._head is None
        assert np.isfinite(stream.push(np.zeros(model.frame_size, np.uint8)).mean).all()
    finally:
        model._pipeline.stages = stages
