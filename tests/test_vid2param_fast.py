"""The NumPy single-frame path (methods/vid2param/fast.py) against the torch modules.

Why not rtol 1e-5 against torch over a whole video: the network's second-difference feature
multiplies the fed-back position's rounding by 400, so any two float32 evaluations drift apart
over 200 frames -- torch's own batched ``filter`` and its single-frame ``push`` differ by up to
~7e-4 (camera model). The tests therefore compare each float32 path with a float64 evaluation of
the same weights: the NumPy path must be no further from it than torch's batched filter is
(within a factor), and exact to float32 rounding on the first frames, before any amplification.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from methods.vid2param import SHIPPED_CHECKPOINTS, Vid2Param
from methods.vid2param.fast import FrameFilter, LazyPosterior, Unsupported, fast_support
from sysid_bench.core.datasets import make_dataset

needs = {k: pytest.mark.skipif(not p.exists(), reason=f"no shipped {k} checkpoint")
         for k, p in SHIPPED_CHECKPOINTS.items()}


def _video(name: str) -> np.ndarray:
    """A 200-frame test video rendered as checkpoint ``name`` was trained (size, nuisances)."""
    from methods.vid2param.checkpoint import load_checkpoint

    tr = load_checkpoint(SHIPPED_CHECKPOINTS[name])["train"]
    return np.asarray(make_dataset("test", 1, 2024, size=tuple(tr["size"]),
                                   nuisance=tr.get("nuisance")).frames[0])


#: Every shipped checkpoint the NumPy path serves (all of them, on the CPU): the sensitivity
#: models and the changing model take the path as the two main ones do.
EVERY_SHIPPED = ("28x28", "camera", "changing",
                 *(f"sensitivity/{c.replace(':', '_')}" for c in (
                     "extrapolation:e", "extrapolation:g", "extrapolation:d", "extrapolation:r",
                     "noise:0", "noise:0.1", "noise:0.25", "noise:0.5", "simplified")))


def test_every_shipped_checkpoint_is_compared():
    assert set(SHIPPED_CHECKPOINTS) <= set(EVERY_SHIPPED)


@pytest.mark.parametrize("name", [pytest.param(n, marks=needs[n]) if n in needs else
                                  pytest.param(n, marks=pytest.mark.skip(reason=f"no {n}"))
                                  for n in EVERY_SHIPPED])
def test_numpy_filter_matches_torch_over_a_video(name):
    est = Vid2Param(checkpoint=name, device="cpu")
    net = est._ensure_net()
    assert fast_support(net) is None
    frames = _video(name)  # 200 frames
    with torch.inference_mode():
        mu, sd, state = net.filter(torch.as_tensor(frames[None]))
    torch_out = torch.cat([mu[0], sd[0]], -1).numpy().astype(np.float64)

    def run(dtype):
        ff = FrameFilter(net, dtype)
        return np.array([np.concatenate(ff.step(f)) for f in frames], np.float64), ff

    fast, ff32 = run(np.float32)
    ref, _ = run(np.float64)
    assert fast.shape == torch_out.shape == (200, 2 * net.config.latent)
    # the first frames: the same network to float32 rounding
    np.testing.assert_allclose(fast[:3], torch_out[:3], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ref[:3], torch_out[:3], rtol=1e-5, atol=1e-6)
    # the whole video: no further from the float64 evaluation than torch's float32 filter is
    err_fast = np.abs(fast - ref).max()
    err_torch = np.abs(torch_out - ref).max()
    assert err_fast <= 3 * err_torch + 1e-5, (err_fast, err_torch)
    np.testing.assert_allclose(fast, torch_out, atol=2e-3)
    # and the state after the last frame, in the torch layout
    numpy_state = ff32.torch_state()
    for f in ("h", "c", "last_pos", "last_vel", "n_seen", "roll"):
        a, b = getattr(numpy_state, f), getattr(state, f)
        assert (a is None) == (b is None) == (f == "roll" and not net.config.roll_features), f
        if a is not None:
            np.testing.assert_allclose(a.numpy(), b.numpy(), atol=5e-3, err_msg=f)


@needs["28x28"]
def test_push_uses_numpy_path_and_agrees_with_torch_path():
    est = Vid2Param(device="cpu", n_samples=16)
    frames = _video("28x28")[:40]
    fast = est.stream()
    assert fast._fast is not None  # the shipped checkpoint runs the NumPy path on the CPU
    slow = est.stream()
    slow._fast, slow._state = None, est.net_.init_state(1)  # force the torch modules
    for f in frames:
        a, b = fast.push(f), slow.push(f)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-4)
    np.testing.assert_allclose(a.std, b.std, rtol=1e-4)
    assert a.extras["n_frames"] == b.extras["n_frames"] == 40
    # samples: the same keyed noise on either path
    np.testing.assert_allclose(a.samples, b.samples, rtol=1e-3, atol=1e-6)
    # the state round-trips through the torch layout
    st = fast.state
    fast.state = st
    np.testing.assert_array_equal(fast.state.h.numpy(), st.h.numpy())
    np.testing.assert_array_equal(fast.state.roll.numpy(), st.roll.numpy())


@needs["28x28"]
def test_reset_restarts_and_weights_change_is_picked_up():
    est = Vid2Param(device="cpu", n_samples=0)
    frames = _video("28x28")[:10]
    s = est.stream()
    first = [s.push(f).mean for f in frames]
    s.reset()
    again = [s.push(f).mean for f in frames]
    np.testing.assert_array_equal(np.array(first), np.array(again))
    ff = s._fast
    with torch.no_grad():
        est.net_.posterior.mlp[2].bias.add_(0.01)  # an in-place change, as an optimiser step makes
    try:
        s.reset()
        assert s._fast is not ff  # weights copied again
        changed = [s.push(f).mean for f in frames]
        assert not np.allclose(np.array(changed), np.array(first))
    finally:
        with torch.no_grad():
            est.net_.posterior.mlp[2].bias.sub_(0.01)


@needs["camera"]
def test_numpy_filter_matches_torch_with_the_run_fit_statistic():
    """The shipped camera network given the run-fit rolling statistic (as a fine-tune from it
    starts), over a rolling camera video: the NumPy path's posteriors and its float64 rolling
    columns are the torch filter's."""
    from methods.vid2param.checkpoint import load_checkpoint
    from methods.vid2param.data import rolls_mask
    from methods.vid2param.model import V2PConfig, Vid2ParamNet
    from methods.vid2param.parts import RunFits
    from methods.vid2param.presets import PRESETS
    from methods.vid2param.train import load_matching

    cfg = load_checkpoint(SHIPPED_CHECKPOINTS["camera"])["config"]
    net = Vid2ParamNet(V2PConfig.from_dict({**cfg, "roll_features": True, "roll_stat": "fit"}))
    load_matching(net, SHIPPED_CHECKPOINTS["camera"])
    net.eval()
    assert fast_support(net) is None
    ds = make_dataset("test", 12, 5, size=(50, 100), nuisance=PRESETS["camera"].train["nuisance"])
    with torch.inference_mode():
        mu, sd, state = net.filter(torch.as_tensor(np.asarray(ds.frames)))
    count = RunFits.summary(state.roll)[0][:, 0].numpy()
    assert (count[~rolls_mask(ds.states, ds.floor)] == 0).all()  # no roll where none is
    i = int(np.flatnonzero(count)[0])  # a video whose rolls were found
    ff = FrameFilter(net, np.float64)
    fast = np.array([np.concatenate(ff.step(f)) for f in np.asarray(ds.frames[i])])
    np.testing.assert_allclose(fast, torch.cat([mu[i], sd[i]], -1).numpy(), atol=2e-3)
    got = ff.torch_state().roll[0]
    assert got.dtype == state.roll.dtype == torch.float64
    assert RunFits.summary(got[None])[0].item() == count[i]  # the same rolling frames
    # the run sums to 1e-4; the finished runs' weighted deceleration (column 12, a parabola's
    # curvature from float32 positions times length^3) to what r needs: its mean to 1e-3 m/s^2
    # (measured 3e-5 apart with the 4500-step camera network)
    cols = [c for c in range(14) if c != 12]
    np.testing.assert_allclose(got.numpy()[cols], state.roll[i].numpy()[cols], rtol=1e-4, atol=1e-4)
    assert abs(RunFits.summary(got[None])[1].item()
               - RunFits.summary(state.roll[i:i + 1])[1].item()) < 1e-3
    ff.set_torch_state(state.map(lambda t: t[i:i + 1]))  # and back
    np.testing.assert_array_equal(np.array(ff.stats), state.roll[i].numpy())
    with pytest.raises(ValueError, match="14 rolling columns"):  # a steps-statistic state
        ff.set_torch_state(state.map(lambda t: t[i:i + 1, :3]))


