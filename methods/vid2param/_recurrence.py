"""The training recurrence of a system's network over its observed frames, with a written-out
backward pass (``Vid2ParamNet._observed_pass`` uses it where it applies).

Per frame ``t`` (the arithmetic of ``enc_step`` then ``step_rnn``, as ``_observed_pass`` writes
it): the posterior's hidden layer ``z1 = relu(pre_t + r W_read)`` of the read-out ``r = [h, c]``,
its output ``[mu0, s] = z1 W_2 + b_2``, ``std = softplus(s) + MIN_STD``, the keypoint blend
``mu = mu0 * scale + shift_t``, the fed-back positions' velocity and acceleration features, and
the LSTM cell on ``[relu(mu W_z + b_z), clamp(vel), clamp(acc), h]``.

Autograd records ~40 small operations a frame and, in the backward pass, a weight gradient per
frame and per weight, each added into the weight's gradient (~1/3 of the loop's matrix products
and all of its ``add_`` calls: docs/vid2param-training-speed.md). Here the forward pass runs
without a graph, keeping what the backward pass reads, and the backward pass walks the frames
back computing only the activations' gradients; each weight's gradient over all frames is then
one large product (as cuDNN's LSTM does). The numbers are autograd's up to float order
(``tests/test_vid2param_recurrence.py``: float64 gradcheck and float32 against autograd).
"""

from __future__ import annotations

import torch

__all__ = ["ObservedRecurrence"]


