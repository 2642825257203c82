"""Batched model checks (``methods._check_batch``, issue 39): the per-video checks' verdicts."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from methods._check_batch import check_batch
from methods._simulation import check_prefixes
from methods.vid2param import SHIPPED_CHECKPOINT, Vid2Param
from methods.vid2param.estimator import DEFAULT_SIGMA
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation

needs_model = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")


def _videos() -> np.ndarray:
    v = np.asarray(make_dataset("test", 3, 2024).frames)
    # a ball jumping between two places every frame: no trajectory explains it
    jumps = v[1:2, np.arange(v.shape[1]) % 2 * 60]
    blank = np.zeros_like(v[:1])  # nothing to track: the per-video path says why
    return np.concatenate([v, jumps, blank])


@needs_model
def test_batched_checks_pass_a_ball_and_fail_what_no_trajectory_explains(one_thread):
    v = _videos()[[0, 3, 4]]
    posts = Vid2Param(device="cpu").identify_batch(v)  # check_batch inside
    assert posts[0].check.ok and not posts[1].check.ok and not posts[2].check.ok
    assert posts[2].check.note.startswith("no track to check")
    assert posts[1].extras["check_failed"] and posts[1].check.rms_m > 0.1
    assert 0 < posts[0].extras["check_simulations"] < 400


@needs_model
@pytest.mark.slow  # the per-video checks it compares with: ~5-20 s on a busy 2-core machine
def test_batched_checks_give_the_per_video_verdicts(one_thread):
    videos = _videos()
    est = Vid2Param(device="cpu")
    posts = est.identify_batch(videos, check=False)
    T = videos.shape[1]
    old = [check_prefixes([copy.deepcopy(p)], Observation(frames=v), [T], DEFAULT_SIGMA)[0]
           for p, v in zip(posts, videos)]
    new = check_batch([copy.deepcopy(p) for p in posts], videos, DEFAULT_SIGMA)
    assert [p.check.ok for p in new] == [p.check.ok for p in old]
    assert not new[3].check.ok and not new[4].check.ok
    assert new[4].check.note == old[4].check.note  # "no track to check: ..."
    for a, b in zip(old, new):
        # the same kind of verdict (mean / region / widened), the same widening to the prior
        assert a.check.note.split(":")[0][:20] == b.check.note.split(":")[0][:20]
        assert a.extras.get("check_failed") == b.extras.get("check_failed")
        assert a.extras.get("uninformed") == b.extras.get("uninformed")
        np.testing.assert_array_equal(a.mean, b.mean)
        assert b.extras["check_simulations"] > 0 or not np.isfinite(b.check.rms_m)
    # the batched path simulates less (one video's old check: ~480 simulations)
    assert (sum(p.extras["check_simulations"] for p in new[:3])
            < sum(p.extras["check_simulations"] for p in old[:3]))
    # identify_batch runs them
    got = est.identify_batch(videos)
    assert [p.check.ok for p in got] == [p.check.ok for p in new]


def test_check_batch_bad_input():
    assert check_batch([], np.zeros((0, 10, 28, 28)), DEFAULT_SIGMA) == []
    with pytest.raises(ValueError, match="frames"):
        check_batch([None, None], np.zeros((3, 10, 28, 28)), DEFAULT_SIGMA)
