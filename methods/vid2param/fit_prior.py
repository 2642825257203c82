"""Train the latent rollout's physics prior (its process noise) of a checkpoint.

The last phase of the recipe: the encoder and the recurrence stay as they are; only
``PhysicsPrior`` (``methods.vid2param.prior``) learns. Each training video is filtered up to a
random number of observed frames, its state and parameters drawn from the filtered posterior
(``methods.vid2param.rollout``), and the prior unrolled closed-loop over the next ``horizon``
frames; the loss is the Gaussian NLL of the true positions under the particles' mixture
moments, so the noise learns how far the rollout drifts from the truth. Half the videos deviate
from our physics (spin loss and contact dwell at bounces, as in the encoder's training), so the
bands also cover what the physics misses.

``python -m methods.vid2param.fit_prior --checkpoint 28x28 --out PATH`` writes a checkpoint
with ``config.physics_prior = True``; the record of the run is stored under ``prior_fit``.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from methods.vid2param.checkpoint import load_checkpoint, save_atomic, upgrade_state_dict
from methods.vid2param.data import make_split, perturb_dataset
from methods.vid2param.model import V2PConfig, Vid2ParamNet
from methods.vid2param.rollout import fit_state, sample_trajectories
from sysid_bench._validate import check_positive_int

__all__ = ["PriorFitConfig", "with_physics_prior", "fit_prior", "main"]

#: Largest NLL of one coordinate and frame that counts (a 6-sigma miss).
NLL_CLIP = 18.0


@dataclass
class PriorFitConfig:
    """Settings of the prior's training (defaults: the shipped recipe).

    Attributes
    ----------
    n_videos, n_val : int
        Training and validation videos (train split; validation from another seed).
    obs_range : (int, int)
        Observed frames are drawn uniformly from this range, per video.
    horizon : int
        Frames unrolled (and scored) after the observed ones.
    particles : int
        Posterior draws per video.
    steps, batch, lr : int, int, float
        Adam steps, videos per step, learning rate.
    perturb : dict
        ``spin``, ``dwell`` maxima and fraction ``p`` of deviating videos.
    seed : int
    """

    n_videos: int = 300
    n_val: int = 100
    obs_range: tuple[int, int] = (40, 100)
    horizon: int = 60
    particles: int = 8
    steps: int = 150
    batch: int = 32
    lr: float = 0.05
    perturb: dict | None = None
    seed: int = 0

    def __post_init__(self):
        if self.perturb is None:
            self.perturb = {"spin": 0.3, "dwell": 0.01, "p": 0.5}
        self.obs_range = tuple(int(v) for v in self.obs_range)


def with_physics_prior(ck: dict) -> Vid2ParamNet:
    """The checkpoint's network with a physics prior at its starting values (one the
    checkpoint already has is replaced: the phase starts afresh, so its result does not
    depend on what it is run on)."""
    cfg = V2PConfig.from_dict({**ck["config"], "physics_prior": True})
    net = Vid2ParamNet(cfg)
    weights = {k: v for k, v in upgrade_state_dict(ck["state_dict"]).items()
               if not k.startswith("phys_prior.")}
    missing, unexpected = net.load_state_dict(weights, strict=False)
    if unexpected or any(not k.startswith("phys_prior.") for k in missing):
        raise ValueError(f"checkpoint: weights do not match its config (missing {missing}, "
                         f"unexpected {unexpected})")
    return net


def _pool(est, n: int, seed: int, cfg: PriorFitConfig, desc: str) -> dict:
    """Filter ``n`` videos to a random prefix each and draw their posterior particles."""
    size = tuple(est.frame_size)
    tr = est.checkpoint_info_.get("train") or {}
    ds = make_split("train", n, seed, size, tr.get("nuisance"), 200)
    p = cfg.perturb
    ds = perturb_dataset(ds, p["spin"], p["dwell"], seed=seed, p=p["p"])
    rng = np.random.default_rng([seed, 5])
    lo, hi = cfg.obs_range
    fl = np.asarray(ds.floor, dtype=np.float64)
    out = {"phys": [], "theta": [], "truth": []}
    for i in tqdm(range(n), desc=desc, mininterval=10):
        t0 = int(rng.integers(lo, hi + 1))
        frames = np.asarray(ds.frames[i, :t0])
        pos, th_mu, th_sd, _ = est._track(frames)
        fit = fit_state(pos, th_mu, th_sd, floor=est.floor_prior())
        # the rollout runs above each draw's floor, as the truths (floor-relative) are
        states, theta, _ = sample_trajectories(fit, t0, 0, cfg.particles, rng)
        out["phys"].append(states[:, 0])
        out["theta"].append(theta)
        truth = np.asarray(ds.states[i, t0:t0 + cfg.horizon, :2]) - [0.0, fl[i]]
        out["truth"].append(truth)
    return out


def _rollouts(net, pool, idx, cfg, gen):
    """Mixture mean (noise-free paths) and variance (noisy paths) of videos ``idx``, each
    (B, H, 2), and their truths."""
    P, H = cfg.particles, cfg.horizon
    phys = torch.as_tensor(np.concatenate([pool["phys"][i] for i in idx]), dtype=torch.float32)
    theta = torch.as_tensor(np.concatenate([pool["theta"][i] for i in idx]), dtype=torch.float32)
    B = len(idx)
    with torch.no_grad():
        path, _, _ = net.rollout_physics(phys, theta, H, sample=False)
    mean, std, _ = net.rollout_physics(phys, theta, H, generator=gen)
    m = mean[..., :2].reshape(B, P, H, 2)
    s = std[..., :2].reshape(B, P, H, 2)
    mix_m = path[..., :2].reshape(B, P, H, 2).mean(1)
    mix_v = (s**2).mean(1) + m.var(1, unbiased=False)
    truth = torch.as_tensor(np.stack([pool["truth"][i] for i in idx]), dtype=torch.float32)
    return mix_m, mix_v, truth


def _nll(mix_m, mix_v, truth):
    """Gaussian NLL per coordinate and frame, clipped at ``NLL_CLIP``: a few videos whose state
    fit failed (metres off) would otherwise set the noise."""
    nll = 0.5 * (math.log(2 * math.pi) + torch.log(mix_v) + (truth - mix_m) ** 2 / mix_v)
    return nll.clamp(max=NLL_CLIP)


def _loss(net, pool, idx, cfg, gen):
    """Mean NLL (per coordinate and frame) and MSE (m^2) of the truths of videos ``idx``."""
    mix_m, mix_v, truth = _rollouts(net, pool, idx, cfg, gen)
    return _nll(mix_m, mix_v, truth).mean(), ((truth - mix_m) ** 2).mean()


def _coverage(net, pool, cfg, seed: int) -> dict:
    """NLL, position MSE (m^2) and 90% coverage of the mixture on a pool, all videos at once."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        mix_m, mix_v, truth = _rollouts(net, pool, list(range(len(pool["truth"]))), cfg, gen)
    cov = ((truth - mix_m).abs() <= 1.645 * mix_v.sqrt()).float().mean()
    return {"nll": float(_nll(mix_m, mix_v, truth).mean()),
            "mse_m2": float(((truth - mix_m) ** 2).mean()), "cov90": float(cov)}


