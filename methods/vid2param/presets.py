"""Vid2Param's presets: one record per system (and per shipped ball model) holding everything
that differs between them -- the network's settings, what its targets are, the training recipe
and the stages fitted after training.

A preset is looked up by its name (``"28x28"``, ``"camera"``, ``"pendulum"``, ...) or by a
system's name (``"ball"`` is the ``"28x28"`` preset); a system a user registered
(``sysid_bench.core.systems.register``) gets a record derived from the ``System`` (:func:`get`).
Code branches on a record's fields (``space``), never on a system's name.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

__all__ = ["Preset", "PRESETS", "get", "space_of", "BOX", "VIEW"]

#: ``Preset.space`` of the ball's networks: one point's (x, y) normalised by the ball's box and
#: the ball's parameters (``model.TARGETS``), with the ball's own parts (rolling statistic,
#: physics prior) and stages (drag evidence, physics calibration) available.
BOX = "box"
#: ``Preset.space`` of every other system's network: its K tracked points' (x, y) normalised by
#: its view's extent, then its P parameters normalised by its prior (``model.system_targets``).
VIEW = "view"


def _frozen(d: Mapping | None) -> Mapping[str, Any]:
    return MappingProxyType(dict(d or {}))


@dataclass(frozen=True)
class Preset:
    """The settings of one Vid2Param model.

    Attributes
    ----------
    name : str
        The preset's name (``--preset``).
    system : str
        The system (``sysid_bench.core.systems``) whose videos the network reads.
    space : {"box", "view"}
        What the network's targets are (:data:`BOX`: the ball's; :data:`VIEW`: a system's K
        tracked points and P parameters).
    net : mapping
        ``V2PConfig`` fields that differ from its defaults (read-only); a :data:`VIEW`
        preset's targets and frame size default to its system's (``V2PConfig.preset``).
    train : mapping
        ``TrainConfig`` fields the recipe takes instead of the defaults (a flag given
        overrides them; read-only).
    stages : tuple of (str, mapping)
        The stages fitted after the network, in order, with their options
        (``methods.vid2param.stages``).
    """

    name: str
    system: str
    space: str = VIEW
    net: Mapping[str, Any] = field(default_factory=dict)
    train: Mapping[str, Any] = field(default_factory=dict)
    stages: tuple = ()

    def __post_init__(self) -> None:
        if self.space not in (BOX, VIEW):
            raise ValueError(f"space: expected {BOX!r} or {VIEW!r}, got {self.space!r}")
        object.__setattr__(self, "net", _frozen(self.net))
        object.__setattr__(self, "train", _frozen(self.train))
        object.__setattr__(self, "stages", tuple((str(n), _frozen(o)) for n, o in self.stages))


#: A system's network: the ball's network with the ball's parts off (targets and frame size
#: from the system).
_VIEW_NET = {"roll_features": False, "physics_prior": False}

#: A system's from-scratch recipe (``--system S``), sized for ~7 minutes on one GPU with three
#: runs sharing it (``scripts/gpu_train_systems.sh``, with ``--max-minutes`` and
#: ``--time-schedule``): 1500 steps of 64 videos (a step's cost on a GPU is the 200-frame
#: recurrence's kernel launches, nearly flat in the batch), the first 60% the encoder's NLL alone
#: (the ball's lesson: the VRNN terms from the start left no trace of g, and a 15% warm-up left
#: the pendulum's g, b, mu and the spring's w2, k3 at guessing level), chunks reused over several
#: passes (a pendulum video takes ~0.05 s to draw on one core).
_VIEW_TRAIN = {"steps": 1500, "batch": 64, "nll_only_steps": 900,
               "early_aux_grad_steps": 1500, "warmup": 50, "val_n": 100, "val_every": 250,
               "threads": 4}

#: Per-system scales of the recurrence's velocity and acceleration features
#: (``V2PConfig.diff_scales``): their median magnitude over the moving coordinates ~1 on
#: train-split trajectories with 0.02 px keypoint noise (docs/vid2param-systems-probe.md,
#: variant b). The ball's (10, 40) left the velocity at ~0.05.
_DIFF_SCALES = {"pendulum": (197.0, 3.4), "spring": (142.0, 5.3), "collision": (259.0, 14.4)}

#: The points curriculum of a system whose points are its fixed keypoint channels
#: (``TrainConfig.points_steps``, sized for 2 CPU cores): the recurrence and heads learn from the
#: tracked points' noisy true positions, no frame and no convolution (a step of 32 x 200 ~0.7-1.1
#: s of one loaded core against ~7 s for 64 x 200 frames), the encoder's NLL alone, lr 1e-3
#: decayed to 1e-4 over the run; 1000 steps of 32 trajectories (32,000 seen, the probe's w2 drop
#: came after 20,000-25,000). The model reads rendered frames through those channels' centroids
#: (0.01-0.03 px RMS off the truth), which its posterior alone reads
#: (``Vid2ParamNet.read_points_only_``); its conv encoder, prior and decoder stay untrained (the
#: latent forecast is not learnt).
_POINTS_TRAIN = {"points_steps": 1000, "steps": 1000, "batch": 32, "nll_only_steps": 1000,
                 "early_aux_grad_steps": 0, "warmup": 20, "lr_min": 1e-4, "val_every": 100,
                 "ckpt_every": 120.0, "threads": 1}

#: A system's stages: the generic one only (the others read the ball's track or physics). 1000
#: train videos: on the pendulum's 6000-step network, 300 left b's 90% intervals holding 0.72
#: of 300 test truths after 200 frames, 1000 0.74 (model card, session 30).
_VIEW_STAGES = (("std_scale", {"n": 1000}),)
#: The shipped systems' stages: their damping (the collision's friction and wall restitution)
#: read off the network's track by a weak-form fit first (``weak_evidence``, fitted on 500
#: train videos; the pendulum's mean nMSE after 200 test frames 0.026 -> 0.001, model card,
#: session 31), then the std factors with it in place. A user's system has no weak form, so
#: ``_VIEW_STAGES``.
_WEAK_STAGES = (("weak_evidence", {"n": 500}),) + _VIEW_STAGES

#: The three shipped systems' runs (session 30): 6000 points steps, ~28 minutes of one core
#: with another run beside it. At 2000 steps the pendulum's g was read but unsteadily (0.023
#: nMSE after 200 test frames; 0.0006 at 6000) and its b and mu were still falling; at 1000 the
#: spring's w2 was 0.0018 (0.0002 at 6000 on validation); at 2000 the collision's eb was not
#: read (0.072; 0.0036 at 6000).
_LONG_POINTS = {"points_steps": 6000, "steps": 6000, "nll_only_steps": 6000}

_RECORDS = (
    # V2PConfig()'s network. Stages: std_scale on 500 videos is the shipped 28x28 model's; the
    # 28x28 network reads d at 0.0029 without drag evidence (model card).
    Preset("28x28", "ball", BOX, stages=(("std_scale", {"n": 500}), ("prior_noise", {"steps": 150}))),
    # The 100x50 camera-like recipe's network, with the run-fit rolling statistic (the shipped
    # camera model predates it and has none; its checkpoint keeps its own config). It trains on
    # the shipped camera model's nuisances and starts from the shipped 28x28 model's weights
    # (``init``): from scratch, its run had learnt none of e, g, d after 2250 of 4000 steps
    # (model card), while the 28x28 recipe learns g by step 2000. The network already
    # identifies, so no early aux-grad phase, a short encoder-only warm-up for the new
    # size-dependent layers, and half the videos with spin and contact dwell (as the shipped
    # camera model). 4500 steps: at 1500 and at 3000 e and d were still falling (model card).
    # Its stages read drag off the ball's track.
    Preset("camera", "ball", BOX,
           net={"frame_size": (50, 100), "kp_threshold": 0.2, "kp_visibility": True, "pool": 2,
                "roll_stat": "fit"},
           train={"nuisance": {"blur": 0.5, "occlusion": 0.05, "drop": 0.05, "noise": 8.0,
                               "floor_offset": 1.0},
                  "init": "28x28", "steps": 4500, "nll_only_steps": 150,
                  "early_aux_grad_steps": 0, "chunk": 600, "val_n": 100, "val_every": 500,
                  "perturb": {"spin": 0.3, "dwell": 0.01, "p": 0.5}},
           stages=(("prior_noise", {"steps": 150}), ("drag_evidence", {"n_videos": 300}),
                   ("physics_calibration", {"n": 100}))),
    # ``kp_threshold`` sits above the dim parts of a scene (the pendulum's rod at 0.3 of white,
    # the spring's wall and coil at 0.25, the collision's puck 2 at 130/255), so keypoint
    # channel 0's centroid is the bob, block or puck 1 from the first step.
    # pool 2: the conv path and decoder see 32x32 (64x64 made a 5.4 MB checkpoint)
    Preset("pendulum", "pendulum", VIEW, net={**_VIEW_NET, "kp_threshold": 0.4, "pool": 2,
                                              "diff_scales": _DIFF_SCALES["pendulum"]},
           # g came only after ~900 probe steps of 64 trajectories, and held only as the
           # learning rate fell (_LONG_POINTS)
           train={**_VIEW_TRAIN, "chunk": 1600, "chunk_epochs": 8, **_POINTS_TRAIN,
                  **_LONG_POINTS},
           stages=_WEAK_STAGES),
    Preset("spring", "spring", VIEW, net={**_VIEW_NET, "kp_threshold": 0.4,
                                          "diff_scales": _DIFF_SCALES["spring"]},
           train={**_VIEW_TRAIN, "chunk": 2000, "chunk_epochs": 4, **_POINTS_TRAIN,
                  **_LONG_POINTS},
           stages=_WEAK_STAGES),
    # Two fixed keypoint channels (``kp_second``), so the points curriculum qualifies: channel 0
    # above 0.55 of white (puck 2 is 130/255 = 0.51) is puck 1; channel 1 is the frame above 0.3
    # outside 3.9 px of channel 0's centre (puck 1's radius 3.2 px plus its anti-aliased rim)
    # at the default 16 x 128 frame, puck 2. Measured on 40 test-split videos of 200 frames: the
    # two centroids 0.013 and 0.023 px RMS off the truth in x (0 in y), at most 0.04 and 0.17 px
    # (the largest within a pixel of contact); channel 0 above 0.75 was 0.061 px RMS off.
    Preset("collision", "collision", VIEW,
           net={**_VIEW_NET, "kp_threshold": 0.55, "keypoints": 2, "kp_second": (0.3, 3.9),
                "diff_scales": _DIFF_SCALES["collision"]},
           train={**_VIEW_TRAIN, "chunk": 2000, "chunk_epochs": 4, **_POINTS_TRAIN,
                  **_LONG_POINTS},
           stages=_WEAK_STAGES),
)

#: The presets by name (read-only).
PRESETS: Mapping[str, Preset] = MappingProxyType({r.name: r for r in _RECORDS})
#: A system's preset where its name is not a preset's.
_BY_SYSTEM = {"ball": "28x28"}


def get(name: str) -> Preset:
    """The preset named ``name`` (a preset's or a system's name).

    A system registered without a preset of its own (a user's) gets one derived from it: the
    generic network, recipe and stages of every :data:`VIEW` system.

    Raises
    ------
    ValueError
        ``name`` names neither a preset nor a registered system.
    """
    if not isinstance(name, str):
        raise TypeError(f"preset: expected a preset or system name (str), got "
                        f"{type(name).__name__} {name!r}")
    name = _BY_SYSTEM.get(name, name)
    if name in PRESETS:
        return PRESETS[name]
    from sysid_bench.core import systems

    if name not in systems.available():
        raise ValueError(f"preset: expected a preset ({', '.join(sorted(PRESETS))}) or a "
                         f"registered system ({', '.join(systems.available())}), got {name!r}")
    return Preset(name, name, VIEW, net={**_VIEW_NET, "diff_scales": diff_scales(name)},
                  train=_VIEW_TRAIN, stages=_VIEW_STAGES)


_MEASURED: dict = {}


def diff_scales(system: str, n: int = 512, noise_px: float = 0.02,
                seed: int = 0) -> tuple[float, float]:
    """The recurrence's difference scales for ``system``, measured from its simulated data.

    ``n`` train-split trajectories of 200 frames at 20 frames/s, their points normalised to the
    view's unit square with ``noise_px`` of keypoint noise (pixels of the system's default
    frame): the velocity scale makes the median first difference 1, the acceleration scale the
    median second difference of the scaled velocity 1, over the coordinates that move (the
    probe's variant b, which set the shipped systems' :data:`_DIFF_SCALES`;
    docs/vid2param-systems-probe.md). Measured once per registered system.

    Returns
    -------
    (float, float)
        ``V2PConfig.diff_scales``: (velocity, acceleration).
    """
    import numpy as np

    from sysid_bench.core import systems

    sys_ = systems.get(system)
    # a class registered twice (under two names, with other views) is measured for each
    key = (system, type(sys_), tuple(sys_.extent), tuple(sys_.size), int(n),
           float(noise_px), int(seed))
    if key not in _MEASURED:
        rng = np.random.default_rng(seed)
        theta, state0 = sys_.sample_cases(int(n), rng, "train")
        pts = np.asarray(sys_.observe(sys_.simulate(theta, state0, 200, 0.05), theta),
                         dtype=np.float64)  # (n, T, K, 2)
        x0, x1, y0, y1 = (float(v) for v in sys_.extent)
        unit = (pts - [x0, y0]) / [x1 - x0, y1 - y0]
        h, w = sys_.size
        moving = np.nanmax(np.abs(np.diff(unit, axis=1)), axis=(0, 1)) > 1e-9  # (K, 2)
        unit = unit + rng.normal(size=unit.shape) * (noise_px / np.array([w, h]))
        d1 = np.abs(np.diff(unit, axis=1))[..., moving]
        d2 = np.abs(np.diff(unit, n=2, axis=1))[..., moving]
        if not moving.any() or not np.isfinite(d1).any():
            raise ValueError(f"system: expected {system}'s points to move in its simulation, "
                             "got none that does (no difference scales to measure)")
        s_vel = 1.0 / float(np.nanmedian(d1))
        _MEASURED[key] = (s_vel, 1.0 / (s_vel * float(np.nanmedian(d2))))
    return _MEASURED[key]


def space_of(system: str) -> str:
    """The :attr:`Preset.space` of ``system``'s networks (``"box"`` or ``"view"``).

    Raises
    ------
    ValueError
        ``system`` is not a registered system (the registry's message, naming the known ones).
    """
    if _BY_SYSTEM.get(system, system) not in PRESETS:
        from sysid_bench.core import systems

        systems.get(system)  # an unknown system: its ValueError names the registered ones
    return get(system).space
