"""The training recurrence's written-out backward pass (``methods.vid2param._recurrence``)
gives autograd's gradients: float64 to rounding, float32 to float order."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import methods.vid2param.model as model
from methods.vid2param._recurrence import ObservedRecurrence
from methods.vid2param.model import V2PConfig, Vid2ParamNet


def _net(system: str, dtype, **small):
    torch.manual_seed(3)
    c = V2PConfig.preset(system)
    if small:
        c = dataclasses.replace(c, **small)
    net = Vid2ParamNet(c).to(dtype)
    if dtype != torch.float32:  # the reference loop starts from init_state's float32 zeros
        init = net.recurrence.init_state
        net.recurrence.init_state = lambda b, device=None: dataclasses.replace(
            init(b, device), **{k: getattr(init(b, device), k).to(dtype)
                                for k in ("h", "c", "last_pos", "last_vel", "n_seen")})
    with torch.no_grad():  # a gate away from 0, so the network's own means count too
        net.keypoints.gate.fill_(0.3)
    return net


def _grads(net, fx, written: bool, monkeypatch):
    monkeypatch.setattr(model, "WRITTEN_BACKWARD", written)
    net.zero_grad()
    x = fx.detach().clone().requires_grad_(True)
    hs, (mu, sd), st = net._observed_pass(x)
    w = torch.linspace(-1, 1, mu.numel(), dtype=mu.dtype).reshape(mu.shape)
    loss = ((torch.stack(hs, 1) ** 2).mean() + (mu * w).sum() + sd.log().sum()
            + st.h.sum() + (st.c ** 2).sum() + (st.last_pos * 3).sum() + st.last_vel.sum())
    loss.backward()
    out = {"fx": x.grad, "mu": mu.detach(), "sd": sd.detach(), "h": st.h.detach()}
    out.update({k: p.grad.clone() for k, p in net.named_parameters() if p.grad is not None})
    return out


@pytest.mark.parametrize("system", ["pendulum", "collision"])
def test_written_backward_gives_autograds_gradients_in_float64(system, monkeypatch):
    net = _net(system, torch.float64, hidden=6, feat=5)
    fx = torch.randn(3, 7, net.encoder.n_out, dtype=torch.float64)
    got, want = (_grads(net, fx, w, monkeypatch) for w in (True, False))
    assert got.keys() == want.keys() and len(got) > 8
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=1e-10, atol=1e-12, msg=k)


def test_written_backward_in_float32_on_the_pendulum_preset(monkeypatch):
    net = _net("pendulum", torch.float32)
    fx = torch.randn(4, 40, net.encoder.n_out)
    got, want = (_grads(net, fx, w, monkeypatch) for w in (True, False))
    for k in ("mu", "sd", "h"):  # the forward pass: the same operations
        assert torch.equal(got[k], want[k]), k
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=1e-4, atol=1e-5, msg=k)


def test_the_function_passes_gradcheck():
    torch.manual_seed(0)
    T, B, H1, Z, F, hid, n = 4, 2, 5, 6, 3, 4, 2
    d = dict(dtype=torch.float64, requires_grad=True)
    args = (torch.randn(T, B, H1, **d), torch.rand(Z, **d), torch.randn(T, B, Z, **d) * 0.1,
            torch.randn(2 * hid, H1, **d), torch.randn(H1, 2 * Z, **d), torch.randn(2 * Z, **d),
            torch.randn(Z, F, **d), torch.randn(F, **d),
            torch.randn(F + 2 * n + hid, 4 * hid, **d) * 0.5, torch.randn(4 * hid, **d))
    consts = (1, n, 0.7, 0.3, 1e-3)
    assert torch.autograd.gradcheck(lambda *a: ObservedRecurrence.apply(*a, consts), args)
