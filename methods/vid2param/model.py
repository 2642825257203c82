"""The Vid2Param network: a VRNN whose first latent dimensions are the physical quantities,
composed of the named parts of ``methods.vid2param.parts`` and ``methods.vid2param.prior``.

Shapes use B = batch, T = frames, H x W = frame size, Z = latent size, K = supervised dims
(``len(config.targets)``, the first K latent dimensions), R = what the heads read of the
recurrent state.

Cost is part of the design (training runs on a 2-core CPU): everything that does not depend on
the recurrence is computed for all frames at once -- the frame encoder before the time loop,
the prior, the decoder and every loss term after it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F

from methods.vid2param.parts import (
    _MIN_STD,
    ROLL_STATS,
    Decoder,
    FrameEncoder,
    GaussianHead,
    KeypointPosition,
    PriorHead,
    Recurrence,
    RecurrentState,
    RollingEvidence,
    _roll_features,
)
from methods.vid2param.prior import PhysicsPrior
from sysid_bench.core.physics import BOX_WIDTH, DT

#: Train a system's recurrence with the written-out backward pass (``_recurrence``); False:
#: autograd through the per-frame loop (the tests' reference).
WRITTEN_BACKWARD = True

__all__ = ["V2PConfig", "Vid2ParamNet", "RecurrentState", "TARGETS",
           "LEGACY_DEFAULTS", "REMOVED", "position_names", "system_targets"]

#: Supervised quantities the ball's latent dimensions can carry, in this order when present.
TARGETS = ("x", "y", "e", "g", "d", "r", "vx", "vy")


def position_names(n_points: int) -> tuple[str, ...]:
    """Target names of K tracked points' positions: ``x, y`` (point 0), ``x1, y1``, ..."""
    return tuple(f"{a}{k or ''}" for k in range(int(n_points)) for a in "xy")


def system_targets(system: str) -> tuple[str, ...]:
    """The supervised targets of a system's network: its K points' (x, y) (normalised by the
    view's ``extent``), then its P parameters (normalised by the prior); the ball's are
    ``V2PConfig()``'s (``presets.BOX``)."""
    from methods.vid2param import presets

    if presets.space_of(system) == presets.BOX:
        return V2PConfig.targets
    from sysid_bench.core import systems

    s = systems.get(system)
    return position_names(s.n_points) + tuple(s.params)
_LOG2PI = math.log(2 * math.pi)


