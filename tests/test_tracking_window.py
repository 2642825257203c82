"""Fast tracking at 1080p (issue 38 §3): the windowed search gives the whole frame's track, bit
for bit, and still says "not seen" where the object is not; exact shortcuts in decoding and in
the tracker's backgrounds."""

from __future__ import annotations

import numpy as np
import pytest

from sysid_bench.core import footage
from sysid_bench.core.footage import _block_means, _follow, _median_over_time, find_object


def _frames(centres, *, size=(240, 480), radius=7.0, seed=0, distractor=None):
    """Grey (T, H, W) uint8: a bright soft disc on a textured wall with noise.

    ``centres`` (T, 2) ``(col, row)``, NaN: no disc. ``distractor`` (T, 2): the centre of a
    darker hand-like block (a palm and a forearm, another grey than the ball), NaN: none."""
    h, w = size
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    wall = 100 + 10 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
    out = np.empty((len(centres), h, w), np.uint8)
    for t, c in enumerate(centres):
        img = wall.copy()
        if distractor is not None and np.isfinite(distractor[t]).all():
            dc, dr = distractor[t]
            palm = (np.abs(xx - dc) < 14) & (np.abs(yy - dr) < 11)
            arm = (np.abs(yy - dr) < 6) & (xx > dc) & (xx < dc + 60)
            img[palm | arm] = 45
        if np.isfinite(c).all():
            cov = np.clip(radius + 0.5 - np.hypot(xx - c[0], yy - c[1]), 0, 1)
            img = img * (1 - cov) + 220 * cov
        out[t] = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    return out


def _both(frames):
    """find_object windowed and searched whole, and how the windowed pass searched."""
    stats = {}
    orig = footage._follow

    def counted(*a, **k):
        return orig(*a, **{**k, "stats": stats})

    footage._follow = counted
    try:
        win = find_object(frames)
    finally:
        footage._follow = orig
    full = find_object(frames, window=False)
    return win, full, stats


def _same(a, b):
    assert np.array_equal(a.pixels, b.pixels, equal_nan=True)
    assert np.array_equal(a.radii, b.radii, equal_nan=True)
    assert np.array_equal(a.found, b.found)


def _path(t):
    return np.stack([30 + 4.0 * t, 40 + 0.12 * (t - 15) ** 2], axis=1)


def test_lost_and_found_again_same_as_the_whole_frame():
    t = np.arange(28, dtype=float)
    c = _path(t)
    c[10:16] = np.nan  # behind something for 6 frames, then back further on
    win, full, stats = _both(_frames(c))
    _same(win, full)
    assert stats["window"] >= 14  # most frames searched in a window only
    seen = np.isfinite(c).all(axis=1)
    assert not win.found[~seen].any()  # never an invented position
    assert win.found[seen].sum() >= seen.sum() - 2
    err = np.hypot(*(win.pixels[win.found] - c[win.found]).T)
    assert err.max() < 1.0


def test_object_leaving_the_frame_is_not_seen_then_found_on_return():
    t = np.arange(36, dtype=float)
    c = np.stack([390 + 9.0 * t, 70 + 0 * t], axis=1)  # right edge (480) at t = 10
    c[24:] = np.stack([20 + 4.0 * (t[24:] - 24), 90 + 0 * t[24:]], axis=1)  # re-enters left
    fr = _frames(c)
    win, full, _ = _both(fr)
    _same(win, full)
    out = c[:, 0] - 7.5 > 480  # wholly outside
    assert out.sum() >= 10 and not win.found[out].any()
    back = np.arange(36) >= 26
    assert win.found[back].all()
    err = np.hypot(*(win.pixels - c).T)
    inside = (c[:, 0] + 7.5 < 480) & (c[:, 0] - 7.5 > 0)
    assert err[win.found & inside].max() < 1.0
    # a ball cut by the edge: "not seen", or the centre of what is in view (within a radius)
    assert np.all(err[win.found & ~inside] < 7.0)