def test_unsupported_network_falls_back_to_torch(tmp_path):
    from methods.vid2param.fast import frame_filter_for
    from methods.vid2param.model import V2PConfig, Vid2ParamNet

    net = Vid2ParamNet(V2PConfig(latent=8, hidden=16, feat=16, channels=(4, 8)))
    assert fast_support(net) is None
    net.posterior.mlp[1] = torch.nn.Tanh()  # a part built otherwise than the NumPy path knows
    with pytest.raises(Unsupported, match="mlp"):
        FrameFilter(net)
    assert "mlp" in fast_support(net) and frame_filter_for(net, "cpu") is None
    with pytest.raises(ValueError, match="dtype"):
        FrameFilter(net, np.float16)


def test_lazy_posterior_draws_when_read_and_is_keyed():
    # a ball posterior within the prior (g negative: Posterior checks the physics' envelope)
    from sysid_bench.core.physics import PARAMS, PRIOR

    lo, hi = (np.array([PRIOR[p][k] for p in PARAMS]) for k in (0, 1))
    loc, std = (lo + hi) / 2, (hi - lo) / 5

    def make(seed=(3, 0, 7)):
        return LazyPosterior(loc, std, {}, loc=loc, seed=seed, n_samples=50, bounds=(lo, hi))

    a = make()
    assert a.__dict__["_draw"] is not None  # nothing drawn yet
    s = a.samples
    assert s.shape == (50, 4) and (s >= lo).all() and (s <= hi).all()
    assert a.samples is s
    expect = np.clip(loc + std * np.random.default_rng([3, 0, 7]).standard_normal((50, 4)), lo, hi)
    np.testing.assert_array_equal(s, expect)
    # another key, other samples; same key, same bytes whatever was read before
    assert not np.array_equal(make((3, 0, 8)).samples, s)
    np.testing.assert_array_equal(make().samples, s)
    # picklable before and after the draw; interval uses the samples
    b = pickle.loads(pickle.dumps(make()))
    np.testing.assert_array_equal(b.samples, s)
    lo90, hi90 = a.interval(0.9)
    np.testing.assert_allclose(lo90, np.quantile(s, 0.05, axis=0))
    a.samples = None
    assert a.samples is None


