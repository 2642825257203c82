"""The drag evidence (``methods.vid2param.drag``): its statistics read d off a flight (the
bounce-free one also off a ball that loses speed at bounces), its blend weighs them by their
evidence and agreement, its fit recovers a known blend, and an estimator whose checkpoint holds
one gives the same d batched, one frame at a time and through ``identify``."""

from __future__ import annotations

import numpy as np
import pytest

from methods.vid2param.drag import ACC_CAP, DragBlend, DragStatistic, fit_blend, statistic_track
from sysid_bench.core.physics import PRIOR, simulate

LO, HI = PRIOR["d"]


def _flights(d, n_frames=200):
    """Noise-free tracks (B, T, 2) of balls launched from the middle with drag ``d`` (B,)."""
    d = np.asarray(d, float)
    B = len(d)
    theta = np.column_stack([np.full(B, 0.85), np.full(B, -9.81), d, np.full(B, 0.3)])
    state0 = np.column_stack([np.full(B, 5.0), np.full(B, 4.0), np.full(B, 4.0), np.full(B, 6.0)])
    return simulate(theta, state0, n_frames=n_frames)[..., :2]


def test_the_statistic_reads_drag_off_a_clean_flight():
    d = np.array([0.005, 0.02, 0.045])
    D, S = statistic_track(_flights(d))
    assert D.shape == S.shape == (3, 200, 2)
    assert np.isnan(D[:, :12]).all() and (S[:, :12] == 0).all()  # no full window yet
    assert (np.diff(S, axis=1) >= 0).all()  # evidence only accumulates
    assert (S[:, -1, 1] < S[:, -1, 0]).all()  # bounce-free windows are fewer
    for c in (0, 1):
        assert np.all(np.abs(D[:, -1, c] - d) < 0.25 * d + 0.002), D[:, -1]
    # one frame at a time gives the same numbers as the whole track
    st = DragStatistic(3)
    for t in range(200):
        st.update(_flights(d)[:, t])
    np.testing.assert_array_equal(st.summary()[0], D[:, -1])


def test_a_ball_that_loses_speed_at_bounces_moves_only_the_all_window_statistic():
    from sysid_bench.core.physics import simulate_perturbed

    theta = np.array([[0.85, -9.81, 0.01, 0.3]] * 2)
    state0 = np.array([[5.0, 4.0, 4.0, 6.0]] * 2)
    spun = simulate_perturbed(theta, state0, spin=np.array([0.0, 0.3]), dwell=np.zeros(2),
                              n_frames=200)[..., :2]
    D, _ = statistic_track(spun)
    assert abs(D[0, -1, 0] - 0.01) < 0.003 and abs(D[0, -1, 1] - 0.01) < 0.003
    assert D[1, -1, 0] > 0.02  # the spin's lost speed reads as drag ...
    assert abs(D[1, -1, 1] - 0.01) < 0.004  # ... but not between bounces


def test_the_statistic_ignores_rolls_and_misreadings():
    t = np.arange(100) * 0.05
    roll = np.column_stack([2.0 + 3.0 * t - 0.2 * t**2, np.zeros_like(t)])  # flat: no drag
    D, S = statistic_track(roll[None])
    assert np.isnan(D).all() and (S == 0).all()
    track = _flights([0.02])[0]
    bad = track.copy()
    bad[100] += [0.0, 3.0]  # a misread frame, metres off
    bad[120, 0] += 1.0
    clean, noisy = statistic_track(track[None])[0][0, -1], statistic_track(bad[None])[0][0, -1]
    assert np.all(np.abs(noisy - clean) < 0.2 * clean)  # windows with misreadings do not count
    unseen = track.copy()
    unseen[50:60] = np.nan  # unseen frames: no window across them, no NaN in the sums
    D, S = statistic_track(unseen[None])
    assert np.isfinite(S).all() and np.isfinite(D[0, -1]).all()
    assert ACC_CAP > 0