def test_hand_like_distractor_of_another_grey_is_never_the_ball():
    t = np.arange(40, dtype=float)
    c = _path(t)
    hand = np.full((40, 2), np.nan)
    # crosses below the ball for 16 frames; where it passed in more than a tenth of the frames
    # it is in find_ball's low-quantile background of a bright ball, and its ghost hides the
    # ball there (the last 8 frames): "not seen" then, never a position
    hand[8:24] = np.stack([40 + 6.0 * t[8:24], 110 - 1.0 * t[8:24]], axis=1)
    win, full, _ = _both(_frames(c, distractor=hand))
    _same(win, full)
    assert win.found[:32].all()
    err = np.hypot(*(win.pixels[win.found] - c[win.found]).T)
    assert err.max() < 1.0  # the hand's block is never reported as the ball


def test_window_fallback_when_a_blob_crosses_its_edge():
    # a bar across the whole frame (a blob cut by any window) in some frames: the whole frame
    # decides there, and the track is still the whole frame's
    t = np.arange(30, dtype=float)
    c = _path(t)
    fr = _frames(c)
    fr[10:14, 120:124, :] = 250
    stats = {}
    bg = footage._background(fr.astype(np.float32))
    args = (fr.astype(np.float32), bg, 20.0, 5, False, True)
    a = _follow(*args, window=True, stats=stats)
    b = _follow(*args, window=False)
    assert stats["full"] >= 4 + 1 and stats["window"] > 0
    for x, y in zip(a, b):
        assert np.array_equal(x, y, equal_nan=True)


