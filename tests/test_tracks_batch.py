"""``methods._tracks_batch.prepare_batch``: bitwise ``methods._tracks.prepare``'s Tracks.

``check_batch`` (``identify_batch``'s checks, issue 39) prepares every video with
``prepare_batch``; its checks are only those of the per-video path if each Track is the same to
the last bit (floor, start and its errors, segments, contacts). Compared here on tracked test
videos (as ``check_batch`` tracks them) and on noisy, dropped, known-floor, known-start and
shorter tracks (another group), and on what ``prepare`` refuses.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from methods._tracks import prepare
from methods._tracks_batch import prepare_batch
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation
from sysid_bench.core.physics import BOX_WIDTH
from sysid_bench.core.tracking import track_batch


@pytest.fixture(scope="module")
def observations() -> list[Observation]:
    data = make_dataset("test", 12, 2024)
    tracked = track_batch(np.asarray(data.frames), 0.0)
    tracked[..., 0] = np.clip(tracked[..., 0], 0.0, BOX_WIDTH)  # as check_batch
    obs = [Observation(positions=p) for p in tracked]
    rng = np.random.default_rng(7)
    truth = np.asarray(data.states)[..., :2]
    for i in range(6):  # noisy truth, some frames dropped
        p = np.clip(truth[i] + rng.normal(0.0, 0.01, truth[i].shape), 0.0, BOX_WIDTH)
        p[rng.random(len(p)) < 0.1] = np.nan
        obs.append(Observation(positions=p))
    obs.append(Observation(positions=truth[6], floor=0.0))  # known floor
    obs.append(Observation(positions=truth[7], state0=np.asarray(data.states)[7, 0]))
    obs.append(Observation(positions=truth[8, :120]))  # another length: its own group
    obs.append(Observation(positions=truth[9, :120] + 0.003))
    few = np.full_like(truth[10], np.nan)
    few[:2] = truth[10, :2]
    obs.append(Observation(positions=few))  # 2 seen frames: prepare refuses
    return obs


def test_prepare_batch_gives_prepare_s_tracks_bit_for_bit(observations):
    got = prepare_batch(observations)
    assert len(got) == len(observations)
    n_contacts = 0
    for i, (obs, track) in enumerate(zip(observations, got)):
        try:
            want = prepare(obs)
        except ValueError:
            assert track is None, i
            continue
        assert track is not None, i
        # every field, arrays and contacts included, to the byte
        assert pickle.dumps(track) == pickle.dumps(want), i
        n_contacts += len(track.segments.contacts)
    assert got[-1] is None  # the 2-frame track
    assert n_contacts >= 10  # the bounces' polynomial fits and roots were compared


def test_prepare_batch_refuses_what_is_not_an_observation(observations):
    assert prepare_batch([]) == []
    with pytest.raises(ValueError, match=r"observations\[1\]: expected .*Observation, got ndarray"):
        prepare_batch([observations[0], np.zeros((10, 2))])