def _blend(**kw):
    base = dict(scale=1.0, bias=0.0, log_c=np.log(1e-3), log_b=np.log(1e-3),
                log_c_free=np.log(1e-3), log_b_free=np.log(1e-3), log_gamma=np.log(100.0))
    return DragBlend(**{**base, **kw})


def test_the_blend_weighs_the_statistics_by_their_evidence_and_agreement():
    b = _blend()
    mu, sd = np.full(4, 0.5), np.full(4, 0.2)
    d8, d2 = LO + 0.8 * (HI - LO), LO + 0.2 * (HI - LO)
    D = np.array([[np.nan, np.nan], [d8, np.nan], [d8, d8], [d8, d2]])
    S = np.array([[0.0, 0.0], [1e-3, 0.0], [1e6, 1e6], [1e6, 1e6]])
    out_mu, out_sd = b.apply(mu, sd, D, S)
    assert out_mu[0] == 0.5 and out_sd[0] == 0.2  # no window: the network's d as it was
    assert 0.5 < out_mu[1] < out_mu[2] and out_sd[2] < out_sd[1] < 0.2
    assert abs(out_mu[2] - 0.8) < 0.01
    # the all-window estimate disagrees with the bounce-free one: the latter decides
    assert abs(out_mu[3] - 0.2) < 0.02


def test_a_blend_record_is_checked():
    assert DragBlend.from_record(None) is None
    rec = {"scale": 1.2, "bias": 0.0, "log_c": 0.5, "log_b": -7.0, "log_c_free": 0.1,
           "log_b_free": -8.0, "log_gamma": 1.0, "k": 6, "nll": -3.0}
    assert DragBlend.from_record(rec) == DragBlend(1.2, 0.0, 0.5, -7.0, 0.1, -8.0, 1.0, 6)
    with pytest.raises(ValueError, match="lacks 'log_b'"):
        DragBlend.from_record({k: v for k, v in rec.items() if k != "log_b"})
    with pytest.raises(ValueError, match="finite"):
        DragBlend.from_record({**rec, "scale": float("nan")})


def test_the_fit_recovers_a_known_blend():
    rng = np.random.default_rng(0)
    N, T = 200, 60  # 200 balls recover the blend as 400 did (scale 1.27 vs 1.3): half the fit's cost
    truth = rng.uniform(0, 1, N)
    span = HI - LO
    S1 = np.broadcast_to(np.linspace(0, 4e3, T), (N, T)).copy()
    true = _blend(scale=1.3, bias=-0.001, log_c=np.log(0.01), log_b=np.log(2e-3),
                  log_c_free=np.log(0.03), log_b_free=np.log(2e-3))
    sd_stat = np.sqrt(np.exp(true.log_c) / np.maximum(S1, 1e-9) + np.exp(2 * true.log_b))
    d = LO + span * truth
    # scale * D + bias is the true d up to each statistic's noise (the bounce-free one noisier)
    D = np.stack([np.where(S1 > 0, (d[:, None] - true.bias + f * sd_stat
                                    * rng.standard_normal((N, T))) / true.scale, np.nan)
                  for f in (1.0, 1.7)], -1)
    S = np.stack([S1, S1], -1)
    sd_n = np.full((N, T), 0.15)
    mu_n = truth[:, None] + sd_n * rng.standard_normal((N, T))
    got, nll = fit_blend(mu_n, sd_n, D, S, truth)
    assert np.isfinite(nll)
    assert abs(got.scale - 1.3) < 0.1  # (the two variances trade off: not each identified)
    mu_b, _ = got.apply(mu_n, sd_n, D, S)
    assert np.mean((mu_b[:, -1] - truth) ** 2) < 0.2 * np.mean((mu_n[:, -1] - truth) ** 2)




