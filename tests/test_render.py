import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sysid_bench.core import physics
from sysid_bench.core.render import RADIUS_FRACTION, render, view_geometry
from sysid_bench.core.tracking import track_batch


def _still(x, y, vx=0.0, vy=0.0, t=1):
    """(1, T, 4) states of a ball at one place."""
    return np.tile(np.array([x, y, vx, vy], dtype=float), (1, t, 1))


@pytest.fixture(scope="module")
def states():
    rng = np.random.default_rng(3)
    th = physics.sample_theta(6, rng)
    s0 = physics.sample_state0(6, rng)
    return physics.simulate(th, s0, n_frames=40)


def test_shape_dtype_and_look(states):
    fr = render(states)
    assert fr.shape == (6, 40, 28, 28) and fr.dtype == np.uint8
    r = RADIUS_FRACTION * 28
    # anti-aliased disc: total brightness is the disc's area, the centre is white
    mass = fr.astype(float).sum(axis=(2, 3)) / 255
    np.testing.assert_allclose(mass, np.pi * r**2, rtol=0.03)
    assert (fr.max(axis=(2, 3)) == 255).all()
    # anti-aliased: some pixels are grey
    assert ((fr > 0) & (fr < 255)).any()


@pytest.mark.parametrize("size", [(28, 28), (50, 100)])
def test_ball_touching_walls_touches_image_edges(size):
    h, w = size
    corners = np.concatenate([_still(0.0, 0.0), _still(10.0, 10.0)], axis=0)
    fr = render(corners, size)
    low_left, up_right = fr[0, 0], fr[1, 0]
    # touches the left and bottom edges (rows run downwards), but not the opposite ones
    assert low_left[:, 0].max() > 100 and low_left[-1, :].max() > 100
    assert low_left[:, -1].max() == 0 and low_left[0, :].max() == 0
    assert up_right[:, -1].max() > 100 and up_right[0, :].max() > 100
    assert up_right[:, 0].max() == 0 and up_right[-1, :].max() == 0
    # the blob's centroid lies one radius from the touched edges
    r = RADIUS_FRACTION * min(h, w)
    im = low_left.astype(float)
    col = (im.sum(0) * (np.arange(w) + 0.5)).sum() / im.sum()
    row = (im.sum(1) * (np.arange(h) + 0.5)).sum() / im.sum()
    np.testing.assert_allclose([col, h - row], [r, r], atol=0.05)


def test_rows_run_downwards():
    fr = render(np.concatenate([_still(5, 2), _still(5, 8)], axis=0))
    rows = [np.argmax(f[0].sum(axis=1)) for f in fr]
    assert rows[0] > rows[1]


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(0, 10),
    y=st.floats(-3, 13),
    floor=st.floats(-5, 5),
    h=st.integers(8, 120),
    w=st.integers(8, 120),
)
def test_geometry_round_trip(x, y, floor, h, w):
    g = view_geometry((h, w), floor)
    back = g.to_metres(g.to_pixels([x, y]))
    np.testing.assert_allclose(back, [x, y], atol=1e-9)


def test_geometry_box_maps_to_image_minus_radius():
    g = view_geometry((50, 100), floor=2.0)
    r = RADIUS_FRACTION * 50
    np.testing.assert_allclose(g.to_pixels([0.0, 2.0]), [r, 50 - r])
    np.testing.assert_allclose(g.to_pixels([10.0, 12.0]), [100 - r, r])


def test_floor_per_video_shifts_view(states):
    fl = np.array([0.0, 1.0, -2.0, 0.5, 3.0, 0.0])
    shifted = states.copy()
    shifted[..., 1] += fl[:, None]
    np.testing.assert_array_equal(render(shifted, floor=fl), render(states))


def test_same_seed_same_bytes_and_per_video_streams(states):
    kw = dict(blur=0.5, occlusion=0.3, drop=0.2, noise=8.0, floor_offset=0.5)
    a = render(states, seed=7, **kw)
    b = render(states, seed=7, **kw)
    c = render(states, seed=8, **kw)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()
    seeds = [np.random.SeedSequence([5, i]) for i in range(6)]
    whole = render(states, seed=seeds, **kw)
    part = render(states[2:4], seed=seeds[2:4], **kw)
    np.testing.assert_array_equal(whole[2:4], part)


