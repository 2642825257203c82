"""The one "is there a ball" rule of tracking.track and the video reader, and the reader's centre
of a shaded, lit ball (issue 29)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from shaded_ball import path, shaded_frames

from sysid_bench.apps.video import find_ball
from sysid_bench.core import physics, tracking
from sysid_bench.core.render import render, view_geometry
from sysid_bench.core.tracking import ball_centre, ball_seen, noise_level, track


def _meaningless(kind: str, size, n: int = 12) -> np.ndarray:
    h, w = size
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:h, 0:w]
    if kind == "white":
        return np.full((n, h, w), 255, np.uint8)
    if kind == "black":
        return np.zeros((n, h, w), np.uint8)
    if kind == "grey":
        return np.full((n, h, w), 128, np.uint8)
    if kind == "uniform noise":
        return rng.integers(0, 256, (n, h, w)).astype(np.uint8)
    if kind == "gaussian noise":
        return np.clip(rng.normal(128, 40, (n, h, w)), 0, 255).astype(np.uint8)
    if kind == "frozen background":  # a still scene, no ball: a gradient with texture
        scene = 60 + 120 * xx / w + 25 * np.sin(yy / 3.0) + rng.normal(0, 4, (h, w))
        return np.broadcast_to(np.clip(scene, 0, 255).astype(np.uint8), (n, h, w)).copy()
    if kind == "half white":  # a bright wall filling half the view
        fr = np.zeros((n, h, w), np.uint8)
        fr[:, :, : w // 2] = 255
        return fr
    raise ValueError(kind)


KINDS = ["white", "black", "grey", "uniform noise", "gaussian noise", "frozen background",
         "half white"]


@pytest.mark.parametrize("size", [(28, 28), (50, 100)])
@pytest.mark.parametrize("kind", KINDS)
def test_no_ball_in_meaningless_frames(kind, size):
    # before: track saw a ball at the centre in every white, noise and frozen-scene frame
    fr = _meaningless(kind, size)
    assert np.isnan(track(fr)).all()
    assert find_ball(fr).n_found == 0


def test_a_bright_square_is_not_a_ball():
    g = view_geometry((28, 28))
    fr = np.zeros((6, 28, 28), np.uint8)
    for t in range(6):  # a square four ball-widths wide, moving (the reader sees it move)
        fr[t, 4:24, 2 + t : 22 + t] = 230
    assert np.isnan(track(fr)).all()
    assert find_ball(fr).n_found == 0
    # a ball-sized disc is a ball for both
    s = np.zeros((1, 6, 4))
    s[0, :, 0] = np.linspace(2.0, 8.0, 6)
    s[0, :, 1] = 5.0
    balls = render(s)[0]
    assert np.isfinite(track(balls)).all()
    trk = find_ball(balls)
    assert trk.n_found == 6
    np.testing.assert_allclose(trk.pixels, g.to_pixels(s[0, :, :2]), atol=0.05)


def test_both_trackers_apply_ball_seen(monkeypatch):
    """One rule: refusing every candidate in ball_seen blinds tracking.track and the reader."""
    s = np.zeros((1, 8, 4))
    s[0, :, 0] = np.linspace(2.0, 8.0, 8)
    s[0, :, 1] = 5.0
    fr = render(s)[0]
    assert np.isfinite(track(fr)).all() and find_ball(fr).n_found == 8
    reader = sys.modules[find_ball.__module__]

    def never(contrast, centres, radius, threshold):
        return np.zeros(len(contrast), dtype=bool)

    monkeypatch.setattr(tracking, "ball_seen", never)
    monkeypatch.setattr(reader, "ball_seen", never)
    assert np.isnan(track(fr)).all() and find_ball(fr).n_found == 0


@pytest.mark.parametrize("size", [(28, 28), (50, 100)])
def test_rendered_balls_with_camera_nuisances_are_all_seen(size):
    rng = np.random.default_rng(29)
    st = physics.simulate(physics.sample_theta(4, rng), physics.sample_state0(4, rng),
                          n_frames=40)
    fr, info = render(st, size, blur=0.5, occlusion=0.05, drop=0.05, noise=8.0, seed=3,
                      return_info=True)
    clear = ~info["dropped"] & ~info["occluded"]
    pos = tracking.track_batch(fr)
    assert np.isfinite(pos[clear]).all() and np.isnan(pos[info["dropped"]]).all()
    geo = view_geometry(size)
    pix = np.stack([find_ball(v).pixels for v in fr])
    assert np.isfinite(pix[clear]).all() and np.isnan(pix[info["dropped"]]).all()
    err = np.hypot(*(pix[clear] - geo.to_pixels(st[..., :2])[clear]).T)
    # measured (scripts/measure_tracking.py, 800 frames): RMS 0.03 px at both sizes
    assert np.sqrt(np.mean(err**2)) < 0.08 and err.max() < 0.3


@pytest.mark.parametrize("radius", [3.0, 4.5, 8.0, 12.0])
def test_shaded_lit_ball_centre_within_a_fifth_of_a_pixel(radius):
    # a Lambertian ball lit from above-left on a wall a little brighter than its lit top: the
    # lit top barely differs from the wall. Before (weights |difference|): 0.07 r px right and
    # 0.2 r px low (0.2 and 0.6 px at r = 3, 0.8 and 2.4 px at r = 12)
    size = (64, 96)
    truth = path(30, radius, size, seed=int(10 * radius))
    trk = find_ball(shaded_frames(truth, radius, size, seed=int(radius)))
    assert trk.n_found == len(truth)
    err = np.hypot(*(trk.pixels - truth).T)
    assert err.max() <= 0.2
    assert trk.radius == pytest.approx(radius, abs=0.3)


@pytest.mark.parametrize("wall, ambient, case", [(128.0, 25.0, "band"), (0.0, 40.0, "dark")])
@pytest.mark.parametrize("radius", [3.0, 12.0])
def test_shaded_ball_on_other_walls(wall, ambient, case, radius):
    # band: a mid-grey wall crosses the ball's shading, so a band across the ball matches the
    # wall's grey and the ball falls apart into two blobs (before: up to 4 px off at r = 12);
    # dark: a dark wall makes the shaded bottom the faint part
    size = (64, 96)
    truth = path(30, radius, size, seed=7)
    trk = find_ball(shaded_frames(truth, radius, size, wall=wall, ambient=ambient, seed=7))
    assert trk.n_found == len(truth), case
    assert np.hypot(*(trk.pixels - truth).T).max() <= 0.2, case


def test_ball_centre_of_a_plain_disc_and_no_ball():
    fr = render(np.array([[[4.37, 6.12, 0.0, 0.0]]]), (64, 64))[0, 0].astype(float)
    g = view_geometry((64, 64))
    c, area = ball_centre(fr, 20.0, g.to_pixels([4.0, 6.0]), g.radius)
    np.testing.assert_allclose(c, g.to_pixels([4.37, 6.12]), atol=0.02)
    assert area == pytest.approx(np.pi * g.radius**2, rel=0.02)
    c, area = ball_centre(np.zeros((64, 64)), 20.0, (30.0, 30.0), 7.0)
    assert np.isnan(c).all() and area == 0.0


def test_ball_seen_area_and_compactness():
    g = view_geometry((64, 64))
    disc = render(np.array([[[5.0, 5.0, 0.0, 0.0]]]), (64, 64))[0].astype(np.float32)
    cen = g.to_pixels([5.0, 5.0])[None]
    assert ball_seen(disc, cen, g.radius, 64.0).tolist() == [True]
    assert ball_seen(disc, cen, 2 * g.radius, 64.0).tolist() == [False]  # too small a blob
    assert ball_seen(disc, cen, g.radius / 2, 64.0).tolist() == [False]  # too big a blob
    assert ball_seen(disc, np.full((1, 2), np.nan), g.radius, 64.0).tolist() == [False]
    ring = disc.copy()
    ring[0, 20:44, 20:44] = 0  # a hollow square outline around the candidate: not compact
    ring[0, 22:42, 22:42] = 255
    ring[0, 24:40, 24:40] = 0
    assert ball_seen(ring, np.array([[32.0, 32.0]]), 7.0, 64.0).tolist() == [False]


def test_noise_level_is_the_standard_deviation():
    rng = np.random.default_rng(0)
    x = rng.normal(100.0, 10.0, (3, 5000))
    x[:, :100] = 255  # a ball's worth of outliers does not move it
    np.testing.assert_allclose(noise_level(x, axis=1), 10.0, rtol=0.05)


def test_uint8_shortcuts_equal_the_plain_formula():
    # _centroids' shortcuts for uint8 frames (integer cut-offs, the background by the bytes, no
    # sort where the wall dominates) against the formulas they replace, on walls and on noise
    from sysid_bench.core import tracking as tr

    rng = np.random.default_rng(39)
    fr = rng.integers(0, 256, (40, 28, 28), dtype=np.uint8)
    fr[:10] = 0  # dark walls with a few bright specks: the cheap branches
    fr[:10, ::7, ::5] = rng.integers(0, 256, (10, 4, 6), dtype=np.uint8)
    fr[10:15] = rng.integers(120, 124, (5, 28, 28), dtype=np.uint8)  # grey, narrow spread
    img = fr.astype(np.float32) / np.float32(255.0)
    k = (28 * 28 - 1) // 2
    for level in (0.1, 0.25, 0.625, 0.999, 1.5):
        mask = tr._at_least(img, fr, level)
        np.testing.assert_array_equal(mask, img >= level)
        want = np.where(mask, img, np.float32(0.0))
        got = tr._kept(img, fr, mask)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    bg = np.sort(img.reshape(40, -1), axis=1)[:, k]
    assert tr._background(img, fr, k).tobytes() == bg.tobytes()
    contrast = img - bg[:, None, None]
    for thr in (0.05, 0.25, 0.6):
        noise = np.float32(1.4826) * np.sort(np.abs(contrast.reshape(40, -1)), axis=1)[:, k]
        want = np.maximum(np.float32(thr), np.float32(tr.NOISE_K) * noise)
        assert tr._stand_out(contrast, thr, k).tobytes() == want.tobytes()


def _scipy_region(stand):
    """ball_centre's masks as scipy made them before the compiled kernels (qhull's hull of the
    edge pixels with a 1e-9 tolerance, the cross's erosions and dilations)."""
    from scipy import ndimage
    from scipy.spatial import ConvexHull, QhullError

    region = stand
    pts = np.argwhere(stand & ~ndimage.binary_erosion(stand)).astype(np.float64)
    try:
        hull = ConvexHull(pts) if len(pts) >= 3 else None
    except QhullError:  # all on a line: nothing to fill
        hull = None
    if hull is not None:
        (r0, c0), (r1, c1) = pts.min(axis=0).astype(int), pts.max(axis=0).astype(int)
        rr, cc = np.mgrid[r0:r1 + 1, c0:c1 + 1]
        grid = np.stack([rr.ravel(), cc.ravel()], axis=1).astype(np.float64)
        inside = (grid @ hull.equations[:, :2].T + hull.equations[:, 2] <= 1e-9).all(axis=1)
        region = stand.copy()
        region[r0:r1 + 1, c0:c1 + 1] |= inside.reshape(rr.shape)
    core = ndimage.binary_erosion(region)
    inner = ndimage.binary_erosion(region, iterations=tracking.RIM)
    rim = ndimage.binary_dilation(region, iterations=tracking.RIM) & ~inner
    ring = core & ~ndimage.binary_erosion(core, iterations=3)
    return region, inner, rim, ring


