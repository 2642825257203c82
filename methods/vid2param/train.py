"""Train Vid2Param: ``python -m methods.vid2param.train --help``.

Training data are fresh chunks of the ``train`` split (sub-ranges 0, 2, 4, 6, 8), each drawn with
its own seed derived from ``--data-seed`` (so no video repeats and the run is reproducible), or a
fixed dataset passed to :func:`train` (what ``Vid2Param.fit`` does). Validation uses the ``test``
split with ``--val-seed`` (distinct from the seed of the reported evaluation).

Every random choice is a function of ``(seed, step)``: a run killed and resumed from its last
state (``<out>/state.pt``, written atomically every ``--ckpt-every`` seconds) continues with the
same batches and noise it would have drawn.

Example (the from-scratch recipe, ``V2PConfig()`` with ``TrainConfig()``; each shipped
checkpoint's own command is in its card and in ``methods/vid2param/README.md``)::

    python -m methods.vid2param.train --out runs/v2p_28x28 --export runs/v2p_28x28.pt
    python -m methods.vid2param.train --out runs/camera --preset camera   # the 100x50 model
    python -m methods.vid2param.train --system pendulum --out runs/pendulum \
        --export runs/v2p_pendulum.pt   # another system's model, from scratch
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import functools
import json
import math
import numbers
import os
import sys
import time
import typing
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
from tqdm.auto import tqdm

from methods.vid2param import presets
from methods.vid2param.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    SHIPPED_CHECKPOINTS,
    build_net,
    checkpoint_path,
    git_info,
    load_checkpoint,
    record_name,
    save_atomic,
    source_sha256,
    upgrade_optimizer_state,
    upgrade_state_dict,
)
from methods.vid2param.data import (
    PointVideos,
    chunk_seed,
    make_split,
    make_system_split,
    perturb_dataset,
    rolls_mask,
    targets_from_dataset,
)
from methods.vid2param.inference import FitContext, resolve_device
from methods.vid2param.model import V2PConfig, Vid2ParamNet, count_parameters
from methods.vid2param.stages import (
    LEGACY_KEYS,
    STAGES,
    Pipeline,
    calibrate,
)
from sysid_bench.core import systems
from sysid_bench.core._io import atomic_write
from sysid_bench.core._validate import SEED_MAX

__all__ = ["TrainConfig", "train", "evaluate", "export", "fit_stages", "parse_stages",
           "calibrate", "resolve_device", "load_matching", "main"]


@dataclass(frozen=True)
class Range:
    """The range of a numeric field, declared once in its annotation
    (``Annotated[int, Range(1)]``): ``TrainConfig`` checks it on construction and the training
    command's flags take it (``--help`` shows it, a value outside is refused before anything is
    built). A tuple field's range holds for each of its values.

    Attributes
    ----------
    lo, hi : float, optional
        Bounds (None: unbounded), inclusive unless ``lo_open``.
    lo_open : bool
        Exclude ``lo`` itself (a positive rate).
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False

    def text(self, kind: type) -> str:
        """The range as words: ``"an int >= 1"``, ``"a float in (0, 1]"``."""
        what = "an int" if kind is int else "a float"
        lo, hi = self._num(self.lo, kind), self._num(self.hi, kind)
        if self.hi is not None:
            return f"{what} in {'(' if self.lo_open else '['}{lo}, {hi}]"
        return f"{what} {'>' if self.lo_open else '>='} {lo}"

    @staticmethod
    def _num(x, kind: type) -> str:
        return "" if x is None else str(int(x)) if kind is int else f"{x:g}"

    def metavar(self, kind: type) -> str:
        """The range for ``--help``: ``INT>=1``, ``FLOAT(0,1]``."""
        name = kind.__name__.upper()
        lo, hi = self._num(self.lo, kind), self._num(self.hi, kind)
        if self.hi is not None:
            return f"{name}{'(' if self.lo_open else '['}{lo},{hi}]"
        return f"{name}{'>' if self.lo_open else '>='}{lo}"

    def check(self, name: str, value, kind: type):
        """``value`` as ``kind`` if it is one in the range, else a ``ValueError`` naming
        ``name``, the range and the value."""
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
        if ok:
            v = float(value)
            ok = (math.isfinite(v) and (kind is float or v == int(v))
                  and (self.lo is None or (v > self.lo if self.lo_open else v >= self.lo))
                  and (self.hi is None or v <= self.hi))
        if not ok:
            raise ValueError(f"{name}: expected {self.text(kind)}, got {value!r}")
        return kind(value)

    @staticmethod
    @functools.cache
    def of(cls) -> dict[str, tuple[Range, type]]:
        """``{field: (range, kind)}`` of the dataclass ``cls``'s ranged fields (``kind``: int or
        float, a tuple field's element type; ``X | None``: X's)."""
        out = {}
        for name, hint in typing.get_type_hints(cls, include_extras=True).items():
            if typing.get_origin(hint) is not Annotated:
                continue
            base, *meta = typing.get_args(hint)
            rng = next((m for m in meta if isinstance(m, Range)), None)
            if rng is None:
                continue
            kinds = [a for a in (typing.get_args(base) or (base,)) if a not in (type(None), Ellipsis)]
            out[name] = (rng, kinds[0])
        return out

    @classmethod
    def check_fields(cls, obj) -> None:
        """Check every ranged field of the dataclass instance ``obj`` (None passes: unset)."""
        for name, (rng, kind) in cls.of(type(obj)).items():
            v = getattr(obj, name)
            for x in (v if isinstance(v, (tuple, list)) else () if v is None else (v,)):
                rng.check(name, x, kind)


#: Annotation marker of a field given on the command line as JSON (``'{"blur": 0.5}'``,
#: ``null`` for None).
JSON = "json"