@pytest.fixture(scope="module")
def camera_with_and_without_drag(tmp_path_factory):
    """The shipped camera network with a given drag evidence, and with none."""
    from methods.vid2param import SHIPPED_CHECKPOINTS
    from methods.vid2param.checkpoint import load_checkpoint, save_atomic

    path = SHIPPED_CHECKPOINTS["camera"]
    if not path.exists():
        pytest.skip("no shipped camera checkpoint")
    ck = dict(load_checkpoint(path))
    folder = tmp_path_factory.mktemp("drag")
    ck["drag_evidence"] = {"scale": 1.01, "bias": -0.001, "log_c": 0.61, "log_b": -13.4,
                           "log_c_free": -0.9, "log_b_free": -11.7, "log_gamma": 0.01, "k": 6}
    save_atomic(ck, folder / "with.pt")
    ck.pop("drag_evidence")
    save_atomic(ck, folder / "without.pt")
    return folder / "with.pt", folder / "without.pt"


def test_an_estimator_with_drag_evidence_agrees_batched_streamed_and_identified(
        camera_with_and_without_drag):
    from methods.vid2param import Vid2Param
    from sysid_bench.core.datasets import make_dataset
    from sysid_bench.core.estimator import Observation

    path_with, path_without = camera_with_and_without_drag
    with_drag = Vid2Param(checkpoint=str(path_with), n_samples=0, device="cpu")
    plain = Vid2Param(checkpoint=str(path_without), n_samples=0, device="cpu")
    ds = make_dataset("test", 3, 5, size=with_drag.frame_size, n_frames=120)
    frames = np.asarray(ds.frames)
    mu, sd = with_drag.normalised_prefixes(frames, [40, 120])
    mu0, sd0 = plain.normalised_prefixes(frames, [40, 120])
    i = 2  # d
    np.testing.assert_array_equal(np.delete(mu, i, -1), np.delete(mu0, i, -1))
    assert not np.allclose(mu[..., i], mu0[..., i])  # the flights' evidence moved d ...
    assert (sd[..., i] <= sd0[..., i] + 1e-12).all()  # ... and narrowed it
    stream = with_drag.stream()
    for t in range(120):
        post = stream.push(frames[0, t])
    span = HI - LO
    assert abs((post.mean[i] - LO) / span - mu[0, 1, i]) < 2e-3
    ident = with_drag.identify(Observation(frames=frames[0]))
    assert abs((ident.mean[i] - LO) / span - mu[0, 1, i]) < 1e-6  # batch of 1 vs of 3
    assert with_drag.checkpoint_info_["drag_evidence"]["k"] == 6
    assert plain.drag_ is None


def test_fit_drag_writes_a_checkpoint_the_estimator_uses(tmp_path):
    from methods.vid2param import SHIPPED_CHECKPOINTS, Vid2Param
    from methods.vid2param.checkpoint import load_checkpoint
    from methods.vid2param.train import fit_stages

    if not SHIPPED_CHECKPOINTS["camera"].exists():
        pytest.skip("no shipped camera checkpoint")
    out = tmp_path / "c.pt"
    opts = {"n_videos": 12, "n_val": 4, "seed": 3}  # the stage's plumbing, not its accuracy
    fit_stages("camera", out, [("drag_evidence", opts)], log=lambda s: None)
    ck = load_checkpoint(out)
    assert [s["name"] for s in ck["stages"]] == ["drag_evidence"]
    rec = ck["stages"][0]["state"]
    assert rec["from"] == "camera"  # a name, not a machine path
    assert set(rec["val_network"]) == set(rec["val_blended"]) == {"50", "100", "200"}
    est = Vid2Param(checkpoint=str(out), n_samples=0, device="cpu")
    est._ensure_net()
    assert est.drag_ == DragBlend.from_record(rec)
    fit_stages("camera", tmp_path / "d.pt", [("drag_evidence", opts)], log=lambda s: None)
    again = load_checkpoint(tmp_path / "d.pt")["stages"][0]["state"]
    assert again["scale"] == rec["scale"] and again["log_c"] == rec["log_c"]  # seeded
