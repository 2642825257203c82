"""The named parts :class:`~methods.vid2param.model.Vid2ParamNet` is composed of.

Each is built from the ``V2PConfig`` (``c``) or the sizes it needs. Shapes: B = batch,
H x W = frame size, Hp x Wp = the frame pooled by ``c.pool``, Z = latent size, K = keypoint
channels, R = what the heads read of the recurrent state (``Recurrence.n_read``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import nn
from torch.nn import functional as F

from sysid_bench.core.physics import BOX_WIDTH, DT, PRIOR

__all__ = ["FrameEncoder", "KeypointPosition", "RecurrentState", "Recurrence", "GaussianHead",
           "PriorHead", "RollingEvidence", "Decoder"]

_MIN_STD = 1e-3
#: Rolling-statistic gates (``RollingEvidence``), chosen on validation videos: fed-back height
#: (m) under which the ball may roll (a 28x28 keypoint's height is ~5 mm off; a hop from the
#: 0.25 m/s rolling threshold rises 3 mm), distance (m) from the walls inside which a frame is
#: left out (a wall contact breaks the second difference), largest deceleration (m/s^2) taken as
#: rolling (r <= 0.7 plus ~2 m/s^2 of per-frame noise; a spun bounce gives tens), smallest
#: horizontal step (normalised units per frame).
ROLL_HEIGHT, ROLL_WALL, ROLL_DEC_MAX, ROLL_STEP = 0.015, 0.5, 10.0, 0.002
#: Scale of the rolling features the heads read: Adam moves a new input's weights by about the
#: learning rate per step whatever the input's size, so its size sets how fast it takes effect.
ROLL_GAIN = 5.0
_R_TOP = PRIOR["r"][1]  # m/s^2: top of the prior's r


def _gauss(raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a (..., 2Z) head output into mean and std (softplus keeps std positive)."""
    mu, s = raw.chunk(2, dim=-1)
    return mu, F.softplus(s) + _MIN_STD


def _xy_place(targets: tuple[str, ...], latent: int,
              positions: tuple[str, ...] = ("x", "y")) -> torch.Tensor:
    """(2K, Z) one-hot rows: where the K points' (x, y) pairs go in the latent vector."""
    place = torch.zeros(len(positions), latent)
    for i, name in enumerate(positions):
        place[i, targets.index(name)] = 1.0
    return place


def _centre_grid(h: int, w: int) -> torch.Tensor:
    """(2, h*w) pixel centres: column and row as fractions of the width and height."""
    gy, gx = torch.meshgrid((torch.arange(h) + 0.5) / h, (torch.arange(w) + 0.5) / w,
                            indexing="ij")
    return torch.stack([gx.flatten(), gy.flatten()], 0)


#: Run the keypoint convolution on a channels_last input (see ``FrameEncoder.forward``); the
#: batched-identification benchmark turns it off to time the path before it.
KEYPOINT_CHANNELS_LAST = True