@dataclass
class TrainConfig:
    """Optimisation and data settings (stored in checkpoints).

    Attributes
    ----------
    steps : int
        Optimiser steps (batches) in total.
    batch : int
        Videos per batch.
    lr : float
        Adam learning rate: linear warm-up for ``warmup`` steps, then cosine decay to ``lr_min``.
    lr_min : float
        The learning rate at the last step (the cosine's end).
    warmup : int
        Steps of the linear learning-rate warm-up.
    seed : int
        Initial weights, batch order, sampling noise, observed lengths.
    data_seed : int
        Seeds of the training chunks.
    chunk : int
        Fresh training videos generated at a time (memory: chunk x T x H x W bytes).
    chunk_epochs : int
        Passes over each chunk before the next is drawn (1: every video seen once). A system
        whose videos are slow to draw (the pendulum's, ~0.1 s each) reuses them so a GPU is
        not left waiting; a system's chunk is drawn by ``threads`` threads.
    n_frames : int
        Frames per training video.
    rec_frac : float
        Fraction of frames decoded for the reconstruction term (see ``Vid2ParamNet.forward``).
    p_full : float
        Probability that a batch is observed for all frames; otherwise only the first
        ``U[min_obs, n_frames)`` frames are observed and the rest forecast from the prior.
    min_obs : int
        Fewest observed frames of a partly observed batch.
    p_blank : float
        Probability that a video's frames are all blanked (ball never seen), so the network
        learns to answer such input with a wide posterior near the prior.
    clip : float
        Gradient-norm clip.
    val_n : int
        Validation videos (``test`` split; 0: no validation).
    val_seed : int
        Seed of the validation videos.
    val_every : int
        Steps between validations (and one at the end).
    ckpt_every : float
        Seconds between resumable states.
    threads : int
        ``torch.set_num_threads`` on CPU (a resumed run takes the value given now).
    nll_only_steps : int
        Warm-up: for the first steps the loss is the encoder's NLL of the supervised dimensions
        alone, as a plain recurrent regressor; the VRNN terms (reconstruction, KL, the prior's
        NLL) join afterwards. Measured on CPU (500 steps, all terms from the start): a ridge
        probe found no trace of g in the LSTM state, while the same LSTM trained on the NLL
        alone (a probe script, since removed) reads g by step 500.
    early_aux_grad : float
        Scale of the gradient the prior and the decoder send into the recurrent state during
        the first ``early_aux_grad_steps`` steps.
    early_aux_grad_steps : int
        Steps of that early phase: the prior and the decoder send back into the recurrent
        state ``early_aux_grad`` of their gradient instead of the model's ``aux_grad``
        (``Vid2ParamNet.forward``); 0 steps: the model's value throughout (fine-tunes). The
        shipped model first learnt to identify with 0.01.
    size : (int, int)
        Frame size (H, W).
    nuisance : dict, optional
        Options passed to the renderer through ``make_dataset`` (camera-like configuration).
    perturb : dict, optional
        ``{"spin": s, "dwell": d, "p": q}``: a fraction q of the training videos is
        re-simulated with a spin loss ``U(0, s)`` and a contact dwell ``U(0, d)`` s
        (``data.perturb_dataset``), so the network meets physics that is not exactly ours.
    init : str, optional
        Checkpoint the weights started from (fine-tuning; see :func:`load_matching`).
    variant : str
        ``sysid_bench.core.datasets`` variant of the training chunks: ``"interleaved"`` (the shipped
        models), or a sensitivity condition's (``"extrapolation"``, ``"noisy"``,
        ``"simplified"``, ``"changing"``), with its ``variant_options`` (e.g.
        ``{"param": "e"}``, ``{"label_noise": 0.25}``). Validation stays on the interleaved
        test split.
    variant_options : dict, optional
        Options of ``variant`` (e.g. ``{"param": "e"}``).
    points_steps : int
        Curriculum (a system's network whose K points are its K fixed keypoint channels:
        channel 0, and channel 1 with ``V2PConfig.kp_second``): for the first steps the network
        is fed no frames but the tracked points as its keypoints would see them
        (``Vid2ParamNet.point_features``: true positions of fresh train-split trajectories
        with Gaussian noise of ``points_noise_px`` pixels), and the loss is the encoder's NLL
        alone; no convolution runs, so a step costs the recurrence only (~20x cheaper). The
        posterior's weights on the other frame features start at zero
        (``Vid2ParamNet.read_points_only_``), so the network reads rendered frames as it read
        the points and the frame steps that follow start from what was learnt.
    points_noise_px : float
        Standard deviation (pixels of the frame) of the points' keypoint noise; the keypoint
        centroid of the systems' rendered frames is off by 0.03 px RMS (pendulum, spring).
    points_positions : bool
        The points curriculum's NLL includes the positions (the keypoint's x, y, whose std
        sinks to the 1e-3 floor and whose gradient then swamps the parameters' in the shared
        weights); off: the parameters' NLL alone, as the probe (docs/vid2param-systems-probe.md),
        and the positions stay channel 0's centroid (``KeypointPosition.gate`` at 0).
    """

    steps: Annotated[int, Range(1)] = 4000
    batch: Annotated[int, Range(1)] = 32
    lr: Annotated[float, Range(0, lo_open=True)] = 1e-3
    lr_min: Annotated[float, Range(0)] = 5e-5
    warmup: Annotated[int, Range(0)] = 100
    seed: Annotated[int, Range(0, SEED_MAX)] = 0
    data_seed: Annotated[int, Range(0, SEED_MAX)] = 0
    chunk: Annotated[int, Range(1)] = 2000
    chunk_epochs: Annotated[int, Range(1)] = 1
    n_frames: Annotated[int, Range(2)] = 200
    rec_frac: Annotated[float, Range(0, 1, lo_open=True)] = 0.25
    p_full: Annotated[float, Range(0, 1)] = 0.7
    min_obs: Annotated[int, Range(1)] = 50
    p_blank: Annotated[float, Range(0, 1)] = 0.02
    clip: Annotated[float, Range(0, lo_open=True)] = 10.0
    val_n: Annotated[int, Range(0)] = 200
    val_seed: Annotated[int, Range(0, SEED_MAX)] = 1
    val_every: Annotated[int, Range(1)] = 250
    ckpt_every: Annotated[float, Range(0, lo_open=True)] = 180.0
    threads: Annotated[int, Range(1)] = 1
    nll_only_steps: Annotated[int, Range(0)] = 600
    early_aux_grad: Annotated[float, Range(0, 1)] = 0.01
    early_aux_grad_steps: Annotated[int, Range(0)] = 3200
    size: Annotated[tuple[int, int], Range(4)] = (28, 28)
    nuisance: Annotated[dict | None, JSON] = field(default=None)
    perturb: Annotated[dict | None, JSON] = field(default=None)
    init: str | None = None
    variant: str = "interleaved"
    variant_options: Annotated[dict | None, JSON] = field(default=None)
    points_steps: Annotated[int, Range(0)] = 0
    points_noise_px: Annotated[float, Range(0)] = 0.03
    points_positions: bool = True

    def __post_init__(self) -> None:
        from sysid_bench.core.datasets import VARIANTS

        if self.variant not in VARIANTS:
            raise ValueError(f"variant: expected one of {VARIANTS}, got {self.variant!r}")
        if self.variant_options is not None and not isinstance(self.variant_options, dict):
            raise ValueError(f"variant_options: expected a dict, got {self.variant_options!r}")
        Range.check_fields(self)  # every field's range, from its annotation
        if int(self.points_steps) > int(self.steps):
            raise ValueError(f"points_steps: expected an int in [0, steps={self.steps}], got "
                             f"{self.points_steps!r}")
        if self.perturb is not None:
            bad = set(self.perturb) - {"spin", "dwell", "p"}
            if bad or not isinstance(self.perturb, dict):
                raise ValueError(
                    f"perturb: expected a dict with keys among spin, dwell, p, got {self.perturb!r}"
                )

    @classmethod
    def recipe(cls, steps: int | None = None, **overrides) -> TrainConfig:
        """The from-scratch recipe with its length set to ``steps``: the warm-up phases
        (``nll_only_steps``, ``early_aux_grad_steps``) keep their share of the default
        length. ``overrides`` set any other field."""
        d = cls()
        if steps is None:
            return cls(**overrides)
        steps = int(steps)
        if steps < 1:
            raise ValueError(f"steps: expected an int >= 1, got {steps}")
        shares = {"nll_only_steps": steps * d.nll_only_steps // d.steps,
                  "early_aux_grad_steps": steps * d.early_aux_grad_steps // d.steps}
        return cls(**{"steps": steps, **shares, **overrides})

    def to_dict(self) -> dict:
        d = asdict(self)
        d["size"] = list(self.size)
        return d


def init_record(path) -> dict:
    """Identity of a checkpoint a run starts from: path, sha256 of its bytes, and its config,
    training record, commit and validation metrics. Taken when the run starts, since the file
    may be replaced later (a shipped checkpoint refined in place)."""
    import hashlib

    src = load_checkpoint(checkpoint_path(path))
    return {
        "path": record_name(path),  # a shipped checkpoint's name, no machine path
        "sha256": hashlib.sha256(checkpoint_path(path).read_bytes()).hexdigest(),
        **{k: src.get(k) for k in ("config", "train", "git_commit", "val_metrics")},
    }


#: First-layer weights whose new inputs, if any, are appended at the end of the old ones.
_WIDENED = ("recurrence.cell.weight_ih", "posterior.mlp.0.weight", "prior.mlp.0.weight",
            "decoder.fc.0.weight")


def load_matching(net: Vid2ParamNet, path) -> tuple[list[str], list[str]]:
    """Copy into ``net`` every tensor of the checkpoint at ``path`` whose name and shape match.

    For fine-tuning from another configuration (a new loss weight or flag, another frame
    size): what the two networks share starts trained, the rest starts fresh. Older weight
    names are read as today's (``checkpoint.RENAMED``). The keypoint map is never copied: it is
    set from ``net``'s own view geometry. From a checkpoint whose prior was absolute (the
    removed ``prior_residual`` option off), the prior's x, y means start at a step of 0. A
    first-layer weight whose input has grown by inputs appended at its end (the heads' with
    ``roll_features``) gets the old columns and zeros for the new ones, so the fine-tune starts
    from exactly the old network's function.

    Returns
    -------
    loaded, skipped : list of str
        Names of ``net``'s tensors copied and not copied.
    """
    ck = load_checkpoint(path)
    src = upgrade_state_dict(ck["state_dict"])
    own = net.state_dict()
    loaded, skipped = [], []
    for name, val in own.items():
        other = src.get(name)
        if other is not None and other.shape == val.shape and not name.startswith("keypoints.map."):
            own[name] = other.to(val.dtype)
            loaded.append(name)
        elif (other is not None and name in _WIDENED and other.ndim == 2
              and other.shape[0] == val.shape[0] and other.shape[1] < val.shape[1]):
            w = torch.zeros_like(val)
            w[:, : other.shape[1]] = other.to(val.dtype)
            own[name] = w
            loaded.append(name)
        else:
            skipped.append(name)
    c = net.config
    if not ck["config"].get("prior_residual", True):
        # the source prior predicts absolute positions; as a step from the last position start
        # its x, y means at 0 ("stay put") instead of doubling the position
        w, b = own["prior.mlp.2.weight"], own["prior.mlp.2.bias"]
        for name in ("x", "y"):
            w[c.targets.index(name)] = 0.0
            b[c.targets.index(name)] = 0.0
    net.load_state_dict(own)
    return loaded, skipped


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask; ``os.cpu_count`` elsewhere)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity call (macOS, Windows)
        return max(1, os.cpu_count() or 1)


def train_threads(threads: int) -> int:
    """The torch threads a CPU run uses for ``TrainConfig.threads``: at most the usable cores.

    More threads than free cores is the training step's worst case: OpenMP's threads wait for
    each other at every one of the ~10^4 small operations of a step, and a descheduled thread
    stalls the rest (on 2 cores shared with ~6 other busy processes, a pendulum step of 8
    videos took 69-98 s wall with 2 threads, 4.5-5.2 s with 1; docs/vid2param-training-speed.md).
    The systems' presets ask for 4 (a GPU machine's data threads).
    """
    return max(1, min(int(threads), usable_cores()))


