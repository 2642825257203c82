"""Drag evidence: the drag constant read off the network's own track, blended into its d.

Drag acts slowly (``ax = -d |v| vx``: a few percent of the speed per second), and the camera
network's posterior over d stays well above what a fit of our physics to its own track gets
(model card). The track carries it: over a window of ``2 k + 1`` frames that flies between
the walls, the k-frame second difference of x (which averages the track's centimetre
misreadings) is the deceleration averaged with triangular weights over the window, and the
same average of ``|v| vx`` (one-frame central differences) its regressor. A running least-squares sum
over every such window gives an estimate ``D = sum(-ax f) / sum(f^2)`` and its evidence
``S = sum(f^2)``.

Two sums are kept: over all windows (``D_a``), and over the windows without a bounce
(``D_b``: no one-frame rise of the vertical velocity above ``BOUNCE_DV``). Our physics keeps vx
through a bounce, so on our videos both read d and the first has far more windows; a real ball
(spin, a soft contact) loses horizontal speed at a bounce, which the first reads as drag. They
are blended with the network's d by inverse variance::

    var_a = c_a / S_a + b_a^2 + gamma (D_a - D_b)^2,   var_b = c_b / S_b + b_b^2
    d_a = scale * D_a + bias,                          d_b = scale * D_b + bias

so the all-window estimate counts as long as the bounce-free one agrees with it. The seven
numbers (``DragBlend``) are fitted by Gaussian NLL on train-split videos, half of them
re-simulated with spin and contact dwell as in the network's training, the network frozen (as
the physics prior is, ``fit_prior``). The blended d is not fed back into the recurrence: the
network runs exactly as trained, and a checkpoint without a fitted blend answers as before.

The blend is the ``drag_evidence`` stage (``methods.vid2param.stages``); ``python -m
methods.vid2param.train --preset camera --export F`` fits it after the network, and
``python -m methods.vid2param.train --refit camera --stages ... --export F`` refits a
checkpoint's stages.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from sysid_bench.core.physics import BOX_WIDTH, DT, PRIOR

__all__ = ["DragBlend", "DragStatistic", "DragFitConfig", "statistic_track", "fit_blend",
           "fit_drag_stage", "K", "WALL_M", "FLY_M", "ACC_CAP", "BOUNCE_DV"]

#: Frames between the three positions of a window's second difference (window 2 K + 1).
#: Chosen on validation tracks of the camera model (train split; K = 4, 6, 8: model card).
K = 6
#: A window counts only away from the walls (a wall hit flips vx), ...
WALL_M = 0.6
#: ... when the ball flies (heights spread over more than this: a roll has no drag) ...
FLY_M = 0.3
#: ... and when its deceleration is below this (m/s^2; a misread frame gives metres per s^2).
ACC_CAP = 8.0
#: A window holds a bounce when its one-frame vertical velocity rises by more than this (m/s;
#: gravity changes it by 0.5 per frame; chosen on validation tracks with 1.5 and 3).
BOUNCE_DV = 1.5
#: Frames before which the blend's fit does not score the posterior (no window yet).
FIT_FROM = 20

_LO_D, _HI_D = PRIOR["d"]
_SPAN_D = _HI_D - _LO_D


def _exp(v: float) -> float:
    """``exp`` kept finite and nonzero (an optimiser's trial values may be far out)."""
    return math.exp(min(max(v, -600.0), 600.0))


_FIELDS = ("scale", "bias", "log_c", "log_b", "log_c_free", "log_b_free", "log_gamma")


@dataclass(frozen=True)
class DragBlend:
    """The fitted blend of the drag statistics into the posterior's d (see the module).

    Attributes
    ----------
    scale, bias : float
        ``d = scale * D + bias`` (1/m), both statistics.
    log_c, log_b : float
        The all-window statistic's ``var = exp(log_c) / S + exp(2 log_b)`` ((1/m)^2), ...
    log_c_free, log_b_free : float
        ... the bounce-free one's, ...
    log_gamma : float
        ... and the weight of their squared disagreement in the first's variance.
    k : int
        The statistics' ``K``.
    """

    scale: float
    bias: float
    log_c: float
    log_b: float
    log_c_free: float
    log_b_free: float
    log_gamma: float
    k: int = K

    @classmethod
    def from_record(cls, rec: dict | None) -> DragBlend | None:
        """The blend stored under a checkpoint's ``drag_evidence`` (None when absent)."""
        if not rec:
            return None
        try:
            out = cls(**{f: rec[f] for f in (*_FIELDS, "k")})
        except KeyError as exc:
            raise ValueError(f"checkpoint: drag_evidence lacks {exc.args[0]!r}") from None
        vals = np.array([getattr(out, f) for f in _FIELDS], dtype=float)
        if not np.isfinite(vals).all() or int(out.k) < 1:
            raise ValueError(f"checkpoint: drag_evidence must be finite with k >= 1, got {rec}")
        return out

    def apply(self, mu_n, sd_n, D, S) -> tuple[np.ndarray, np.ndarray]:
        """The blended posterior of d.

        Parameters
        ----------
        mu_n, sd_n : ndarray, shape (...)
            The network's (calibrated) mean and std of d, normalised to the prior's range.
        D, S : ndarray, shape (..., 2)
            The statistics' estimates (1/m; NaN before a window counted) and evidence: all
            windows, bounce-free windows (``DragStatistic.summary``).

        Returns
        -------
        mu_n, sd_n : ndarray, shape (...)
            Normalised, as given.
        """
        mu_n, sd_n = np.asarray(mu_n, float), np.asarray(sd_n, float)
        D, S = np.asarray(D, float), np.asarray(S, float)
        ok = np.isfinite(D) & (S > 0)
        Dz, Sz = np.where(ok, D, 0.0), np.where(ok, S, 1.0)
        gap = np.where(ok.all(-1), (Dz[..., 0] - Dz[..., 1]) ** 2, 0.0)
        var_a = _exp(self.log_c) / Sz[..., 0] + _exp(2 * self.log_b) + _exp(self.log_gamma) * gap
        var_b = _exp(self.log_c_free) / Sz[..., 1] + _exp(2 * self.log_b_free)
        w = np.where(ok, _SPAN_D**2 / np.stack([var_a, var_b], -1), 0.0)
        d = (self.scale * Dz + self.bias - _LO_D) / _SPAN_D
        prec = 1.0 / sd_n**2 + w.sum(-1)
        return (mu_n / sd_n**2 + (w * d).sum(-1)) / prec, 1.0 / np.sqrt(prec)


class DragStatistic:
    """The running drag statistic of B tracks, one frame at a time.

    Parameters
    ----------
    batch : int
    k : int
        Frames between a window's three positions.
    dt : float
        Seconds per frame.
    """

    def __init__(self, batch: int, k: int = K, dt: float = DT):
        self.k, self.dt, self.w = int(k), float(dt), 2 * int(k) + 1
        # the k-frame second difference is the acceleration averaged with these weights over
        # the window's inner frames (a triangle); the regressor is averaged with the same
        j = np.arange(-self.k + 1, self.k)
        self.tri = (self.k - np.abs(j)) / self.k**2
        self.buf = np.full((int(batch), self.w, 2), np.nan)
        self.n = 0
        self.saf = np.zeros((int(batch), 2))  # columns: all windows, bounce-free windows
        self.sff = np.zeros((int(batch), 2))

    def update(self, pos) -> None:
        """Add each track's newest position ``pos`` (B, 2), metres (x, height; NaN: unseen)."""
        self.buf[:, self.n % self.w] = pos
        self.n += 1
        if self.n < self.w:
            return
        win = self.buf[:, (self.n + np.arange(self.w)) % self.w]  # oldest first
        xs, ys, k, dt = win[..., 0], win[..., 1], self.k, self.dt
        dx = np.diff(xs, axis=1)
        with np.errstate(invalid="ignore"):
            ax = (xs[:, 2 * k] - 2 * xs[:, k] + xs[:, 0]) / (k * dt) ** 2
            vx = (xs[:, 2:] - xs[:, :-2]) / (2 * dt)  # the inner frames' velocities
            vy = (ys[:, 2:] - ys[:, :-2]) / (2 * dt)
            f = (np.hypot(vx, vy) * vx) @ self.tri
            ok = (np.isfinite(win).all((1, 2)) & ((dx > 0).all(1) | (dx < 0).all(1))
                  & (xs > WALL_M).all(1) & (xs < BOX_WIDTH - WALL_M).all(1)
                  & (ys.max(1) - ys.min(1) > FLY_M) & (np.abs(ax) < ACC_CAP))
            ok = np.stack([ok, ok & (np.diff(vy, axis=1).max(1) < BOUNCE_DV)], -1)
        f = np.where(ok, f[:, None], 0.0)
        self.saf += np.where(ok, -ax[:, None] * f, 0.0)
        self.sff += f * f

    def summary(self) -> tuple[np.ndarray, np.ndarray]:
        """The estimates ``D`` (B, 2) (1/m; NaN while no window counted) and evidence ``S``
        (B, 2): over all windows, over the bounce-free ones."""
        pos = self.sff > 0
        return np.where(pos, self.saf / np.where(pos, self.sff, 1.0), np.nan), self.sff.copy()


def statistic_track(pos, k: int = K, dt: float = DT) -> tuple[np.ndarray, np.ndarray]:
    """``DragStatistic`` after every frame of whole tracks.

    Parameters
    ----------
    pos : ndarray, shape (B, T, 2)
        Metres.

    Returns
    -------
    D, S : ndarray, shape (B, T, 2)
    """
    pos = np.asarray(pos, dtype=np.float64)
    st = DragStatistic(pos.shape[0], k, dt)
    D, S = np.empty((*pos.shape[:2], 2)), np.empty((*pos.shape[:2], 2))
    for t in range(pos.shape[1]):
        st.update(pos[:, t])
        D[:, t], S[:, t] = st.summary()
    return D, S


def _nll(blend: DragBlend, mu_n, sd_n, D, S, truth_n) -> float:
    mu, sd = blend.apply(mu_n, sd_n, D, S)
    return float(np.mean(np.log(sd) + 0.5 * ((mu - truth_n) / sd) ** 2))


def fit_blend(mu_n, sd_n, D, S, truth_n, k: int = K) -> tuple[DragBlend, float]:
    """The ``DragBlend`` of least Gaussian NLL of the true d (Nelder-Mead, deterministic).

    Parameters
    ----------
    mu_n, sd_n : ndarray, shape (N, T)
        The network's normalised d posterior after every frame.
    D, S : ndarray, shape (N, T, 2)
        The statistics after every frame.
    truth_n : ndarray, shape (N,)
        True d, normalised.

    Returns
    -------
    DragBlend, float
        The blend and its mean NLL over frames ``FIT_FROM`` on.
    """
    from scipy.optimize import minimize

    sl = (slice(None), slice(FIT_FROM, None))
    args = (mu_n[sl], sd_n[sl], D[sl], S[sl], np.asarray(truth_n, float)[:, None])

    def loss(p):
        return _nll(DragBlend(*p, k=k), *args)

    start = [1.0, 0.0, math.log(1e-3), math.log(3e-3), math.log(1e-3), math.log(3e-3), 0.0]
    res = minimize(loss, np.array(start), method="Nelder-Mead",
                   options={"maxiter": 8000, "xatol": 1e-7, "fatol": 1e-10})
    blend = DragBlend(*(float(v) for v in res.x), k=k)
    return blend, float(res.fun)


def _network_d(ctx, ds) -> tuple[np.ndarray, ...]:
    """The normalised d posterior (N, T) each of the network and the stages before this one
    (``ctx``, an ``inference.FitContext``), its track (N, T, 2) m and true d (N,) normalised,
    for the videos of ``ds``."""
    from sysid_bench.core.physics import PARAMS

    i_d = PARAMS.index("d")
    frames = np.asarray(ds.frames)
    mus, sds, pos = [], [], []
    for i in range(0, len(frames), 100):
        mu, sd, p, _ = ctx.parameters(frames[i:i + 100])
        mus.append(mu[..., i_d])
        sds.append(sd[..., i_d])
        pos.append(p)
    theta = np.asarray(ds.theta)
    d = theta[:, -1, i_d] if theta.ndim == 3 else theta[:, i_d]
    return (np.concatenate(mus), np.concatenate(sds), np.concatenate(pos),
            (d - _LO_D) / _SPAN_D)


def _scores(mu, sd, truth) -> dict:
    """nMSE and 90% coverage of d after 50, 100 and 200 frames (those the videos have)."""
    out = {}
    for n in (50, 100, 200):
        if n <= mu.shape[1]:
            m, s = np.clip(mu[:, n - 1], 0, 1), sd[:, n - 1]
            out[str(n)] = {"nmse": float(np.mean((m - truth) ** 2)),
                           "coverage90": float(np.mean(np.abs(m - truth) <= 1.6448536 * s))}
    return out


@dataclass
class DragFitConfig:
    """Videos of the blend's fit (train split, ``seed``; a fraction ``perturb["p"]`` of them
    re-simulated with spin loss and contact dwell, as the network's training) and of its check
    (``seed + 1``: our physics, and every video perturbed)."""

    n_videos: int = 300
    n_val: int = 100
    seed: int = 7
    k: int = K
    perturb: dict = field(default_factory=lambda: {"spin": 0.3, "dwell": 0.01, "p": 0.5})


def fit_drag_stage(ctx, cfg: DragFitConfig | None = None) -> dict:
    """Fit the drag evidence after the stages of ``ctx`` (an ``inference.FitContext``).

    The videos are the train split rendered as the checkpoint was trained (size, nuisances,
    variant), constant parameters (``DragFitConfig``). Returns the stage's state: the blend,
    its NLL, and d's scores on the validation videos before and after, on our physics
    (``val_*``) and perturbed (``val_perturbed_*``).
    """
    import torch

    from methods.vid2param.data import perturb_dataset
    from sysid_bench.core._validate import check_positive_int

    cfg = cfg or DragFitConfig()
    for name in ("n_videos", "n_val", "k"):
        check_positive_int(getattr(cfg, name), name)
    t0 = time.perf_counter()
    pt = cfg.perturb
    fit_set = perturb_dataset(ctx.split(cfg.n_videos, cfg.seed), pt["spin"], pt["dwell"],
                              seed=cfg.seed, p=pt["p"])
    val_set = ctx.split(cfg.n_val, cfg.seed + 1)
    val_pert = perturb_dataset(val_set, pt["spin"], pt["dwell"], seed=cfg.seed + 1, p=1.0)
    with torch.inference_mode():
        mu, sd, pos, truth = _network_d(ctx, fit_set)
        blend, nll = fit_blend(mu, sd, *statistic_track(pos, cfg.k), truth, cfg.k)
        record = {**asdict(blend), "nll": nll, "config": asdict(cfg), "from": ctx.source,
                  "statistic": {"wall_m": WALL_M, "fly_m": FLY_M, "acc_cap": ACC_CAP,
                                "bounce_dv": BOUNCE_DV, "fit_from": FIT_FROM}}
        for name, ds in (("val", val_set), ("val_perturbed", val_pert)):
            vmu, vsd, vpos, vtruth = _network_d(ctx, ds)
            bmu, bsd = blend.apply(vmu, vsd, *statistic_track(vpos, cfg.k))
            record[name + "_network"] = _scores(vmu, vsd, vtruth)
            record[name + "_blended"] = _scores(bmu, bsd, vtruth)
    record["wall_s"] = time.perf_counter() - t0
    ctx.log(f"drag evidence: {asdict(blend)}; validation d nMSE network {record['val_network']} "
            f"-> blended {record['val_blended']}; perturbed {record['val_perturbed_network']} -> "
            f"{record['val_perturbed_blended']}")
    return record
