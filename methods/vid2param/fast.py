"""Fast inference paths of the Vid2Param network (the same network, fewer and cheaper calls).

Read-only users of a loaded :class:`~methods.vid2param.model.Vid2ParamNet`; measured figures and
profiles in ``docs/vid2param-speed.md``.

``FrameFilter``
    One frame at a time in plain NumPy (float32, as the network): what
    :meth:`Vid2ParamStream.push <methods.vid2param.estimator.Vid2ParamStream.push>` runs when the
    network is on the CPU. Weights copied once, preallocated buffers, one matrix product per
    layer, strided im2col for the convolutions, one product and one ``tanh`` for the LSTM
    gates, the state kept in NumPy between frames. Why: a push through the torch modules is
    ~60 small torch calls, each a few microseconds of dispatch and allocation; the arithmetic
    of one frame is ~0.4 M multiply-adds. In float32 the frame's elementwise passes (scaling,
    pooling, the keypoint heats, the LSTM's gate arithmetic) are numba loops doing numpy's
    operations in numpy's order (``fused``): the same bytes in fewer calls.

``encode_frames_batch``
    ``encode_frames`` over many frames in cache-sized pieces, used by
    :meth:`Vid2ParamNet.filter <methods.vid2param.model.Vid2ParamNet.filter>` (same numbers).

``LazyPosterior``
    A ``Posterior`` whose samples are drawn, from a stream keyed by the seed and the frame
    count, only when read.

Agreement with the torch modules is tested over whole videos (``tests/test_vid2param_fast.py``):
only the float32 rounding differs (sums in another order).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import nn

from methods.vid2param import parts as _parts
from methods.vid2param.parts import RecurrentState
from sysid_bench.core.estimator import Posterior

__all__ = ["FrameFilter", "LazyPosterior", "Unsupported", "fast_support", "frame_filter_for",
           "encode_frames_batch", "ENCODE_CHUNK"]

# -- fused elementwise passes of a float32 frame (FrameFilter, fused=True) -----------------------
# Each kernel is a few numpy calls of the same frame done in one loop: the same IEEE float32
# operations in the same order per element (numba rounds every product and sum, no fused
# multiply-add), so the bytes are numpy's; reductions, matrix products and tanh/log stay numpy
# calls (their order and implementations are numpy's and BLAS's). Why: a push is ~55 numpy
# calls on a few thousand numbers each, and the call, not the arithmetic, is the cost.
_njit = numba.njit(cache=True, nogil=True)
#: Frame dtypes the fused first pass takes (native byte order); other frames (float16, a
#: big-endian array, a list) take the numpy calls, whose casts numba does not all have.
_FUSED_FRAME_DTYPES = frozenset(np.dtype(t) for t in (np.uint8, np.float32, np.float64))


@_njit
def _frame_heat(frame, full, x, heat, pool, t_on, t, eps, scale, quarter):
    """``full = frame / scale``; channel 0's ``heat = max(full - t, 0) + eps`` (``full + eps``
    without a threshold, ``t_on`` False); with ``pool`` 2 the first conv's input ``x`` = the
    2x2 sums numpy adds (``(f00 + f01) + (f10 + f11)``) divided by ``quarter`` (pool 1: ``x``
    is ``full``, not written)."""
    H, W = frame.shape
    zero = np.float32(0.0)
    for i in range(H):
        for j in range(W):
            v = np.float32(frame[i, j]) / scale
            full[i, j] = v
            if t_on:
                h = v - t
                if h < zero:  # np.maximum(h, 0) (NaN kept)
                    h = zero
                heat[i, j] = h + eps
            else:
                heat[i, j] = v + eps
    if pool == 2:
        for i in range(H // 2):
            for j in range(W // 2):
                a = full[2 * i, 2 * j] + full[2 * i, 2 * j + 1]
                b = full[2 * i + 1, 2 * j] + full[2 * i + 1, 2 * j + 1]
                x[i, j] = (a + b) / quarter


@_njit
def _second_heat(full, grid, px, py, cx, cy, r2, level, eps, out):
    """``FrameEncoder._second_channel``'s float32 heat, into ``out`` (H W,) float64: the frame
    above ``level`` outside the disc ``((g - c) * px)^2 + ((g - c) * py)^2 > r2`` (x term
    first, as numpy's sum over the pair), times the disc mask as 1/0, plus ``eps``."""
    H, W = full.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    for i in range(H):
        for j in range(W):
            p = i * W + j
            dx = (grid[0, p] - cx) * px
            dy = (grid[1, p] - cy) * py
            far = one if dx * dx + dy * dy > r2 else zero
            h = full[i, j] - level
            if h < zero:
                h = zero
            out[p] = np.float64(h * far + eps)


@_njit
def _relu_eps(a, eps):
    """``np.maximum(a, 0, out=a); a += eps`` on a 2-D array."""
    zero = np.float32(0.0)
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            v = a[i, j]
            if v < zero:
                v = zero
            a[i, j] = v + eps


@_njit
def _lstm_cell(g, c, half):
    """After ``tanh`` of the gates ``g`` (i, f, o, g rows; the sigmoid rows' inputs halved):
    the sigmoids ``g * half + half`` (o written back into ``g``) and ``c = c * f + i * g``."""
    n = c.shape[0]
    for j in range(n):
        ig = g[j] * half + half
        fg = g[n + j] * half + half
        g[2 * n + j] = g[2 * n + j] * half + half
        c[j] = c[j] * fg + ig * g[3 * n + j]


class Unsupported(ValueError):
    """The network has a part the fast path does not implement (the torch path is used)."""


def _np(t: torch.Tensor, dtype=np.float32) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy().astype(dtype))


