"""What the estimator and the stages' fits share: the network's pass over videos and the units.

Nothing here trains or imports training code; ``methods.vid2param.stages`` (the stages after
the network) and the estimator build on it, and so do the stages' fits, so a fit answers with
exactly the numbers the estimator would.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from sysid_bench.core.physics import BOX_WIDTH, PARAMS, PRIOR

__all__ = ["LO", "HI", "SPAN", "UNSEEN_SD_M", "physical", "positions", "param_index",
           "unseen_as_nan",
           "latent_pass", "floor_prior", "resolve_device", "stream_device", "FitContext"]

LO = np.array([PRIOR[p][0] for p in PARAMS])
HI = np.array([PRIOR[p][1] for p in PARAMS])
SPAN = HI - LO

#: A frame whose network position std in x exceeds this (m) is taken as unseen by
#: ``vid2param-physics``'s fit. Measured on test-split videos: seen frames 0.01 m (28x28) and at
#: most 0.85 m (camera, blurred or occluded); black frames at least 2.5 m (28x28), 1.07 m (camera).
UNSEEN_SD_M = 1.0


def physical(mu_n: np.ndarray, sd_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised posterior mean and (calibrated) std of (e, g, d, r), (4,) each, in physical
    units; the mean clipped to the prior."""
    return LO + SPAN * np.clip(mu_n, 0.0, 1.0), SPAN * sd_n


def unseen_as_nan(pos: np.ndarray, sd: np.ndarray, targets) -> np.ndarray:
    """The track ``vid2param-physics`` fits: ``pos`` (..., T, 2) with every frame whose network
    x-std (``sd`` (..., T, K)) exceeds ``UNSEEN_SD_M`` set to NaN (a frame without the ball gets
    the network's guess, metres wide: unseen, not a point on the path). In place; returned."""
    pos[BOX_WIDTH * sd[..., list(targets).index("x")] > UNSEEN_SD_M] = np.nan
    return pos


def param_index(targets) -> list[int]:
    """Latent dimensions of ``PARAMS`` among ``targets``; ValueError when one is missing."""
    missing = [p for p in PARAMS if p not in targets]
    if missing:
        raise ValueError(f"checkpoint: its latent space carries no {missing}")
    return [list(targets).index(p) for p in PARAMS]


def positions(mu: np.ndarray, targets) -> np.ndarray:
    """Floor-relative positions (..., T, 2) (m) of latent means (..., T, K)."""
    names = list(targets)
    return BOX_WIDTH * mu[..., [names.index("x"), names.index("y")]]


def latent_pass(net, frames: np.ndarray, device) -> tuple[np.ndarray, np.ndarray, object]:
    """The network's latent means and stds (N, T, K) after every frame of checked videos
    (N, T, H, W) (float64), and the recurrent state after the last."""
    if not frames.flags.writeable:  # the harness's cached cases are read-only; torch warns on them
        frames = frames.copy()
    with torch.inference_mode():
        mu, sd, state = net.filter(torch.as_tensor(frames, device=device))
    return mu.cpu().numpy().astype(np.float64), sd.cpu().numpy().astype(np.float64), state


def system_posteriors(net, stages, frames: np.ndarray, device, extent):
    """A system's network (``presets.VIEW``) then ``stages`` over (N, T, H, W) checked videos.

    Returns
    -------
    m, s : ndarray, shape (N, T, P)
        Every frame's normalised parameter posterior after the stages, the network's order.
    pts : ndarray, shape (N, T, K, 2)
        The network's points, metres (``extent`` ``(x0, x1, y0, y1)`` of its view).
    state : RecurrentState
        After the last frame.
    """
    c = net.config
    mu, sd, state = latent_pass(net, frames, device)
    pidx = [c.targets.index(p) for p in c.params]
    m, s = mu[..., pidx], sd[..., pidx]
    x0, x1, y0, y1 = extent
    p = mu[..., [c.targets.index(q) for q in c.positions]]
    pts = p.reshape(*p.shape[:-1], -1, 2) * np.array([x1 - x0, y1 - y0]) + np.array([x0, y0])
    for stage in stages:
        m, s = stage.apply(m, s, pts)
    return m, s, pts, state


