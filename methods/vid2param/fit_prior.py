"""Train the latent rollout's physics prior (its process noise) of a checkpoint.

The last phase of the recipe: the encoder and the recurrence stay as they are; only
``PhysicsPrior`` (``methods.vid2param.prior``) learns. Each training video is filtered up to a
random number of observed frames, its state and parameters drawn from the filtered posterior
(``methods.vid2param.rollout``), its backtest error measured (how well our physics forecast the
last frames seen, ``rollout.backtest_error``), and the prior unrolled closed-loop over the next
``horizon`` frames. Half the videos deviate from our physics (spin loss and contact dwell at
bounces, as in the encoder's training), so the bands also cover what the physics misses.

Two stages: Adam on the interval score of the 90% band of the particles' mixture moments (the
noise's level and its gain on the backtest), then ``calibrate``: the noise is rescaled so that
the training videos with a backtest below the median and those above each get 90% coverage.

This is the ``prior_noise`` stage (``methods.vid2param.stages``): ``python -m
methods.vid2param.train ... --export F`` fits it after the network (its noise weights and the
record of the run are the stage's state).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
from tqdm import tqdm

from methods.vid2param.checkpoint import upgrade_state_dict
from methods.vid2param.data import make_split, perturb_dataset
from methods.vid2param.model import V2PConfig, Vid2ParamNet
from methods.vid2param.rollout import backtest_error, fit_state, sample_trajectories
from sysid_bench.core._validate import check_positive_int

__all__ = ["PriorFitConfig", "with_physics_prior", "fit_prior_stage"]

#: Largest NLL of one coordinate and frame that counts (a 6-sigma miss).
NLL_CLIP = 18.0
#: Half-width of a Gaussian's central 90% interval, in standard deviations.
_Z90 = 1.6448536269514722


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
        Posterior draws per video (with 8, the mixture's variance of a few draws came out
        small and noisy, the noise grew to make up for it, and the estimator's 200 draws
        then gave bands holding 97%).
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
    particles: int = 64
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


def _pool(ctx, n: int, seed: int, cfg: PriorFitConfig, desc: str) -> dict:
    """Filter ``n`` videos to a random prefix each (the network and the stages before, ``ctx``)
    and draw their posterior particles."""
    ds = make_split("train", n, seed, ctx.frame_size, ctx.train.get("nuisance"), 200)
    p = cfg.perturb
    ds = perturb_dataset(ds, p["spin"], p["dwell"], seed=seed, p=p["p"])
    rng = np.random.default_rng([seed, 5])
    lo, hi = cfg.obs_range
    fl = np.asarray(ds.floor, dtype=np.float64)
    out = {"phys": [], "theta": [], "truth": [], "skill": []}
    for i in tqdm(range(n), desc=desc, mininterval=10):
        t0 = int(rng.integers(lo, hi + 1))
        frames = np.asarray(ds.frames[i, :t0])
        pos, th_mu, th_sd = ctx.track(frames)
        fit = fit_state(pos, th_mu, th_sd, floor=ctx.floor_prior())
        out["skill"].append(backtest_error(pos, th_mu, th_sd, floor=ctx.floor_prior()))
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
    skill = torch.as_tensor(np.repeat([pool["skill"][i] for i in idx], P), dtype=torch.float32)
    B = len(idx)
    with torch.no_grad():
        path, _, _ = net.rollout_physics(phys, theta, H, sample=False)
    mean, std, _ = net.rollout_physics(phys, theta, H, generator=gen, skill=skill)
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


def _interval_score(mix_m, mix_v, truth, level: float = 0.9):
    """Interval score (m) of the central ``level`` band of the mixture moments, per coordinate
    and frame: the band's width plus ``2 / (1 - level)`` times the miss. Its minimum is the
    band that holds ``level`` of the truths given what the band reads (here the backtest), as
    narrow as that allows (Gneiting & Raftery 2007)."""
    half = _Z90 * mix_v.sqrt()
    miss = ((truth - mix_m).abs() - half).clamp(min=0.0)
    return 2.0 * half + 2.0 / (1.0 - level) * miss


def _loss(net, pool, idx, cfg, gen):
    """Mean interval score (per coordinate and frame, m) and MSE (m^2) of the truths of videos
    ``idx``."""
    mix_m, mix_v, truth = _rollouts(net, pool, idx, cfg, gen)
    return _interval_score(mix_m, mix_v, truth).mean(), ((truth - mix_m) ** 2).mean()


def _cov90(mix_m, mix_v, truth) -> float:
    """Share of the truths inside the central 90% band of the mixture moments."""
    return float(((truth - mix_m).abs() <= _Z90 * mix_v.sqrt()).float().mean())


def _halves(skill, split_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the videos whose backtest error is below / above ``split_m`` (an unknown
    backtest, NaN, counts below)."""
    above = np.asarray(skill, dtype=np.float64) > split_m
    return np.flatnonzero(~above), np.flatnonzero(above)