class _Conv:
    """One Conv2d (+ optional ReLU) on a single (C, H, W) image: im2col as one strided copy
    into a buffer whose last row is ones, then one matrix product with ``[W | b]``.

    The zero-padded input lives in ``buf`` (padding stays 0; write the interior, ``inner``);
    ``buf`` may be shared with another convolution of the same input and padding.
    """

    def __init__(self, conv: nn.Conv2d, c: int, h: int, w: int, relu: bool, dtype,
                 buf: np.ndarray | None = None):
        k, s, p = conv.kernel_size[0], conv.stride[0], conv.padding[0]
        if (conv.kernel_size[0] != conv.kernel_size[1] or conv.stride[0] != conv.stride[1]
                or conv.padding[0] != conv.padding[1] or conv.groups != 1
                or conv.dilation != (1, 1) or conv.bias is None or conv.padding_mode != "zeros"
                or p < 1):
            raise Unsupported("conv: only square, ungrouped, biased convolutions with zero "
                              f"padding >= 1, got {conv}")
        self.p, self.relu, self.out_c = p, relu, conv.out_channels
        hp, wp = h + 2 * p, w + 2 * p
        self.ho, self.wo = (hp - k) // s + 1, (wp - k) // s + 1
        if buf is None:
            buf = np.zeros((c, hp, wp), dtype)
        elif buf.shape != (c, hp, wp):
            raise Unsupported(f"conv: shared buffer {buf.shape}, expected {(c, hp, wp)}")
        self.buf = buf
        self.inner = buf[:, p:-p, p:-p]
        st = buf.strides
        # (c, k, k, ho, wo) patches in torch's unfold order, a view of the padded input
        self.patches = np.lib.stride_tricks.as_strided(
            buf, (c, k, k, self.ho, self.wo), (st[0], st[1], st[2], st[1] * s, st[2] * s),
            writeable=False)
        self.cols = np.ones((c * k * k + 1, self.ho * self.wo), dtype)  # last row: the bias's
        self.cols_view = self.cols[:-1].reshape(c, k, k, self.ho, self.wo)
        self.w = np.ascontiguousarray(np.concatenate(
            [_np(conv.weight, dtype).reshape(conv.out_channels, -1),
             _np(conv.bias, dtype)[:, None]], 1))
        self.y = np.empty((self.out_c, self.ho * self.wo), dtype)  # the product, reused
        self.zero = dtype(0)

    def __call__(self, out: np.ndarray | None = None) -> np.ndarray:
        """The convolution of what is in ``inner`` -> (out_c, ho * wo), a buffer reused by the
        next call; with ``out`` (a ReLU layer), the ReLU is written there instead (any shape of
        out_c * ho * wo elements: the next layer's ``inner``) and ``out`` returned."""
        np.copyto(self.cols_view, self.patches)
        y = np.matmul(self.w, self.cols, out=self.y)
        if self.relu:
            if out is None:
                return np.maximum(y, self.zero, out=y)
            return np.maximum(y.reshape(out.shape), self.zero, out=out)
        return y


def _conv_stack(module: nn.Module, c: int, h: int, w: int, dtype, buf=None) -> list[_Conv]:
    """``_Conv``s for a Conv2d or a Sequential of Conv2d, each optionally followed by ReLU."""
    mods = list(module) if isinstance(module, nn.Sequential) else [module]
    out: list[_Conv] = []
    i = 0
    while i < len(mods):
        m = mods[i]
        if not isinstance(m, nn.Conv2d):
            raise Unsupported(f"conv: expected Conv2d then ReLU, got {type(m).__name__}")
        relu = i + 1 < len(mods) and isinstance(mods[i + 1], nn.ReLU)
        layer = _Conv(m, c, h, w, relu, dtype, buf if not out else None)
        out.append(layer)
        c, h, w = layer.out_c, layer.ho, layer.wo
        i += 2 if relu else 1
    return out