def _fused_cases():
    from methods.vid2param._points import SYSTEM_CHECKPOINTS

    cases = [pytest.param(("ball", n), marks=needs[n]) for n in ("28x28", "camera", "changing")]
    cases += [pytest.param((s, None), marks=pytest.mark.skipif(not p.is_file(),
                                                              reason=f"no {s} model"))
              for s, p in SYSTEM_CHECKPOINTS.items()]
    return cases


@pytest.mark.parametrize("case", _fused_cases(), ids=lambda c: c[1] or c[0])
def test_fused_passes_are_numpys_bytes(case):
    """The compiled elementwise passes (pooling, keypoint heats, the LSTM's gate arithmetic)
    give the bytes of the numpy calls they replace: every output and the state, every frame
    (uint8 frames, and float frames with fractions)."""
    system, name = case
    if system == "ball":
        net = Vid2Param(checkpoint=name, device="cpu")._ensure_net()
        frames = _video(name)[:120]
    else:
        from methods.vid2param.data import make_system_split

        net = Vid2Param(system=system, device="cpu")._model()._net
        frames = np.asarray(make_system_split(system, "test", 1, 11, 120,
                                              net.config.frame_size).frames[0])
    rng = np.random.default_rng(5)
    frames_f = np.clip(frames + rng.uniform(-0.5, 0.5, frames.shape), 0, 255)
    # dtypes the fused pass leaves to numpy: the same numbers either way
    odd = [frames_f[:3].astype(">f8"), frames_f[:3].astype(np.float16), frames[:3].tolist()]
    for video in (frames, frames_f, *odd):
        fused, ref = FrameFilter(net), FrameFilter(net, fused=False)
        assert fused.fused and not ref.fused
        for f in video:
            (m1, s1), (m2, s2) = fused.step(f), ref.step(f)
            assert m1.tobytes() == m2.tobytes() and s1.tobytes() == s2.tobytes()
            assert fused.enc_in.tobytes() == ref.enc_in.tobytes()
            assert fused.lstm_in.tobytes() == ref.lstm_in.tobytes()


@needs["28x28"]
def test_fused_argument_is_checked():
    net = Vid2Param(device="cpu")._ensure_net()
    assert not FrameFilter(net, np.float64).fused  # the float64 reference: numpy calls
    with pytest.raises(ValueError, match="fused"):
        FrameFilter(net, np.float64, fused=True)
    with pytest.raises(ValueError, match="fused"):
        FrameFilter(net, fused="yes")