def floor_prior(train_record: dict | None) -> tuple[float, float]:
    """Prior mean and std (m) of the floor in the network's height frame, from a checkpoint's
    ``train`` record: a network trained with the floor raised by ``U(0, floor_offset)`` reads
    heights above the floor it expects, so the state fit fits the floor from this uniform's
    spread; otherwise the floor is the track's zero (5 mm)."""
    nuis = (train_record or {}).get("nuisance") or {}
    spread = float(nuis.get("floor_offset", 0.0)) / np.sqrt(12.0)
    return 0.0, max(spread, 0.005)


def resolve_device(device: str = "auto") -> torch.device:
    """``"auto"``: CUDA when available, else CPU; otherwise the named device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {device!r}") from exc


def stream_device(device: str = "auto") -> torch.device:
    """The device a stream of single frames runs on: ``"auto"`` means the CPU.

    A push is one frame through small layers: on a GPU it costs kernel launches and two
    host-device copies (measured on an H200: 2.42 ms a push on CUDA, 0.17 ms on its CPU, issue
    39), so ``"auto"`` streams on the CPU even where a batch would use CUDA; a device named
    explicitly is honoured.
    """
    if device == "auto":
        return torch.device("cpu")
    return resolve_device(device)


@dataclass
class FitContext:
    """What a stage's fit sees: the frozen network, the stages fitted before it, and the
    checkpoint's training record (the videos to fit on are rendered as the network was
    trained: size, nuisances, frames, variant).

    Attributes
    ----------
    net : Vid2ParamNet
        In eval mode; a fit does not change it (the physics prior's noise fit returns a network
        with the trained noise instead).
    pipeline : stages.Pipeline
        The stages before the one being fitted (their outputs are the fit's inputs).
    train : dict
        The checkpoint's ``train`` record.
    source : str
        Name of the checkpoint being fitted, for records and messages.
    device : torch.device
    log : callable
    """

    net: object
    pipeline: object
    train: dict = field(default_factory=dict)
    source: str = "checkpoint"
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    log: object = print

    @property
    def frame_size(self) -> tuple[int, int]:
        return tuple(self.net.config.frame_size)

    @property
    def n_frames(self) -> int:
        return int(self.train.get("n_frames", 200))

    def split(self, n: int, seed: int, n_frames: int | None = None, **kw):
        """``n`` train-split videos (``seed``) rendered as the network was trained."""
        from methods.vid2param.data import make_split

        kw.setdefault("variant", self.train.get("variant", "interleaved"))
        return make_split("train", int(n), int(seed), self.frame_size, self.train.get("nuisance"),
                          self.n_frames if n_frames is None else int(n_frames), **kw)

    def parameters(self, frames: np.ndarray):
        """The parameter posteriors after every frame of (N, T, H, W) checked videos through the
        network and the stages so far: normalised mean, std (N, T, 4), the track (N, T, 2) m,
        and the network's latent stds (N, T, K)."""
        mu, sd, _ = latent_pass(self.net, frames, self.device)
        m, s, pos = self.pipeline.apply(mu, sd, self.net.config.targets)
        return m, s, pos, sd

    def system_parameters(self, frames: np.ndarray, batch: int = 100):
        """:func:`system_posteriors` of (N, T, H, W) videos through the network and the stages
        so far, ``batch`` videos at a time: mean, std (N, T, P), points (N, T, K, 2)."""
        from sysid_bench.core import systems

        extent = systems.get(self.net.config.system).extent
        parts = [system_posteriors(self.net, self.pipeline.stages,
                                   np.asarray(frames[i:i + int(batch)]), self.device, extent)[:3]
                 for i in range(0, len(frames), int(batch))]
        return tuple(np.concatenate(a) for a in zip(*parts))

    def track(self, frames: np.ndarray):
        """One video's (T, H, W) track (T, 2) m and parameter posterior after its last frame,
        physical units (as ``Vid2Param.filtered_track``)."""
        m, s, pos, _ = self.parameters(frames[None])
        return (pos[0], *physical(m[0, -1], s[0, -1]))

    def floor_prior(self) -> tuple[float, float]:
        return floor_prior(self.train)