def test_region_masks_are_scipys():
    # the compiled hull fill (integer monotone chain) and erosions give scipy's bits: random
    # pixels, discs cut by a band (the shading's gap), discs off the crop's edge, a few points
    # and lines (qhull's flat case: no fill)
    from sysid_bench.core._ball_region import region_masks

    rng = np.random.default_rng(7)
    for t in range(400):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        yy, xx = np.mgrid[:h, :w]
        if t % 3 == 0:
            m = rng.random((h, w)) < rng.random()
        elif t % 3 == 1:
            cy, cx, r = rng.uniform(-5, h + 5), rng.uniform(-5, w + 5), rng.uniform(0.5, 18)
            m = ((yy - cy) ** 2 + (xx - cx) ** 2 <= r * r) & (
                np.abs(yy - cy - rng.uniform(-r, r)) >= rng.uniform(0, 3))
        else:
            m = np.zeros((h, w), bool)
            k = int(rng.integers(0, 6))
            m[rng.integers(0, h, k), rng.integers(0, w, k)] = True
            m[int(rng.integers(0, h)), int(rng.integers(0, w)):] = t % 2 == 0
        got = region_masks(m, tracking.RIM)
        for a, b in zip(got, _scipy_region(m)):
            assert np.array_equal(a, b), t


def test_keep_large_pieces_is_scipys_label():
    # ball_centre's specks filter: scipy's 4-connected pieces and their sizes, as it was
    from scipy import ndimage

    from sysid_bench.core._ball_region import keep_large_pieces

    rng = np.random.default_rng(11)
    for t in range(300):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        m = rng.random((h, w)) < rng.uniform(0.05, 0.7)
        min_size = float(rng.choice([2.0, 0.1 * np.pi * rng.uniform(1, 12) ** 2]))
        ref = m
        lab, n = ndimage.label(m)
        if n > 1:
            keep = np.bincount(lab.ravel(), minlength=n + 1) >= min_size
            keep[0] = False
            if keep.any():
                ref = keep[lab]
        assert np.array_equal(keep_large_pieces(m, min_size), ref), t
