"""The object's apparent size through a blur (``footage._minor_radii``, session 27, issue 38).

A disc of known radius, anti-aliased (its pixels' coverage), moving across a textured wall and
blurred as a camera's file blurs it: H.264's 4:2:0 colour, one sample per 2 x 2 pixels. The
radius across the path must come out within 1% once the blur's variance is taken out, where the
plain second moment reads it 3-5% large (the 7 cm ball at 10-16 px across, as measured on the
camera section's clips, docs/camera-footage.md).
"""

import numpy as np
import pytest

from sysid_bench.core import footage
from sysid_bench.core.footage import BallTrack, _minor_radii, chroma_spacing, turned_chroma

H, W, T = 64, 160, 31


def _disc(cx, cy, r, n=8):
    """Coverage of a disc (n x n samples a pixel), pixel centres at (j + 0.5, i + 0.5)."""
    s = (np.arange(n) + 0.5) / n
    yy = (np.arange(H)[:, None] + s[None, :]).ravel()
    xx = (np.arange(W)[:, None] + s[None, :]).ravel()
    inside = (xx[None, :] - cx) ** 2 + (yy[:, None] - cy) ** 2 <= r * r
    return inside.reshape(H, n, W, n).mean(axis=(1, 3))


def _frames(r, streak=0.0, chroma=False, seed=0):
    """A disc crossing the wall left to right (each frame the mean of 4 positions ``streak``
    px apart along x: motion blur), 2 x 2 blocks averaged when ``chroma`` (4:2:0's colour)."""
    rng = np.random.default_rng(seed)
    wall = 90.0 + 20.0 * rng.random((H, W))
    cx = np.linspace(25.0, W - 25.0, T) + rng.uniform(0, 1, T)
    cy = 32.0 + rng.uniform(-0.5, 0.5, T)
    out = np.empty((T, H, W))
    for t in range(T):
        cov = np.mean([_disc(cx[t] + d, cy[t], r) for d in np.linspace(-streak / 2, streak / 2, 4)],
                      axis=0)
        img = wall * (1 - cov) + 200.0 * cov
        if chroma:  # one value per 2 x 2 block, shown on each of its four pixels
            img = img.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3)).repeat(2, 0).repeat(2, 1)
        out[t] = img
    trk = BallTrack(pixels=np.column_stack([cx, cy]), radius=r, found=np.ones(T, bool),
                    radii=np.full(T, r))
    return out, trk


@pytest.mark.parametrize("r", [5.0, 8.0])
def test_radius_through_the_colour_blocks_within_1_percent(r):
    fr, trk = _frames(r, chroma=True)
    plain = _minor_radii(fr, trk, blur_var=(0.0, 0.0)).radii
    fixed = _minor_radii(fr, trk, blur_var=(4 / 12, 4 / 12)).radii
    # the blur read as size: 4/12 px^2 on r^2/4, 2.7% of r at r = 5, 1% at r = 8
    assert np.median(plain) / r - 1 > 0.7 * (4 / 12) / (r * r / 2)
    assert abs(np.median(fixed) / r - 1) < 0.01, np.median(fixed)


def test_radius_across_a_streak_and_the_pixel_area():
    fr, trk = _frames(6.0, streak=9.0)  # 9 px of motion along x: the narrow axis is y
    got = _minor_radii(fr, trk).radii  # the pixel's own area taken out (1/12 px^2)
    assert abs(np.median(got) / 6.0 - 1) < 0.01, np.median(got)
    assert np.std(got) / 6.0 < 0.02


def test_find_object_takes_the_colour_blocks_out():
    fr, _ = _frames(6.0, chroma=True, seed=3)
    grey = np.clip(np.rint(fr), 0, 255).astype(np.uint8)
    colour = np.repeat(grey[..., None], 3, axis=-1)
    colour[..., 0] = np.clip(grey.astype(int) + 40 * (grey > 150), 0, 255)  # a reddish disc
    with_blocks = footage.find_object(grey, colour=colour, chroma_px=(2, 2))
    assert abs(with_blocks.radius / 6.0 - 1) < 0.015, with_blocks.radius
    with pytest.raises(ValueError, match="^chroma_px: "):
        footage.find_object(grey, colour=colour, chroma_px=(0.5, 2))


def test_chroma_spacing_of_pixel_formats_and_turns():
    assert chroma_spacing("yuv420p") == (2.0, 2.0)
    assert chroma_spacing("yuv422p") == (2.0, 1.0)
    assert chroma_spacing("yuv444p") == (1.0, 1.0)
    assert chroma_spacing("rgb24") == (1.0, 1.0)
    assert chroma_spacing("no such format") == (1.0, 1.0)
    assert turned_chroma((2.0, 1.0), 90) == (1.0, 2.0)
    assert turned_chroma((2.0, 1.0), 180) == (2.0, 1.0)
