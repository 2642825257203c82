"""Vid2Param's network as named parts: the shipped checkpoints give the numbers they gave before.

``tests/data/vid2param_shipped_outputs.npz`` holds what both shipped checkpoints answered on a
few small seeded videos (filter means and stds, the recurrent state's read-out, the learned
prior's and the physics prior's rollouts, the training pass's loss terms and gradient size, the
stream's pushes on both its paths, forecasts), written by this file's ``__main__`` with the
network as it was before it was split into parts. Regenerate only for a deliberate change of
the numbers: ``PYTHONPATH=. python tests/test_vid2param_parts.py``. The camera model's forecasts
were re-recorded after changes of the forecast, not of the network: the state fit drops
misread frames; its physics prior's noise was refitted (so its physics rollout too); with the floor given, heights are put
on it from above the fitted floor. The training pass's loss terms and gradient size were re-recorded when the
forecast frames' fed-back positions were kept in the box (as ``rollout`` keeps them). Both
models' physics-prior rollouts (sampled, so their means too) and forecast stds were re-recorded
when the prior's noise learnt to read the backtest and was recalibrated (forecast means
unchanged). The camera model's entries were all re-recorded when its checkpoint was replaced
by the camera preset's model (``_write_fixture(["camera"])``), and again when that checkpoint
gained its drag evidence (``methods.vid2param.drag``: d of identify, the pushes and the
forecasts moved; the network's own outputs by float rounding only, from the channels_last
keypoint convolution, within the tolerances). Every other entry is as recorded before the split.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from methods.vid2param import SHIPPED_CHECKPOINTS, Vid2Param
from methods.vid2param.checkpoint import build_net, load_checkpoint
from methods.vid2param.data import targets_from_arrays
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation
from sysid_bench.core.physics import simulate
from sysid_bench.core.render import render

FIXTURE = Path(__file__).parent / "data" / "vid2param_shipped_outputs.npz"
N_FRAMES = 60
#: A ball rolling from the first frame (seeded test videos rarely roll within 60 frames): the
#: 28x28 model's rolling statistic and its blend into r have something to read.
ROLL_THETA = np.array([0.8, -9.81, 0.02, 0.4])
ROLL_STATE0 = np.array([1.0, 0.0, 3.0, 0.0])
needs = {k: pytest.mark.skipif(not p.exists(), reason=f"no shipped {k} checkpoint")
         for k, p in SHIPPED_CHECKPOINTS.items()}


def _videos(name: str):
    """The checkpoint, frames (3, T, H, W) and targets (3, T, K): two seeded test videos (with
    the camera nuisances for the camera model) and the rolling ball."""
    ck = load_checkpoint(SHIPPED_CHECKPOINTS[name])
    size = tuple(ck["config"]["frame_size"])
    nuis = dict(ck["train"].get("nuisance") or {})
    ds = make_dataset("test", 2, 31, n_frames=N_FRAMES, size=size, nuisance=nuis or None)
    states = simulate(ROLL_THETA[None], ROLL_STATE0[None], N_FRAMES)
    nuis.pop("floor_offset", None)
    rolling = render(states, size, seed=5, **nuis)
    frames = np.concatenate([np.asarray(ds.frames), rolling])
    targets = targets_from_arrays(
        np.concatenate([ds.states, states]),
        np.concatenate([ds.labels, np.broadcast_to(ROLL_THETA, (1, N_FRAMES, 4))]),
        np.append(ds.floor, 0.0), ck["config"]["targets"])
    return ck, frames, targets


def _outputs(name: str) -> dict[str, np.ndarray]:
    """Everything the pinned checkpoint answers on its videos (see the module docstring)."""
    torch.manual_seed(0)
    ck, frames_np, targets = _videos(name)
    net = build_net(ck)
    frames = torch.as_tensor(frames_np)
    out = {}
    with torch.no_grad():
        mu, sd, state = net.filter(frames)
        out["filter_mu"], out["filter_std"] = mu.numpy(), sd.numpy()
        out["read"] = net.read(state).numpy()
        out["last_position"] = net.last_position(state).numpy()
        rollout = net.rollout(state, 12, generator=torch.Generator().manual_seed(1))
        for k, v in zip(("rollout_mu", "rollout_std", "rollout_z"), rollout):
            out[k] = v.numpy()
        phys = torch.tensor([[2.0, 6.0, 5.0, 3.5], [8.0, 1.0, -6.0, -4.0]])
        theta = torch.tensor([[0.8, -9.81, 0.02, 0.3], [0.6, -5.0, 0.1, 0.5]])
        rollout = net.rollout_physics(phys, theta, 15, generator=torch.Generator().manual_seed(2))
        for k, v in zip(("physics_mean", "physics_std", "physics_z"), rollout):
            out[k] = v.numpy()
    # the training pass: loss terms (some frames forecast) and the gradient's size
    tg = torch.as_tensor(targets)
    net.train()
    terms = net(frames, tg, n_obs=40, rec_frac=0.5, generator=torch.Generator().manual_seed(3))
    terms["loss"].backward()
    net.eval()
    for k, v in terms.items():
        out["train_" + k] = v.detach().numpy()
    out["train_grad_sq"] = np.array(sum(float((p.grad.double() ** 2).sum())
                                        for p in net.parameters() if p.grad is not None))
    # the estimator: pushes on the NumPy and torch paths, identify, forecasts
    est = Vid2Param(checkpoint=name, device="cpu", n_samples=16, seed=4)
    obs = Observation(frames=frames_np[-1])
    for path in ("fast", "torch"):
        s = est.stream()
        if path == "torch":
            s._fast, s._state = None, est._ensure_net().init_state(1)
        posts = [s.push(f) for f in obs.frames]
        out[f"push_{path}_mean"] = np.array([p.mean for p in posts])
        out[f"push_{path}_std"] = np.array([p.std for p in posts])
        fc = s.forecast(10)
        out[f"push_{path}_forecast_mean"], out[f"push_{path}_forecast_std"] = fc.mean, fc.std
    post = est.identify(obs)
    out["identify_mean"], out["identify_std"] = post.mean, post.std
    fc = est.forecast(obs.prefix(50), 10)
    out["forecast_mean"], out["forecast_std"] = fc.mean, fc.std
    return out


#: the outputs were pinned with the torch the project pins (pyproject: torch==2.13.0); another
#: torch computes the float32 network with other kernels (torch 2.11 on an Intel Xeon: up to
#: 1.4e-4 apart), so there the test checks the same outputs to 1e-3
_PIN_TOL = 1e-5 if torch.__version__.split("+")[0] == "2.13.0" else 1e-3
#: the training pass's terms are sums over every frame and parameter, computed by the training
#: path's own kernels (``FrameEncoder.train_features``: channels_last convolutions, one product
#: for the keypoint centres), which order their float32 sums otherwise than ``forward``; the
#: camera's squared gradient size (~1.8e9, a few large NLL gradients) moves by 1.9e-5 of itself
#: with them. Inference, which users' answers come from, stays at ``_PIN_TOL``.
_TRAIN_TOL = max(_PIN_TOL, 1e-4)


@pytest.mark.parametrize("name", [pytest.param("28x28", marks=needs["28x28"]),
                                  pytest.param("camera", marks=needs["camera"])])
def test_shipped_checkpoints_give_the_pinned_outputs(name):
    want = np.load(FIXTURE)
    got = _outputs(name)
    keys = sorted(k.split("/", 1)[1] for k in want.files if k.startswith(name + "/"))
    assert keys == sorted(got), "the fixture and _outputs name different outputs"
    for k in keys:
        if k == "identify_std":
            # the model check (issue 29) widens identify's intervals where the track does not
            # inform a parameter or the fit fails (to the best fit's distance, or the prior's):
            # the network's own std, pinned, is a lower bound
            assert np.all(got[k] >= want[f"{name}/{k}"] * (1 - 1e-5)), f"{name}: {k} narrowed"
            continue
        tol = _TRAIN_TOL if k.startswith("train_") else _PIN_TOL
        np.testing.assert_allclose(got[k], want[f"{name}/{k}"], rtol=tol, atol=tol,
                                   err_msg=f"{name}: {k}")


def test_a_removed_option_loads_at_its_fixed_value_and_is_refused_at_another():
    from methods.vid2param.model import REMOVED, V2PConfig

    d = V2PConfig().to_dict()
    assert not set(REMOVED) & set(d)
    # older checkpoints store the removed options: at the value the network has, they load
    assert V2PConfig.from_dict({**d, **REMOVED}) == V2PConfig()
    other = {"recur_noise": 1.0, "pixel_skip": True, "diff_features": False, "read_cell": False,
             "prior_residual": False, "layers": 2}
    assert set(other) == set(REMOVED)
    for name, value in other.items():
        with pytest.raises(ValueError, match=f"'{name}' was removed"):
            V2PConfig.from_dict({**d, name: value})
    with pytest.raises(ValueError, match="keypoints: expected an int >= 1"):
        V2PConfig(keypoints=0)
    with pytest.raises(TypeError):
        V2PConfig(recur_noise=0.0)


def test_older_weight_names_load_and_an_older_training_state_resumes_in_place():
    """The renaming (``checkpoint.RENAMED``) also moved parameters: Adam's per-parameter state,
    kept by position, must follow them."""
    from methods.vid2param.checkpoint import RENAMED, upgrade_optimizer_state, upgrade_state_dict
    from methods.vid2param.model import V2PConfig, Vid2ParamNet

    torch.manual_seed(0)
    net = Vid2ParamNet(V2PConfig(latent=8, hidden=16, feat=16, channels=(4, 8)))
    opt = torch.optim.Adam(net.parameters())
    for p in net.parameters():
        p.grad = torch.randn_like(p)
    opt.step()
    # the same weights and state as an older network saved them: old names, its order
    back = {new: old for old, new in RENAMED.items()}
    def old_name(name):
        for new, old in back.items():
            if name == new or (new.endswith(".") and name.startswith(new)):
                return old + name[len(new):]
        return name
    names = [n for n, _ in net.named_parameters()]
    old_order = sorted(range(len(names)), key=lambda i: old_name(names[i]))
    sd = {old_name(names[i]): net.state_dict()[names[i]] for i in old_order}
    st = opt.state_dict()
    saved = {"state": {j: st["state"][i] for j, i in enumerate(old_order)},
             "param_groups": [{**st["param_groups"][0], "params": list(range(len(names)))}]}
    assert "cells.0.weight_ih" in sd and "kp_gate" in sd
    assert list(upgrade_state_dict(net.state_dict())) == list(net.state_dict())  # no-op
    torch.manual_seed(1)
    fresh = Vid2ParamNet(net.config)
    fresh.load_state_dict(upgrade_state_dict(sd))
    opt2 = torch.optim.Adam(fresh.parameters())
    opt2.load_state_dict(upgrade_optimizer_state(saved, sd, fresh))
    for (name, p), q in zip(net.named_parameters(), fresh.parameters()):
        torch.testing.assert_close(q, p, msg=name)
        torch.testing.assert_close(opt2.state[q]["exp_avg"], opt.state[p]["exp_avg"], msg=name)


def test_the_recurrent_state_is_named_and_maps_over_its_tensors():
    from methods.vid2param.model import V2PConfig, Vid2ParamNet

    net = Vid2ParamNet(V2PConfig(latent=8, hidden=16, feat=16, channels=(4, 8)))
    st = net.step_rnn(torch.rand(2, 8), net.init_state(2))
    assert st.h.shape == st.c.shape == (2, 16) and st.roll.shape == (2, 3)
    assert st.last_pos.shape == st.last_vel.shape == (2, 2) and st.n_seen.tolist() == [[1], [1]]
    wide = st.map(lambda t: t.repeat(3, 1))
    assert wide.h.shape == (6, 16) and wide.roll.shape == (6, 3)
    assert net.init_state(1).map(lambda t: t + 1).n_seen.item() == 1.0
    cam = Vid2ParamNet(V2PConfig.preset("camera"))
    roll = cam.init_state(1).roll  # the run-fit statistic keeps float64 sums
    assert roll.shape == (1, 14) and roll.dtype == torch.float64 and cam.rolling is not None
    assert cam.read(cam.init_state(1)).shape == (1, 2 * cam.config.hidden + 2)
    assert cam.read(cam.init_state(1)).dtype == torch.float32
    bare = Vid2ParamNet(V2PConfig(latent=8, hidden=16, feat=16, channels=(4, 8),
                                  roll_features=False))
    assert bare.init_state(1).roll is None and bare.rolling is None
    assert bare.read(bare.init_state(1)).shape == (1, 2 * 16)


@pytest.mark.parametrize("preset", ["default", "camera"])
def test_the_channels_last_keypoint_convolution_gives_the_nchw_numbers(preset, monkeypatch):
    import methods.vid2param.parts as parts
    from methods.vid2param.model import V2PConfig

    torch.manual_seed(0)
    c = V2PConfig() if preset == "default" else V2PConfig.preset("camera")
    enc = parts.FrameEncoder(c)
    frames = (torch.rand(6, *c.frame_size) ** 8 * 255).to(torch.uint8)

    def run(channels_last: bool):
        monkeypatch.setattr(parts, "KEYPOINT_CHANNELS_LAST", channels_last)
        enc.zero_grad()
        fx = enc(frames)
        fx.square().sum().backward()
        return fx.detach(), enc.kp.weight.grad.clone()

    (fx_cl, g_cl), (fx_old, g_old) = run(True), run(False)
    assert fx_cl.shape == (6, enc.n_out)
    torch.testing.assert_close(fx_cl, fx_old, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(g_cl, g_old, rtol=1e-4, atol=1e-5)
    with torch.no_grad():  # batches and single frames (im2col) agree too
        torch.testing.assert_close(enc(frames[:1]), enc(frames)[:1], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("preset", ["default", "camera", "pendulum", "collision", "one-keypoint"])
def test_the_training_encoder_path_gives_forwards_features(preset):
    """``FrameEncoder.train_features`` (``Vid2ParamNet.forward``'s path) is ``forward`` up to
    float order, gradients included (its convolutions run channels_last, the learned keypoints'
    centres are one product); channel 0's centre and mass and the pooled frames (the
    reconstruction target) bitwise."""
    import methods.vid2param.parts as parts
    from methods.vid2param.model import V2PConfig

    torch.manual_seed(0)
    c = {"default": V2PConfig(), "one-keypoint": V2PConfig(keypoints=1, pool=2)}.get(
        preset) or V2PConfig.preset(preset)
    enc = parts.FrameEncoder(c)
    frames = (torch.rand(2, 3, *c.frame_size) ** 8 * 255).to(torch.uint8)

    def run(fn):
        enc.zero_grad()
        fx = fn(frames)
        fx.square().sum().backward()
        return fx.detach(), [p.grad.clone() for p in enc.parameters() if p.grad is not None]

    (fx, grads), (fx_old, grads_old) = run(lambda f: enc.train_features(f)[0]), run(enc)
    assert fx.shape == (2, 3, enc.n_out) and len(grads) == len(grads_old) > 0
    torch.testing.assert_close(fx, fx_old, rtol=1e-5, atol=1e-6)
    for g, g_old in zip(grads, grads_old, strict=True):
        torch.testing.assert_close(g, g_old, rtol=1e-4, atol=1e-5)
    i, k = enc.n_out - 3 * c.keypoints, c.keypoints
    assert torch.equal(fx[..., i:i + 2], fx_old[..., i:i + 2])  # channel 0's centre
    assert torch.equal(fx[..., -k], fx_old[..., -k])  # and log mass
    pooled = enc.train_features(frames)[1]
    want = enc.pooled(frames.reshape(-1, 1, *c.frame_size).to(torch.float32) / 255.0)
    assert torch.equal(pooled, want.reshape(pooled.shape))


def _write_fixture(names=("28x28", "camera")) -> None:
    """Record ``names``' outputs; the fixture's entries of other checkpoints are kept."""
    arrays = dict(np.load(FIXTURE)) if FIXTURE.exists() else {}
    for name in names:
        arrays = {k: v for k, v in arrays.items() if not k.startswith(name + "/")}
        for k, v in _outputs(name).items():
            v = np.asarray(v)
            arrays[f"{name}/{k}"] = v.astype(np.float32) if v.dtype == np.float64 else v
    FIXTURE.parent.mkdir(exist_ok=True)
    np.savez_compressed(FIXTURE, **arrays)
    print(FIXTURE, FIXTURE.stat().st_size, "bytes")


if __name__ == "__main__":
    import sys

    torch.set_num_threads(1)
    _write_fixture(sys.argv[1:] or ("28x28", "camera"))


@pytest.mark.parametrize("preset", ["28x28", "camera", "collision"])
def test_the_fused_training_pass_gives_the_per_frame_posterior(preset):
    """``forward``'s fused recurrence (``_observed_pass``) is the per-frame ``filter`` up to
    floating-point order: the same posterior means (its ``mse`` terms), and its final state
    continues the forecast frames as ``step_rnn`` would."""
    from methods.vid2param.model import V2PConfig, Vid2ParamNet

    c = V2PConfig.preset(preset)
    torch.manual_seed(0)
    net = Vid2ParamNet(c)
    with torch.no_grad():
        net.keypoints.gate.fill_(0.3)  # the MLP's x, y enter the posterior too
    g = torch.Generator().manual_seed(3)
    frames = (torch.rand(2, 10, *c.frame_size, generator=g) * 255).to(torch.uint8)
    targets = torch.rand(2, 10, len(c.targets), generator=g)
    K = len(c.targets)
    with torch.no_grad():
        mu, _, _ = net.filter(frames)
        for n_obs in (10, 7):
            out = net(frames, targets, n_obs=n_obs, generator=torch.Generator().manual_seed(1))
            want = ((mu[:, :n_obs, :K] - targets[:, :n_obs]) ** 2).mean(1)
            torch.testing.assert_close(out["mse"], want, rtol=1e-4, atol=1e-7)
            _, _, state = net.filter(frames[:, :n_obs])
            hs, (qmu, _), got = net._observed_pass(net.encode_frames(frames[:, :n_obs]))
            assert len(hs) == n_obs and qmu.shape == (2, n_obs, c.latent)
            # the velocity feature multiplies the positions' float-order differences by its
            # scale (the collision's 259 against the ball's 10)
            tol = max(1.0, c.diff_scales[0] / 10.0)
            for f in dataclasses.fields(state):
                a, b = getattr(got, f.name), getattr(state, f.name)
                if b is not None:
                    torch.testing.assert_close(a, b, rtol=1e-4 * tol, atol=1e-5 * tol,
                                               msg=f.name)


@pytest.mark.parametrize("preset", ["pendulum", "collision", "camera", "28x28"])
def test_the_training_decoder_gives_the_inference_decoders_numbers(preset):
    """The decoder of a training step (NHWC, its one-channel layer as a convolution per output
    phase) computes the transposed convolutions' sums in another order: equal in float64, on
    frame sizes the layers crop (camera 25 x 50), and its weights get the same gradients."""
    from methods.vid2param.model import V2PConfig, Vid2ParamNet
    from methods.vid2param.parts import _phase_deconv

    torch.manual_seed(0)
    dec = Vid2ParamNet(V2PConfig.preset(preset)).double().decoder
    x = torch.randn(7, dec.fc[0].in_features, dtype=torch.float64)
    fz, h = x[:, :128], x[:, 128:]
    with torch.no_grad():
        plain = dec(fz, h)  # inference: the layers themselves
    trained = dec(fz, h)
    assert trained.shape == plain.shape == (7, *dec.size)
    assert torch.allclose(trained, plain, rtol=0, atol=1e-12)
    last = [m for m in dec.deconv if isinstance(m, torch.nn.ConvTranspose2d)][-1]
    u = torch.randn(3, last.in_channels, 5, 6, dtype=torch.float64)
    g1 = torch.autograd.grad((_phase_deconv(last, u) ** 2).sum(), [last.weight, last.bias])
    g2 = torch.autograd.grad((last(u) ** 2).sum(), [last.weight, last.bias])
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)