def _conv_im2col(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """``conv(x)`` for one (1, C, H, W) image as a patch matrix times the weights."""
    (k, _), (s, _), (pad, _) = conv.kernel_size, conv.stride, conv.padding
    ho = (x.shape[-2] + 2 * pad - k) // s + 1
    wo = (x.shape[-1] + 2 * pad - k) // s + 1
    cols = F.unfold(x, k, padding=pad, stride=s)[0]  # (C k k, ho wo)
    out = torch.addmm(conv.bias[:, None], conv.weight.reshape(conv.out_channels, -1), cols)
    return out.reshape(1, conv.out_channels, ho, wo)


def _apply_convs(module: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``module(x)`` for FrameEncoder's convolutions (square, biased; alone or with ReLUs).

    A single frame without gradients (a ``push`` on the torch path) goes through im2col and one
    matrix product per layer: 59 us for the 28x28 encoder's convolutions on one CPU thread,
    145 us through oneDNN (faster on batches). Same numbers up to float rounding.
    """
    if x.shape[0] != 1 or torch.is_grad_enabled():
        return module(x)
    for m in (module if isinstance(module, nn.Sequential) else [module]):
        x = _conv_im2col(m, x) if isinstance(m, nn.Conv2d) else m(x)
    return x


class FrameEncoder(nn.Module):
    """Frame features ``fx = [phi_x(conv(frame)), keypoint centres, keypoint log masses]``.

    Keypoints are spatial expectations (as in deep spatial autoencoders): K non-negative heat
    maps -- channel 0 the full-resolution frame less ``kp_threshold``, with ``kp_second``
    channel 1 the full-resolution frame less its grey level outside a disc around channel 0's
    centre, the others learned 3x3 convolutions of the pooled frame -- each give their centre of
    mass (column, row, in [0, 1]) and log total mass. Channel 0 is the ball's intensity
    centroid: sub-pixel positions from the first training step. The conv path and the learned
    channels see the frame average-pooled by ``pool`` (convolutions over 5000-pixel frames made
    a CPU training step ~10 s).
    """

    def __init__(self, c):
        super().__init__()
        H, W = c.frame_size
        Hp, Wp = H // c.pool, W // c.pool
        self.pool, self.kp_threshold, self.keypoints = c.pool, float(c.kp_threshold), c.keypoints
        convs, ch = [], 1
        for out in c.channels:  # each halves the frame (stride 2)
            convs += [nn.Conv2d(ch, out, 4, stride=2, padding=1), nn.ReLU()]
            ch = out
        self.conv = nn.Sequential(*convs)
        with torch.no_grad():
            n_conv = self.conv(torch.zeros(1, 1, Hp, Wp)).numel()
        self.phi_x = nn.Sequential(nn.Flatten(), nn.Linear(n_conv, c.feat), nn.ReLU())
        #: channel 1's (grey level, exclusion radius in px), or None (``kp_second``)
        self.second = tuple(c.kp_second) if c.kp_second else None
        n_learned = c.keypoints - (2 if self.second else 1)
        self.kp = nn.Conv2d(1, n_learned, 3, padding=1) if n_learned > 0 else None
        self.frame_hw = (H, W)
        self.register_buffer("grid", _centre_grid(H, W), persistent=False)
        self.register_buffer("grid_pool", _centre_grid(Hp, Wp), persistent=False)
        self.n_out = c.feat + 3 * c.keypoints  # size of fx

    def pooled(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 1, H, W) frames in [0, 1] average-pooled by ``pool`` -> (N, 1, Hp, Wp)."""
        return x if self.pool == 1 else F.avg_pool2d(x, self.pool)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """``fx`` (..., feat + 3 K) of frames (..., H, W), uint8 or float in [0, 255]."""
        lead = frames.shape[:-2]
        full = frames.reshape(-1, 1, *frames.shape[-2:]).to(torch.float32) / 255.0
        x = self.pooled(full)
        out = self.phi_x(_apply_convs(self.conv, x))
        t = self.kp_threshold
        # without the threshold, pixel noise spread over a camera frame pulls the centroid to
        # the middle; 1e-6 keeps a blank frame's centre defined
        heat0 = (full if not t else torch.relu(full - t)).flatten(2) + 1e-6
        mass0 = heat0.sum(-1, keepdim=True)
        centre = (heat0 / mass0) @ self.grid.T  # (N, 1, 2)
        mass = mass0
        if self.second is not None:
            # both centres in float64: a float32 sum's order differs between a batch and one
            # frame by ~1e-6, which this network's difference scales (the collision's 259 and
            # 14.4) carry into its stream's posterior at 3e-4 of the batch's
            centre = ((heat0.double() / mass0.double()) @ self.grid.double().T).float()
            centre, mass = self._second_channel(full, centre, mass0)
        if self.kp is not None:
            if KEYPOINT_CHANNELS_LAST and (x.shape[0] > 1 or torch.is_grad_enabled()):
                # a 1 -> K-1 channel conv runs ~5x faster on the CPU on a channels_last input
                # (oneDNN's direct NHWC kernel; 35 -> 7 ms per 1024 28x28 frames, one thread;
                # training's forward + backward 87 -> 50 ms); the maps come out (N, Hp, Wp, K-1)
                x = x.to(memory_format=torch.channels_last)
            maps = torch.relu(_apply_convs(self.kp, x)).permute(0, 2, 3, 1)
            heat = maps.reshape(x.shape[0], -1, self.kp.out_channels) + 1e-6  # (N, Hp*Wp, L)
            m = heat.sum(1)[..., None]  # (N, L, 1)
            centre_k = torch.matmul(self.grid_pool, heat).transpose(1, 2) / m  # (N, L, 2)
            centre = torch.cat([centre, centre_k], 1)  # (N, K, 2)
            mass = torch.cat([mass, m], 1)
        out = torch.cat([out, centre.flatten(1), torch.log(mass[..., 0])], -1)
        return out.reshape(*lead, -1)

    def _second_channel(self, full: torch.Tensor, centre0: torch.Tensor, mass0: torch.Tensor):
        """Channel 0's centre and mass with channel 1 (``kp_second``) appended: (N, 2, 2) and
        (N, 2, 1), from the full-resolution frames ``full`` (N, 1, H, W) in [0, 1].

        Channel 1 is ``relu(frame - level)`` outside ``radius`` pixels of channel 0's centre:
        the point channel 0 sees is drawn over the second one, and its anti-aliased rim lies
        within its radius + 0.71 px, so the mask takes out all of it and the second point's
        disc is left whole (a centroid at its centre) except when the two come within about a
        pixel of touching.
        """
        level, radius = self.second
        H, W = self.frame_hw
        heat = torch.relu(full - level).flatten(2)  # (N, 1, H W)
        d = (self.grid[None] - centre0.transpose(1, 2)) * self.grid.new_tensor([[W], [H]])
        far = (d * d).sum(1, keepdim=True) > radius * radius  # (N, 1, H W)
        heat1 = (heat * far + 1e-6).double()
        m1 = heat1.sum(-1, keepdim=True)
        centre1 = ((heat1 / m1) @ self.grid.double().T).float()
        return torch.cat([centre0, centre1], 1), torch.cat([mass0, m1.float()], 1)

    def train_features(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward``'s ``fx`` (up to float order) and the pooled frames: a training step's path.

        Arranged for a cheap training step on the CPU (docs/vid2param-training-speed.md,
        "One conversion of the frames"); inference keeps ``forward``. The frames carry no
        gradient, so their conversion runs without autograd in pieces of ~1 M pixels that stay
        in cache (``forward`` writes and reads several full-resolution float copies of the whole
        batch): each frame is converted once (the pooled frames are also the decoder's
        reconstruction target), pooled by summing ``pool x pool`` strided views (bitwise
        ``avg_pool2d``'s numbers, at ~half its CPU time), and channel 0's centre and mass are
        ``forward``'s arithmetic on each piece (bitwise). The convolutions run on channels_last
        tensors and the learned channels' centres and masses are one matrix product of their
        NHWC maps: only those differ from ``forward`` (float order; a 64 x 200 pendulum step
        3.7 -> 3.0 s on 2 idle cores, docs/vid2param-training-speed.md).

        Parameters
        ----------
        frames : Tensor, shape (..., H, W)
            uint8, or float in [0, 255].

        Returns
        -------
        fx : Tensor, shape (..., feat + 3 K)
        pooled : Tensor, shape (..., Hp, Wp)
            The frames in [0, 1] average-pooled by ``pool`` (the frames themselves if 1),
            float32, bitwise ``pooled(frames / 255)``.
        """
        lead, (H, W) = frames.shape[:-2], frames.shape[-2:]
        if self.second is not None:  # the fixed second channel reads full frames: forward's path
            full = frames.reshape(-1, 1, H, W).to(torch.float32) / 255.0
            x = self.pooled(full) if self.pool > 1 else full
            return self.forward(frames), x.reshape(*lead, *x.shape[-2:])
        flat = frames.reshape(-1, 1, H, W)
        n, p, t, dev = flat.shape[0], self.pool, self.kp_threshold, frames.device
        Hp, Wp = H // p, W // p
        x = torch.empty(n, 1, Hp, Wp, device=dev)
        centre = torch.empty(n, 1, 2, device=dev)
        mass = torch.empty(n, 1, device=dev)
        chunk = max(1, 2**20 // (H * W))
        with torch.no_grad():
            for i in range(0, n, chunk):
                full = flat[i:i + chunk].to(torch.float32).div_(255.0)
                if p == 1:
                    x[i:i + chunk] = full
                else:  # the window's pixels in row order, then / p^2: as avg_pool2d sums
                    acc = full[..., 0::p, 0::p].clone()
                    for k in range(1, p * p):
                        acc += full[..., k // p::p, k % p::p]
                    torch.div(acc, p * p, out=x[i:i + chunk])
                # channel 0 as ``forward`` computes it (full is not read again)
                heat = (full.sub_(t).clamp_(min=0.0) if t else full).flatten(2).add_(1e-6)
                m = heat.sum(-1, keepdim=True)
                mass[i:i + chunk] = m[:, 0]
                torch.matmul(heat.div_(m), self.grid.T, out=centre[i:i + chunk])
        # NHWC: oneDNN's direct kernels for these few-channel layers (the 1 -> 8 convolution's
        # forward + backward ~3x faster than NCHW on 32x32 frames)
        xc = x.to(memory_format=torch.channels_last)
        out = self.phi_x(self.conv(xc))
        if self.kp is not None:
            k1 = self.keypoints - 1
            gp = torch.cat([self.grid_pool, torch.ones(1, Hp * Wp, device=dev)]).T.contiguous()
            # the K-1 maps' column, row and mass sums as one product: rows (pixel, channel) of
            # the NHWC maps against columns (column/row/1, channel), not N small batched ones;
            # ``forward``'s 1e-6 per pixel is added to the sums
            sums = torch.relu(self.kp(xc)).permute(0, 2, 3, 1).reshape(n, -1) @ torch.kron(
                gp, torch.eye(k1, device=dev))
            sums = sums.reshape(n, 3, k1) + 1e-6 * gp.sum(0)[:, None]
            centre = torch.cat([centre, (sums[:, :2] / sums[:, 2:]).transpose(1, 2)], 1)
            mass = torch.cat([mass, sums[:, 2]], 1)
        fx = torch.cat([out, centre.flatten(1), torch.log(mass)], -1)
        return fx.reshape(*lead, -1), x.reshape(*lead, Hp, Wp)


class KeypointPosition(nn.Module):
    """The posterior's x, y means: keypoint channel 0's centre mapped to metres by the view
    geometry, plus the MLP's means scaled by ``gate`` (starts at 0).

    The map is fixed: with it or the heat maps learnable, the other loss terms (KL to an
    imprecise prior, reconstruction) dragged the positions from 5 mm to 3-20 cm off, which
    buries gravity's 2.5 cm per frame^2. With ``kp_visibility`` the map is weighted by how
    visible the ball is, ``v = sigmoid(4 (log m0 - log m_ref))`` (m0 channel 0's mass, m_ref a
    third of a full ball's): ``v (map + gate mlp) + (1 - v) mlp``. On a dropped or occluded
    frame the map reports the middle of the frame (or a sliver of the ball); the MLP, which
    reads the recurrent state, carries the position on.
    """

    def __init__(self, c):
        from sysid_bench.core.render import view_geometry

        super().__init__()
        self.keypoints, self.use_visibility = c.keypoints, bool(c.kp_visibility)
        positions = c.positions
        self.map = nn.Linear(3 * c.keypoints, len(positions)).requires_grad_(bool(c.kp_learn))
        self.gate = nn.Parameter(torch.zeros(()))
        place = _xy_place(c.targets, c.latent, positions)
        self.register_buffer("place", place, persistent=False)
        self.register_buffer("mask", place.sum(0), persistent=False)  # (Z,) 1 at x, y
        from methods.vid2param import presets

        if presets.space_of(c.system) == presets.VIEW:
            # positions normalised by the system's view extent, which the frame spans linearly
            # (``systems._draw.View``): x = column fraction, y = 1 - row fraction; point k reads
            # fixed channel k (``V2PConfig.fixed_channels``), any other point starts at channel
            # 0's centre (with ``kp_learn`` the map then learns the others)
            with torch.no_grad():
                self.map.weight.zero_()
                self.map.bias.zero_()
                for k in range(len(positions) // 2):
                    ch = k if k < c.fixed_channels else 0
                    self.map.weight[2 * k, 2 * ch] = 1.0
                    self.map.weight[2 * k + 1, 2 * ch + 1] = -1.0
                    self.map.bias[2 * k + 1] = 1.0
            # visibility: half at a tenth of the frame's pixels lit (no ball geometry here)
            self.log_mref = math.log(0.1 * c.frame_size[0] * c.frame_size[1] *
                                     (1 - c.kp_threshold))
            return
        # channel 0's centre (fractions of W and H) to normalised x, y: col = radius + x sx,
        # x_norm = x / 10; rows grow downwards from the floor: row = H - radius - (y - floor) sy
        H, W = c.frame_size
        geo = view_geometry((H, W))
        sx, sy = geo.px_per_m  # pixels per metre
        with torch.no_grad():
            self.map.weight.zero_()
            self.map.bias.zero_()
            self.map.weight[0, 0] = W / (10.0 * sx)
            self.map.bias[0] = -geo.radius / (10.0 * sx)
            self.map.weight[1, 1] = -H / (10.0 * sy)
            self.map.bias[1] = (H - geo.radius) / (10.0 * sy)
        # a full ball's mass in channel 0 (an anti-aliased disc of value 1, less the threshold)
        self.log_mref = math.log(max(1e-3, math.pi * geo.radius**2 * (1 - c.kp_threshold) / 3))

    def visibility(self, fx: torch.Tensor) -> torch.Tensor:
        """How visible the ball is, (B, 1) in (0, 1), from ``fx`` (B, feat + 3 K): 0.5 at a
        third of a full ball's mass in channel 0."""
        return torch.sigmoid(4.0 * (fx[:, -self.keypoints, None] - self.log_mref))

    def forward(self, fx: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
        """The posterior's means ``mu`` (B, Z) with x, y replaced as above."""
        kp = self.map(fx[:, -3 * self.keypoints:]) @ self.place
        if self.use_visibility:
            vis = self.visibility(fx)
            return (mu * (1 - self.mask) + vis * (kp + self.gate * mu * self.mask)
                    + (1 - vis) * mu * self.mask)
        return mu * (1 - self.mask + self.gate * self.mask) + kp


@dataclass(frozen=True, eq=False)
class RecurrentState:
    """The recurrence's state after some frames, batch B.

    Attributes
    ----------
    h, c : Tensor, shape (B, hidden)
    last_pos, last_vel : Tensor, shape (B, 2K)
        The last fed-back positions of the K points (normalised: the ball's by the view width)
        and velocity feature.
    n_seen : Tensor, shape (B, 1)
        Frames seen, capped at 2 (what the differences need).
    roll : Tensor, shape (B, n_cols), or None
        With ``roll_features``: the rolling statistic's columns (``StepDecelerations``,
        ``RunFits``).
    """

    h: torch.Tensor
    c: torch.Tensor
    last_pos: torch.Tensor
    last_vel: torch.Tensor
    n_seen: torch.Tensor
    roll: torch.Tensor | None = None

    def map(self, fn) -> RecurrentState:
        """The state with ``fn`` applied to each tensor (e.g. ``lambda t: t.to(device)``)."""
        return RecurrentState(**{f.name: None if getattr(self, f.name) is None
                                 else fn(getattr(self, f.name)) for f in fields(self)})


class Recurrence(nn.Module):
    """``h_t = LSTM([phi_z(z_t), velocity, acceleration], h_{t-1})``.

    The LSTM sees the fed-back z only, so forecasting runs in latent space without decoding
    frames. Beside ``phi_z(z)`` it gets the first and second differences of z's position
    dimensions, scaled to order 1 (velocity in metres per frame, acceleration x 40): fed
    positions alone, an LSTM must difference numbers of order 0.5 twice to see gravity's
    0.0025 per frame^2 (a plain LSTM on true positions left g at the prior's level; with these
    features it read g at nMSE ~0.005). The heads read ``[h, c]`` (the evidence is integrated in
    the cell, which ``h = o tanh(c)`` hides), and with ``roll_features`` the rolling mean and
    count (``RollingEvidence``).
    """

    def __init__(self, c):
        super().__init__()
        self.hidden, self.roll_features = c.hidden, bool(c.roll_features)
        self.roll_stat = ROLL_STATS[c.roll_stat] if c.roll_features else None
        self.phi_z = nn.Sequential(nn.Linear(c.latent, c.feat), nn.ReLU())
        self.pos_idx = [c.targets.index(name) for name in c.positions]  # 2K
        self.cell = nn.LSTMCell(c.feat + 2 * len(self.pos_idx), c.hidden)
        # Python floats: the ball's 10.0 and 40.0 multiply exactly as the literals did
        self.diff_scales = tuple(float(v) for v in c.diff_scales)
        self.n_read = 2 * c.hidden + (2 if self.roll_features else 0)  # R

    def init_state(self, batch: int, device=None) -> RecurrentState:
        """The state before the first frame: zeros."""
        z = torch.zeros(batch, self.hidden, device=device)
        m = torch.zeros(batch, len(self.pos_idx), device=device)
        st = self.roll_stat
        roll = None if st is None else torch.zeros(batch, st.n_cols, device=device, dtype=st.dtype)
        return RecurrentState(z, z, m, m, torch.zeros(batch, 1, device=device), roll)

    def read(self, state: RecurrentState) -> torch.Tensor:
        """What the posterior, prior and decoder read of the state: (B, R)."""
        out = torch.cat([state.h, state.c], -1)
        if state.roll is not None:
            out = torch.cat([out, _roll_features(*self.roll_stat.summary(state.roll))], -1)
        return out

    def forward(self, z: torch.Tensor, state: RecurrentState) -> RecurrentState:
        """The state after feeding back ``z`` (B, Z)."""
        n, vel_prev = state.n_seen, state.last_vel
        pos = z[:, self.pos_idx]
        s_vel, s_acc = self.diff_scales
        vel = torch.where(n >= 1, (pos - state.last_pos) * s_vel, torch.zeros_like(pos))
        acc = torch.where(n >= 2, (vel - vel_prev) * s_acc, torch.zeros_like(pos))
        inp = torch.cat([self.phi_z(z), vel.clamp(-5, 5), acc.clamp(-10, 10)], dim=-1)
        h, c = self.cell(inp, (state.h, state.c))
        # a fixed function of the fed-back z: gradient stopped
        roll = None if state.roll is None else self.roll_stat.update(
            pos.detach(), vel.detach(), vel_prev.detach(), n, state.roll)
        return RecurrentState(h, c, pos, vel, torch.clamp(n + 1, max=2.0), roll)


class GaussianHead(nn.Module):
    """A diagonal Gaussian over z from an MLP: (..., n_in) -> mean, std, each (..., Z)."""

    def __init__(self, n_in: int, hidden: int, latent: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, 2 * latent))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return _gauss(self.mlp(x))


class PriorHead(GaussianHead):
    """The prior p(z_t | h_{t-1}): its x, y means are a step from the last fed-back position.

    Forecasting unrolls the prior; a step of at most 0.05 (0.5 m per frame) is a far easier
    target than an absolute position.
    """

    def __init__(self, n_read: int, hidden: int, latent: int, targets: tuple[str, ...],
                 positions: tuple[str, ...] = ("x", "y")):
        super().__init__(n_read, hidden, latent)
        self.register_buffer("place", _xy_place(targets, latent, positions), persistent=False)

    def forward(self, h: torch.Tensor, last: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and std (..., Z) from the read-out ``h`` (..., R) and the last fed-back
        positions ``last`` (..., 2K)."""
        mu, std = _gauss(self.mlp(h))
        return mu + last @ self.place, std


def _roll_features(count: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """The heads' rolling inputs (B, 2) from a statistic's frame count and mean deceleration
    (m/s^2), each (B, 1): ``ROLL_GAIN`` times the mean divided by the prior's top r (about r
    normalised) and ``n / (n + 10)``."""
    count, mean = count.to(torch.float32), mean.to(torch.float32)
    return torch.cat([ROLL_GAIN * (mean / _R_TOP).clamp(-2, 2),
                      ROLL_GAIN * count / (count + 10.0)], -1)


class StepDecelerations:
    """``roll_stat="steps"`` (28x28 models): the mean of per-frame decelerations.

    Columns (B, 3), float32: consecutive low frames, rolling frames, summed deceleration. A
    frame rolls when the last three fed-back heights are below ``ROLL_HEIGHT`` (absolute, so
    the floor must be at 0), the last two horizontal steps exceed ``ROLL_STEP`` with one sign,
    the ball is more than ``ROLL_WALL`` from the walls and the deceleration under
    ``ROLL_DEC_MAX``.
    """

    n_cols, dtype = 3, torch.float32

    @staticmethod
    def update(pos, vel, vel_prev, n, stats) -> torch.Tensor:
        """The statistics (B, 3) after the newest fed-back frame: ``pos`` (B, 2) normalised;
        ``vel``, ``vel_prev`` (B, 2) metres per frame; ``n`` (B, 1) frames seen before this one
        (capped at 2)."""
        low = torch.where(pos[:, 1:2] * BOX_WIDTH < ROLL_HEIGHT, stats[:, 0:1] + 1.0,
                          torch.zeros_like(n)).clamp(max=3.0)
        vx, vxp = vel[:, 0:1], vel_prev[:, 0:1]
        dec = -torch.sign(vx) * (vx - vxp) / DT**2
        x = pos[:, 0:1] * BOX_WIDTH  # positions are normalised by the view width
        ok = ((low >= 3) & (n >= 2) & (vx.abs() > ROLL_STEP) & (vxp.abs() > ROLL_STEP)
              & (vx * vxp > 0) & (dec.abs() < ROLL_DEC_MAX)
              & (x > ROLL_WALL) & (x < BOX_WIDTH - ROLL_WALL)).to(pos.dtype)
        return torch.cat([low, stats[:, 1:2] + ok, stats[:, 2:3] + ok * dec], -1)

    @staticmethod
    def summary(stats) -> tuple[torch.Tensor, torch.Tensor]:
        """Rolling frames and their mean deceleration (m/s^2), each (B, 1)."""
        return stats[:, 1:2], stats[:, 2:3] / stats[:, 1:2].clamp(min=1.0)


#: ``RunFits`` gates, chosen on the camera and 28x28 models' fed-back tracks of train-split
#: videos (docs in the model card): largest height change (m per frame) of a rolling frame,
#: flat frames in a row before a frame joins a run, frames of a run before its fit counts.
FIT_DY, FIT_FLAT, FIT_MIN = 0.02, 4, 10


def _det3(a, b, c, d, e, f, g, h, i):
    """Determinant of [[a, b, c], [d, e, f], [g, h, i]] (tensors or floats)."""
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def run_fit_deceleration(n, s1, s2, s3, s4, sx, stx, sttx, direction):
    """Deceleration (m/s^2) of the least-squares parabola ``x = a + b t + c t^2`` through a run
    from its sums (``RunFits``): ``-2 c sgn(direction) / DT^2``. Tensors or floats; a run of
    fewer than 3 frames gives 0."""
    det = _det3(n, s1, s2, s1, s2, s3, s2, s3, s4)
    num = _det3(n, s1, sx, s1, s2, stx, s2, s3, sttx)
    if isinstance(det, torch.Tensor):
        c = torch.where(n >= 3, num / torch.where(n >= 3, det, torch.ones_like(det)), 0.0)
        return -2.0 * c * torch.sign(direction) / DT**2
    return -2.0 * (num / det if n >= 3 else 0.0) * math.copysign(1.0, direction) / DT**2


class RunFits:
    """``roll_stat="fit"`` (camera): parabolas fitted to runs of flat fed-back frames.

    On camera video one frame's height is a pixel row (~0.26 m) and a misread frame is off by
    a metre, so neither an absolute height gate nor per-frame second differences find the
    rolls. Rolling is flat instead: a frame joins the current run when its height moved less
    than ``FIT_DY`` in each of the last ``FIT_FLAT`` frames, its horizontal step exceeds
    ``ROLL_STEP`` with the previous step's sign, and it is more than ``ROLL_WALL`` from the
    walls. A ball in flight is flat for at most two frames at its apex. Rolling is a constant
    deceleration, so each run of at least ``FIT_MIN`` frames gets a least-squares parabola of
    x over time, whose curvature averages out the per-frame noise; runs combine weighted by
    length^3 (a run's curvature variance falls as length^-5).

    Columns (B, 14), float64 (the normal equations of 200-frame runs lose float32's digits):
    flat frames in a row, then the current run's n, sum t, t^2, t^3, t^4, sum x, t x, t^2 x
    (x from the run's first x), that first x and the run's direction, then the finished runs'
    summed weight, weighted deceleration and frames.
    """

    n_cols, dtype = 14, torch.float64

    @staticmethod
    def update(pos, vel, vel_prev, n, stats) -> torch.Tensor:
        """As ``StepDecelerations.update``."""
        pos, vel, vel_prev = pos.double(), vel.double(), vel_prev.double()
        n = n.double()
        col = lambda k: stats[:, k:k + 1]  # noqa: E731
        vx, vxp, vy = vel[:, 0:1], vel_prev[:, 0:1], vel[:, 1:2]
        x = pos[:, 0:1] * BOX_WIDTH
        ok = ((n >= 2) & (vy.abs() < FIT_DY) & (vx.abs() > ROLL_STEP) & (vx * vxp > 0)
              & (x > ROLL_WALL) & (x < BOX_WIDTH - ROLL_WALL))
        flat = torch.where(ok, (col(0) + 1.0).clamp(max=FIT_FLAT), torch.zeros_like(n))
        join = flat >= FIT_FLAT
        run = stats[:, 1:11]
        # a frame that does not join ends the run: a long enough run is added to the finished
        r_n = col(1)
        done = (~join) & (r_n >= FIT_MIN)
        dec = run_fit_deceleration(*run[:, :8].T[:, :, None], col(10))
        w = torch.where(done, r_n**3, torch.zeros_like(r_n))
        fin = torch.cat([col(11) + w, col(12) + w * dec, col(13) + torch.where(done, r_n, 0.0)], -1)
        # the joining frame's time in its run, and x from the run's first x
        first = r_n == 0
        x0 = torch.where(first, x, col(9))
        dirn = torch.where(first, torch.sign(vx), col(10))
        t, u = r_n, x - x0
        add = torch.cat([torch.ones_like(t), t, t**2, t**3, t**4, u, t * u, t**2 * u], -1)
        grown = torch.cat([run[:, :8] + add, x0, dirn], -1)
        run = torch.where(join, grown, torch.zeros_like(grown))
        return torch.cat([flat, run, fin], -1)

    @staticmethod
    def summary(stats) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames in counted runs and their weighted mean deceleration (m/s^2), each (B, 1):
        the finished runs and, once it has ``FIT_MIN`` frames, the current one."""
        r_n = stats[:, 1:2]
        live = r_n >= FIT_MIN
        dec = run_fit_deceleration(*stats[:, 1:9].T[:, :, None], stats[:, 10:11])
        w = torch.where(live, r_n**3, torch.zeros_like(r_n))
        total = stats[:, 11:12] + w
        mean = (stats[:, 12:13] + w * dec) / torch.where(total > 0, total, torch.ones_like(total))
        return stats[:, 13:14] + torch.where(live, r_n, 0.0), mean


#: The rolling statistics by ``V2PConfig.roll_stat``.
ROLL_STATS = {"steps": StepDecelerations, "fit": RunFits}


class RollingEvidence(nn.Module):
    """The rolling statistic and its blend into the posterior's r.

    Rolling resistance is at most 0.7 m/s^2, 1.75 mm per frame^2, against ~5 mm of per-frame
    noise in the second difference of 28x28 keypoint positions, so one frame's acceleration
    hides it. Over a roll the noise averages out. So the recurrent state keeps
    (``RecurrentState.roll``) a statistic of the fed-back track (``V2PConfig.roll_stat``:
    ``StepDecelerations``, the mean of per-frame decelerations, whose second differences
    telescope, or ``RunFits``, parabolas fitted to runs of flat frames) that gives a mean
    horizontal deceleration over the frames where the track rolls and their count n. The heads
    read both (``Recurrence.read``), and the posterior's r is blended towards the mean by the
    evidence ``v = n / (n + n_half)``::

        mu_r = (1 - v) mlp + v (scale * mean + bias),  std_r = (1 - v) mlp_std + v exp(log_std)

    with ``scale``, ``bias``, ``log_std``, ``log_half`` learned (from 1, 0, log 0.06, log 10):
    fed to the MLP alone, the statistic left r where it was. ``r_index``: r's latent dimension.
    """

    def __init__(self, r_index: int):
        super().__init__()
        self.r_index = int(r_index)
        self.scale = nn.Parameter(torch.ones(()))
        self.bias = nn.Parameter(torch.zeros(()))
        self.log_std = nn.Parameter(torch.tensor(math.log(0.06)))
        self.log_half = nn.Parameter(torch.tensor(math.log(10.0)))

    def forward(self, mu: torch.Tensor, std: torch.Tensor, h: torch.Tensor):
        """The posterior's ``mu``, ``std`` (B, Z) with r blended; ``h`` (B, R) the read-out,
        whose last two columns are the rolling features."""
        i = self.r_index
        feats = h[:, -2:] / ROLL_GAIN  # the mean (normalised r) and c = n / (n + 10)
        c = feats[:, 1:2]
        v = 10.0 * c / (10.0 * c + torch.exp(self.log_half) * (1.0 - c))  # n / (n + n_half)
        r_mu = (1 - v) * mu[:, i:i + 1] + v * (self.scale * feats[:, 0:1] + self.bias)
        r_sd = (1 - v) * std[:, i:i + 1] + v * torch.exp(self.log_std)
        return (torch.cat([mu[:, :i], r_mu, mu[:, i + 1:]], -1),
                torch.cat([std[:, :i], r_sd, std[:, i + 1:]], -1))


#: Kernel taps of a stride-2, 4-tap, padding-1 transposed convolution read by each output phase
#: ``r`` (output index 2 m + r) from inputs m - 1, m, m + 1; 4 is a zero tap.
_PHASE_TAPS = ((3, 1, 4), (4, 2, 0))


def _phase_deconv(m: nn.ConvTranspose2d, x: torch.Tensor) -> torch.Tensor:
    """``m(x)`` for ``Decoder``'s layers (kernel 4, stride 2, padding 1), as one 3 x 3
    convolution with an output channel per output phase, then ``pixel_shuffle``.

    Output pixel (2 i + ry, 2 j + rx) of a stride-2 transposed convolution sums inputs i - 1..i + 1
    and j - 1..j + 1 with the taps ``_PHASE_TAPS[ry]`` x ``_PHASE_TAPS[rx]``: the same sums in
    another order (equal up to float rounding), differentiable in ``m``'s own weight, and
    oneDNN's forward convolution is ~3x faster on a CPU than its transposed one for the
    one-channel output layer (8 -> 1 channels, 16 x 16 -> 32 x 32: 0.24 -> 0.08 s of one AVX2
    thread for 3200 frames, forward and backward).
    """
    w = m.weight  # (Cin, Cout, 4, 4)
    cin, cout = w.shape[:2]
    taps = torch.tensor(_PHASE_TAPS, device=w.device)
    wz = F.pad(w, (0, 1, 0, 1))  # tap 4 reads a zero
    # (Cin, Cout, ry, rx, a, b) -> (Cout * 4 phases, Cin, 3, 3), channels in pixel_shuffle order
    w3 = wz[:, :, taps[:, None, :, None], taps[None, :, None, :]]
    w3 = w3.permute(1, 2, 3, 0, 4, 5).reshape(cout * 4, cin, 3, 3)
    bias = None if m.bias is None else m.bias.repeat_interleave(4)
    return F.pixel_shuffle(F.conv2d(x, w3, bias, padding=1), 2)


class Decoder(nn.Module):
    """Frame logits from ``phi_z(z_t)`` and the read-out of ``h_{t-1}``.

    Mirrors the encoder: dense to a base grid, then stride-2 transposed convolutions (each
    doubles the size); the base is the pooled frame's size / 2^layers rounded up and the output
    cropped, so sizes not divisible by 2^layers (50x100) work. It reconstructs the pooled frame.
    """

    def __init__(self, c, n_read: int):
        super().__init__()
        self.size = (c.frame_size[0] // c.pool, c.frame_size[1] // c.pool)  # (Hp, Wp)
        k = 2 ** len(c.channels)
        self.base = (c.channels[-1], -(-self.size[0] // k), -(-self.size[1] // k))
        self.fc = nn.Sequential(nn.Linear(c.feat + n_read, c.feat), nn.ReLU(),
                                nn.Linear(c.feat, int(math.prod(self.base))), nn.ReLU())
        deconvs = []
        chans = list(c.channels[::-1]) + [1]
        for i in range(len(c.channels)):
            deconvs.append(nn.ConvTranspose2d(chans[i], chans[i + 1], 4, stride=2, padding=1))
            if i < len(c.channels) - 1:
                deconvs.append(nn.ReLU())
        self.deconv = nn.Sequential(*deconvs)

    def forward(self, fz: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Logits (N, Hp, Wp) from ``fz`` (N, feat) and ``h`` (N, R)."""
        u = self.fc(torch.cat([fz, h], -1)).reshape(-1, *self.base)
        if torch.is_grad_enabled():
            # a training step: NHWC tensors, and the one-channel output layer as a convolution
            # per output phase (:func:`_phase_deconv`): the decoder's forward and backward
            # 0.36 -> 0.25 s of one AVX2 thread for a 64 x 200 pendulum step's 3200 decoded
            # frames (docs/vid2param-training-speed.md); inference keeps the layers' own numbers
            u = u.contiguous(memory_format=torch.channels_last)
            for m in self.deconv:
                u = _phase_deconv(m, u) if isinstance(m, nn.ConvTranspose2d) and \
                    m.out_channels == 1 else m(u)
        else:
            u = self.deconv(u)
        return u[:, 0, : self.size[0], : self.size[1]]