def fit_prior(checkpoint, out, cfg: PriorFitConfig | None = None, threads: int | None = None,
              log=print) -> dict:
    """Train the physics prior of ``checkpoint`` and write the result to ``out``.

    Returns
    -------
    dict
        The record stored in the checkpoint as ``prior_fit``: settings, validation metrics of
        the untrained prior (physics alone) and of the trained one, wall time.
    """
    import methods

    cfg = cfg or PriorFitConfig()
    check_positive_int(cfg.steps, "steps")
    if threads is not None:
        torch.set_num_threads(check_positive_int(threads, "threads"))
    t_start = time.perf_counter()
    est = methods.get("vid2param", checkpoint=checkpoint)
    path = est._checkpoint_path()
    ck = load_checkpoint(path)
    net = with_physics_prior(ck)
    est._ensure_net()
    est.net_ = net  # the estimator filters with the same weights; its prior is trained below
    for p in net.parameters():
        p.requires_grad_(False)
    for p in net.phys_prior.parameters():
        p.requires_grad_(True)
    train = _pool(est, cfg.n_videos, cfg.seed * 1000 + 101, cfg, "prior: training videos")
    val = _pool(est, cfg.n_val, cfg.seed * 1000 + 202, cfg, "prior: validation videos")
    before = _coverage(net, val, cfg, seed=1)
    log(f"starting noise (validation): {before}")
    opt = torch.optim.Adam(net.phys_prior.parameters(), lr=cfg.lr)
    rng = np.random.default_rng([cfg.seed, 9])
    gen = torch.Generator().manual_seed(cfg.seed)
    bar = tqdm(range(cfg.steps), desc="prior: steps", mininterval=10)
    for step in bar:
        idx = rng.choice(cfg.n_videos, size=min(cfg.batch, cfg.n_videos), replace=False)
        nll, mse = _loss(net, train, idx, cfg, gen)
        opt.zero_grad()
        nll.backward()
        opt.step()
        if step % 25 == 0:
            bar.set_postfix(nll=f"{nll.item():.3f}", rmse=f"{mse.item() ** 0.5:.3f}")
            log(f"step {step}: nll {nll.item():.3f} noise "
                f"{torch.exp(net.phys_prior.log_noise).tolist()} "
                f"bounce {torch.exp(net.phys_prior.log_bounce).tolist()}")
    after = _coverage(net, val, cfg, seed=1)
    log(f"trained (validation): {after}")
    record = {"config": asdict(cfg), "val_noise0": before, "val_trained": after,
              "noise_per_frame": torch.exp(net.phys_prior.log_noise).tolist(),
              "bounce_noise": torch.exp(net.phys_prior.log_bounce).tolist(),
              "wall_s": time.perf_counter() - t_start, "from": str(path)}
    ck = dict(ck)
    ck["config"] = net.config.to_dict()
    ck["state_dict"] = net.state_dict()
    ck["prior_fit"] = record
    save_atomic(ck, out)
    return record


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m methods.vid2param.fit_prior",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="28x28", help="shipped name or path")
    ap.add_argument("--out", required=True, help="checkpoint file to write")
    ap.add_argument("--steps", type=int, default=PriorFitConfig.steps)
    ap.add_argument("--n-videos", type=int, default=PriorFitConfig.n_videos)
    ap.add_argument("--n-val", type=int, default=PriorFitConfig.n_val)
    ap.add_argument("--seed", type=int, default=PriorFitConfig.seed)
    ap.add_argument("--perturb-p", type=float, default=None,
                    help="fraction of videos that deviate from our physics (default 0.5)")
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)
    cfg = PriorFitConfig(steps=a.steps, n_videos=a.n_videos, n_val=a.n_val, seed=a.seed)
    if a.perturb_p is not None:
        cfg.perturb = {**cfg.perturb, "p": a.perturb_p}
    fit_prior(a.checkpoint, Path(a.out), cfg, threads=a.threads)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