@dataclass
class V2PConfig:
    """Architecture and loss weights; stored in every checkpoint.

    Attributes
    ----------
    frame_size : (int, int)
        (H, W) of the frames the network takes.
    targets : tuple of str
        Supervised quantities, normalised to about [0, 1], in the first latent dimensions;
        ``x`` and ``y`` among them (the keypoint position and the recurrence's differences).
    latent : int
        Z, total latent size (>= len(targets)).
    hidden : int
        LSTM hidden size.
    feat : int
        Size of phi_x(x) and phi_z(z).
    channels : tuple of int
        Conv encoder channels; each layer halves the frame size (stride 2).
    alpha, beta, gamma : float
        Weights of reconstruction, KL and the parameter NLL (paper: 1, 1, 10).
    gamma_prior : float
        Weight of the NLL of the prior's parameter dimensions against the targets of the same
        frame; it teaches the prior the one-step dynamics that forecasting unrolls.
    keypoints : int >= 1
        Keypoint channels of the frame encoder (``parts.FrameEncoder``); channel 0 gives the
        posterior's x, y (``parts.KeypointPosition``).
    kp_threshold : float in [0, 1)
        Grey level (fraction of 255) subtracted from keypoint channel 0: at 100x50 with noise
        sigma 8 the noise floor holds as much mass as the ball; 0 for clean video.
    kp_visibility : bool
        Weight the keypoint position by how visible the ball is (dropped and occluded frames).
    aux_grad : float
        Scale of the gradient that the prior and the decoder send back into the recurrent state
        (their own weights learn at full rate; the forward pass is unchanged). 1 is the plain
        VRNN. Why: the prior's NLL of the next positions (std ~1e-3) sent the LSTM ~100x the
        gradient of the parameters' NLL, so the parameters barely shaped the recurrence.
    pool : int
        Average-pooling factor of the frames the conv paths see and the decoder reconstructs
        (keypoint channel 0 keeps the full resolution).
    roll_features : bool
        Keep the rolling statistic in the recurrent state and blend it into the posterior's r
        (``parts.RollingEvidence``). Needs ``r`` among the targets.
    roll_stat : {"steps", "fit"}
        Which rolling statistic (``parts.ROLL_STATS``): ``"steps"`` averages per-frame
        decelerations of frames low above floor 0 (28x28); ``"fit"`` fits parabolas to runs of
        flat frames at any height (camera: noisy heights and an unseen raised floor).
    physics_prior : bool
        The latent rollout's physics transition (``methods.vid2param.prior``).
    system : str
        The system (``sysid_bench.core.systems``) whose videos the network reads. ``"ball"``: the
        targets are ``TARGETS``' names, positions normalised by the ball's box. Any other: the
        targets are ``system_targets(system)`` (its K points' x, y normalised by its view's
        extent, its parameters by its prior), and the ball's parts (``roll_features``,
        ``physics_prior``) are off.
    kp_learn : bool
        The keypoint map learns (its weights read every keypoint channel): a system with more
        than one tracked point, whose channel 0 sees only the brightest. Off: the fixed map of
        the view geometry (as the ball's).
    diff_scales : (float, float)
        Scales of the recurrence's difference features: velocity ``s_v d1`` (clamped to +-5)
        and acceleration ``s_a (vel_t - vel_{t-1})`` (clamped to +-10), d1 the first
        difference of the fed-back normalised positions. The ball's (10, 40) make the systems'
        velocity feature ~0.05; per-system scales bring both to a median of ~1
        (docs/vid2param-systems-probe.md: it sped up or enabled lq, w2, mu, c there).
    kp_second : () or (float, float)
        A fixed keypoint channel for a second tracked point (``parts.FrameEncoder``): keypoint
        channel 1 is the frame less this grey level (fraction of 255) outside a disc of this
        radius (pixels) around channel 0's centre, where the point channel 0 sees is drawn with
        its anti-aliased rim; the view's fixed map reads point 1 from it. Empty: off (channels
        1.. are learned). A two-point system's network then reads both points without a learned
        map, so the points curriculum (``TrainConfig.points_steps``) qualifies for it.
    """

    frame_size: tuple[int, int] = (28, 28)
    targets: tuple[str, ...] = ("x", "y", "e", "g", "d", "r")
    latent: int = 24
    hidden: int = 128
    feat: int = 128
    channels: tuple[int, ...] = (8, 16)
    alpha: float = 1.0
    beta: float = 1.0
    gamma: float = 10.0
    gamma_prior: float = 10.0
    keypoints: int = 4
    kp_threshold: float = 0.0
    kp_visibility: bool = False
    aux_grad: float = 0.1
    pool: int = 1
    roll_features: bool = True
    roll_stat: str = "steps"
    physics_prior: bool = True
    system: str = "ball"
    kp_learn: bool = False
    diff_scales: tuple[float, float] = (10.0, 40.0)
    kp_second: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        self.frame_size = tuple(int(v) for v in self.frame_size)
        ds = tuple(self.diff_scales)
        if len(ds) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0
                                   for v in ds):
            raise ValueError(f"diff_scales: expected two finite floats > 0 (velocity, "
                             f"acceleration), got {self.diff_scales!r}")
        self.diff_scales = tuple(float(v) for v in ds)
        self.targets = tuple(self.targets)
        self.channels = tuple(int(c) for c in self.channels)
        from methods.vid2param import presets

        if presets.space_of(self.system) == presets.BOX:
            allowed = TARGETS
        else:
            allowed = system_targets(self.system)  # ValueError for an unknown system
            if self.roll_features or self.physics_prior:
                raise ValueError(
                    f"roll_features, physics_prior: the ball's parts, expected False for the "
                    f"{self.system} system, got {self.roll_features}, {self.physics_prior}")
        bad = [t for t in self.targets if t not in allowed]
        if bad:
            raise ValueError(f"targets: expected names from {allowed}, got {bad}")
        if not set(self.positions) <= set(self.targets):
            raise ValueError(f"targets: expected {self.positions} among them, got {self.targets}")
        if int(self.keypoints) < 1:
            raise ValueError(f"keypoints: expected an int >= 1 (the network without keypoints "
                             f"was removed), got {self.keypoints}")
        if int(self.pool) < 1 or any(v % int(self.pool) for v in self.frame_size):
            raise ValueError(
                f"pool: expected an int >= 1 dividing frame_size {self.frame_size}, got {self.pool}"
            )
        self.keypoints, self.pool = int(self.keypoints), int(self.pool)
        if self.roll_stat not in ROLL_STATS:
            raise ValueError(f"roll_stat: expected one of {sorted(ROLL_STATS)}, got {self.roll_stat!r}")
        if self.roll_features and "r" not in self.targets:
            raise ValueError("roll_features: needs 'r' among targets")
        if not 0.0 <= float(self.kp_threshold) < 1.0:
            raise ValueError(f"kp_threshold: expected a float in [0, 1), got {self.kp_threshold}")
        self._check_kp_second()
        if self.latent < len(self.targets):
            raise ValueError(
                f"latent: expected at least len(targets)={len(self.targets)}, got {self.latent}"
            )

    def _check_kp_second(self) -> None:
        ks = tuple(self.kp_second) if isinstance(self.kp_second, (tuple, list)) else None
        if ks == ():
            self.kp_second = ()
            return
        ok = (ks is not None and len(ks) == 2 and all(isinstance(v, (int, float)) and math.isfinite(v) for v in ks)
              and 0.0 <= ks[0] < 1.0 and ks[1] > 0)
        if not ok:
            raise ValueError(f"kp_second: expected () or (grey level in [0, 1), exclusion radius "
                             f"> 0 px), got {self.kp_second!r}")
        if self.n_points != 2 or self.keypoints < 2:
            raise ValueError(f"kp_second: expected a network of a two-point system with "
                             f"keypoints >= 2, got system {self.system!r} ({self.n_points} "
                             f"points), keypoints {self.keypoints}")
        self.kp_second = tuple(float(v) for v in ks)

    @property
    def fixed_channels(self) -> int:
        """Keypoint channels with a fixed (unlearned) heat map: channel 0, and channel 1 with
        ``kp_second``."""
        return 2 if self.kp_second else 1

    @property
    def n_points(self) -> int:
        """K, the tracked points whose positions are targets (1 for the ball)."""
        from methods.vid2param import presets

        if presets.space_of(self.system) == presets.BOX:
            return 1
        from sysid_bench.core import systems

        return systems.get(self.system).n_points

    @property
    def positions(self) -> tuple[str, ...]:
        """The position targets, ``(x, y, x1, y1, ...)``."""
        return position_names(self.n_points)

    @property
    def params(self) -> tuple[str, ...]:
        """The parameter targets, in ``targets`` order."""
        return tuple(t for t in self.targets if t not in self.positions)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["frame_size"] = list(self.frame_size)
        d["targets"] = list(self.targets)
        d["channels"] = list(self.channels)
        d["diff_scales"] = list(self.diff_scales)
        d["kp_second"] = list(self.kp_second)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> V2PConfig:
        """The config stored in a checkpoint.

        Every field must be present: a checkpoint never silently takes today's defaults
        (they are the shipped model's, not what an older run used). The one exception is a
        field added after checkpoints were written, which takes the value that reproduces
        their behaviour (``LEGACY_DEFAULTS``). A removed option (``REMOVED``) may be present
        at the value the network now always has, never at another.
        """
        d = dict(d)
        for name, fixed in REMOVED.items():
            if name in d and d.pop(name) != fixed:
                raise ValueError(
                    f"config: the option {name!r} was removed (the network now always has "
                    f"{name}={fixed!r}); this config sets it to another value and cannot be loaded"
                )
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"config: unknown fields {sorted(unknown)}")
        missing = sorted(known - set(d) - set(LEGACY_DEFAULTS))
        if missing:
            raise ValueError(
                f"config: the checkpoint's config lacks fields {missing}; it was written by an "
                "older version whose defaults differ, so it cannot be loaded with today's"
            )
        return cls(**{**LEGACY_DEFAULTS, **d})

    @classmethod
    def preset(cls, name: str) -> V2PConfig:
        """The network of preset ``name`` (``presets.get``: a preset's or a system's name):
        the defaults, then the preset's ``net``; a ``presets.VIEW`` preset takes its targets and
        default frame size from its system."""
        from methods.vid2param import presets

        p = presets.get(name)
        d = dict(p.net)
        if p.space == presets.VIEW:
            from sysid_bench.core import systems

            d.setdefault("system", p.system)
            d.setdefault("targets", system_targets(p.system))
            d.setdefault("frame_size", systems.get(p.system).size)
        return cls(**d)