def _linear(m: nn.Module, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(m, nn.Linear) or m.bias is None:
        raise Unsupported(f"linear: expected a biased nn.Linear, got {m}")
    return _np(m.weight, dtype), _np(m.bias, dtype)


def _mlp(seq: nn.Module, pattern: tuple[str, ...], dtype=np.float32):
    """Weights of a Sequential whose layer types follow ``pattern`` ("L" Linear, "R" ReLU)."""
    mods = list(seq) if isinstance(seq, nn.Sequential) else []
    kinds = tuple("L" if isinstance(m, nn.Linear) else "R" if isinstance(m, nn.ReLU)
                  else "F" if isinstance(m, nn.Flatten) else "?" for m in mods)
    if kinds != pattern:
        raise Unsupported(f"mlp: expected layers {pattern}, got {kinds}")
    return [_linear(m, dtype) for m in mods if isinstance(m, nn.Linear)]


def fast_support(net: nn.Module) -> str | None:
    """Why ``net`` cannot run on the fast paths, or None when it can."""
    try:
        FrameFilter(net)
    except Unsupported as exc:
        return str(exc)
    return None


class FrameFilter:
    """The network's filter for one video, one frame per call, in NumPy.

    ``step(frame)`` is ``enc_step(encode_frames(frame), read(state))`` then
    ``step_rnn(mu, state)`` of :class:`~methods.vid2param.model.Vid2ParamNet` for a batch of one,
    with the state kept here. The weights are copied at construction: build a new one (or call
    :meth:`reload`) after changing the network's weights.

    How it saves time: every vector lives in a buffer allocated once, laid out so that each
    layer's input is one contiguous slice ending in a constant 1 -- the bias is the weight
    matrix's last column, so a layer is one matrix product and one in-place ReLU; the LSTM
    state ``[h, c]`` sits inside the encoder head's input, where it is read.

    Parameters
    ----------
    net : Vid2ParamNet
        Any device; its weights are copied to host memory.
    dtype : {numpy.float32, numpy.float64}
        Working precision. float32 is the network's own (and the fast one); float64 evaluates
        the same float32 weights without rounding in between, a reference for tests: the
        network's second-difference feature multiplies position rounding by 400, so two float32
        evaluations (torch's batched and single-frame ones included) drift apart by ~1e-4 over
        a video.
    fused : bool, optional
        Run the frame's elementwise passes (scaling, pooling, the keypoint heats, the LSTM's
        gate arithmetic) as compiled loops: numpy's bytes in fewer calls. Default: with
        float32. False: numpy calls only (the reference the fused path is tested against).

    Raises
    ------
    Unsupported
        A part of ``net`` this path does not implement (checked at construction): a network
        built differently from what ``methods.vid2param.parts`` builds.
    """

    def __init__(self, net: nn.Module, dtype=np.float32, fused: bool | None = None):
        if np.dtype(dtype) not in (np.dtype(np.float32), np.dtype(np.float64)):
            raise ValueError(f"dtype: expected numpy.float32 or numpy.float64, got {dtype!r}")
        if fused is not None and not isinstance(fused, bool):
            raise ValueError(f"fused: expected True, False or None, got {fused!r}")
        self.F = np.dtype(dtype).type
        if fused and self.F is not np.float32:
            raise ValueError("fused: the fused passes are float32 only (dtype float64 given)")
        #: the frame's elementwise passes as numba loops (float32: numpy's bytes, fewer calls)
        self.fused = self.F is np.float32 if fused is None else fused
        self.net = net
        self.reload()
        self.reset()

    # -- weights --------------------------------------------------------------------------------
    def reload(self) -> None:
        """Copy the network's weights (again) and lay out the buffers."""
        net, F = self.net, self.F
        try:
            c = self.c = net.config
            enc = net.encoder
            H, W = c.frame_size
            self.H, self.W, self.pool = H, W, c.pool
            Hp, Wp = H // c.pool, W // c.pool
            self.convs = _conv_stack(enc.conv, 1, Hp, Wp, F)
            if not all(cv.relu for cv in self.convs):
                raise Unsupported("conv: expected a ReLU after each layer")
            K = self.K = int(c.keypoints)
            # kp_second: channel 1 is fixed (the frame above a grey level outside a disc about
            # channel 0's centre), the learned channels follow it
            self.second = tuple(float(v) for v in c.kp_second) if c.kp_second else None
            self.n_fixed = 2 if self.second else 1
            # the learned keypoint channels read the same zero-padded frame as the first conv
            self.kp = (_conv_stack(enc.kp, 1, Hp, Wp, F, buf=self.convs[0].buf)[0]
                       if enc.kp is not None else None)
            if self.kp is not None and self.kp.relu:
                raise Unsupported("kp: expected a bare Conv2d")
            # the frame in [0, 1] (with pool 1: the first conv's input itself) and its pooled
            # copy, written in place: views and buffers made once
            self.x_in = self.convs[0].inner[0]
            self.full = self.x_in if self.pool == 1 else np.empty((H, W), F)
            if self.pool == 2:
                self.q = np.empty((H, W // 2), F)
                self.full_pairs = (self.full[:, 0::2], self.full[:, 1::2])
                self.q_pairs = (self.q[0::2], self.q[1::2])
            # the scaling, pooling and channel 0's heat as one compiled pass (even sides only:
            # numpy refuses the odd ones' pairs, and so the path without it)
            self.fuse_frame = self.fused and (self.pool == 1 or (
                self.pool == 2 and H % 2 == 0 and W % 2 == 0))
            self.heat0 = np.empty(H * W, F)  # channel 0's heat, then its 2-D view
            self.heat0_2d = self.heat0.reshape(H, W)
            self.zero = F(0)
            # (H W, 2) and (Hp Wp, 2) pixel centres; channel 0's in float64 (see encode)
            self.grid64 = enc.grid.detach().cpu().double().numpy().T.copy()
            if self.second:
                # channel 1's disc test in the network's float32 arithmetic
                self.grid32 = np.ascontiguousarray(enc.grid.detach().cpu().numpy(), np.float32)
                self.px = np.array([[W], [H]], np.float32)
                self.heat1 = np.empty(H * W)  # its heat, float64 (the fused path's buffer)
            self.grid_pool = _np(enc.grid_pool, F).T.copy()
            wx, bx = _mlp(enc.phi_x, ("F", "L", "R"), F)[0]
            self.phi_x = np.ascontiguousarray(np.concatenate([wx, bx[:, None]], 1))
            n_conv = wx.shape[1]
            self.conv_out = np.zeros(n_conv + 1, F)  # last conv's output, then 1
            self.conv_out[-1] = 1
            self.conv_feat = self.conv_out[:-1]
            self.kp_pos = _linear(net.keypoints.map, F)
            self.kp_gate = float(net.keypoints.gate.item())
            # the tracked points' x, y in the latent (the keypoint map writes them; the
            # recurrence differences them): one point on the ball, K on a system's network
            self.xy_idx = [c.targets.index(name) for name in c.positions]
            self.vis = bool(net.keypoints.use_visibility)
            self.log_mref = float(net.keypoints.log_mref)
            Z, hid, feat = int(c.latent), int(c.hidden), int(c.feat)
            self.Z, self.hidden = Z, hid
            # encoder head input: [phi_x (feat), centres (2K), log masses (K), h, c, roll (0|2), 1]
            self.roll = net.rolling is not None
            n_fx = feat + 3 * K
            self.sl_fx = slice(0, n_fx)
            self.sl_kp = slice(feat, n_fx)
            self.sl_h = slice(n_fx, n_fx + hid)
            self.sl_c = slice(n_fx + hid, n_fx + 2 * hid)
            self.i_roll = n_fx + 2 * hid  # roll features at i_roll, i_roll + 1
            self.enc_in = np.zeros(n_fx + 2 * hid + (2 if self.roll else 0) + 1, F)
            self.enc_in[-1] = 1
            self.fx_feat = self.enc_in[:feat]  # phi_x's output
            self.kp_view = self.enc_in[self.sl_kp]
            self.kp_c0 = self.kp_view[:2]  # channel 0's centre
            if self.kp is not None:
                n0 = self.n_fixed
                self.kp_m = np.empty(K - n0, F)  # the learned channels' masses
                self.kp_m_col = self.kp_m[:, None]
                # their centres (K - n0, 2) and log masses, written into the head's input
                self.kp_xy = self.kp_view[2 * n0:2 * K].reshape(K - n0, 2)
                self.kp_logm = self.kp_view[2 * K + n0:]
            (w1, b1), (w2, b2) = _mlp(net.posterior.mlp, ("L", "R", "L"), F)
            if w1.shape[1] != self.enc_in.size - 1:
                raise Unsupported(f"enc: expected {self.enc_in.size - 1} inputs, got {w1.shape[1]}")
            self.enc1 = np.ascontiguousarray(np.concatenate([w1, b1[:, None]], 1))
            self.enc2 = np.ascontiguousarray(np.concatenate([w2, b2[:, None]], 1))
            self.enc_hid = np.zeros(w1.shape[0] + 1, F)
            self.enc_hid[-1] = 1
            self.enc_hid_h = self.enc_hid[:-1]
            wz, bz = _mlp(net.recurrence.phi_z, ("L", "R"), F)[0]
            self.phi_z = np.ascontiguousarray(np.concatenate([wz, bz[:, None]], 1))
            self.z_in = np.zeros(Z + 1, F)
            self.z_in[-1] = 1
            self.z_head = self.z_in[:-1]
            cell = net.recurrence.cell
            if not isinstance(cell, nn.LSTMCell) or cell.bias is False:
                raise Unsupported(f"cells: expected a biased nn.LSTMCell, got {cell}")
            # LSTM input: [phi_z (feat), velocity (2), acceleration (2), h, 1]; one product
            # [W_ih | W_hh | b_ih + b_hh] instead of two. The i, f, o rows are halved (exact in
            # binary) so that one tanh gives all four gates: sigmoid(x) = (1 + tanh(x / 2)) / 2.
            wl = np.concatenate([_np(cell.weight_ih, F), _np(cell.weight_hh, F),
                                 (_np(cell.bias_ih, F) + _np(cell.bias_hh, F))[:, None]], 1)
            n_xy = len(self.xy_idx)
            if wl.shape[1] != feat + 2 * n_xy + hid + 1:
                raise Unsupported(f"cells: expected {feat + 2 * n_xy} inputs, got "
                                  f"{wl.shape[1] - hid - 1}")
            wl[:2 * hid] *= F(0.5)
            wl[3 * hid:] *= F(0.5)
            # rows reordered (i, f, o, g) from torch's (i, f, g, o): the three sigmoid gates
            # are one slice (each row's product is the same dot product wherever it sits)
            self.lstm = np.ascontiguousarray(np.concatenate(
                [wl[:2 * hid], wl[3 * hid:], wl[2 * hid:3 * hid]]))
            self.lstm_in = np.zeros(wl.shape[1], F)
            self.lstm_in[-1] = 1
            self.sl_feat = slice(0, feat)
            self.sl_lh = slice(feat + 2 * n_xy, feat + 2 * n_xy + hid)
            self.li_feat = self.lstm_in[:feat]
            self.li_h = self.lstm_in[self.sl_lh]
            self.gates = np.zeros(4 * hid, F)
            g = self.gates
            self.g_sig, self.g_i, self.g_f = g[:3 * hid], g[:hid], g[hid:2 * hid]
            self.g_o, self.g_g = g[2 * hid:3 * hid], g[3 * hid:]
            self.tmp_h = np.zeros(hid, F)
            self.tmp_ig = np.zeros(hid, F)
            self.ei_h, self.ei_c = self.enc_in[self.sl_h], self.enc_in[self.sl_c]
            self.pos_idx = [int(i) for i in net.recurrence.pos_idx]
            # the clipped velocity then acceleration of the fed-back positions
            self.li_diff = self.lstm_in[feat:feat + 2 * len(self.pos_idx)]
            if self.roll and len(self.pos_idx) != 2:
                raise Unsupported("roll_features: the NumPy path rolls one point only")
            self.s_vel, self.s_acc = net.recurrence.diff_scales
            if self.roll:
                r = net.rolling
                self.roll_stat = net.recurrence.roll_stat
                # the statistic's float update and (count, mean) summary, chosen once
                paths = {_parts.StepDecelerations: (self._roll_stats, self._steps_summary),
                         _parts.RunFits: (self._fit_stats, self._fit_summary)}
                if self.roll_stat not in paths:
                    raise Unsupported(f"roll_stat: no NumPy path for {self.roll_stat!r}")
                self._roll_update, self._roll_summary = paths[self.roll_stat]
                self.r_idx = r.r_index
                self.roll_scale, self.roll_bias = float(r.scale.item()), float(r.bias.item())
                self.roll_half = math.exp(r.log_half.item())
                self.roll_std = math.exp(r.log_std.item())
        except AttributeError as exc:  # a network built differently from what this path knows
            raise Unsupported(f"net: {exc}") from exc

    # -- state ----------------------------------------------------------------------------------
    def reset(self) -> None:
        """Zero state (no frame seen)."""
        self.enc_in[self.sl_h] = 0
        self.enc_in[self.sl_c] = 0
        # The few scalars of the state are Python floats (float64): numpy scalar arithmetic
        # costs ~10x more per operation, and float64 rounds less than torch's float32 does.
        self.pos = (0.0,) * len(self.pos_idx)
        self.vel = self.pos
        self.n = 0.0
        # the rolling statistic's columns (parts.StepDecelerations or parts.RunFits)
        self.stats = (0.0,) * self.roll_stat.n_cols if self.roll else ()
        self._set_roll_features()

    def torch_state(self, device=None) -> RecurrentState:
        """The state as the network's (batch of one, float32)."""
        t = lambda a, d=torch.float32: torch.tensor(np.asarray(a, np.float64).reshape(1, -1),  # noqa: E731
                                                    dtype=d, device=device)
        roll = t(self.stats, self.roll_stat.dtype) if self.roll else None
        return RecurrentState(t(self.enc_in[self.sl_h]), t(self.enc_in[self.sl_c]), t(self.pos),
                              t(self.vel), t([self.n]), roll)

    def set_torch_state(self, state: RecurrentState) -> None:
        """Take the state from the network's (batch of one)."""
        a = lambda x: x.detach().to("cpu", torch.float64).numpy().reshape(-1)  # noqa: E731
        if not isinstance(state, RecurrentState) or (state.roll is not None) != self.roll:
            kind = "with" if self.roll else "without"
            raise ValueError(f"state: expected a RecurrentState {kind} rolling statistics, "
                             f"got {state!r}")
        if self.roll and state.roll.shape[-1] != self.roll_stat.n_cols:
            raise ValueError(f"state: expected {self.roll_stat.n_cols} rolling columns "
                             f"({self.roll_stat.__name__}), got {state.roll.shape[-1]}")
        self.enc_in[self.sl_h], self.enc_in[self.sl_c] = a(state.h), a(state.c)
        self.pos, self.vel = tuple(a(state.last_pos).tolist()), tuple(a(state.last_vel).tolist())
        self.n = float(a(state.n_seen)[0])
        if self.roll:
            self.stats = tuple(a(state.roll).tolist())
        self._set_roll_features()

    def _set_roll_features(self) -> None:
        """``Recurrence.read``'s rolling mean and count features from ``stats``."""
        if not self.roll:
            return
        s, g = self.stats, _parts.ROLL_GAIN
        count, mean = self._roll_summary(s)
        mean = min(max(mean / _parts._R_TOP, -2.0), 2.0)
        self.enc_in[self.i_roll:self.i_roll + 2] = (g * mean, g * (count / (count + 10.0)))

    # -- the network, one frame -----------------------------------------------------------------
    def encode(self, frame: np.ndarray) -> np.ndarray:
        """``encode_frames`` of one (H, W) frame (uint8 or float in [0, 255]), written into the
        encoder head's input; returns that slice (n_fx,) (a view: copy to keep it).

        Every step writes into a buffer made at :meth:`reload` (``out=``): a numpy call on
        these few thousand numbers costs more in overhead than in arithmetic."""
        F, zero = self.F, self.zero
        K, t = self.K, self.c.kp_threshold
        heat0, h2 = self.heat0, self.heat0_2d
        full = self.full
        if (self.fuse_frame and type(frame) is np.ndarray
                and frame.dtype in _FUSED_FRAME_DTYPES):  # scaling, pooling, channel 0's heat
            _frame_heat(frame, full, self.x_in, h2, self.pool, bool(t), F(t), F(1e-6),
                        F(255.0), F(4))
        else:
            np.divide(frame, F(255.0), dtype=F, out=full)
            if self.pool == 2:  # the pairs numpy's sum over axes (1, 3) adds, in its order
                (a, b), (qa, qb), x = self.full_pairs, self.q_pairs, self.x_in
                np.add(a, b, out=self.q)
                np.add(qa, qb, out=x)
                np.divide(x, F(4), out=x)
            elif self.pool > 1:
                p = self.pool
                self.x_in[...] = (full.reshape(self.H // p, p, self.W // p, p).sum((1, 3))
                                  / F(p * p))
            if t:
                np.subtract(full, F(t), out=h2)
                np.maximum(heat0, zero, out=heat0)
                heat0 += F(1e-6)
            else:
                np.add(full, F(1e-6), out=h2)
        convs = self.convs
        for i in range(len(convs) - 1):  # each ReLU written into the next layer's input
            convs[i](out=convs[i + 1].inner)
        convs[-1](out=self.conv_feat)
        np.matmul(self.phi_x, self.conv_out, out=self.fx_feat)
        np.maximum(self.fx_feat, zero, out=self.fx_feat)
        # The centres are sums over thousands of pixels: float64 here, as float32 dot products
        # put ~1e-5 into the fed-back position, which the second-difference feature multiplies
        # by 400 (measured on the camera model: 5x torch's own deviation from a float64 run).
        m0 = np.add.reduce(heat0)  # heat0.sum() without its Python wrappers
        kp = self.kp_view
        np.divide(heat0 @ self.grid64, np.float64(m0), out=self.kp_c0)
        kp[2 * K] = np.log(m0)
        if self.second:
            self._second_channel(full, kp)
        if self.kp is not None:
            heat = self.kp()  # (K - n0, Hp Wp); the frame is already in the first conv's buffer
            if self.fused:
                _relu_eps(heat, F(1e-6))
            else:
                np.maximum(heat, zero, out=heat)
                heat += F(1e-6)
            m = np.add.reduce(heat, 1, out=self.kp_m)  # heat.sum(1)
            # these centres feed the head's MLP only (kp_pos reads channel 0): float32 will do
            heat /= self.kp_m_col
            np.matmul(heat, self.grid_pool, out=self.kp_xy)
            np.log(m, out=self.kp_logm)
        return self.enc_in[self.sl_fx]

    def _second_channel(self, full: np.ndarray, kp: np.ndarray) -> None:
        """``FrameEncoder._second_channel`` for one frame: channel 1's centre into ``kp[2:4]``
        and its log mass into ``kp[2 K + 1]``, from the frame ``full`` (H, W) in [0, 1] and
        channel 0's centre in ``kp[:2]`` (as the network: the disc test in float32 pixels,
        the centroid in float64)."""
        level, radius = self.second
        f32 = np.float32
        if self.fused:  # full and kp are float32
            heat = self.heat1
            _second_heat(full, self.grid32, self.px[0, 0], self.px[1, 0], kp[0], kp[1],
                         f32(radius * radius), f32(level), f32(1e-6), heat)
            m1 = np.add.reduce(heat)
            np.divide(heat, m1, out=heat)
            kp[2:4] = heat @ self.grid64
        else:
            d = (self.grid32 - kp[:2].astype(f32)[:, None]) * self.px
            far = (d * d).sum(0) > f32(radius * radius)
            heat = np.maximum(full.reshape(-1).astype(f32) - f32(level), f32(0))
            heat = (heat * far + f32(1e-6)).astype(np.float64)
            m1 = heat.sum()
            kp[2:4] = (heat / m1) @ self.grid64
        kp[2 * self.K + 1] = np.log(f32(m1))

    def enc_step(self) -> tuple[np.ndarray, np.ndarray]:
        """Encoder head on the buffer (frame features and state) -> mu, std, each (Z,)."""
        F, Z, ei = self.F, self.Z, self.enc_in
        hb, h = self.enc_hid, self.enc_hid_h
        np.matmul(self.enc1, ei, out=h)
        np.maximum(h, self.zero, out=h)
        raw = self.enc2 @ hb
        mu = raw[:Z]
        # torch's softplus (threshold 20) to within an ulp
        std = np.logaddexp(F(0), raw[Z:])
        std += F(_parts._MIN_STD)
        # the scalar blends in Python floats (see reset)
        K, kp = self.K, self.kp_view
        kxy = (self.kp_pos[0] @ kp + self.kp_pos[1]).tolist()
        g = self.kp_gate
        if self.vis:
            v = 1.0 / (1.0 + math.exp(-4.0 * (float(kp[2 * K]) - self.log_mref)))
            for i, k in zip(self.xy_idx, kxy):
                m = float(mu[i])
                mu[i] = v * (k + g * m) + (1.0 - v) * m
        else:
            for i, k in zip(self.xy_idx, kxy):
                mu[i] = float(mu[i]) * g + k
        if self.roll:
            f0, c = (x / _parts.ROLL_GAIN for x in ei[self.i_roll:self.i_roll + 2].tolist())
            v = 10.0 * c / (10.0 * c + self.roll_half * (1.0 - c))
            i = self.r_idx
            mu[i] = (1.0 - v) * float(mu[i]) + v * (self.roll_scale * f0 + self.roll_bias)
            std[i] = (1.0 - v) * float(std[i]) + v * self.roll_std
        return mu, std

    def step_rnn(self, z: np.ndarray) -> None:
        """Advance the state with the fed-back z (Z,)."""
        F, li = self.F, self.lstm_in
        self.z_head[...] = z
        np.matmul(self.phi_z, self.z_in, out=self.li_feat)
        np.maximum(self.li_feat, self.zero, out=self.li_feat)
        n = self.n
        pos = tuple(float(z[i]) for i in self.pos_idx)
        sv, sa = self.s_vel, self.s_acc
        vel = tuple((p - q) * sv for p, q in zip(pos, self.pos)) if n >= 1 else (0.0,) * len(pos)
        acc = tuple((p - q) * sa for p, q in zip(vel, self.vel)) if n >= 2 else (0.0,) * len(pos)
        self.li_diff[...] = ([min(max(v, -5.0), 5.0) for v in vel]
                             + [min(max(a, -10.0), 10.0) for a in acc])
        self.li_h[...] = self.ei_h
        g, c = self.gates, self.ei_c
        np.matmul(self.lstm, li, out=g)
        np.tanh(g, out=g)
        # tanh(x/2) of the input, forget and output gates -> sigmoid(x); c = f c + i g
        if self.fused:
            _lstm_cell(g, c, F(0.5))
        else:
            sg = self.g_sig
            sg *= F(0.5)
            sg += F(0.5)
            c *= self.g_f
            c += np.multiply(self.g_i, self.g_g, out=self.tmp_ig)
        np.tanh(c, out=self.tmp_h)
        np.multiply(self.g_o, self.tmp_h, out=self.ei_h)
        if self.roll:
            self.stats = self._roll_update(pos, vel, self.vel, n, self.stats)
            self._set_roll_features()
        self.pos, self.vel, self.n = pos, vel, min(n + 1.0, 2.0)

    @staticmethod
    def _roll_stats(pos, vel, vel_prev, n, stats) -> tuple[float, float, float]:
        """``parts._roll_update`` for one frame, on Python floats."""
        M = _parts
        low = min(stats[0] + 1.0 if pos[1] * M.BOX_WIDTH < M.ROLL_HEIGHT else 0.0, 3.0)
        vx, vxp = vel[0], vel_prev[0]
        dec = -math.copysign(1.0, vx) * (vx - vxp) / M.DT**2 if vx else 0.0
        x = pos[0] * M.BOX_WIDTH
        ok = (low >= 3 and n >= 2 and abs(vx) > M.ROLL_STEP and abs(vxp) > M.ROLL_STEP
              and vx * vxp > 0 and abs(dec) < M.ROLL_DEC_MAX
              and M.ROLL_WALL < x < M.BOX_WIDTH - M.ROLL_WALL)
        return (low, stats[1] + 1.0, stats[2] + dec) if ok else (low, stats[1], stats[2])

    @staticmethod
    def _steps_summary(stats) -> tuple[float, float]:
        """``parts.StepDecelerations.summary`` on Python floats: (frames, mean deceleration)."""
        return stats[1], stats[2] / max(stats[1], 1.0)

    @staticmethod
    def _fit_stats(pos, vel, vel_prev, n, stats) -> tuple[float, ...]:
        """``parts.RunFits.update`` for one frame, on Python floats."""
        M = _parts
        vx, vxp, vy = vel[0], vel_prev[0], vel[1]
        x = pos[0] * M.BOX_WIDTH
        ok = (n >= 2 and abs(vy) < M.FIT_DY and abs(vx) > M.ROLL_STEP and vx * vxp > 0
              and M.ROLL_WALL < x < M.BOX_WIDTH - M.ROLL_WALL)
        flat = min(stats[0] + 1.0, M.FIT_FLAT) if ok else 0.0
        r_n, fin = stats[1], stats[11:14]
        if flat < M.FIT_FLAT:
            if r_n >= M.FIT_MIN:
                w = r_n**3
                dec = M.run_fit_deceleration(*stats[1:9], stats[10])
                fin = (fin[0] + w, fin[1] + w * dec, fin[2] + r_n)
            return (flat,) + (0.0,) * 10 + tuple(fin)
        x0, dirn = (x, math.copysign(1.0, vx) if vx else 0.0) if r_n == 0 else stats[9:11]
        t, u = r_n, x - x0
        s = stats[1:9]
        run = (s[0] + 1.0, s[1] + t, s[2] + t * t, s[3] + t**3, s[4] + t**4, s[5] + u,
               s[6] + t * u, s[7] + t * t * u)
        return (flat,) + run + (x0, dirn) + tuple(fin)

    @staticmethod
    def _fit_summary(stats) -> tuple[float, float]:
        """``parts.RunFits.summary`` on Python floats: (frames, mean deceleration)."""
        M, r_n = _parts, stats[1]
        w = r_n**3 if r_n >= M.FIT_MIN else 0.0
        dec = M.run_fit_deceleration(*stats[1:9], stats[10]) if w else 0.0
        total = stats[11] + w
        mean = (stats[12] + w * dec) / total if total > 0 else 0.0
        return stats[13] + (r_n if w else 0.0), mean

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One frame: the posterior given it and the frames before, then the state update
        (``Vid2ParamNet.filter`` for a batch of one).

        Parameters
        ----------
        frame : ndarray, shape (H, W)
            uint8, or float in [0, 255].

        Returns
        -------
        mu, std : ndarray, shape (Z,)
            Normalised units, as ``enc_step``; fresh arrays.
        """
        self.encode(frame)
        mu, std = self.enc_step()
        self.step_rnn(mu)
        return mu, std



#: Frames per piece in ``encode_frames_batch``: the conv activations of 1024 28x28 frames take
#: ~6 MB, those of a whole batch of 100 videos (20,000 frames) ~0.7 GB.
ENCODE_CHUNK = 1024


def encode_frames_batch(net: nn.Module, frames: torch.Tensor,
                        chunk: int | None = None) -> torch.Tensor:
    """``net.encode_frames(frames)`` in pieces of ``chunk`` frames (same numbers).

    Why: on all frames of a batch at once, the encoder's intermediate tensors (conv
    activations, keypoint heat maps and their normalised copies) are hundreds of megabytes,
    written once and read once: measured on the 2-core CPU, one thread, 100 videos x 200 frames
    took 2.3 s of CPU in one piece and ~0.6 s in pieces that stay in cache. With gradients
    (training) the call is passed through unchanged.

    Parameters
    ----------
    frames : Tensor, shape (..., H, W)
    chunk : int, optional
        Frames per piece; default ``ENCODE_CHUNK``.

    Returns
    -------
    Tensor, shape (..., feat + 3 * keypoints)
    """
    chunk = ENCODE_CHUNK if chunk is None else int(chunk)
    lead = frames.shape[:-2]
    n = int(np.prod(lead)) if lead else 1
    if torch.is_grad_enabled() or n <= chunk:
        return net.encode_frames(frames)
    flat = frames.reshape(n, *frames.shape[-2:])
    first = net.encode_frames(flat[:chunk])
    out = torch.empty((n, first.shape[-1]), dtype=first.dtype, device=first.device)
    out[:chunk] = first
    for i in range(chunk, n, chunk):
        out[i:i + chunk] = net.encode_frames(flat[i:i + chunk])
    return out.reshape(*lead, -1)

def _weights_version(net: nn.Module) -> tuple[int, ...]:
    """Changes whenever a parameter or buffer is modified in place (optimiser steps,
    ``load_state_dict``) or replaced."""
    return tuple((id(t), t._version) for t in (*net.parameters(), *net.buffers()))


def frame_filter_for(net: nn.Module, device, previous: FrameFilter | None = None):
    """A reset :class:`FrameFilter` for ``net``, or None where the torch modules must run.

    None when ``device`` is not the CPU (the weights stay on the accelerator) or when the
    network has a part the NumPy path does not implement. ``previous`` (a filter of the same
    network) is reused when no weight has changed since it copied them.
    """
    if torch.device(device).type != "cpu":
        return None
    version = _weights_version(net)
    if previous is not None and previous.net is net and previous.version == version:
        previous.reset()
        return previous
    try:
        ff = FrameFilter(net)
    except Unsupported:
        return None
    ff.version = version
    return ff


class LazyPosterior(Posterior):
    """A :class:`~sysid_bench.core.estimator.Posterior` whose ``samples`` are drawn when first read.

    The samples are ``clip(loc + std * eps, lo, hi)`` with ``eps`` the first ``(n_samples, 4)``
    standard normals of ``numpy.random.default_rng(seed)``: each posterior has its own keyed
    stream, so the bytes depend on the seed only, not on which posteriors were read before or
    in what order, and a posterior nobody samples costs no draw. Why: drawing, clipping and
    checking 200 x 4 samples was ~40% of a streamed frame's time, and an online consumer
    (a controller reading the mean) never reads them.

    Parameters
    ----------
    mean, std : ndarray, shape (P,)
    extras : dict
    loc : ndarray, shape (P,)
        Centre of the samples (the mean before clipping).
    seed : sequence of int
        Key of the samples' stream.
    n_samples : int
    bounds : (ndarray, ndarray), optional
        Clip the samples to ``[lo, hi]``.
    system : str
        Whose parameters (``Posterior.system``).
    """

    def __init__(self, mean, std, extras, *, loc, seed, n_samples: int, bounds=None,
                 system: str = "ball"):
        super().__init__(mean=mean, std=std, samples=None, extras=extras, system=system)
        self._draw = (np.asarray(loc, np.float64), tuple(int(s) for s in seed), int(n_samples),
                      bounds)

    @classmethod
    def from_floats(cls, mean: list, std: list, extras: dict, *, seed, n_samples: int,
                    bounds=None, system: str, mean_bounds=None) -> LazyPosterior:
        """``cls(np.array(mean), np.array(std), extras, loc=<the mean array>, ...)``, the same
        object, from Python floats, with :class:`Posterior`'s checks made on the floats.

        Why: a stream builds one posterior a frame, and ``Posterior.__post_init__`` (a system
        look-up, the envelope's bounds computed again, array checks) cost about as much as the
        arithmetic of the posterior head. Where every check passes on the floats the object is
        assembled without running them again; where one fails (or ``mean_bounds`` is None) the
        ordinary constructor runs and raises its own error.

        Parameters
        ----------
        mean, std : list of float, length P
            Physical units, the system's order.
        extras : dict
        seed, n_samples, bounds, system
            As the constructor's (``loc`` is the mean).
        mean_bounds : list of (float, float), optional
            Per parameter, the range ``system``'s ``check_posterior_mean`` accepts
            (``System._mean_bounds()``); the caller's promise that the system checks nothing
            else. None: always the ordinary constructor.
        """
        ok = (mean_bounds is not None and len(mean) == len(std) == len(mean_bounds)
              and type(system) is str and type(extras) is dict)
        if ok:
            for m, s, (a, b) in zip(mean, std, mean_bounds):
                # finite, inside the envelope's margin; std >= 0 (NaN fails both)
                if not (a <= m <= b and math.isfinite(m) and s >= 0):
                    ok = False
                    break
        m_arr, s_arr = np.array(mean, np.float64), np.array(std, np.float64)
        if not ok:
            return cls(m_arr, s_arr, extras, loc=m_arr, seed=seed, n_samples=n_samples,
                       bounds=bounds, system=system)
        post = cls.__new__(cls)
        # what the constructor leaves in __dict__ (dataclass fields, then the samples' draw)
        post.__dict__.update(mean=m_arr, std=s_arr, _draw=(m_arr, tuple(map(int, seed)),
                                                            int(n_samples), bounds),
                             _samples=None, extras=extras, check=None, system=system)
        return post

    @property
    def samples(self):
        draw = self.__dict__.get("_draw")
        if draw is not None:
            loc, seed, n, bounds = draw
            s = loc + self.std * np.random.default_rng(seed).standard_normal((n, loc.size))
            if bounds is not None:
                np.minimum(np.maximum(s, bounds[0], out=s), bounds[1], out=s)
            self.__dict__["_samples"] = s
            self.__dict__["_draw"] = None
        return self.__dict__.get("_samples")

    @samples.setter
    def samples(self, value) -> None:
        self.__dict__["_draw"] = None
        self.__dict__["_samples"] = value