def test_clean_render_ignores_seed(states):
    np.testing.assert_array_equal(render(states, seed=1), render(states, seed=2))


def test_drop_and_occlusion(states):
    fr, info = render(states, drop=0.3, occlusion=0.4, seed=0, return_info=True)
    assert 0.15 < info["dropped"].mean() < 0.45
    assert 0.25 < info["occluded"].mean() < 0.55
    assert (fr[info["dropped"]] == 0).all()
    b, t = np.nonzero(info["occluded"])
    for i, k in zip(b, t, strict=True):
        r0, r1, c0, c1 = info["occlusion_box"][i, k]
        assert 0 <= r0 < r1 <= 28 and 0 <= c0 < c1 <= 28
        assert (r1 - r0) >= 8 and (c1 - c0) >= 8
        assert (fr[i, k, r0:r1, c0:c1] == 0).all()
    assert (info["occlusion_box"][~info["occluded"]] == -1).all()
    clean = render(states)
    keep = ~info["dropped"] & ~info["occluded"]
    np.testing.assert_array_equal(fr[keep], clean[keep])


def test_noise_statistics():
    fr = render(_still(5, 5, t=50), noise=10.0, seed=0)
    clean = render(_still(5, 5, t=50))
    bg = clean == 0
    diff = fr.astype(float) - clean
    # background noise is clipped at 0: half the pixels stay 0, the rest are |N(0, 10)|
    assert 0.4 < (fr[bg] == 0).mean() < 0.6
    np.testing.assert_allclose(diff[bg][diff[bg] > 0].mean(), 10 * np.sqrt(2 / np.pi), rtol=0.1)


def test_blur_spreads_along_velocity_and_keeps_centroid():
    size = (50, 100)
    s = _still(5.0, 5.0, vx=8.0, vy=0.0)
    sharp = render(s, size)[0, 0].astype(float)
    blurred = render(s, size, blur=1.0)[0, 0].astype(float)

    def moments(im, axis):
        idx = np.arange(im.shape[1 - axis]) + 0.5
        p = im.sum(axis=axis) / im.sum()
        m = (p * idx).sum()
        return m, (p * (idx - m) ** 2).sum()

    (c_sharp, vc_sharp), (c_blur, vc_blur) = moments(sharp, 0), moments(blurred, 0)
    (_, vr_sharp), (_, vr_blur) = moments(sharp, 1), moments(blurred, 1)
    # streak of 8 m/s * 0.05 s = 0.4 m (3.5 px) drawn as 7 evenly spaced discs: the spread
    # across grows by the variance of those offsets, 0.111 L^2; up/down it does not change
    px = 0.4 * view_geometry(size).px_per_m[0]
    np.testing.assert_allclose(
        vc_blur - vc_sharp, np.var(np.linspace(-0.5, 0.5, 7)) * px**2, rtol=0.1
    )
    np.testing.assert_allclose(vr_blur, vr_sharp, rtol=0.01)
    assert abs(c_sharp - c_blur) < 0.02
    np.testing.assert_allclose(blurred.sum(), sharp.sum(), rtol=0.02)


def test_floor_offset_lifts_ball_by_drawn_amount(states):
    fr, info = render(states, floor_offset=1.0, seed=4, return_info=True)
    off = info["floor_offset"]
    assert off.shape == (6,) and (off >= 0).all() and (off <= 1).all() and off.std() > 0
    pos = track_batch(fr)
    ok = np.isfinite(pos[..., 1])
    err = pos[..., 1] - off[:, None] - states[..., 1]
    assert np.abs(err[ok]).max() < 0.1