#: Fields added after checkpoints were written, with the value that reproduces those
#: checkpoints (``V2PConfig.from_dict``).
LEGACY_DEFAULTS = {"physics_prior": False, "roll_stat": "steps", "system": "ball",
                   "kp_learn": False, "diff_scales": (10.0, 40.0), "kp_second": ()}
#: Options removed (no shipped model used another value), with the value the network now
#: always has (``V2PConfig.from_dict``): a 1-layer LSTM, fed the mean of z (not a sample), with
#: the position differences as inputs, read as ``[h, c]`` by the heads, a residual prior, and
#: no linear map of the raw pixels beside the conv path.
REMOVED = {"recur_noise": 0.0, "pixel_skip": False, "diff_features": True, "read_cell": True,
           "prior_residual": True, "layers": 1}


def _scale_grad(x: torch.Tensor, scale: float) -> torch.Tensor:
    """``x`` forward (exactly: ``x - x`` is 0); its gradient multiplied by ``scale`` backward."""
    return x if scale == 1.0 or not x.requires_grad else x.detach() + scale * (x - x.detach())


def gaussian_nll(mu, std, target) -> torch.Tensor:
    """Elementwise Gaussian negative log-likelihood (the paper's eq. for the theta loss)."""
    return 0.5 * _LOG2PI + torch.log(std) + 0.5 * ((target - mu) / std) ** 2


def gaussian_kl(mu_q, std_q, mu_p, std_p) -> torch.Tensor:
    """Elementwise KL( N(mu_q, std_q) || N(mu_p, std_p) )."""
    return torch.log(std_p / std_q) + (std_q**2 + (mu_q - mu_p) ** 2) / (2 * std_p**2) - 0.5