def feed_steps_per_chunk(tc: TrainConfig) -> int:
    """Optimiser steps one fresh chunk feeds (``chunk * chunk_epochs // batch``)."""
    return max(1, tc.chunk * tc.chunk_epochs // tc.batch)


def _lr_at(step: int, tc: TrainConfig) -> float:
    """The learning rate at schedule step ``step``: linear warm-up over ``warmup`` steps, then
    cosine from ``lr`` down to ``lr_min`` at ``steps``."""
    if step < tc.warmup:
        return tc.lr * (step + 1) / tc.warmup
    frac = (step - tc.warmup) / max(1, tc.steps - tc.warmup)
    return tc.lr_min + 0.5 * (tc.lr - tc.lr_min) * (1 + math.cos(math.pi * min(1.0, frac)))


def lr_schedule(opt: torch.optim.Optimizer, tc: TrainConfig) -> torch.optim.lr_scheduler.LambdaLR:
    """``opt``'s learning-rate schedule (:func:`_lr_at`) as a ``torch.optim.lr_scheduler``.

    The lambda gives the rate itself over a base rate of exactly 1 (``1.0 * x == x``), so every
    step's rate is :func:`_lr_at`'s bit for bit (``tc.lr`` times a factor would round). Move it
    to schedule step ``k`` with :func:`set_schedule_step` (``time_schedule`` may skip steps).
    """
    for g in opt.param_groups:
        g["initial_lr"] = 1.0
    return torch.optim.lr_scheduler.LambdaLR(opt, lambda k: _lr_at(k, tc), last_epoch=-1)


def set_schedule_step(sched: torch.optim.lr_scheduler.LambdaLR, step: int) -> float:
    """Set ``sched``'s optimizer to the rate of schedule step ``step``; returns that rate."""
    sched.last_epoch = int(step) - 1  # step() advances it by one, to ``step``
    with warnings.catch_warnings():
        # set before the step's optimizer.step() on purpose: the rate the step uses
        warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step", category=UserWarning)
        sched.step()
    return sched.get_last_lr()[0]


class _Feed:
    """Batches of (frames, targets), a pure function of (seed, step).

    With ``dataset`` given, chunk k is epoch k over that dataset; else chunk k is a fresh draw
    of ``chunk`` videos from the train split with seed ``chunk_seed(data_seed, k)``. With
    ``prefetch`` chunk k + 1 is drawn on a background thread while chunk k's batches train (the
    same batches; ``close`` ends the thread).
    """

    def __init__(self, tc: TrainConfig, targets: tuple[str, ...], dataset=None,
                 system: str = "ball", prefetch: bool = False):
        self.tc, self.names, self.system = tc, targets, system
        self.prefetch = bool(prefetch)
        self.fixed = dataset
        if dataset is not None:
            self.frames = np.asarray(dataset.frames)
            self.targets = targets_from_dataset(dataset, targets)
            self.per_chunk = len(self.frames) // tc.batch
            if self.per_chunk < 1:
                raise ValueError(
                    f"train: expected at least batch={tc.batch} videos, got {len(self.frames)}"
                )
        else:
            self.per_chunk = tc.chunk * tc.chunk_epochs // tc.batch
        self.k = None
        self.supervised = None
        self._ahead = None  # (k, thread, result box) of the chunk drawn in the background

    def _draw(self, k: int, workers: int) -> tuple[np.ndarray, np.ndarray]:
        """Chunk k's frames (N, T, H, W) and targets (N, T, K): a function of (data_seed, k)
        only (the videos do not depend on ``workers``)."""
        tc = self.tc
        seed = chunk_seed(tc.data_seed, k)
        if presets.space_of(self.system) == presets.VIEW:
            ds = make_system_split(self.system, "train", tc.chunk, seed, tc.n_frames,
                                   tc.size, tc.nuisance, workers=workers)
        else:
            ds = make_split("train", tc.chunk, seed, tc.size, tc.nuisance, tc.n_frames,
                            variant=tc.variant, **(tc.variant_options or {}))
        if tc.perturb:
            ds = perturb_dataset(ds, seed=seed, **tc.perturb)
        return np.asarray(ds.frames), targets_from_dataset(ds, self.names)

    def _draw_ahead(self, k: int) -> None:
        """Start drawing chunk k on one background thread, so the steps of the chunk before it
        do not wait for it when it is due (a pendulum chunk of 1600 videos is minutes of one
        core; the renderers' array work releases the GIL). A daemon thread: a run that stops
        early (``max_minutes``) does not wait for a chunk it will not use."""
        import threading

        box: dict = {}

        def work() -> None:
            try:
                box["out"] = self._draw(k, 1)
            except BaseException as e:  # re-raised by the step that needs the chunk
                box["error"] = e

        th = threading.Thread(target=work, name="vid2param-feed", daemon=True)
        th.start()
        self._ahead = (k, th, box)

    def _take_ahead(self) -> tuple[np.ndarray, np.ndarray]:
        _, th, box = self._ahead
        th.join()
        if "error" in box:
            raise box["error"]
        return box["out"]

    def close(self) -> None:
        """Forget a chunk being drawn ahead (its daemon thread ends with the process)."""
        self._ahead = None

    def _load_chunk(self, k: int) -> None:
        tc = self.tc
        if self.fixed is None:
            if self._ahead is not None and self._ahead[0] == k:
                self.frames, self.targets = self._take_ahead()
            else:  # the first chunk (or a jump): all usable cores draw it, nothing else runs
                self.frames, self.targets = self._draw(k, train_threads(tc.threads))
            self._ahead = None
            if self.prefetch:
                self._draw_ahead(k + 1)
        # a label equal in every video of the chunk (a fixed parameter) is not supervised
        spread = np.ptp(self.targets.reshape(-1, self.targets.shape[-1]), axis=0)
        self.supervised = None if (spread > 0).all() else spread > 0
        rng = np.random.default_rng([tc.seed, k, 17])
        self.order = rng.permutation(len(self.frames))
        if self.fixed is None and tc.chunk_epochs > 1:
            self.order = np.concatenate([self.order] + [rng.permutation(len(self.frames))
                                                        for _ in range(tc.chunk_epochs - 1)])
        self.k = k

    def batch(self, step: int):
        k, pos = divmod(step, self.per_chunk)
        if k != self.k:
            self._load_chunk(k)
        idx = np.sort(self.order[pos * self.tc.batch : (pos + 1) * self.tc.batch])
        return self.frames[idx], self.targets[idx]

    def supervised_targets(self, step: int):
        """(K,) bool: the targets that vary in ``step``'s chunk; None when all do."""
        if divmod(step, self.per_chunk)[0] != self.k:
            self.batch(step)
        return self.supervised


class _PointFeed:
    """Batches of (points, targets) for the points curriculum (``TrainConfig.points_steps``):
    ``batch`` fresh train-split trajectories per step, a pure function of (data_seed, step).

    Simulating is ~0.03 s for 64 trajectories of 200 frames (no rendering), so every step
    draws its own: no trajectory is seen twice.
    """

    def __init__(self, tc: TrainConfig, targets: tuple[str, ...], system: str):
        from methods.vid2param.model import position_names

        self.tc, self.names, self.sys = tc, targets, systems.get(system)
        pos = position_names(self.sys.n_points)
        #: (K,) bool: the parameter targets (``TrainConfig.points_positions`` off)
        self.params_only = np.array([n not in pos for n in targets])
        #: (K,) bool: the targets that vary in the last batch (a condition's held parameters,
        #: ``simplified``, do not)
        self.varying = np.ones(len(targets), dtype=bool)

    def supervised(self) -> np.ndarray | None:
        """(K,) bool: the targets whose NLL counts in the last batch, None for all. A target
        held at one value (the simplified condition's) is left out, as the frames feed leaves
        it out (``_Feed.supervised_targets``): its NLL, with a std free to shrink, grew without
        bound and its gradient drowned every other target's (the pendulum's first simplified
        model learnt neither g nor L in 800 steps)."""
        keep = self.varying if self.tc.points_positions else self.varying & self.params_only
        return None if keep.all() else keep

    def batch(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """The system's P points (B, T, 2 P) in the view's unit square with keypoint noise
        (``x, y, x1, y1, ...``), and targets (B, T, K), both float32."""
        from methods.vid2param.data import normalise_points, system_targets_from_arrays

        tc, s = self.tc, self.sys
        rng = np.random.default_rng([tc.data_seed, int(step), 29])
        # the training condition's draws (System.sample_variant; "interleaved" draws as
        # sample_cases, so the shipped models' batches are unchanged)
        theta, labels, state0, _ = s.sample_variant(tc.batch, rng, "train", tc.variant,
                                                    **(tc.variant_options or {}))
        states = s.simulate(theta, state0, n_frames=tc.n_frames, dt=0.05)
        pts = s.observe(states, theta)
        tg = system_targets_from_arrays(s, pts, labels, self.names)
        h, w = tc.size
        seen = normalise_points(pts, s.extent)  # (B, T, P, 2)
        seen = seen + rng.normal(size=seen.shape) * (tc.points_noise_px / np.array([w, h]))
        self.varying = np.ptp(tg.reshape(-1, tg.shape[-1]), axis=0) > 0
        return seen.reshape(*seen.shape[:2], -1).astype(np.float32), tg


def _frame_step(net, opt, schedule, feed, tc: TrainConfig, step: int, sched: int, dev):
    """One step's forward and backward on a batch of frames (the optimiser steps after it):
    returns the learning rate set and the loss terms."""
    fr_np, tg_np = feed.batch(step)
    rng = np.random.default_rng([tc.seed, step])
    T = fr_np.shape[1]
    n_obs = T if rng.random() < tc.p_full else int(rng.integers(tc.min_obs, T))
    fr = torch.as_tensor(fr_np, device=dev)
    blank = rng.random(len(fr_np)) < tc.p_blank
    if blank.any():
        fr = fr.clone()
        fr[torch.as_tensor(blank, device=dev)] = 0
    gen = torch.Generator(device=dev).manual_seed(int(rng.integers(2**62)))
    lr_now = set_schedule_step(schedule, sched)
    aux = tc.early_aux_grad if sched < tc.early_aux_grad_steps else None
    outd = net(fr, torch.as_tensor(tg_np, device=dev), n_obs=n_obs, rec_frac=tc.rec_frac,
               generator=gen, aux_grad=aux, supervised=feed.supervised_targets(step))
    opt.zero_grad(set_to_none=True)
    (outd["loss"] if sched >= tc.nll_only_steps else outd["loss_nll"]).backward()
    return lr_now, outd


@torch.no_grad()
def _prefix_posteriors(net: Vid2ParamNet, frames: np.ndarray, lengths, batch: int = 100,
                       device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """Encoder means and stds of the supervised dimensions after each of ``lengths`` frames,
    one filtering pass per ``batch`` videos: two arrays (N, L, K)."""
    sel = [int(L) - 1 for L in lengths]
    K = len(net.config.targets)
    mus, stds = [], []
    for i in range(0, len(frames), batch):
        mu, sd, _ = net.filter(torch.as_tensor(frames[i : i + batch], device=device))
        mus.append(mu[:, sel, :K].cpu().numpy())
        stds.append(sd[:, sel, :K].cpu().numpy())
    return np.concatenate(mus), np.concatenate(stds)


@torch.no_grad()
def evaluate(net: Vid2ParamNet, ds, lengths=(10, 25, 50, 100, 150, 200), batch: int = 100,
             device="cpu") -> dict:
    """Parameter errors of the encoder posterior after each of ``lengths`` frames.

    Errors are MSEs of parameters normalised by ``PRIOR``; ``r`` is reported over all videos
    and over those in which the ball rolls (``rolls_mask``).

    Parameters
    ----------
    net : Vid2ParamNet
    ds : Dataset-like with frames (N, T, H, W), states (N, T, 4), theta/labels, floor (N,)

    Returns
    -------
    dict
        ``nmse`` {length: {param: float}}, ``nmse_r_rolling`` {length: float},
        ``coverage90`` / ``coverage50`` {param: float} at the last length,
        ``r_std_not_rolling`` mean posterior std of normalised r where the ball never rolls,
        ``n``, ``n_rolling``.
    """
    names = net.config.targets
    tg = targets_from_dataset(ds, names)
    frames = np.asarray(ds.frames)
    n, t = frames.shape[:2]
    lengths = [int(L) for L in lengths if L <= t]
    mu, sd = _prefix_posteriors(net, frames, lengths, batch, device)  # (N, L, K)
    truth = tg[:, [L - 1 for L in lengths]]
    if isinstance(ds, PointVideos):
        return _evaluate_system(net.config, mu, sd, truth, lengths)
    rolls = rolls_mask(ds.states, ds.floor)
    params = [p for p in ("e", "g", "d", "r") if p in names]
    out = {"n": int(n), "n_rolling": int(rolls.sum()), "nmse": {}, "nmse_r_rolling": {}}
    err = (mu - truth) ** 2
    for j, L in enumerate(lengths):
        out["nmse"][L] = {p: float(err[:, j, names.index(p)].mean()) for p in params}
        if "r" in names and rolls.any():
            out["nmse_r_rolling"][L] = float(err[rolls, j, names.index("r")].mean())
    z = np.abs(mu[:, -1] - truth[:, -1]) / sd[:, -1]
    out["coverage90"] = {p: float((z[:, names.index(p)] <= 1.6448536).mean()) for p in params}
    out["coverage50"] = {p: float((z[:, names.index(p)] <= 0.6744898).mean()) for p in params}
    if "r" in names and (~rolls).any():
        out["r_std_not_rolling"] = float(sd[~rolls, -1, names.index("r")].mean())
        out["r_std_rolling"] = float(sd[rolls, -1, names.index("r")].mean()) if rolls.any() else None
    return out


def _evaluate_system(config, mu, sd, truth, lengths) -> dict:
    """``evaluate`` of a system's network: per parameter, the nMSE after each length (errors of
    prior-normalised parameters), 90% and 50% coverage at the last length, and the RMS error
    of the points (normalised by the view) at each length."""
    names = list(config.targets)
    params, pos = config.params, [names.index(p) for p in config.positions]
    err = (mu - truth) ** 2
    out = {"n": int(len(mu)), "nmse": {}, "nmse_r_rolling": {}, "points_rmse": {}}
    for j, L in enumerate(lengths):
        out["nmse"][L] = {p: float(err[:, j, names.index(p)].mean()) for p in params}
        out["points_rmse"][L] = float(np.sqrt(err[:, j, pos].mean()))
    z = np.abs(mu[:, -1] - truth[:, -1]) / sd[:, -1]
    out["coverage90"] = {p: float((z[:, names.index(p)] <= 1.6448536).mean()) for p in params}
    out["coverage50"] = {p: float((z[:, names.index(p)] <= 0.6744898).mean()) for p in params}
    return out


def val_nmse(m: dict) -> float:
    """The validation metrics ``m``'s nMSE after the most frames, averaged over the parameters
    (what the progress bar shows)."""
    return float(np.mean(list(m["nmse"][max(m["nmse"])].values())))


def _summary(m: dict) -> str:
    L = max(m["nmse"])
    s = " ".join(f"{p}={v:.4f}" for p, v in m["nmse"][L].items())
    r = m["nmse_r_rolling"].get(L)
    cov = " ".join(f"{p}={v:.2f}" for p, v in m["coverage90"].items())
    return f"nMSE@{L}: {s} r_rolling={r if r is None else round(r, 4)} | cov90: {cov}"


def _state_dict(net, opt, mc, tc, step, wall, history, final=False, init=None) -> dict:
    ck = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": mc.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
        "train": {**tc.to_dict(), "step": int(step), "wall_s": float(wall)},
        "git_commit": git_info(),
        "source_sha256": source_sha256(),
        "torch_version": str(torch.__version__),
        "val_history": history,
        "val_metrics": history[-1][1] if history else None,
    }
    if init is not None:
        ck["init_checkpoint"] = init
    if not final:
        ck["optimizer"] = opt.state_dict()
    return ck


def _jsonable(o):
    if isinstance(o, torch.Tensor):
        return o.tolist()
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return o


def export_card(path) -> Path:
    """Write the JSON card of a shipped checkpoint next to it (``.json``), atomically."""
    path = Path(path)
    ck = load_checkpoint(path)
    info = {k: ck.get(k) for k in ("format", "format_version", "config", "train", "git_commit",
                                    "source_sha256", "torch_version", "val_metrics",
                                    "init_checkpoint", "stages", *LEGACY_KEYS) if k in ck}
    info["file_bytes"] = path.stat().st_size
    info["n_parameters"] = int(sum(v.numel() for v in ck["state_dict"].values()))
    text = json.dumps(_jsonable(info), indent=1, sort_keys=True)
    return atomic_write(path.with_suffix(".json"), text + "\n")


def export(state_path, out_path, card: bool = True, stages=(), record: dict | None = None) -> Path:
    """Write a shipped checkpoint (no optimizer state) and a JSON card from a training state,
    then fit ``stages`` after its network (:func:`fit_stages`).

    Parameters
    ----------
    state_path : path of ``state.pt`` written by :func:`train`
    out_path : path of the ``.pt`` to write; the card goes next to it as ``.json``.
    stages : sequence of (name, options)
        The stages to fit, in order (``presets.Preset.stages``; :func:`parse_stages`).
    record : dict, optional
        Added to the checkpoint's ``train`` record (e.g. that ``--max-minutes`` ended the run
        before its ``steps``).
    """
    ck = load_checkpoint(state_path)
    ck.pop("optimizer", None)
    if record:
        ck["train"] = {**ck["train"], **record}
    out_path = Path(out_path)
    init = (ck.get("train") or {}).get("init")
    if init and "init_checkpoint" not in ck and checkpoint_path(init).exists():
        # states written before the record was taken at the start: identify the file now
        ck["init_checkpoint"] = init_record(init)
    ck["stages"] = []  # the network alone until the stages are fitted
    for key in LEGACY_KEYS:
        ck.pop(key, None)
    save_atomic(ck, out_path)
    if stages:
        return fit_stages(out_path, out_path, stages, card=card)
    if card:
        export_card(out_path)
    return out_path


def parse_stages(specs) -> list[tuple[str, dict]]:
    """Stage specs as ``[(name, options)]``: each a ``(name, options)`` pair or a string
    ``"name"`` / ``"name:key=value,key=value"`` (values read as JSON where they parse)."""
    out = []
    for spec in specs:
        if isinstance(spec, str):
            name, _, rest = spec.partition(":")
            opts = {}
            for item in filter(None, rest.split(",")):
                key, eq, val = item.partition("=")
                if not eq:
                    raise ValueError(f"stages: expected name:key=value,..., got {spec!r}")
                try:
                    opts[key.strip()] = json.loads(val)
                except json.JSONDecodeError:
                    opts[key.strip()] = val
            spec = (name, opts)
        name, opts = spec
        if name not in STAGES:
            raise ValueError(f"stages: unknown stage {name!r} (known stages: "
                             f"{', '.join(sorted(STAGES))})")
        opts = dict(opts)
        if opts.get("keep") and len(opts) > 1:
            raise ValueError(f"stages: stage {name!r} is kept as fitted (keep=true), so its "
                             f"options {sorted(k for k in opts if k != 'keep')} would be ignored")
        STAGES[name].check_options({k: v for k, v in opts.items() if k != "keep"})
        out.append((name, opts))
    return out


def fit_stages(checkpoint, out, stages, threads: int | None = None, card: bool = True,
               log=print) -> Path:
    """Fit ``stages`` in order after the network of ``checkpoint`` and write ``out``.

    Each stage is fitted on train videos with the network frozen and the stages before it in
    place (``inference.FitContext``); the checkpoint is written after each stage (a run
    stopped midway keeps the stages fitted so far) with ``checkpoint["stages"]`` in order, and
    its card once at the end. The checkpoint's own stages are replaced, except those given
    with the option ``keep=True``, which are taken as the checkpoint has them (refitting only
    the later ones: ``["prior_noise:keep=true", "drag_evidence:keep=true",
    "physics_calibration"]``).

    Parameters
    ----------
    checkpoint : str or path
        A shipped checkpoint's name or a path.
    out : path
        The checkpoint to write (may be the same file).
    stages : sequence
        ``(name, options)`` pairs or ``"name:key=value"`` strings (:func:`parse_stages`).
    """
    stages = parse_stages(stages)
    path = checkpoint_path(checkpoint)
    ck = dict(load_checkpoint(path))
    net = build_net(ck, path)
    old = Pipeline.from_checkpoint(ck, path, net)
    Pipeline.check([n for n, _ in stages], net.config, str(path))
    if threads is not None:
        torch.set_num_threads(int(threads))
    source = record_name(checkpoint)  # a name, not a machine path, in the records
    if source not in SHIPPED_CHECKPOINTS:
        source = Path(path).name
    pipeline = Pipeline()
    ctx = FitContext(net=net, pipeline=pipeline, train=ck.get("train") or {}, source=source,
                     log=log)
    for key in LEGACY_KEYS:
        ck.pop(key, None)
    for name, opts in stages:
        if opts.pop("keep", False):
            stage = old.get(name)
            if stage is None:
                raise ValueError(f"stages: {name!r} is to be kept, but checkpoint {str(path)!r} "
                                 f"has no such stage (it has {old.names})")
            log(f"stage {name}: kept as fitted")
        else:
            log(f"stage {name}: fitting ({opts or 'defaults'})")
            stage = STAGES[name].fit(ctx, **opts)
        stage.bind(ctx.net)
        pipeline.stages.append(stage)
        ck["config"] = ctx.net.config.to_dict()
        ck["state_dict"] = {k: v.detach().cpu().clone() for k, v in ctx.net.state_dict().items()}
        ck["stages"] = pipeline.records()
        save_atomic(ck, out)
    if not stages:
        ck["stages"] = []
        save_atomic(ck, out)
    if card:
        export_card(out)
    return Path(out)


def train(
    model_config: V2PConfig | None = None,
    train_config: TrainConfig | None = None,
    *,
    dataset=None,
    out=None,
    resume: bool = True,
    device: str = "auto",
    max_minutes: float | None = None,
    stop_at: int | None = None,
    progress: bool = True,
    log=None,
    init_net: Vid2ParamNet | None = None,
    validate_on_stop: bool = False,
    time_schedule: bool = False,
) -> tuple[Vid2ParamNet, dict]:
    """Train a Vid2Param network.

    Parameters
    ----------
    model_config : V2PConfig, optional
        Architecture; default ``V2PConfig()``. Ignored when resuming (the state's is used).
    train_config : TrainConfig, optional
    dataset : Dataset, optional
        Fixed training set (epochs over it); default fresh chunks of the train split.
    out : path, optional
        Folder for ``state.pt`` (resumable, atomic, every ``ckpt_every`` s and at the end).
    resume : bool
        Continue from ``<out>/state.pt`` when it exists.
    device : str
        "auto" (CUDA if present), "cpu", "cuda", ...
    max_minutes : float, optional
        Stop after this much wall-clock time (state saved; resume continues the same run).
    stop_at : int, optional
        Stop once this many steps are done (state saved), e.g. to change ``steps`` (the
        learning-rate schedule's length) on resume at an exact step.
    progress : bool
        tqdm progress bar.
    log : callable, optional
        Receives progress lines; default prints to stderr.
    init_net : Vid2ParamNet, optional
        Start from these weights (fine-tuning; its config must equal ``model_config``).
    validate_on_stop : bool
        Validate also when ``max_minutes`` ends the run early (a run exported as it stands).
    time_schedule : bool
        With ``max_minutes``: the learning-rate schedule and the warm-up phases advance with the
        share of the budget spent when that is ahead of ``step / steps``, so a run that the
        budget ends early still ends with its schedule run through (batches stay a function
        of the step; the schedule then depends on the machine's speed).

    Returns
    -------
    net : Vid2ParamNet
        In eval mode, on CPU.
    info : dict
        ``step``, ``wall_s``, ``val_history`` [(step, metrics)], ``done`` (all steps run).
    """
    mc = model_config or V2PConfig()
    tc = train_config or TrainConfig()
    if time_schedule and max_minutes is None:
        raise ValueError("time_schedule: expected max_minutes with it, got max_minutes=None")
    dev = resolve_device(device)
    if dev.type == "cpu":
        torch.set_num_threads(train_threads(tc.threads))
    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    state_path = Path(out) / "state.pt" if out is not None else None
    start, wall0, history = 0, 0.0, []
    ck = None
    init_ck = None  # identity of tc.init, kept in every state
    if resume and state_path is not None and state_path.exists():
        ck = load_checkpoint(state_path, expect_resumable=True)
        mc = V2PConfig.from_dict(ck["config"])
        saved = dict(ck["train"])
        start, wall0 = int(saved.pop("step")), float(saved.pop("wall_s"))
        saved["size"] = tuple(saved["size"])
        saved["steps"] = tc.steps  # a resumed run may be extended (or shortened)
        saved["threads"] = tc.threads  # and given the cores that are free now
        tc = TrainConfig(**saved)
        history = [tuple(h) for h in ck.get("val_history", [])]
        init_ck = ck.get("init_checkpoint")
        log(f"resuming from {state_path} at step {start}")
    if tuple(mc.frame_size) != tuple(tc.size):
        raise ValueError(
            f"size: expected the model's frame_size {tuple(mc.frame_size)}, got {tuple(tc.size)}"
        )
    torch.manual_seed(tc.seed)
    net = Vid2ParamNet(mc).to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=tc.lr)
    if ck is not None:
        net.load_state_dict(upgrade_state_dict(ck["state_dict"]))
        opt.load_state_dict(upgrade_optimizer_state(ck["optimizer"], ck["state_dict"], net))
    elif init_net is not None:
        if init_net.config.to_dict() != mc.to_dict():
            raise ValueError("init_net: expected a network with model_config's architecture")
        net.load_state_dict(init_net.state_dict())
    elif tc.init:
        init_ck = init_record(tc.init)
        loaded, skipped = load_matching(net, checkpoint_path(tc.init))
        log(f"init from {tc.init}: {len(loaded)} tensors copied, fresh: {skipped}")
    if tc.points_steps and ck is None:
        # before the optimiser has seen a step: the network reads channel 0's centre only
        net.read_points_only_()  # ValueError for a network whose point is not channel 0's
    schedule = lr_schedule(opt, tc)
    log(f"Vid2Param: {count_parameters(net)} parameters, device {dev}, threads "
        f"{torch.get_num_threads()}, steps {start}->{tc.steps}, batch {tc.batch}")
    # a fresh chunk is drawn ahead only when this run will step into another chunk
    last = min(tc.steps, stop_at if stop_at is not None else tc.steps) - 1
    per = feed_steps_per_chunk(tc)
    prefetch = dataset is None and last // per > start // per
    feed = _Feed(tc, mc.targets, dataset, system=mc.system, prefetch=prefetch)
    point_feed = _PointFeed(tc, mc.targets, mc.system) if tc.points_steps > start else None
    # with the positions unsupervised, the keypoint gate (the MLP's share of x, y) is held at
    # its value: the parameters' NLL would otherwise move the fed-back positions off the points
    hold_gate = point_feed is not None and not tc.points_positions
    net.keypoints.gate.requires_grad_(not hold_gate)
    view = presets.space_of(mc.system) == presets.VIEW
    if view and tc.variant != "interleaved" and tc.points_steps < tc.steps:
        raise ValueError(f"variant: a {mc.system} network trains on {tc.variant!r} data in its "
                         f"points curriculum only, expected points_steps = steps = {tc.steps}, "
                         f"got points_steps = {tc.points_steps}")
    if view and tc.perturb:
        raise ValueError(f"perturb: the ball's physics deviations, expected None for the "
                         f"{mc.system} system, got {tc.perturb!r}")
    if tc.val_n <= 0:
        val = None
    elif view:  # the system's test split, as the ball's
        val = make_system_split(mc.system, "test", tc.val_n, tc.val_seed, tc.n_frames, tc.size,
                                tc.nuisance)
    else:
        val = make_split("test", tc.val_n, tc.val_seed, tc.size, tc.nuisance, tc.n_frames)
    t_start = time.time()
    t_ckpt = t_start

    def wall() -> float:
        return wall0 + time.time() - t_start

    def save(step: int, name: str = "state.pt") -> None:
        if state_path is not None:
            save_atomic(_state_dict(net, opt, mc, tc, step, wall(), history, init=init_ck),
                        state_path.with_name(name))

    # the bar's latest validation nMSE (a resumed run's last) and time left of a budget
    shown = {"val_nmse": f"{val_nmse(history[-1][1]):.4f}"} if history else {}

    def validate(step: int) -> None:
        net.eval()
        m = evaluate(net, val, device=dev)
        net.train()
        history.append((int(step), m))
        shown["val_nmse"] = f"{val_nmse(m):.4f}"
        log(f"[val step {step}, {wall() / 60:.1f} min] {_summary(m)}")

    net.train()
    bar = tqdm(range(start, tc.steps), disable=not progress, mininterval=5 if sys.stderr.isatty() else 60,
               desc="vid2param", initial=start, total=tc.steps)
    run_avg = None
    step = start
    prev_sched = None
    for step in bar:
        # the schedule's step: the step itself, or with ``time_schedule`` the share of the
        # budget spent, whichever is further on
        sched = step if not time_schedule else max(
            step, int(tc.steps * (time.time() - t_start) / (60.0 * max_minutes)))
        if (state_path is not None and prev_sched is not None
                and prev_sched < tc.nll_only_steps <= sched):
            # the network as the NLL-only warm-up left it: a regressor that the VRNN terms
            # may still disturb (export it with ``--export-warmup``)
            save(step, WARMUP_STATE)
            log(f"warm-up ends at step {step}: state kept in {WARMUP_STATE}")
        prev_sched = sched
        if hold_gate and step == tc.points_steps:
            net.keypoints.gate.requires_grad_(True)
        if step < tc.points_steps:  # the points curriculum: no frames, the encoder's NLL
            pts_np, tg_np = point_feed.batch(step)
            lr_now = set_schedule_step(schedule, sched)
            outd = net.points_loss(torch.as_tensor(pts_np, device=dev),
                                   torch.as_tensor(tg_np, device=dev), point_feed.supervised())
            opt.zero_grad(set_to_none=True)
            outd["loss_nll"].backward()
        else:
            lr_now, outd = _frame_step(net, opt, schedule, feed, tc, step, sched, dev)
        torch.nn.utils.clip_grad_norm_(net.parameters(), tc.clip)
        opt.step()
        cur = np.array([outd["loss"].item(), outd["rec"].item(), outd["kl"].item(),
                        outd["nll"].item(), outd["nll_prior"].item()])
        run_avg = cur if run_avg is None else 0.98 * run_avg + 0.02 * cur
        if (step + 1) % 100 == 0:
            log(f"step {step + 1} {wall() / 60:.1f} min lr {lr_now:.2e} loss "
                f"{run_avg[0]:.2f} rec {run_avg[1]:.2f} kl {run_avg[2]:.2f} nll {run_avg[3]:.3f} "
                f"nll_prior {run_avg[4]:.3f}")
        if val is not None and (step + 1) % tc.val_every == 0:
            validate(step + 1)
        if progress:  # after the step's validation, so the bar shows its nMSE
            if max_minutes is not None:
                shown["budget_left"] = f"{max(0.0, max_minutes - (time.time() - t_start) / 60):.1f}min"
            bar.set_postfix(loss=f"{run_avg[0]:.1f}", nll=f"{run_avg[3]:.2f}", **shown,
                            refresh=False)
        if time.time() - t_ckpt > tc.ckpt_every:
            save(step + 1)
            t_ckpt = time.time()
        if stop_at is not None and step + 1 >= stop_at:
            log(f"stopping at step {step + 1} as asked (resumable)")
            step += 1
            break
        if max_minutes is not None and time.time() - t_start > 60 * max_minutes:
            log(f"stopping after {max_minutes} min at step {step + 1} (resumable)")
            step += 1
            break
    else:
        step = tc.steps
    bar.close()
    feed.close()
    done = step >= tc.steps
    stopped = None if done else ("stop_at" if stop_at is not None and step >= stop_at
                                 else "max_minutes")
    end_val = done or (validate_on_stop and stopped == "max_minutes")
    if end_val and val is not None and (not history or history[-1][0] != step):
        validate(step)
    save(step)
    net.eval()
    return net.cpu(), {"step": step, "wall_s": wall(), "val_history": history, "done": done,
                       "stopped": stopped}


#: The resumable state kept when the NLL-only warm-up ends (in the run's folder).
WARMUP_STATE = "state_warmup.pt"

def _resolve_init(init: str | None) -> str | None:
    """``init`` as recorded: a shipped checkpoint's name (``"28x28"``, ``"camera"``) as given,
    so that records name no machine path (``train`` finds its file); a path to a shipped
    checkpoint's file as that checkpoint's name; another path as given."""
    if init is None or init.lower() == "none":  # "none": from scratch, whatever the preset
        return None
    return record_name(init)


# -- the training command: its flags from three declarations (RunFlags, TrainConfig, NetFlags) -
@dataclass
class RunFlags:
    """What to do with the recipe.

    Attributes
    ----------
    out : str, optional
        Folder of the run's resumable state.pt (required, except with --refit).
    export : str, optional
        Write a shipped checkpoint (+ .json card) here at the end: the network, then every stage
        of --stages fitted in order.
    export_warmup : str, optional
        With --export: also export the state kept when the NLL-only warm-up ended
        (<out>/state_warmup.pt) here, with the same stages.
    export_only : bool
        Only export <out>/state.pt to --export, no training.
    refit : str, optional
        No training: fit --stages afresh after this checkpoint's network (a shipped name or a
        path) and write --export.
    stages : tuple of str
        The stages fitted after the network, in order, as NAME[:KEY=VALUE,...] (e.g.
        drag_evidence:n_videos=300; methods.vid2param.stages); the default is the preset's;
        --stages alone fits none.
    resume : bool
        Continue from <out>/state.pt when it exists (--no-resume: start afresh).
    device : str
        auto (CUDA when present, else the CPU), cpu, cuda or cuda:N; one this machine does
        not have is refused before anything is built.
    max_minutes : float, optional
        Stop (resumable) after this much wall-clock time.
    time_schedule : bool
        With --max-minutes: the learning-rate schedule and warm-up phases advance with the
        budget spent, so a run the budget ends early has run its schedule through.
    export_on_stop : bool
        With --export: export also when --max-minutes ends the run early (the card's train
        record says stopped: max_minutes and the step).
    stop_at : int, optional
        Stop (resumable) after this step.
    progress : bool
        The progress bar: step, time left and the latest validation nMSE (--no-progress: none).
    preset : str
        The model configuration (V2PConfig.preset), its recipe and its stages: 28x28, camera,
        pendulum, spring, collision.
    system : str, optional
        Train a system's model from scratch with its preset (a system a user registered gets
        one derived from it); ball keeps --preset.
    """

    out: str | None = None
    export: str | None = None
    export_warmup: str | None = None
    export_only: bool = False
    refit: str | None = None
    stages: tuple[str, ...] = ()
    resume: bool = True
    device: str = "auto"
    max_minutes: Annotated[float | None, Range(0, lo_open=True)] = None
    time_schedule: bool = False
    export_on_stop: bool = False
    stop_at: Annotated[int | None, Range(1)] = None
    progress: bool = True
    preset: str = "28x28"
    system: str | None = None


@dataclass
class NetFlags:
    """The network's settings a training command may change (``V2PConfig`` fields; defaults:
    the preset's).

    Attributes
    ----------
    latent : int
        Total latent size (>= the number of targets).
    hidden : int
        LSTM hidden size.
    feat : int
        Size of the frame and latent features.
    keypoints : int
        Keypoint channels of the frame encoder (channel 0 gives the position).
    pool : int
        Average-pool the frames by this factor before the conv path and decoder.
    channels : tuple of int
        Conv encoder channels; each layer halves the frame size.
    alpha : float
        Weight of the reconstruction term.
    beta : float
        Weight of the KL term.
    gamma : float
        Weight of the parameters' NLL.
    gamma_prior : float
        Weight of the NLL of the prior's parameter dimensions (the one-step dynamics).
    aux_grad : float
        Scale of the gradient the prior and decoder send back into the recurrent state.
    kp_threshold : float
        Grey level (fraction of white) subtracted from keypoint channel 0.
    kp_visibility : bool
        A visibility channel beside the keypoints.
    roll_features : bool
        The ball's rolling statistic as features of the heads.
    physics_prior : bool
        The ball's physics prior in the latent rollout.
    kp_learn : bool
        Learn the keypoint map (a second object in learned channels).
    targets : tuple of str
        Supervised quantities in the first latent dimensions.
    roll_stat : str
        The rolling statistic: steps or fit.
    diff_scales : tuple of float
        Scales of the recurrence's velocity and acceleration features (VEL ACC).
    """

    latent: Annotated[int, Range(1)] = 16
    hidden: Annotated[int, Range(1)] = 128
    feat: Annotated[int, Range(1)] = 64
    keypoints: Annotated[int, Range(1)] = 4
    pool: Annotated[int, Range(1)] = 1
    channels: Annotated[tuple[int, ...], Range(1)] = (16, 32)
    alpha: Annotated[float, Range(0)] = 1.0
    beta: Annotated[float, Range(0)] = 1.0
    gamma: Annotated[float, Range(0)] = 10.0
    gamma_prior: Annotated[float, Range(0)] = 1.0
    aux_grad: Annotated[float, Range(0, 1)] = 0.1
    kp_threshold: Annotated[float, Range(0, 1)] = 0.0
    kp_visibility: bool = False
    roll_features: bool = True
    physics_prior: bool = False
    kp_learn: bool = False
    targets: tuple[str, ...] = ()
    roll_stat: str = "steps"
    diff_scales: Annotated[tuple[float, ...], Range(0, lo_open=True)] = (10.0, 40.0)

    def __post_init__(self) -> None:
        Range.check_fields(self)

    @classmethod
    def of(cls, mc: V2PConfig) -> NetFlags:
        """The flags' values in network ``mc`` (a preset's)."""
        d = mc.to_dict()
        return cls(**{f: tuple(d[f]) if isinstance(d[f], list) else d[f] for f in _fields(cls)})


@dataclass
class TrainCommand:
    """The training command's flags: what to do, the recipe and the network."""

    run: RunFlags
    recipe: TrainConfig
    net: NetFlags


def _fields(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def _constructor(name: str, hint):
    """tyro's constructor of field ``name`` (annotation ``hint``) when it is not tyro's own:
    a ranged number (its range as the metavar, INT>=1; a value outside refused naming the
    range) or JSON (``null``: None). None: tyro's own."""
    import tyro

    if typing.get_origin(hint) is not Annotated:
        return None
    base, *meta = typing.get_args(hint)
    if JSON in meta:
        def from_json(args):
            try:
                return json.loads(args[0])
            except json.JSONDecodeError as e:
                raise ValueError(f"expected JSON (an object or null), got {args[0]!r}: "
                                 f"{e.msg}") from None

        return tyro.constructors.PrimitiveConstructorSpec(
            nargs=1, metavar="JSON", instance_from_str=from_json, is_instance=lambda x: True,
            str_from_instance=lambda x: [json.dumps(x)])
    rng = next((m for m in meta if isinstance(m, Range)), None)
    if rng is None:
        return None
    args = [t for t in (typing.get_args(base) or (base,)) if t is not type(None)]
    many = typing.get_origin(base) is tuple
    if many:
        kind = args[0]
        n = "*" if Ellipsis in args else len(args)
    else:
        kind, n = args[0], 1

    def one(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise ValueError(f"expected {rng.text(kind)}, got {text!r}") from None
        try:
            return rng.check(name, v, kind)
        except ValueError:
            raise ValueError(f"expected {rng.text(kind)}, got {text!r}") from None

    meta_one = rng.metavar(kind)
    return tyro.constructors.PrimitiveConstructorSpec(
        nargs=n, metavar=" ".join([meta_one] * n) if n != "*" else f"{meta_one} ...",
        instance_from_str=(lambda a: tuple(one(t) for t in a)) if many else (lambda a: one(a[0])),
        is_instance=lambda x: True,
        str_from_instance=(lambda x: [str(v) for v in x]) if many else (lambda x: [str(x)]))


def _for_tyro(cls):
    """A copy of the dataclass ``cls`` for tyro: the same fields, defaults and docstring (the
    flags' help), each ranged or JSON field carrying its constructor (:func:`_constructor`);
    no checks of its own (the real class's run once parsing is done)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        spec = _constructor(f.name, hint)
        typ = typing.get_args(hint)[0] if typing.get_origin(hint) is Annotated else hint
        default = (dataclasses.field(default_factory=f.default_factory)
                   if f.default is dataclasses.MISSING and f.default_factory is not dataclasses.MISSING
                   else dataclasses.field(default=None if f.default is dataclasses.MISSING
                                          else f.default))  # TrainCommand's default sets them
        fields.append((f.name, typ if spec is None else Annotated[typ, spec], default))
    out = dataclasses.make_dataclass(cls.__name__, fields)
    out.__doc__, out.__module__ = cls.__doc__, __name__
    return out


def _preset_name(system: str | None, preset: str, given: bool) -> str:
    """The preset a command trains: ``--system S``'s own (a user's system gets one derived from
    it) unless it is ``--preset``'s system; ``--system`` with another system's ``--preset`` is
    refused."""
    presets.get(preset)  # an unknown preset: a ValueError naming the known ones
    if system is None:
        return preset
    try:
        own = presets.get(system)
    except ValueError:
        raise ValueError(f"--system: expected a registered system ({', '.join(systems.available())}), "
                         f"got {system!r}") from None
    if presets.get(preset).system == own.system:
        return preset
    if given:
        raise ValueError(f"--system {system} takes its own preset, not --preset {preset}")
    return own.name


def _defaults(argv) -> TrainCommand:
    """The command's defaults for ``argv``'s ``--preset``/``--system``: the preset's network,
    recipe (``presets.Preset.train``, its ``init`` by name) and stages."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default="28x28")
    pre.add_argument("--system", default=None)
    known, _ = pre.parse_known_args(list(argv))
    name = _preset_name(known.system, known.preset,
                        given=any(a == "--preset" or a.startswith("--preset=") for a in argv))
    p = presets.get(name)
    mc = V2PConfig.preset(name)
    recipe = TrainConfig(**copy.deepcopy(dict(p.train)), size=tuple(mc.frame_size))
    stages = tuple(n + (":" + ",".join(f"{k}={json.dumps(v)}" for k, v in o.items()) if o else "")
                   for n, o in p.stages)
    return TrainCommand(run=RunFlags(stages=stages, preset=name, system=known.system),
                        recipe=recipe, net=NetFlags.of(mc))


class FlagError(ValueError):
    """A training flag refused while parsing: one line naming the flag."""


def _flag_name(argument) -> str:
    flags = [f for f in getattr(getattr(argument, "lowered", None), "name_or_flags", ()) or ()
             if f.startswith("--")]
    return flags[0] if flags else ""


def _on_parse_error(event) -> None:
    """tyro's parse failures as one line (``FlagError``) instead of a box."""
    from tyro import _errors as te

    if isinstance(event, te.UnrecognizedArgs):
        raise FlagError(f"unrecognized arguments: {' '.join(event.tokens)}")
    if isinstance(event, te.InstantiationFailure):
        name = _flag_name(event.argument)
        raise FlagError(f"{name}: {event.message}" if name else event.message)
    if isinstance(event, te.InvalidChoice):
        raise FlagError(f"{_flag_name(event.argument)}: expected one of "
                        f"{', '.join(event.choices)}, got {event.value!r}")
    if isinstance(event, te.BadValue):
        raise FlagError(f"{_flag_name(event.argument)}: expected "
                        f"{event.argument.lowered.metavar or 'a value'}"
                        + (f", got {event.offending_value!r}" if event.offending_value else ""))
    return None  # another failure: tyro's own message


@functools.cache
def _tyro_command():
    """The command's dataclass for tyro and its three parts (:func:`_for_tyro`), made once."""
    Run, Recipe, Net = (_for_tyro(c) for c in (RunFlags, TrainConfig, NetFlags))
    Command = dataclasses.make_dataclass("TrainCommand", [("run", Run), ("recipe", Recipe),
                                                          ("net", Net)])
    Command.__doc__, Command.__module__ = __doc__.split("\n\n")[0], __name__
    return Command, Run, Recipe, Net


def _parse(argv=None) -> TrainCommand:
    """The training command's flags (``--help`` prints each with its default, the preset's,
    and its range); a flag refused raises ``FlagError`` (a ``ValueError``) naming it, before
    anything is built. The recipe is a checked ``TrainConfig`` (its ``init`` as given)."""
    import contextlib

    import tyro

    argv = list(sys.argv[1:] if argv is None else argv)
    default = _defaults([a for a in argv if a not in ("--help", "-h")])
    try:
        from tyro._errors import on_parse_error  # one line per refusal (tyro's hook)
        hook = on_parse_error(_on_parse_error)
    except ImportError:  # a tyro without the hook: its own (boxed) messages
        hook = contextlib.nullcontext()
    Command, Run, Recipe, Net = _tyro_command()
    as_tyro = Command(run=Run(**dataclasses.asdict(default.run)),
                      recipe=Recipe(**{f: getattr(default.recipe, f) for f in _fields(Recipe)}),
                      net=Net(**dataclasses.asdict(default.net)))
    with hook:
        got = tyro.cli(Command, args=argv, default=as_tyro, prog="sysid-bench train",
                       config=(tyro.conf.OmitArgPrefixes, tyro.conf.HelptextFromCommentsOff))
    rec = {f: getattr(got.recipe, f) for f in _fields(Recipe)}
    given = {a.split("=")[0] for a in argv}
    if ("--steps" in given and "--points-steps" not in given and default.recipe.points_steps
            and default.recipe.steps):
        # --steps resizes the preset's points curriculum with it (its share of the run)
        rec["points_steps"] = default.recipe.points_steps * rec["steps"] // default.recipe.steps
    return TrainCommand(run=RunFlags(**dataclasses.asdict(got.run)), recipe=TrainConfig(**rec),
                        net=NetFlags(**dataclasses.asdict(got.net)))


def _network(a: TrainCommand) -> V2PConfig:
    """The network of parsed flags ``a``: the preset's with the flags' values, frames of the
    recipe's size."""
    base = V2PConfig.preset(a.run.preset).to_dict()
    for name, v in dataclasses.asdict(a.net).items():
        base[name] = list(v) if isinstance(v, tuple) else v
    base["frame_size"] = list(a.recipe.size)
    return V2PConfig(**base)


def _train_config(a: TrainCommand, mc: V2PConfig | None = None) -> TrainConfig:
    """The recipe of parsed flags ``a``: the preset's (``presets.Preset.train``) with the flags
    given (a JSON flag given as ``null`` clears the preset's), its ``init`` as recorded (a
    shipped name, ``none``: from scratch), frames of the network's size."""
    mc = mc or _network(a)
    return dataclasses.replace(a.recipe, init=_resolve_init(a.recipe.init),
                               size=tuple(mc.frame_size))


def _stages(a: TrainCommand) -> list[tuple[str, dict]]:
    """The stages of parsed flags ``a``: ``--stages``, else the preset's."""
    return parse_stages(a.run.stages)


def check_device(device: str) -> torch.device:
    """The device ``device`` names, if this machine has it: ``auto`` (CUDA when present),
    ``cpu``, ``cuda``, ``cuda:N``, ...; else a ``ValueError`` naming it and what there is."""
    dev = resolve_device(device)
    if dev.type == "cpu":
        return dev
    if dev.type == "cuda":
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if n == 0:
            raise ValueError(f"device: {device!r} is not on this machine (torch sees no CUDA "
                             f"device); expected 'auto' or 'cpu'")
        if dev.index is not None and dev.index >= n:
            raise ValueError(f"device: expected cuda:0 .. cuda:{n - 1} (this machine has {n} CUDA "
                             f"device{'s' if n > 1 else ''}), got {device!r}")
        return dev
    backend = getattr(torch, dev.type, None)
    if backend is None or not getattr(backend, "is_available", lambda: False)():
        raise ValueError(f"device: {device!r} is not on this machine; expected 'auto', 'cpu' "
                         f"or 'cuda[:N]'")
    return dev


def check_command(a: TrainCommand, mc: V2PConfig, tc: TrainConfig) -> None:
    """Refuse flags that contradict each other, a device this machine lacks, and an ``--init``
    or ``--refit`` checkpoint of another system, before anything is trained: one
    ``ValueError`` naming the flags."""
    r = a.run
    for flag, given, needs in (("--export-warmup", r.export_warmup, r.export),
                               ("--export-only", r.export_only, r.export),
                               ("--export-on-stop", r.export_on_stop, r.export),
                               ("--refit", r.refit, r.export),
                               ("--time-schedule", r.time_schedule, r.max_minutes)):
        if given and not needs:
            other = "--max-minutes M" if flag == "--time-schedule" else "--export PATH"
            raise ValueError(f"{flag}: expected {other} with it")
    if r.refit is None and r.out is None:
        raise ValueError("--out: expected the run's folder (required, except with --refit)")
    try:
        check_device(r.device)
    except ValueError as e:
        raise ValueError(f"--{e}") from None
    if r.refit is None and not r.export_only:
        if tc.batch > tc.chunk:
            raise ValueError(f"--batch: expected at most --chunk ({tc.chunk} videos drawn at a "
                             f"time), got {tc.batch}")
        if tc.nll_only_steps > tc.steps:
            raise ValueError(f"--nll-only-steps: the NLL-only phase ({tc.nll_only_steps} steps) "
                             f"is longer than the run (--steps {tc.steps}); give "
                             f"--nll-only-steps N <= {tc.steps}")
        if tc.min_obs >= tc.n_frames:
            raise ValueError(f"--min-obs: expected fewer than --n-frames ({tc.n_frames}), got "
                             f"{tc.min_obs}")
        if tc.val_n > 0 and tc.val_every > tc.steps:
            pass  # validated once at the end: not a contradiction
        if r.stop_at is not None and r.stop_at > tc.steps:
            raise ValueError(f"--stop-at: expected a step <= --steps ({tc.steps}), got "
                             f"{r.stop_at}")
    if tc.init and r.refit is None and not r.export_only:
        _check_other_checkpoint("--init", tc.init, mc)
    if r.refit is not None and r.system is not None:
        _check_other_checkpoint("--refit", r.refit, mc)
    state = Path(r.out) / "state.pt" if r.out is not None else None
    if state is not None and state.exists() and r.resume and r.refit is None:
        _check_other_checkpoint("--out", state, mc, resumable=True)


def _check_other_checkpoint(flag: str, path, mc: V2PConfig, resumable: bool = False) -> None:
    """``flag``'s checkpoint loads (format, version) and is ``mc.system``'s; else a one-line
    ``ValueError`` naming the flag, the file and both systems."""
    try:
        ck = load_checkpoint(checkpoint_path(path), expect_resumable=resumable)
    except ValueError as e:
        raise ValueError(f"{flag}: {e}") from None
    theirs = (ck.get("config") or {}).get("system", "ball")
    if theirs != mc.system:
        what = "the run in it resumes" if resumable else "its weights start"
        raise ValueError(f"{flag}: {Path(str(path)).name} is a model of the {theirs} system, "
                         f"but this command trains the {mc.system} system's ({what} nothing "
                         f"here; --no-resume or another --out)" if resumable else
                         f"{flag}: {record_name(str(path))} is a model of the {theirs} system, "
                         f"expected one of the {mc.system} system")


def _command(argv) -> str:
    """The training command as run, for the card: paths given to ``--out`` and ``--export``
    reduced to their names (records name no machine path)."""
    args = list(sys.argv[1:] if argv is None else argv)
    for i, v in enumerate(args[:-1]):
        if v in ("--out", "--export", "--export-warmup"):
            args[i + 1] = Path(args[i + 1]).name
    return " ".join(["sysid-bench train", *args])


def main(argv=None) -> int:
    a = _parse(argv)
    r = a.run
    stages = _stages(a)  # checked before any training: a misspelt stage fails now, not at export
    mc = _network(a)
    tc = _train_config(a, mc)
    check_command(a, mc, tc)
    if r.refit is not None:
        print(fit_stages(r.refit, r.export, stages, threads=tc.threads))
        return 0
    out = Path(r.out)
    if r.export_only:
        print(export(out / "state.pt", r.export, stages=stages))
        return 0
    _, info = train(mc, tc, out=out, resume=r.resume, device=r.device,
                    max_minutes=r.max_minutes, stop_at=r.stop_at, progress=r.progress,
                    validate_on_stop=r.export_on_stop, time_schedule=r.time_schedule)
    early = r.export_on_stop and info["stopped"] == "max_minutes"
    if r.export and (info["done"] or early):
        record = {"stopped": "max_minutes", "max_minutes": r.max_minutes} if early else {}
        if r.time_schedule:
            record["time_schedule"] = True
        record["command"] = _command(argv)
        print(export(out / "state.pt", r.export, stages=stages, record=record))
        if r.export_warmup and (out / WARMUP_STATE).exists():
            record["snapshot"] = "the end of the NLL-only warm-up"
            print(export(out / WARMUP_STATE, r.export_warmup, stages=stages, record=record))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except ValueError as exc:  # bad flags, before anything is trained: one line, as sysid-bench's
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