class ObservedRecurrence(torch.autograd.Function):
    """``apply(pre, scale, shift, w_read, w2t, b2, wz, bz, w_cell, b_cell, consts)``.

    Parameters
    ----------
    pre : Tensor, shape (T, B, H1)
        The posterior's first layer on the frame features (its bias included).
    scale : Tensor, shape (Z,)
        The keypoint blend's factor on the network's means.
    shift : Tensor, shape (T, B, Z)
        The keypoint positions added to them.
    w_read : Tensor, shape (R2, H1)
        The posterior's first layer on the read-out ``[h, c]`` (R2 = 2 hidden).
    w2t, b2 : Tensor, shapes (H1, 2 Z), (2 Z,)
        Its output layer.
    wz, bz : Tensor, shapes (Z, F), (F,)
        The recurrence's ``phi_z``.
    w_cell, b_cell : Tensor, shapes (F + 2 n + hidden, 4 hidden), (4 hidden,)
        The LSTM's input and hidden weights side by side, and its two biases summed.
    consts : tuple
        ``(pos_lo, n_pos, s_vel, s_acc, min_std)``: the fed-back positions are
        ``mu[:, pos_lo:pos_lo + n_pos]``.

    Returns
    -------
    reads : Tensor, shape (T, B, R2)
        The read-out before each frame.
    mu, std : Tensor, shape (T, B, Z)
    h, c : Tensor, shape (B, hidden)
        After the last frame.
    last_pos, last_vel : Tensor, shape (B, n_pos)
        The last frame's fed-back positions and velocity feature.
    """

    @staticmethod
    def forward(ctx, pre, scale, shift, w_read, w2t, b2, wz, bz, w_cell, b_cell, consts):
        lo, n_pos, s_vel, s_acc, min_std = consts
        T, B, _ = pre.shape
        hid = w_cell.shape[1] // 4
        Z = scale.shape[0]
        h = pre.new_zeros(B, hid)
        c = pre.new_zeros(B, hid)
        reads = pre.new_empty(T, B, 2 * hid)
        a1s = pre.new_empty(pre.shape)
        mu0s, ss = pre.new_empty(T, B, Z), pre.new_empty(T, B, Z)
        mus, stds = pre.new_empty(T, B, Z), pre.new_empty(T, B, Z)
        pzs = pre.new_empty(T, B, wz.shape[1])
        inps = pre.new_empty(T, B, w_cell.shape[0])
        gates = pre.new_empty(T, B, 4 * hid)  # sigmoid / tanh applied
        tcs = pre.new_empty(T, B, hid)
        vels, accs = pre.new_zeros(T, B, n_pos), pre.new_zeros(T, B, n_pos)
        F = wz.shape[1]
        last_pos = last_vel = None
        for t in range(T):
            r = reads[t]
            r[:, :hid] = h
            r[:, hid:] = c
            a1 = torch.addmm(pre[t], r, w_read, out=a1s[t])
            raw = torch.addmm(b2, torch.relu(a1), w2t)
            mu0s[t], ss[t] = raw[:, :Z], raw[:, Z:]
            # on raw's own columns, as the loop computes it (a strided input takes torch's
            # scalar path, whose last bit can differ from the vectorised one's)
            torch.add(torch.nn.functional.softplus(raw[:, Z:]), min_std, out=stds[t])
            mu = torch.add(mu0s[t] * scale, shift[t], out=mus[t])  # not addcmul: no FMA
            pos = mu[:, lo:lo + n_pos]
            vel = (pos - last_pos) * s_vel if t >= 1 else None
            acc = (vel - last_vel) * s_acc if t >= 2 else None
            if vel is not None:
                vels[t] = vel
            if acc is not None:
                accs[t] = acc
            inp = inps[t]
            torch.addmm(bz, mu, wz, out=pzs[t])
            torch.clamp(pzs[t], min=0, out=inp[:, :F])
            torch.clamp(vels[t], -5, 5, out=inp[:, F:F + n_pos])
            torch.clamp(accs[t], -10, 10, out=inp[:, F + n_pos:F + 2 * n_pos])
            inp[:, F + 2 * n_pos:] = h
            g = torch.addmm(b_cell, inp, w_cell, out=gates[t])
            torch.sigmoid(g[:, :2 * hid], out=g[:, :2 * hid])
            torch.tanh(g[:, 2 * hid:3 * hid], out=g[:, 2 * hid:3 * hid])
            torch.sigmoid(g[:, 3 * hid:], out=g[:, 3 * hid:])
            c = g[:, hid:2 * hid] * c + g[:, :hid] * g[:, 2 * hid:3 * hid]
            tc = torch.tanh(c, out=tcs[t])
            h = g[:, 3 * hid:] * tc
            last_pos = pos.clone()
            last_vel = vels[t].clone()
        ctx.consts = consts
        ctx.save_for_backward(scale, w_read, w2t, wz, w_cell, reads, a1s, mu0s, ss, mus, pzs,
                              inps, gates, tcs, vels, accs)
        return reads, mus, stds, h, c, last_pos, last_vel

    @staticmethod
    def backward(ctx, d_reads, d_mus, d_stds, d_h, d_c, d_last_pos, d_last_vel):
        (scale, w_read, w2t, wz, w_cell, reads, a1s, mu0s, ss, mus, pzs, inps, gates, tcs,
         vels, accs) = ctx.saved_tensors
        lo, n_pos, s_vel, s_acc, _ = ctx.consts
        T, B, R2 = reads.shape
        hid, Z, F = R2 // 2, scale.shape[0], wz.shape[1]

        def zeros_if_none(g, *shape):
            return reads.new_zeros(*shape) if g is None else g

        d_reads = zeros_if_none(d_reads, T, B, R2)
        d_mus = zeros_if_none(d_mus, T, B, Z)
        d_stds = zeros_if_none(d_stds, T, B, Z)
        dh = zeros_if_none(d_h, B, hid).clone()
        dc = zeros_if_none(d_c, B, hid).clone()
        dpos_next = zeros_if_none(d_last_pos, B, n_pos).clone()  # into pos_t from later frames
        dvel_next = zeros_if_none(d_last_vel, B, n_pos).clone()  # into vel_t from later frames
        d_gates = reads.new_empty(T, B, 4 * hid)
        d_pz = reads.new_empty(T, B, F)
        d_raw = reads.new_empty(T, B, 2 * Z)
        d_a1 = reads.new_empty(T, B, w_read.shape[1])
        d_mu = reads.new_empty(T, B, Z)
        w_cell_t, wz_t, w2 = w_cell.t(), wz.t(), w2t.t()
        w_read_t = w_read.t()
        for t in range(T - 1, -1, -1):
            g = gates[t]
            i, f, gg, o = (g[:, :hid], g[:, hid:2 * hid], g[:, 2 * hid:3 * hid], g[:, 3 * hid:])
            tc = tcs[t]
            c_prev = reads[t][:, hid:]
            dct = dc + dh * o * (1 - tc * tc)
            dg = d_gates[t]
            torch.mul(dct * gg, i * (1 - i), out=dg[:, :hid])
            torch.mul(dct * c_prev, f * (1 - f), out=dg[:, hid:2 * hid])
            torch.mul(dct * i, 1 - gg * gg, out=dg[:, 2 * hid:3 * hid])
            torch.mul(dh * tc, o * (1 - o), out=dg[:, 3 * hid:])
            dc = dct * f
            d_inp = dg @ w_cell_t
            dh = d_inp[:, F + 2 * n_pos:].clone()
            torch.mul(d_inp[:, :F], pzs[t] > 0, out=d_pz[t])
            vel, acc = vels[t], accs[t]
            dacc = d_inp[:, F + n_pos:F + 2 * n_pos] * ((acc >= -10) & (acc <= 10)) \
                if t >= 2 else None
            dvel = dvel_next + d_inp[:, F:F + n_pos] * ((vel >= -5) & (vel <= 5)) \
                if t >= 1 else None
            if dacc is not None:  # acc_t = (vel_t - vel_{t-1}) s_acc
                dvel = dvel + dacc * s_acc
            dpos = dpos_next
            if dvel is not None:  # vel_t = (pos_t - pos_{t-1}) s_vel
                dpos = dpos + dvel * s_vel
                dpos_next = -dvel * s_vel
            else:
                dpos_next = torch.zeros_like(dpos)
            dvel_next = -dacc * s_acc if dacc is not None else torch.zeros_like(dpos)
            dm = torch.addmm(d_mus[t], d_pz[t], wz_t, out=d_mu[t])
            dm[:, lo:lo + n_pos] += dpos
            s = ss[t]
            dr = d_raw[t]
            torch.mul(dm, scale, out=dr[:, :Z])
            # softplus' gradient: sigmoid, and 1 above its threshold (20) as torch's
            torch.mul(d_stds[t], torch.where(s > 20, torch.ones_like(s), torch.sigmoid(s)),
                      out=dr[:, Z:])
            torch.mul(dr @ w2, a1s[t] > 0, out=d_a1[t])
            d_read = torch.addmm(d_reads[t], d_a1[t], w_read_t)
            dh += d_read[:, :hid]
            dc = dc + d_read[:, hid:]
        # each weight's gradient over every frame: one product
        flat = lambda x: x.reshape(T * B, -1)  # noqa: E731
        g_w_cell = flat(inps).t() @ flat(d_gates)
        g_b_cell = d_gates.sum((0, 1))
        g_wz = flat(mus).t() @ flat(d_pz)
        g_bz = d_pz.sum((0, 1))
        g_w2t = flat(torch.relu(a1s)).t() @ flat(d_raw)
        g_b2 = d_raw.sum((0, 1))
        g_w_read = flat(reads).t() @ flat(d_a1)
        g_scale = (d_mu * mu0s).sum((0, 1))
        return (d_a1, g_scale, d_mu, g_w_read, g_w2t, g_b2, g_wz, g_bz, g_w_cell, g_b_cell,
                None)
