"""Where does a Vid2Param training run stand? Three read-only diagnostics of a ``state.pt``.

    PYTHONPATH=. python scripts/v2p_diagnose.py positions runs/X/state.pt
        RMSE of every supervised latent dimension (normalised units) on 50 test videos, and how
        far the second differences the LSTM is fed (diff_features) are from the true ones.
    PYTHONPATH=. python scripts/v2p_diagnose.py probe runs/X/state.pt [--h-only]
        Ridge regression from the final LSTM state ([h, c], or h) to e, g, d, r on 450 training
        videos, scored on 150 more, next to the encoder's own nMSE: is the evidence in the
        recurrence, and does the encoder read it out?
    PYTHONPATH=. python scripts/v2p_diagnose.py grads runs/X/state.pt
        Norm of each loss term's gradient on the LSTM weights and on all weights (one batch of
        16), with the model's aux_grad: which term shapes the recurrence?

Used on 2026-11-22 to find why CPU runs stayed at prior level (see README, Vid2Param).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from methods.vid2param.checkpoint import load_checkpoint
from methods.vid2param.data import make_split, targets_from_dataset
from methods.vid2param.model import V2PConfig, Vid2ParamNet, _scale_grad, gaussian_kl, gaussian_nll


def _load(path):
    ck = load_checkpoint(path)
    net = Vid2ParamNet(V2PConfig.from_dict(ck["config"]))
    net.load_state_dict(ck["state_dict"])
    print(f"{path}: step {ck['train']['step']}")
    return net.eval()


def positions(net) -> None:
    ds = make_split("test", 50, 5, net.config.frame_size, None, 200)
    tg = targets_from_dataset(ds, net.config.targets)
    with torch.no_grad():
        mu, sd, _ = net.filter(torch.as_tensor(np.asarray(ds.frames)), sample=False)
    mu, sd = mu.numpy(), sd.numpy()
    for j, n in enumerate(net.config.targets):
        err = mu[..., j] - tg[..., j]
        print(f"{n}: rmse {np.sqrt((err ** 2).mean()):.4f}, at the last frame "
              f"{np.sqrt((err[:, -1] ** 2).mean()):.4f} (mean std {sd[:, -1, j].mean():.4f})")
    if {"x", "y"} <= set(net.config.targets):
        iy = net.config.targets.index("y")
        a = np.diff(mu[..., iy], 2, axis=1) * 400
        t = np.diff(tg[..., iy], 2, axis=1) * 400
        print(f"acc_y feature: rmse {np.sqrt(((a - t) ** 2).mean()):.3f} vs gravity's "
              f"{-np.median(t):.3f}")


def probe(net, h_only: bool) -> None:
    ds = make_split("train", 600, 123, net.config.frame_size, None, 200)
    tg = targets_from_dataset(ds, net.config.targets)
    with torch.no_grad():
        mu, _, state = net.filter(torch.as_tensor(np.asarray(ds.frames)), sample=False)
    h = state[-1][0] if h_only else torch.cat([state[-1][0], state[-1][1]], -1)
    X = np.c_[h.numpy(), np.ones(len(h))]
    tr, te = slice(0, 450), slice(450, 600)
    for j, n in enumerate(net.config.targets):
        if n in ("x", "y", "vx", "vy"):
            continue
        y = tg[:, -1, j]
        w = np.linalg.solve(X[tr].T @ X[tr] + 1e-2 * np.eye(X.shape[1]), X[tr].T @ y[tr])
        print(f"{n}: ridge from {'h' if h_only else '[h, c]'} nMSE {((X[te] @ w - y[te]) ** 2).mean():.4f}"
              f" | encoder {((mu[450:, -1, j].numpy() - y[te]) ** 2).mean():.4f}"
              f" | variance {y[te].var():.4f}")


def grads(net) -> None:
    c = net.config
    K = len(c.targets)
    ds = make_split("train", 16, 77, c.frame_size, None, 200)
    fr = torch.as_tensor(np.asarray(ds.frames))
    tg = torch.as_tensor(targets_from_dataset(ds, c.targets))
    torch.manual_seed(0)
    fx = net.encode_frames(fr)
    state = net.init_state(len(fr))
    hs, zs, mus, stds, lasts = [], [], [], [], []
    for t in range(fr.shape[1]):
        h = net.read(state)
        hs.append(h)
        lasts.append(net.last_position(state))
        mu, std = net.enc_step(fx[:, t], h)
        mus.append(mu)
        stds.append(std)
        zs.append(mu + std * torch.randn_like(mu))
        state = net.step_rnn(mu, state)
    H = _scale_grad(torch.stack(hs, 1), c.aux_grad)
    Z = torch.stack(zs, 1)
    pmu, pstd = net.prior_step(H, torch.stack(lasts, 1) if c.prior_residual else None)
    qmu, qstd = torch.stack(mus, 1), torch.stack(stds, 1)
    idx = torch.randperm(fr.shape[1])[:50]
    logits = net.decode(Z[:, idx], H[:, idx])
    rec = torch.nn.functional.binary_cross_entropy_with_logits(
        logits, fr[:, idx].float() / 255, reduction="none").sum((-1, -2)).mean()
    pos = [i for i, n in enumerate(c.targets) if n in ("x", "y")]
    par = [i for i, n in enumerate(c.targets) if n not in ("x", "y")]
    terms = {
        "reconstruction": c.alpha * rec,
        "kl": c.beta * gaussian_kl(qmu, qstd, pmu, pstd).sum(-1).mean(),
        "nll positions": c.gamma * gaussian_nll(qmu[..., pos], qstd[..., pos], tg[..., pos]).sum(-1).mean(),
        "nll parameters": c.gamma * gaussian_nll(qmu[..., par], qstd[..., par], tg[..., par]).sum(-1).mean(),
        "nll prior": c.gamma_prior * gaussian_nll(pmu[..., :K], pstd[..., :K], tg).sum(-1).mean(),
    }
    lstm = list(net.cells.parameters())
    allp = [p for p in net.parameters() if p.requires_grad]
    for name, v in terms.items():
        gl = torch.autograd.grad(v, lstm, retain_graph=True, allow_unused=True)
        ga = torch.autograd.grad(v, allp, retain_graph=True, allow_unused=True)
        nl = float(torch.sqrt(sum((g ** 2).sum() for g in gl if g is not None)))
        na = float(torch.sqrt(sum((g ** 2).sum() for g in ga if g is not None)))
        print(f"{name:15s} value {v.item():9.3f} | grad on LSTM {nl:9.4f} | on all {na:9.3f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=("positions", "probe", "grads"))
    p.add_argument("state")
    p.add_argument("--h-only", action="store_true")
    a = p.parse_args()
    torch.set_num_threads(1)
    net = _load(a.state)
    if a.what == "positions":
        positions(net)
    elif a.what == "probe":
        probe(net, a.h_only)
    else:
        grads(net)


if __name__ == "__main__":
    main()
