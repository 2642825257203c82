"""The stream's device (issue 39): ``device="auto"`` streams single frames on the CPU.

No GPU here: CUDA is made to look available by monkeypatching ``torch.cuda.is_available``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import methods.vid2param.estimator as v2p_estimator
from methods.vid2param import SHIPPED_CHECKPOINT, Vid2Param
from methods.vid2param.inference import resolve_device, stream_device


def test_auto_streams_on_the_cpu_where_a_batch_would_use_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto").type == "cuda"  # the batch: the accelerator
    assert stream_device("auto").type == "cpu"  # a stream of single frames: the CPU
    # a device named explicitly is honoured by both
    assert stream_device("cuda").type == "cuda"
    assert stream_device("cpu").type == "cpu"


def test_auto_streams_on_the_cpu_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto").type == "cpu"
    assert stream_device("auto").type == "cpu"


def test_stream_device_rejects_a_bad_name():
    with pytest.raises(ValueError, match="device"):
        stream_device("gpu please")


@pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")
def test_ball_stream_chooses_the_cpu_with_auto(monkeypatch):
    # CUDA "available": the estimator's batch device would be CUDA; the network itself stays
    # on the CPU here (no GPU), so only the stream's own choice is under test
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    real = v2p_estimator.resolve_device
    monkeypatch.setattr(v2p_estimator, "resolve_device",
                        lambda d: torch.device("cpu") if d == "auto" else real(d))
    est = Vid2Param(device="auto")
    st = est.stream()
    assert st.device.type == "cpu"
    assert st._fast is not None  # the NumPy filter: the CPU path
    frames = np.zeros((3, 28, 28), dtype=np.float32)
    frames[:, 10:13, 10:13] = 1.0
    posts = [st.push(f) for f in frames]
    assert posts[-1].extras["n_frames"] == 3
    assert np.all(np.isfinite(posts[-1].mean))