class Vid2ParamNet(nn.Module):
    """VRNN with supervised latent dimensions (Vid2Param).

    Parameters
    ----------
    config : V2PConfig

    Attributes
    ----------
    encoder : parts.FrameEncoder
    keypoints : parts.KeypointPosition
    recurrence : parts.Recurrence
    posterior : parts.GaussianHead
        q(z_t | x_t, h_{t-1}) before ``keypoints`` and ``rolling`` replace x, y and blend r.
    prior : parts.PriorHead
    phys_prior : PhysicsPrior or None (``config.physics_prior``)
    rolling : parts.RollingEvidence or None (``config.roll_features``)
    decoder : parts.Decoder
    """

    def __init__(self, config: V2PConfig):
        super().__init__()
        self.config = c = config
        # (the creation order fixes which random numbers each part's initial weights take)
        self.encoder = FrameEncoder(c)
        self.keypoints = KeypointPosition(c)
        self.recurrence = Recurrence(c)
        n_read = self.recurrence.n_read
        self.posterior = GaussianHead(self.encoder.n_out + n_read, c.hidden, c.latent)
        self.prior = PriorHead(n_read, c.hidden, c.latent, c.targets, c.positions)
        self.phys_prior = PhysicsPrior() if c.physics_prior else None
        self.rolling = RollingEvidence(c.targets.index("r")) if c.roll_features else None
        self.decoder = Decoder(c, n_read)

    # -- the parts, one step ----------------------------------------------------------------------
    def encode_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """Frame features, (..., H, W) -> (..., feat + 3 keypoints) (``FrameEncoder``)."""
        return self.encoder(frames)

    def init_state(self, batch: int, device=None) -> RecurrentState:
        """The recurrent state before the first frame, batch ``batch``."""
        return self.recurrence.init_state(batch, device)

    def read(self, state: RecurrentState) -> torch.Tensor:
        """What the posterior, prior and decoder see of the recurrent state: (B, R)."""
        return self.recurrence.read(state)

    def step_rnn(self, z: torch.Tensor, state: RecurrentState) -> RecurrentState:
        """The recurrent state after feeding back ``z`` (B, Z)."""
        return self.recurrence(z, state)

    def last_position(self, state: RecurrentState) -> torch.Tensor:
        """The last fed-back (x, y), (B, 2), zeros before the first frame: what the prior adds
        its step to."""
        # detached: the prior learns the step; the posterior's positions stay anchored to the
        # targets rather than pulled towards what the prior predicts
        return (state.last_pos * (state.n_seen >= 1)).detach()

    def enc_step(self, fx: torch.Tensor, h: torch.Tensor):
        """Posterior q(z_t | x_t, h_{t-1}) from features ``fx`` and read-out ``h`` -> (mu, std),
        each (B, Z)."""
        mu, std = self.posterior(torch.cat([fx, h], dim=-1))
        mu = self.keypoints(fx, mu)
        if self.rolling is not None:
            mu, std = self.rolling(mu, std, h)
        return mu, std

    def prior_step(self, h: torch.Tensor, last: torch.Tensor):
        """Prior p(z_t | h_{t-1}) -> (mu, std), each (..., Z), from the read-out ``h`` (..., R)
        and the last fed-back position ``last`` (..., 2) (``last_position``)."""
        return self.prior(h, last)

    def decode(self, z: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Frame logits of the pooled frame from (z_t, h_{t-1}), (..., Z) and (..., R) ->
        (..., H / pool, W / pool)."""
        lead = z.shape[:-1]
        fz = self.recurrence.phi_z(z.reshape(-1, z.shape[-1]))
        u = self.decoder(fz, h.reshape(-1, h.shape[-1]))
        return u.reshape(*lead, *u.shape[-2:])

    # -- training pass --------------------------------------------------------------------------
    def forward(self, frames: torch.Tensor, targets: torch.Tensor, n_obs: int | None = None,
                rec_frac: float = 1.0, generator: torch.Generator | None = None,
                aux_grad: float | None = None,
                supervised: torch.Tensor | None = None) -> dict:
        """Loss terms for a batch of videos.

        Frames ``[0, n_obs)`` are observed (z from the posterior); frames ``[n_obs, T)`` are
        forecast (z from the prior, no frame read), which trains the closed-loop rollout. The
        decoder reads a sampled z; the recurrence is fed the mean (a sample's noise, ~0.1 m in
        the positions early in training, buries gravity's 2.5 cm per frame^2).

        Parameters
        ----------
        frames : Tensor, shape (B, T, H, W)
        targets : Tensor, shape (B, T, K)
            Normalised targets for the first K latent dimensions.
        n_obs : int, optional
            Observed frames; default all T.
        rec_frac : float in (0, 1]
            Fraction of observed frames (chosen at random, shared across the batch) that are
            decoded for the reconstruction term. Decoding is the costliest part after the
            encoder; a random subset gives an unbiased estimate of the per-frame mean.
        generator : torch.Generator, optional
            Source of the sampling noise and the decoded subset.
        aux_grad : float, optional
            Overrides ``config.aux_grad`` for this pass (a training schedule's early phase).
        supervised : Tensor of bool, shape (K,), optional
            Targets whose NLL terms count; default all. A target that does not vary in the
            training data (``simplified``'s fixed d and r) tells nothing to identify, and its
            NLL, unbounded as its std shrinks to the floor, would swamp the others'.

        Returns
        -------
        dict
            ``loss`` (scalar to minimise), ``loss_nll`` (its encoder-NLL term alone, for a
            warm-up phase), ``rec``, ``kl``, ``nll``, ``nll_prior`` (per frame
            means), ``mse`` (B, K) squared error of the encoder means on observed frames
            averaged over time, ``mse_last`` (B, K) at the last observed frame.
        """
        c = self.config
        B, T = frames.shape[:2]
        K = len(c.targets)
        n_obs = T if n_obs is None else int(n_obs)
        aux = c.aux_grad if aux_grad is None else float(aux_grad)
        # (B, n_obs, feat) and the pooled frames (B, n_obs, Hp, Wp), all frames at once; the
        # training path of ``encode_frames`` (the same numbers up to float order)
        fx, pooled = self.encoder.train_features(frames[:, :n_obs])
        # the observed frames in one fused recurrence (``_observed_pass``), then the forecast
        # frames (if any) step by step from its last state
        hs, post, state = self._observed_pass(fx)
        fore = []
        for _ in range(n_obs, T):
            hs.append(self.read(state))
            # kept in the box as ``rollout`` keeps it: an untrained prior's steps otherwise
            # add up over the forecast frames (NLL ~1e6 when the full loss starts)
            mu, std = self.prior_step(_scale_grad(hs[-1], aux), self.last_position(state))
            mu = self._in_box(mu)
            fore.append((mu, std))
            state = self.step_rnn(mu, state)
        H = torch.stack(hs, 1)  # (B, T, R): the read-out of h_{t-1} for each t
        qmu, qstd = post
        # the last fed-back positions (``last_position``): zeros, then the previous frame's
        pos = qmu[..., self.recurrence.pos_idx].detach()
        lasts = torch.cat([torch.zeros_like(pos[:, :1]), pos[:, :-1]], 1)
        Hobs = _scale_grad(H[:, :n_obs], aux)
        pmu, pstd = self.prior_step(Hobs, lasts)  # batched over time
        tgt_obs = targets[:, :n_obs]
        # the decoder reads a sample of z: the noise drawn frame by frame in frame order, as
        # the per-frame loop drew it (the same random stream), but outside the autograd loop
        eps = torch.stack([torch.randn(qmu.shape[::2], generator=generator, device=qmu.device)
                           for _ in range(T)], 1)
        n_rec = max(1, min(n_obs, round(rec_frac * n_obs)))
        if n_rec < n_obs:
            idx = torch.randperm(n_obs, generator=generator, device=frames.device)[:n_rec]
        else:
            idx = torch.arange(n_obs, device=frames.device)
        logits = self.decode(qmu[:, idx] + qstd[:, idx] * eps[:, idx], Hobs[:, idx])
        target = pooled[:, idx]  # bitwise ``encoder.pooled(frames / 255)``
        rec = F.binary_cross_entropy_with_logits(logits, target, reduction="none").sum((-1, -2))  # (B, n_rec): summed over pixels as the authors did
        kl = gaussian_kl(qmu, qstd, pmu, pstd).sum(-1)
        keep = slice(None) if supervised is None else torch.as_tensor(
            supervised, dtype=torch.bool, device=frames.device)
        nll = gaussian_nll(qmu[..., :K], qstd[..., :K], tgt_obs)[..., keep].sum(-1)
        nll_prior = gaussian_nll(pmu[..., :K], pstd[..., :K], tgt_obs)[..., keep].sum(-1)
        if n_obs < T:
            fm, fs = (torch.stack(a, 1) for a in zip(*fore, strict=True))
            nll_fc = gaussian_nll(fm[..., :K], fs[..., :K], targets[:, n_obs:])[..., keep].sum(-1)
            nll_prior = torch.cat([nll_prior, nll_fc], 1)
        per_frame = c.alpha * rec.mean() + c.beta * kl.mean() + c.gamma * nll.mean()
        loss = per_frame + c.gamma_prior * nll_prior.mean()
        err = (qmu[..., :K] - tgt_obs) ** 2
        terms = {"rec": rec.mean(), "kl": kl.mean(), "nll": nll.mean(),
                 "nll_prior": nll_prior.mean(), "mse": err.mean(1), "mse_last": err[:, -1]}
        return {"loss": loss, "loss_nll": c.gamma * nll.mean(),
                **{k: v.detach() for k, v in terms.items()}}

    # -- the points curriculum (``TrainConfig.points_steps``) ---------------------------------------
    def _point_columns(self) -> tuple[int, int]:
        """Where the fixed keypoint channels' centres (column, row; channel 0's, then channel
        1's with ``kp_second``) sit in ``fx``: columns ``[i, i + 2 K)``, the only frame features
        a network trained on points reads (:meth:`read_points_only_`). Returns ``(i, 2 K)``.

        Raises
        ------
        ValueError
            The network's K positions do not come from K fixed channels through the view's
            fixed map (the ball's box geometry, a learned map, or a second point without
            ``kp_second``).
        """
        from methods.vid2param import presets

        c = self.config
        if (presets.space_of(c.system) != presets.VIEW or c.kp_learn or c.kp_visibility
                or c.fixed_channels != c.n_points):
            raise ValueError(
                f"points_steps: expected a system's network whose K tracked points are its K "
                f"fixed keypoint channels through the view's fixed map (space 'view', kp_learn "
                f"and kp_visibility off, kp_second for a second point), got system "
                f"{c.system!r}, kp_learn {c.kp_learn}, kp_visibility {c.kp_visibility}, "
                f"{c.n_points} points and {c.fixed_channels} fixed channels")
        return self.encoder.n_out - 3 * c.keypoints, 2 * c.n_points

    def point_features(self, points: torch.Tensor) -> torch.Tensor:
        """The frame features ``fx`` (B, T, feat + 3 keypoints) that a frame showing its K
        points at ``points`` gives a network that reads only its fixed keypoint channels'
        centres.

        Parameters
        ----------
        points : Tensor, shape (B, T, 2 K)
            The tracked points in the view's unit square, as the targets' positions
            ``x, y, x1, y1, ...``.

        Returns
        -------
        Tensor, shape (B, T, feat + 3 keypoints)
            Zeros except the fixed channels' centres: channel k's column ``x_k``, row
            ``1 - y_k`` (the view's fixed map, ``parts.KeypointPosition``, inverted).
        """
        i, n = self._point_columns()
        if points.shape[-1] != n:
            raise ValueError(f"points: expected (B, T, {n}) for the {self.config.system} "
                             f"system's {n // 2} points, got shape {tuple(points.shape)}")
        fx = points.new_zeros(*points.shape[:2], self.encoder.n_out)
        fx[..., i:i + n:2] = points[..., 0::2]
        fx[..., i + 1:i + n:2] = 1.0 - points[..., 1::2]
        return fx

    @torch.no_grad()
    def read_points_only_(self) -> None:
        """Zero the posterior's weights on every frame feature but the fixed channels' centres.

        A network trained on :meth:`point_features` then reads a rendered frame exactly as it
        read the points (its other features meet zero weights), and the frame features start
        to count only as those weights learn in the pixel phase: the switch from points to
        pixels keeps what was learnt.
        """
        i, n = self._point_columns()
        w = self.posterior.mlp[0].weight
        keep = w[:, i:i + n].clone()
        w[:, :self.encoder.n_out] = 0.0
        w[:, i:i + n] = keep

    def points_loss(self, points: torch.Tensor, targets: torch.Tensor,
                    supervised: torch.Tensor | None = None) -> dict:
        """The encoder's NLL of a batch of tracked points (no frames, no decoder, prior or KL):
        the points curriculum's loss (``TrainConfig.points_steps``).

        Parameters
        ----------
        points : Tensor, shape (B, T, 2 K)
            The K tracked points as their keypoints would see them (with their noise), unit
            square, ``x, y, x1, y1, ...``.
        targets : Tensor, shape (B, T, K)
            Normalised targets (true positions, parameters).
        supervised : Tensor of bool, shape (K,), optional
            Targets whose NLL terms count (``forward``'s); default all.

        Returns
        -------
        dict
            ``loss`` and ``loss_nll`` (the NLL weighted by ``gamma``), ``nll``; ``rec``,
            ``kl``, ``nll_prior`` 0 (not computed); ``mse`` (B, K), ``mse_last`` (B, K).
        """
        K = len(self.config.targets)
        _, (qmu, qstd), _ = self._observed_pass(self.point_features(points))
        keep = slice(None) if supervised is None else torch.as_tensor(
            supervised, dtype=torch.bool, device=points.device)
        nll = gaussian_nll(qmu[..., :K], qstd[..., :K], targets)[..., keep].sum(-1)
        loss = self.config.gamma * nll.mean()
        err = ((qmu[..., :K] - targets) ** 2).detach()
        zero = torch.zeros((), device=points.device)
        return {"loss": loss, "loss_nll": loss, "nll": nll.mean().detach(), "rec": zero,
                "kl": zero, "nll_prior": zero, "mse": err.mean(1), "mse_last": err[:, -1]}

    def _observed_pass(self, fx: torch.Tensor):
        """The recurrence over every observed frame from ``init_state``, for training.

        The same arithmetic as ``enc_step`` then ``step_rnn`` per frame (``filter``), arranged
        for a cheap training step (up to floating-point order): everything that reads only the
        frames (the posterior's first layer on ``fx``, the keypoint positions) is computed for
        all frames in one batched matmul before the loop; the LSTM's gates are one matmul of
        its input and h (not two), with the cell's arithmetic written out; the frame count
        (0, 1, then 2 for every row) is a Python number, so the velocity and acceleration need
        no masks. A 16 x 200 step: 2,420 matmul calls instead of 3,813, ~11% less CPU
        (64 x 200: ~5%, the convolutions are most of it; docs/vid2param-training-speed.md).

        Parameters
        ----------
        fx : Tensor, shape (B, T, F)
            Frame features (``encode_frames``).

        Returns
        -------
        hs : list of T Tensors, shape (B, R)
            The read-out of the state before each frame.
        post : (mu, std), Tensors of shape (B, T, Z)
            The posterior at each frame.
        state : RecurrentState
            After the last frame.
        """
        B, T, n_fx = fx.shape
        rec, kpt, head = self.recurrence, self.keypoints, self.posterior.mlp
        state = self.init_state(B, fx.device)
        roll = state.roll
        w1, b1, w2, b2 = head[0].weight, head[0].bias, head[2].weight, head[2].bias
        # the posterior's first layer on the frames, all frames at once: (T, B, hidden)
        pre = F.linear(fx.transpose(0, 1), w1[:, :n_fx], b1)
        # the LSTM's gates as one matmul of [input, h] (its two weights side by side)
        cell = rec.cell
        w_cell = torch.cat([cell.weight_ih, cell.weight_hh], 1).T
        b_cell = cell.bias_ih + cell.bias_hh
        w_read, w2t = w1[:, n_fx:].T, w2.T
        wz, bz = rec.phi_z[0].weight.T, rec.phi_z[0].bias
        # the keypoint positions replace the posterior's x, y (``KeypointPosition``):
        # mu -> mu * scale + shift, scale and shift of every frame at once
        fx_t = fx.transpose(0, 1)
        kp = kpt.map(fx_t[..., -3 * kpt.keypoints:]) @ kpt.place  # (T, B, Z)
        m = kpt.mask
        if kpt.use_visibility:  # (the camera's) per frame in its own order: its NLL is
            # large (std ~1e-3), and reordering moved its gradient by 5e-5 of its size
            vis = torch.sigmoid(4.0 * (fx_t[..., -kpt.keypoints, None] - kpt.log_mref))
        else:
            scale, shift = (1 - m + kpt.gate * m).expand(T, 1, -1), kp
        idx = rec.pos_idx
        n_pos = len(idx)
        contiguous = idx == list(range(idx[0], idx[0] + n_pos))
        h, c = state.h, state.c
        s_vel, s_acc = rec.diff_scales
        if (WRITTEN_BACKWARD and roll is None and not kpt.use_visibility
                and self.rolling is None and contiguous and torch.is_grad_enabled()):
            # a system's network in training: the written-out backward pass (same numbers
            # forward, the gradients up to float order; ``_recurrence``)
            from methods.vid2param._recurrence import ObservedRecurrence

            reads, mu_t, std_t, h, c, last_pos, last_vel = ObservedRecurrence.apply(
                pre, (1 - m + kpt.gate * m), kp, w_read, w2t, b2, wz, bz, w_cell, b_cell,
                (idx[0], n_pos, s_vel, s_acc, _MIN_STD))
            n_seen = torch.full((B, 1), float(min(T, 2)), device=fx.device)
            state = RecurrentState(h, c, last_pos, last_vel, n_seen, None)
            return list(reads.unbind(0)), (mu_t.transpose(0, 1), std_t.transpose(0, 1)), state
        last_pos = last_vel = None
        hs, mus, stds = [], [], []
        for t in range(T):
            r = torch.cat([h, c], -1)
            if roll is not None:
                r = torch.cat([r, _roll_features(*rec.roll_stat.summary(roll))], -1)
            hs.append(r)
            raw = torch.addmm(b2, torch.relu(torch.addmm(pre[t], r, w_read)), w2t)
            mu, s = raw.chunk(2, dim=-1)
            std = F.softplus(s) + _MIN_STD
            if kpt.use_visibility:
                mu = mu * (1 - m) + vis[t] * (kp[t] + kpt.gate * mu * m) + (1 - vis[t]) * mu * m
            else:
                mu = mu * scale[t] + shift[t]
            if self.rolling is not None:
                mu, std = self.rolling(mu, std, r)
            mus.append(mu)
            stds.append(std)
            # the recurrence fed the mean (``Recurrence.forward``)
            pos = mu[:, idx[0]:idx[0] + n_pos] if contiguous else mu[:, idx]
            vel = (pos - last_pos) * s_vel if t >= 1 else torch.zeros_like(pos)
            acc = (vel - last_vel) * s_acc if t >= 2 else torch.zeros_like(pos)
            if roll is not None:
                n = torch.full((B, 1), float(min(t, 2)), device=fx.device)
                roll = rec.roll_stat.update(pos.detach(), vel.detach(),
                                            last_vel.detach() if t >= 1 else torch.zeros_like(pos),
                                            n, roll)
            inp = torch.cat([torch.relu(torch.addmm(bz, mu, wz)), vel.clamp(-5, 5),
                             acc.clamp(-10, 10), h], -1)
            gi, gf, gg, go = torch.addmm(b_cell, inp, w_cell).chunk(4, 1)
            c = torch.sigmoid(gf) * c + torch.sigmoid(gi) * torch.tanh(gg)
            h = torch.sigmoid(go) * torch.tanh(c)
            last_pos, last_vel = pos, vel
        n_seen = torch.full((B, 1), float(min(T, 2)), device=fx.device)
        state = RecurrentState(h, c, last_pos, last_vel, n_seen, roll)
        return hs, (torch.stack(mus, 1), torch.stack(stds, 1)), state

    # -- inference ------------------------------------------------------------------------------
    @torch.no_grad()
    def filter(self, frames: torch.Tensor, state: RecurrentState | None = None):
        """Every frame's posterior, the recurrence fed the posterior's mean (deterministic).

        Parameters
        ----------
        frames : Tensor, shape (B, T, H, W)
        state : RecurrentState, optional
            State to continue from; default ``init_state``.

        Returns
        -------
        mu, std : Tensor, shape (B, T, Z)
            q(z_t | x_{<=t}) after each frame.
        state : RecurrentState
            After the last frame.
        """
        from methods.vid2param.fast import encode_frames_batch

        B, T = frames.shape[:2]
        fx = encode_frames_batch(self, frames)  # in cache-sized pieces (same numbers)
        if state is None:
            state = self.init_state(B, frames.device)
        out = []
        for t in range(T):
            out.append(self.enc_step(fx[:, t], self.read(state)))
            state = self.step_rnn(out[-1][0], state)
        return *(torch.stack(a, 1) for a in zip(*out)), state

    def _in_box(self, z: torch.Tensor) -> torch.Tensor:
        """z (B, Z) with its position dimensions clamped to the box ([0, 1] each)."""
        return torch.where(self.keypoints.mask.bool(), z.clamp(0.0, 1.0), z)

    @torch.no_grad()
    def rollout(self, state: RecurrentState, horizon: int,
                generator: torch.Generator | None = None):
        """Unroll the learned prior in latent space, feeding its mean back.

        Parameters
        ----------
        state : RecurrentState
            S rows.
        horizon : int
        generator : torch.Generator, optional
            Source of the sampled z.

        Returns
        -------
        mu, std, z : Tensor, shape (S, horizon, Z)
            The prior's mean and std at each future frame and the sampled z. Positions are
            kept inside the box (normalised x and y - floor in [0, 1]): the 50-step error of
            the 28x28 model fell from 7.1 to 6.0 m so, the first 5 steps did not change.
        """
        out = []
        for _ in range(horizon):
            mu, std = self.prior_step(self.read(state), self.last_position(state))
            z = mu + std * torch.randn(mu.shape, generator=generator, device=mu.device)
            mu, z = self._in_box(mu), self._in_box(z)
            out.append((mu, std, z))
            state = self.step_rnn(mu, state)
        return tuple(torch.stack(a, 1) for a in zip(*out))

    def rollout_physics(self, phys: torch.Tensor, theta: torch.Tensor, horizon: int,
                        dt: float = DT, generator: torch.Generator | None = None,
                        sample: bool = True, skill: torch.Tensor | None = None):
        """Unroll the physics prior (``config.physics_prior``) from S particles.

        The latent state of a particle is its ``[x, y, vx, vy]`` and its parameters; each step
        the prior gives the next state's mean (one frame of the physics) and std (the learned
        process noise), a state is sampled and becomes the next step's. No frame is decoded,
        and the transition reads nothing else, so the LSTM is not stepped.

        Parameters
        ----------
        phys : Tensor, shape (S, 4)
            ``[x, y, vx, vy]`` at the last observed frame, floor-relative metres and m/s.
        theta : Tensor, shape (S, 4)
            ``(e, g, d, r)`` per particle, physical units.
        horizon : int
        sample : bool
            Sample the process noise (False: each particle follows its mean).
        skill : Tensor, shape (S,), optional
            Backtest error per particle (m), which scales the noise (``PhysicsPrior``).

        Returns
        -------
        mean, std, states : Tensor, shape (S, horizon, 4)
            The prior's mean and std at each future frame and the sampled states.
        """
        if self.phys_prior is None:
            raise ValueError("rollout_physics: this network has no physics prior "
                             "(config.physics_prior is False)")
        lo_box = torch.tensor([0.0, 0.0, -torch.inf, -torch.inf], device=phys.device)
        hi_box = torch.tensor([BOX_WIDTH, BOX_WIDTH, torch.inf, torch.inf], device=phys.device)
        out = []
        for _ in range(int(horizon)):
            mean, std = self.phys_prior(phys, theta, dt, skill)
            phys = mean
            if sample:
                eps = torch.randn(mean.shape, generator=generator, device=mean.device)
                phys = torch.maximum(torch.minimum(mean + std * eps, hi_box), lo_box)
            out.append((mean, std, phys))
        return tuple(torch.stack(a, 1) for a in zip(*out))


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())