def test_wide_size(states):
    fr = render(states, (50, 100))
    assert fr.shape == (6, 40, 50, 100)
    np.testing.assert_allclose(
        fr.astype(float).sum(axis=(2, 3)) / 255, np.pi * (RADIUS_FRACTION * 50) ** 2, rtol=0.03
    )


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(states=np.zeros((5, 4))), "states"),
        (dict(states=np.zeros((1, 5, 3))), "states"),
        (dict(states=np.full((1, 5, 4), np.nan)), "states"),
        (dict(states=np.array([[["a", "b", "c", "d"]]])), "states"),
        (dict(size=(28,)), "size"),
        (dict(size=(0, 28)), "size"),
        (dict(size=(28.0, 28)), "size"),
        (dict(blur=1.5), "blur"),
        (dict(blur=-0.1), "blur"),
        (dict(occlusion=2), "occlusion"),
        (dict(drop=-1), "drop"),
        (dict(noise=300), "noise"),
        (dict(noise=float("nan")), "noise"),
        (dict(floor_offset=11), "floor_offset"),
        (dict(floor=np.zeros(3)), "floor"),
        (dict(radius=20.0), "radius"),
        (dict(seed="x", noise=1.0), "seed"),
        (dict(seed=[1, 2], noise=1.0), "seed"),
    ],
)
def test_bad_input(kwargs, name):
    kw = dict(states=np.tile([[[5.0, 5.0, 0.0, 0.0]]], (1, 5, 1)))
    kw.update(kwargs)
    with pytest.raises(ValueError, match=name):
        render(**kw)


def _discs_whole_frame(cols, rows, size, radius):
    """The renderer's disc coverage computed over every pixel of every frame (what it did
    before drawing on a window around the ball): the reference the window must equal."""
    h, w = size
    out = np.zeros((cols.shape[0], h, w), dtype=np.float32)
    jc = np.arange(w, dtype=np.float32) + 0.5
    ic = np.arange(h, dtype=np.float32) + 0.5
    r = np.float32(radius + 0.5)
    for k in range(cols.shape[1]):
        dx2 = (jc[None, :] - cols[:, k, None].astype(np.float32)) ** 2
        dy2 = (ic[None, :] - rows[:, k, None].astype(np.float32)) ** 2
        d = np.sqrt(dy2[:, :, None] + dx2[:, None, :])
        np.subtract(r, d, out=d)
        np.clip(d, 0.0, 1.0, out=d)
        out += d
    if cols.shape[1] > 1:
        out /= cols.shape[1]
    return out


@pytest.mark.parametrize("size", [(28, 28), (50, 100), (9, 31)])
@pytest.mark.parametrize("n_sub", [1, 7])
def test_disc_window_gives_the_whole_frame_bytes(size, n_sub):
    from sysid_bench.core.render import _draw_discs

    rng = np.random.default_rng(size[0] * 10 + n_sub)
    h, w = size
    radius = RADIUS_FRACTION * min(h, w)
    # centres anywhere, partly outside the image, with blur-like spreads up to half the view
    c = rng.uniform(-radius, w + radius, (300, 1)) + rng.normal(0, 1, (1, n_sub)) * rng.uniform(0, w / 2, (300, 1))
    r = rng.uniform(-radius, h + radius, (300, 1)) + rng.normal(0, 1, (1, n_sub)) * rng.uniform(0, 3, (300, 1))
    got = _draw_discs(c, r, size, radius)
    np.testing.assert_array_equal(got, _discs_whole_frame(c, r, size, radius))
    assert _draw_discs(c[:0], r[:0], size, radius).shape == (0, h, w)


def test_camera_render_bytes_are_those_of_the_whole_frame_renderer(monkeypatch):
    """Whole camera videos (blur, noise, occlusions, a raised floor) come out byte for byte as
    the whole-frame disc drawing makes them."""
    import sysid_bench.core.render as R

    rng = np.random.default_rng(5)
    sts = physics.simulate(physics.sample_theta(4, rng), physics.sample_state0(4, rng), n_frames=60)
    kw = dict(size=(50, 100), blur=0.5, occlusion=0.05, drop=0.05, noise=8.0, floor_offset=1.0,
              seed=11)
    new = render(sts, **kw)
    monkeypatch.setattr(R, "_draw_discs", _discs_whole_frame)
    np.testing.assert_array_equal(new, render(sts, **kw))
