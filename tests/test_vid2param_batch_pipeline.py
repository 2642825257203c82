"""``Vid2Param.identify_batch`` with its checks overlapped on a second thread (issue 39, section 1).

The pipelined batch (the network on one chunk of videos while the previous chunk's checks run)
must give the answers of one network pass followed by one ``check_batch`` of the whole batch,
in video order: the same verdicts and notes, and means, stds, samples and check RMS equal up to
the float order of the network's matrix products over fewer rows (bitwise on the AVX2
development machine; another CPU's BLAS may choose another kernel for a smaller batch).
"""

from __future__ import annotations

import numpy as np
import pytest

import methods.vid2param.estimator as v2p_estimator
from methods.vid2param import SHIPPED_CHECKPOINT, Vid2Param
from sysid_bench.core.datasets import make_dataset

pytestmark = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")


def _assert_same(a, b) -> None:
    assert len(a) == len(b)
    for p, q in zip(a, b):
        assert (p.check.ok, p.check.note, p.check.n) == (q.check.ok, q.check.note, q.check.n)
        np.testing.assert_allclose(q.check.rms_m, p.check.rms_m, rtol=1e-4)
        for name in ("mean", "std", "samples"):
            np.testing.assert_allclose(getattr(q, name), getattr(p, name), rtol=1e-5, atol=1e-7)
        assert sorted(p.extras) == sorted(q.extras)


def test_pipelined_batch_gives_the_bytes_of_one_pass(one_thread, monkeypatch):
    videos = np.asarray(make_dataset("test", 23, 2024).frames[:, :80])
    # a video no trajectory explains: its check fails and widens, on the worker thread too
    videos[5] = videos[5][np.arange(80) % 2 * 40]
    est = Vid2Param(device="cpu", seed=3)
    monkeypatch.setattr(v2p_estimator, "PIPELINE_CHUNK", 10**6)
    whole = est.identify_batch(videos)
    calls = []
    real = v2p_estimator.check_batch
    monkeypatch.setattr(v2p_estimator, "check_batch",
                        lambda posts, *a: calls.append(len(posts)) or real(posts, *a))
    monkeypatch.setattr(v2p_estimator, "PIPELINE_CHUNK", 7)
    piped = est.identify_batch(videos)
    assert calls == [5, 6, 6, 6]  # four equal chunks, none smaller than the others
    assert all(p.check is not None for p in piped)
    assert not whole[5].check.ok and not piped[5].check.ok
    _assert_same(whole, piped)
    # the chunk is also capped by ``batch`` (videos per network pass)
    est.set_params(batch=5)
    calls.clear()
    _assert_same(whole, est.identify_batch(videos))
    assert calls == [4, 5, 4, 5, 5]


def test_pipelined_batch_raises_a_check_error_of_the_worker(one_thread, monkeypatch):
    videos = np.asarray(make_dataset("test", 4, 2024).frames[:, :40])
    est = Vid2Param(device="cpu")
    monkeypatch.setattr(v2p_estimator, "PIPELINE_CHUNK", 2)

    def broken(*args, **kwargs):
        raise RuntimeError("check failed to run")

    monkeypatch.setattr(v2p_estimator, "check_batch", broken)
    with pytest.raises(RuntimeError, match="check failed to run"):
        est.identify_batch(videos)
    # unchecked, the pipeline is not used and nothing calls the checks
    assert all(p.check is None for p in est.identify_batch(videos, check=False))