def _coverage(net, pool, cfg, seed: int) -> dict:
    """NLL, position MSE (m^2) and 90% coverage of the mixture on a pool, all videos at once."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        mix_m, mix_v, truth = _rollouts(net, pool, list(range(len(pool["truth"]))), cfg, gen)
    return {"nll": float(_nll(mix_m, mix_v, truth).mean()),
            "interval_score_m": float(_interval_score(mix_m, mix_v, truth).mean()),
            "mse_m2": float(((truth - mix_m) ** 2).mean()), "cov90": _cov90(mix_m, mix_v, truth)}


def _group_coverage(net, pool, idx, cfg, log_scale: float) -> float:
    """90% coverage of videos ``idx`` with every noise std scaled by ``exp(log_scale)``."""
    prior = net.phys_prior
    with torch.no_grad():
        prior.log_noise += log_scale
        prior.log_bounce += log_scale
        try:
            gen = torch.Generator().manual_seed(cfg.seed + 3)
            mix_m, mix_v, truth = _rollouts(net, pool, list(idx), cfg, gen)
        finally:
            prior.log_noise -= log_scale
            prior.log_bounce -= log_scale
    return _cov90(mix_m, mix_v, truth)


def _coverage_by_skill(net, pool, cfg, split_m: float) -> dict:
    """90% coverage of the videos whose backtest error is below / above ``split_m``."""
    out = {}
    for name, idx in zip(("below", "above"), _halves(pool["skill"], split_m)):
        out[name] = _group_coverage(net, pool, idx, cfg, 0.0) if len(idx) else float("nan")
    return out


def calibrate(net, pool, cfg: PriorFitConfig, level: float = 0.9, log=print) -> dict:
    """Scale the trained noise so that the videos our physics predicts well and those it
    predicts badly (backtest error below / above the pool's median) each get ``level``
    coverage, in place.

    The interval score is minimised by the band of ``level`` coverage only where the noise's
    form fits the errors; these errors are not Gaussian (a clean ball's forecast is right to a
    centimetre or misses a bounce by a metre), and the trained bands held 97% on clean video.
    For each half a bisection finds the log-scale of all noise stds that gives ``level``
    coverage (or the smallest tried, ``exp(-7)``, where the posterior's own spread already
    covers more); the two points fix the scale's level and its slope in ``log skill``
    (``skill_gain``).

    Returns
    -------
    dict
        ``split_m`` (the median backtest error), each half's median ``log(skill / SKILL_REF)``,
        log-scale and coverage before.
    """
    from methods.vid2param.prior import PhysicsPrior

    sk = np.asarray(pool["skill"], dtype=np.float64)
    x = PhysicsPrior.log_skill(torch.as_tensor(sk)).numpy()
    split = float(np.nanmedian(sk))
    pts, rec = [], {"split_m": split}
    for name, idx in zip(("below", "above"), _halves(sk, split)):
        lo, hi = -7.0, 4.0
        before = _group_coverage(net, pool, idx, cfg, 0.0)
        if _group_coverage(net, pool, idx, cfg, lo) >= level:
            a = lo
        else:
            for _ in range(16):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if _group_coverage(net, pool, idx, cfg, mid) < level else (lo, mid)
            a = 0.5 * (lo + hi)
        pts.append((float(np.median(x[idx])), a))
        rec[name] = {"n": int(len(idx)), "median_log_skill": pts[-1][0], "log_scale": a,
                     "coverage_before": before}
        log(f"calibration, backtest {name} {split:.3f} m: coverage {before:.3f}, scale {np.exp(a):.3g}")
    (x1, a1), (x2, a2) = pts
    slope = (a2 - a1) / (x2 - x1) if x2 - x1 > 1e-6 else 0.0
    with torch.no_grad():
        net.phys_prior.log_noise += a1 - slope * x1
        net.phys_prior.log_bounce += a1 - slope * x1
        net.phys_prior.skill_gain += slope
    rec["slope"] = float(slope)
    return rec


def fit_prior_stage(ctx, cfg: PriorFitConfig | None = None, log=None):
    """Train the physics prior of ``ctx.net`` (an ``inference.FitContext``) afresh.

    Returns
    -------
    record : dict
        Settings, validation metrics of the untrained prior (physics alone) and of the trained
        one, wall time.
    net : Vid2ParamNet
        The network with ``config.physics_prior`` and the trained prior (its other weights
        those of ``ctx.net``).
    """
    cfg = cfg or PriorFitConfig()
    log = log or ctx.log
    check_positive_int(cfg.steps, "steps")
    t_start = time.perf_counter()
    net = with_physics_prior({"config": ctx.net.config.to_dict(),
                              "state_dict": ctx.net.state_dict()})
    net.eval()
    ctx.net = net  # the tracks are filtered with the same weights; its prior is trained below
    for p in net.parameters():
        p.requires_grad_(False)
    for p in net.phys_prior.parameters():
        p.requires_grad_(True)
    train = _pool(ctx, cfg.n_videos, cfg.seed * 1000 + 101, cfg, "prior: training videos")
    val = _pool(ctx, cfg.n_val, cfg.seed * 1000 + 202, cfg, "prior: validation videos")
    before = _coverage(net, val, cfg, seed=1)
    log(f"starting noise (validation): {before}")
    opt = torch.optim.Adam(net.phys_prior.parameters(), lr=cfg.lr)
    rng = np.random.default_rng([cfg.seed, 9])
    gen = torch.Generator().manual_seed(cfg.seed)
    bar = tqdm(range(cfg.steps), desc="prior: steps", mininterval=10)
    for step in bar:
        idx = rng.choice(cfg.n_videos, size=min(cfg.batch, cfg.n_videos), replace=False)
        score, mse = _loss(net, train, idx, cfg, gen)
        opt.zero_grad()
        score.backward()
        opt.step()
        if step % 25 == 0:
            bar.set_postfix(score=f"{score.item():.3f}", rmse=f"{mse.item() ** 0.5:.3f}")
            log(f"step {step}: interval score {score.item():.3f} m, noise "
                f"{torch.exp(net.phys_prior.log_noise).tolist()} "
                f"bounce {torch.exp(net.phys_prior.log_bounce).tolist()} "
                f"skill gain {net.phys_prior.skill_gain.tolist()}")
    after = _coverage(net, val, cfg, seed=1)
    log(f"trained (validation): {after}")
    calibration = calibrate(net, train, cfg, log=log)
    calibrated = _coverage(net, val, cfg, seed=1)
    calibrated["by_skill"] = _coverage_by_skill(net, val, cfg, calibration["split_m"])
    log(f"calibrated (validation): {calibrated}")
    for p in net.parameters():
        p.requires_grad_(False)
    record = {"config": asdict(cfg), "val_noise0": before, "val_trained": after,
              "calibration": calibration, "val_calibrated": calibrated,
              "noise_per_frame": torch.exp(net.phys_prior.log_noise).tolist(),
              "bounce_noise": torch.exp(net.phys_prior.log_bounce).tolist(),
              "skill_gain": net.phys_prior.skill_gain.tolist(),
              "wall_s": time.perf_counter() - t_start, "from": ctx.source}
    return record, net