@pytest.mark.parametrize("shape,k", [((3, 90, 120), 3), ((2, 61, 83), 2), ((2, 40, 90), 7)])
def test_block_means_equal_the_reshaped_mean(shape, k):
    fr = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    h, w = (shape[1] // k) * k, (shape[2] // k) * k
    ref = fr[:, :h, :w].reshape(shape[0], h // k, k, w // k, k).sum(
        axis=(2, 4), dtype=np.uint32).astype(np.float32) / float(k * k)
    assert np.array_equal(_block_means(fr, k), ref)


@pytest.mark.parametrize("n,dtype,shape", [(150, np.float32, (7, 9)), (31, np.uint8, (7, 9)),
                                           (30, np.uint8, (7, 9)), (2, np.float32, (7, 9)),
                                           (1, np.uint8, (7, 9)), (30, np.float32, (70, 130)),
                                           (17, np.uint8, (65, 131))])
def test_median_over_time_is_numpys(n, dtype, shape):
    # the larger stacks are transposed by the compiled blocked copy (ragged last blocks)
    x = np.random.default_rng(n).integers(0, 256, (n, *shape)).astype(dtype)
    if dtype == np.float32:
        x = x / np.float32(9.0)
    got, ref = _median_over_time(x), np.median(x, axis=0)
    assert got.dtype == ref.dtype and np.array_equal(got, ref)


def test_read_video_grey_is_ffmpegs(tmp_path):
    import av

    rng = np.random.default_rng(4)
    frames = rng.integers(0, 256, (6, 48, 64, 3), dtype=np.uint8)
    frames[:, :8] = np.arange(64, dtype=np.uint8)[None, None, :, None] * 4  # every level
    path = footage.write_video(tmp_path / "c.mp4", frames, fps=20)
    with av.open(str(path)) as c:
        ref = np.stack([f.to_ndarray(format="gray") for f in c.decode(video=0)])
    clip = footage.read_video(path)
    assert np.array_equal(clip.frames, ref)
    table = None
    with av.open(str(path)) as c:
        table = footage._luma_table(next(iter(c.decode(video=0))))
    assert table is not False and table[16] == 0 and table[235] == 255  # limited range


def _colour_difference_numpy(c, max_frames=150):
    """colour_difference as it was written in numpy (before the compiled per-pixel pass)."""
    t_n = c.shape[0]
    idx = np.unique(np.linspace(0, t_n - 1, min(t_n, max_frames)).astype(int))
    bg = np.median(c[idx], axis=0).astype(np.float32)
    bg_y = bg.mean(axis=-1)
    bg_c = bg - bg_y[..., None]
    out = np.empty(c.shape[:3], dtype=np.float32)
    for i in range(0, t_n, 32):
        f = c[i:i + 32].astype(np.float32)
        y = f.mean(axis=-1)
        dc = (f - y[..., None]) - bg_c
        out[i:i + 32] = np.sqrt((y - bg_y) ** 2
                                + footage.CHROMA_WEIGHT * (dc * dc).sum(axis=-1))
    sample = out[idx[:: max(1, len(idx) // 20)]]
    sigma = float(footage.noise_level((sample - np.median(sample)).ravel()))
    thr = max(20.0, 5.0 * sigma)
    out[:, (out[idx] > thr).mean(axis=0) > footage.STATIC_SHARE] = 0.0
    return out


@pytest.mark.parametrize("n,dtype", [(40, np.uint8), (3, np.uint8), (17, np.float64)])
def test_colour_difference_is_the_numpy_expression(n, dtype):
    # the compiled pass (split over threads) gives numpy's float32 bits: the channels summed
    # left to right, the same roundings; a moving blob so that some pixels are not static
    rng = np.random.default_rng(n)
    c = rng.integers(0, 256, (n, 23, 31, 3)).astype(dtype)
    c[:, 5:9, :] = rng.integers(0, 256, (n, 1, 1, 3))
    assert np.array_equal(footage.colour_difference(c), _colour_difference_numpy(c))


@pytest.mark.parametrize("n", [1, 2, 7, 150, 151])
def test_counted_median_is_numpys(n):
    # colour_difference's median over time of uint8 frames by counting: np.median's float64
    # values (the middle two averaged for an even count), extremes 0 and 255 included, over
    # more than one 32-column block of counts
    rng = np.random.default_rng(n)
    c = rng.integers(0, 256, (n, 5, 70, 3), dtype=np.uint8)
    c[:, 0] = rng.integers(118, 123, (n, 70, 3))  # a few values per pixel, as a still scene
    c[:, 1, :3] = rng.choice(np.array([0, 255], dtype=np.uint8), (n, 3, 3))
    idx = np.unique(np.linspace(0, n - 1, min(n, 150)).astype(int))
    out = np.full(c.shape[1:], np.nan)
    footage._counted_median(c, idx.astype(np.int64), 0, 5, out)
    assert np.array_equal(out, np.median(c[idx], axis=0))


@pytest.mark.parametrize("n", [150, 31, 2, 1])
def test_background_samples_give_numpys_quantiles(n):
    # find_ball's 10th/90th percentile over time from the background's sorted samples
    x = np.random.default_rng(n).normal(100, 30, (n, 6, 8)).astype(np.float32)
    idx = np.unique(np.linspace(0, n - 1, min(n, 150)).astype(int))
    s = footage._background_samples(x)
    for q in (10, 90):
        ref = np.percentile(x[idx], q, axis=0).astype(np.float32)
        assert np.array_equal(np.percentile(s, q, axis=1).reshape(6, 8).astype(np.float32), ref)
    assert np.array_equal(footage._background(x), np.median(x[idx], axis=0).astype(np.float32))


def test_over_frames_covers_every_frame_once(monkeypatch):
    monkeypatch.setattr(footage, "_kernel_threads", lambda: 3)
    seen = np.zeros(50, dtype=int)

    def part(a, b):
        seen[a:b] += 1

    footage._over_frames(part, 50)
    assert (seen == 1).all()
    with pytest.raises(ZeroDivisionError):  # an error in a part reaches the caller
        footage._over_frames(lambda a, b: 1 / 0, 50)
