"""Vid2Param's recipe for the systems (issue 39 section 2): per-system difference scales
(``V2PConfig.diff_scales``) and the points curriculum (``TrainConfig.points_steps``: the
recurrence and heads trained on tracked points before any frame)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from methods.vid2param.data import make_system_split
from methods.vid2param.model import V2PConfig, Vid2ParamNet
from methods.vid2param.train import TrainConfig, _PointFeed

#: a tiny spring network (the systems' tests' size)
_TINY_NET = {"hidden": 16, "feat": 16, "latent": 12, "channels": (4,), "keypoints": 2}
#: the same as flags, with a tiny run (tests/test_vid2param_systems.py's)
TINY = ["--hidden", "16", "--feat", "16", "--latent", "12", "--channels", "4", "--keypoints", "2",
        "--n-frames", "24", "--min-obs", "8", "--chunk", "8", "--val-n", "4", "--steps", "2",
        "--batch", "4", "--threads", "1", "--no-progress", "--no-resume", "--nll-only-steps", "2"]


def _tiny(system: str = "spring", **kw) -> Vid2ParamNet:
    d = V2PConfig.preset(system).to_dict()
    d.update(_TINY_NET, **kw)
    torch.manual_seed(0)
    return Vid2ParamNet(V2PConfig(**d))


def test_diff_scales_are_the_balls_for_older_checkpoints_and_checked():
    d = V2PConfig().to_dict()
    assert d["diff_scales"] == [10.0, 40.0]
    del d["diff_scales"]  # a checkpoint written before the field
    assert V2PConfig.from_dict(d).diff_scales == (10.0, 40.0)
    assert V2PConfig.preset("spring").diff_scales == (142.0, 5.3)
    for bad in [(1.0,), (0.0, 1.0), (1.0, float("nan")), ("a", 1.0)]:
        with pytest.raises(ValueError, match="diff_scales: expected two finite floats > 0"):
            V2PConfig(diff_scales=bad)


def test_a_network_trained_on_points_reads_frames_as_it_read_the_points():
    """After ``read_points_only_`` the posterior reads channel 0's centre alone: the frames'
    features and ``point_features`` of that centre give the same posterior; an optimiser step
    on ``points_loss`` keeps the other weights at zero."""
    net = _tiny()
    net.read_points_only_()
    ds = make_system_split("spring", "test", 2, 4, n_frames=20)
    with torch.no_grad():
        fx = net.encode_frames(torch.as_tensor(ds.frames))
        i = net.encoder.n_out - 3 * net.config.keypoints
        pts = torch.stack([fx[..., i], 1.0 - fx[..., i + 1]], -1)
        _, (m_fr, s_fr), _ = net._observed_pass(fx)
        _, (m_pt, s_pt), _ = net._observed_pass(net.point_features(pts))
    torch.testing.assert_close(m_pt, m_fr, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(s_pt, s_fr, rtol=1e-5, atol=1e-6)
    # the keypoint's centre is the spring's block: within a pixel of the truth
    truth = ds.targets(net.config.targets)[..., :2]
    assert np.abs(pts.numpy() - truth).max() * 64 < 1.0
    opt = torch.optim.Adam(net.parameters(), 1e-2)
    tc = TrainConfig(batch=4, n_frames=20, size=net.config.frame_size, steps=2, points_steps=1)
    p, tg = _PointFeed(tc, net.config.targets, "spring").batch(0)
    assert p.shape == (4, 20, 2) and tg.shape == (4, 20, len(net.config.targets))
    out = net.points_loss(torch.as_tensor(p), torch.as_tensor(tg))
    out["loss_nll"].backward()
    opt.step()
    w = net.posterior.mlp[0].weight[:, :net.encoder.n_out]
    assert (w[:, i:i + 2] != 0).all() and (w[:, :i] == 0).all() and (w[:, i + 2:] == 0).all()


def test_the_point_feed_is_a_function_of_the_step_with_its_noise():
    size = V2PConfig.preset("spring").frame_size
    tc = TrainConfig(batch=3, n_frames=10, size=size, points_noise_px=0.0)
    names = V2PConfig.preset("spring").targets
    a, ta = _PointFeed(tc, names, "spring").batch(5)
    b, _ = _PointFeed(tc, names, "spring").batch(5)
    assert np.array_equal(a, b) and not np.array_equal(a, _PointFeed(tc, names, "spring").batch(6)[0])
    assert np.array_equal(a, ta[..., :2])  # no noise: the targets' positions
    noisy = TrainConfig(batch=3, n_frames=10, size=size, points_noise_px=0.5)
    c, _ = _PointFeed(noisy, names, "spring").batch(5)
    dx = (c - a)[..., 0] * size[1]  # pixels
    assert 0.2 < dx.std() < 1.0


def test_points_curriculum_bad_input_names_it():
    with pytest.raises(ValueError, match=r"points_steps: expected an int in \[0, steps=2\], got 5"):
        TrainConfig(steps=2, points_steps=5)
    with pytest.raises(ValueError, match="points_noise_px: expected a float >= 0"):
        TrainConfig(points_noise_px=-1.0)
    # a second point from a learned keypoint map (no kp_second): no points curriculum
    with pytest.raises(ValueError, match="points_steps: expected a system's network whose K "
                                         "tracked points are its K fixed keypoint channels"):
        _tiny("collision", keypoints=6, kp_second=(), kp_learn=True).read_points_only_()
    with pytest.raises(ValueError, match="points_steps: expected a system's network"):
        Vid2ParamNet(V2PConfig()).point_features(torch.zeros(1, 2, 2))
    with pytest.raises(ValueError, match=r"points: expected \(B, T, 4\) for the collision "
                                         r"system's 2 points, got shape \(1, 2, 2\)"):
        _tiny("collision").point_features(torch.zeros(1, 2, 2))


def test_one_command_runs_the_points_then_the_frames(tmp_path):
    """``--points-steps 1`` of 2: a points step, then a frame step; recorded in the card."""
    from methods.vid2param.train import main

    out = tmp_path / "v2p_spring.pt"
    assert main(["--system", "spring", "--out", str(tmp_path / "run"), "--export", str(out),
                 "--stages", "std_scale:n=4", "--points-steps", "1", *TINY]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["train"]["points_steps"] == 1 and card["train"]["step"] == 2
    assert card["config"]["diff_scales"] == [142.0, 5.3]


def test_points_positions_off_leaves_the_positions_to_the_keypoint():
    """``points_positions=False``: the parameters' NLL alone (``train`` holds the keypoint
    gate, so the posterior's positions stay channel 0's centre)."""
    net = _tiny()
    net.read_points_only_()
    size = net.config.frame_size
    tc = TrainConfig(batch=3, n_frames=12, size=size, points_positions=False)
    feed = _PointFeed(tc, net.config.targets, "spring")
    assert feed.params_only.tolist() == [False, False, True, True, True, True]
    p, tg = (torch.as_tensor(a) for a in feed.batch(0))
    out = net.points_loss(p, tg, feed.params_only)
    out["loss_nll"].backward()
    full = net.points_loss(p, tg)["nll"]
    assert full.item() != out["nll"].item()


def test_a_points_run_without_positions_holds_the_gate_then_frees_it(tmp_path):
    from methods.vid2param.train import train

    mc = V2PConfig(**{**V2PConfig.preset("spring").to_dict(), **_TINY_NET})
    tc = TrainConfig(steps=2, points_steps=1, points_positions=False, batch=2, n_frames=12,
                     chunk=4, val_n=0, size=mc.frame_size, min_obs=4)
    net, info = train(mc, tc, progress=False, log=lambda s: None)
    assert info["step"] == 2 and net.keypoints.gate.requires_grad
    assert net.keypoints.gate.item() != 0.0  # the frame step moved it
    tc1 = TrainConfig(**{**tc.to_dict(), "steps": 1, "points_steps": 1, "size": mc.frame_size})
    net1, _ = train(mc, tc1, progress=False, log=lambda s: None)
    assert net1.keypoints.gate.item() == 0.0  # held through the points step


def test_the_collision_reads_both_pucks_from_frames_as_it_read_the_points():
    """Two points (``kp_second``): channel 0 is puck 1, channel 1 puck 2 (the frame outside
    puck 1's disc); after ``read_points_only_`` the frames' features and ``point_features`` of
    the two channels' centres give the same posterior, both centres are the pucks', and a
    ``points_loss`` step on the feed's two points keeps every other frame weight at zero."""
    net = _tiny("collision")
    c = net.config
    assert c.kp_second and c.fixed_channels == 2 and not c.kp_learn
    net.read_points_only_()
    ds = make_system_split("collision", "test", 3, 4, n_frames=40)
    with torch.no_grad():
        fx = net.encode_frames(torch.as_tensor(ds.frames))
        i = net.encoder.n_out - 3 * c.keypoints
        pts = torch.stack([fx[..., i], 1.0 - fx[..., i + 1], fx[..., i + 2], 1.0 - fx[..., i + 3]],
                          -1)
        _, (m_fr, s_fr), _ = net._observed_pass(fx)
        _, (m_pt, s_pt), _ = net._observed_pass(net.point_features(pts))
    torch.testing.assert_close(m_pt, m_fr, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(s_pt, s_fr, rtol=1e-5, atol=1e-6)
    # both centres are their pucks' (x1 from channel 1, not channel 0's puck 1): well within a
    # pixel of the truth in x, and the posterior's positions are these centres
    truth = ds.targets(c.targets)[..., :4]
    err_px = np.abs(pts.numpy() - truth) * np.array([128, 16, 128, 16])
    assert err_px.max() < 0.3 and np.sqrt((err_px[..., 2] ** 2).mean()) < 0.05
    assert np.abs(truth[..., 2] - truth[..., 0]).min() * 128 > 6.0  # the pucks never coincide
    torch.testing.assert_close(m_fr[..., :4], pts, rtol=0, atol=1e-6)
    opt = torch.optim.Adam(net.parameters(), 1e-2)
    tc = TrainConfig(batch=4, n_frames=20, size=c.frame_size, steps=2, points_steps=1)
    p, tg = _PointFeed(tc, c.targets, "collision").batch(0)
    assert p.shape == (4, 20, 4) and tg.shape == (4, 20, len(c.targets))
    # both points, 0.03 px of noise (pixels: 128 x 16 frames)
    assert (np.abs(p - tg[..., :4]) * np.array([128, 16, 128, 16])).max() < 0.3
    net.points_loss(torch.as_tensor(p), torch.as_tensor(tg))["loss_nll"].backward()
    opt.step()
    w = net.posterior.mlp[0].weight[:, :net.encoder.n_out]
    assert (w[:, i:i + 4] != 0).all() and (w[:, :i] == 0).all() and (w[:, i + 4:] == 0).all()


def test_kp_second_is_checked_and_off_for_older_checkpoints():
    d = V2PConfig.preset("spring").to_dict()
    assert d["kp_second"] == []
    del d["kp_second"]  # a checkpoint written before the field
    assert V2PConfig.from_dict(d).kp_second == ()
    assert V2PConfig.preset("collision").kp_second == (0.3, 3.9)
    coll = V2PConfig.preset("collision").to_dict()
    for bad in [(0.3,), (1.0, 3.9), (0.3, 0.0), (0.3, float("nan")), "ab", None]:
        with pytest.raises(ValueError, match=r"kp_second: expected \(\) or \(grey level"):
            V2PConfig(**{**coll, "kp_second": bad})
    with pytest.raises(ValueError, match="kp_second: expected a network of a two-point system"):
        V2PConfig(**{**V2PConfig.preset("spring").to_dict(), "kp_second": (0.3, 3.9)})
    with pytest.raises(ValueError, match="keypoints 1"):
        V2PConfig(**{**coll, "keypoints": 1})


def test_the_numpy_stream_reads_both_pucks_as_the_network_does():
    """The NumPy single-frame path (the stream's on a CPU) with the collision's fixed second
    keypoint channel and two points in the recurrence: the torch filter's posteriors."""
    from methods.vid2param.data import make_system_split
    from methods.vid2param.fast import FrameFilter, fast_support

    net = _tiny("collision").eval()
    assert fast_support(net) is None
    frames = np.asarray(make_system_split("collision", "test", 1, 2024, 40,
                                          net.config.frame_size).frames[0])
    with torch.inference_mode():
        mu, sd, state = net.filter(torch.as_tensor(frames[None]))
    want = torch.cat([mu[0], sd[0]], -1).numpy()
    ff = FrameFilter(net, np.float64)
    got = np.array([np.concatenate(ff.step(f)) for f in frames])
    np.testing.assert_allclose(got[:3], want[:3], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got, want, atol=1e-4)
    np.testing.assert_allclose(ff.torch_state().last_pos.numpy(), state.last_pos.numpy(),
                               atol=1e-5)
    assert state.last_pos.shape == (1, 4)  # both pucks' x, y
