"""Ball states to small grey-scale videos, with optional camera nuisances.

The look follows the paper: a white ball on black, its radius ``30/256`` of the image height (the
authors drew a 30 px radius on a 256 px canvas, then resized to 28x28, which gives 3.28 px), drawn
anti-aliased (each pixel holds the fraction of it the disc covers).

Geometry (one source for :func:`render` and :mod:`sysid_bench.core.tracking`, see :func:`view_geometry`)
----------------------------------------------------------------------------------------------------
The box ``[0, 10] x [floor, floor + 10]`` m in which the ball's *centre* moves is mapped onto the
image with the ball's radius as margin on every side, so a ball touching a wall or the floor
touches the image edge. Rows run downwards: ``y = floor`` is near the bottom row. Each axis is
mapped on its own, so for a non-square size (the paper's real-video setup, ``size=(50, 100)``:
H=50, W=100) the whole 10 m box is stretched over the wide view (8.8 px/m across, 3.8 px/m up):
the camera of the real videos was framed on the ball's flight, which spans far more width than
height, and stretching keeps all 100 columns in use. The ball stays a round disc of
``30/256 * min(H, W)`` px.

Continuous pixel coordinates ``(col, row)`` put pixel ``[i, j]``'s centre at ``(j + 0.5, i + 0.5)``;
the image spans ``[0, W] x [0, H]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sysid_bench.core._validate import as_float_array

__all__ = ["ViewGeometry", "view_geometry", "check_size", "render", "RADIUS_FRACTION"]

#: Ball radius as a fraction of the image's smaller side (the authors' 30 px on 256 px).
RADIUS_FRACTION = 30.0 / 256.0
#: Side of the box the ball's centre moves in, metres (physics.BOX_WIDTH; repeated here so the
#: renderer imports without the simulator).
_BOX = 10.0
#: Pixels processed at once; bounds the renderer's scratch memory (~4 float32 arrays this big).
_CHUNK_PIXELS = 1 << 22


def check_size(size) -> tuple[int, int]:
    """Validate an image size ``(H, W)`` and return it as a tuple of two ints >= 4."""
    try:
        h, w = size
    except (TypeError, ValueError) as exc:
        raise ValueError(f"size: expected (H, W), two positive ints, got {size!r}") from exc
    for v in (h, w):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 4:
            raise ValueError(f"size: expected (H, W), two ints >= 4, got {size!r}")
    return int(h), int(w)


@dataclass(frozen=True)
class ViewGeometry:
    """Mapping between metres and continuous pixel coordinates for one image size.

    Attributes
    ----------
    size : (int, int)
        ``(H, W)`` in pixels.
    radius : float
        Ball radius in pixels.
    floor : float
        Height in metres of the floor the view is framed on (ball centre at ``y = floor`` touches
        the bottom edge).
    """

    size: tuple[int, int]
    radius: float
    floor: float = 0.0

    @property
    def px_per_m(self) -> tuple[float, float]:
        """Pixels per metre ``(across, up)``."""
        h, w = self.size
        return (w - 2 * self.radius) / _BOX, (h - 2 * self.radius) / _BOX

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Metres ``[..., (x, y)]`` to continuous pixel coordinates ``[..., (col, row)]``."""
        xy = np.asarray(xy, dtype=np.float64)
        sx, sy = self.px_per_m
        col = self.radius + xy[..., 0] * sx
        row = self.radius + (self.floor + _BOX - xy[..., 1]) * sy
        return np.stack([col, row], axis=-1)

    def to_metres(self, cr: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates ``[..., (col, row)]`` to metres ``[..., (x, y)]``."""
        cr = np.asarray(cr, dtype=np.float64)
        sx, sy = self.px_per_m
        x = (cr[..., 0] - self.radius) / sx
        y = self.floor + _BOX - (cr[..., 1] - self.radius) / sy
        return np.stack([x, y], axis=-1)


def view_geometry(size=(28, 28), floor: float = 0.0, radius: float | None = None) -> ViewGeometry:
    """The metres <-> pixels mapping used by :func:`render` and the tracker.

    Parameters
    ----------
    size : (int, int)
        ``(H, W)``.
    floor : float
        Floor height in metres that the view's bottom margin is framed on.
    radius : float, optional
        Ball radius in pixels; default ``30/256 * min(H, W)``.

    Returns
    -------
    ViewGeometry
    """
    h, w = check_size(size)
    f = float(floor)
    if not np.isfinite(f):
        raise ValueError(f"floor: expected a finite number, got {floor!r}")
    if radius is None:
        r = RADIUS_FRACTION * min(h, w)
    else:
        r = float(radius)
        if not np.isfinite(r) or r <= 0 or 2 * r >= min(h, w):
            raise ValueError(
                f"radius: expected pixels in (0, {min(h, w) / 2:g}) for size {(h, w)}, got {radius!r}"
            )
    return ViewGeometry(size=(h, w), radius=r, floor=f)


def _check_fraction(value, name: str, hi: float = 1.0) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a number in [0, {hi:g}], got {value!r}") from exc
    if not np.isfinite(v) or v < 0 or v > hi:
        raise ValueError(f"{name}: expected a number in [0, {hi:g}], got {value!r}")
    return v


def _video_rngs(seed, n: int) -> list[np.random.Generator]:
    """One independent Generator per video, so a video's nuisances do not depend on its batch."""
    if isinstance(seed, (Sequence, np.ndarray)) and not isinstance(seed, (str, bytes)):
        if len(seed) != n:
            raise ValueError(f"seed: expected one seed per video ({n}), got {len(seed)}")
        return [_one_rng(s) for s in seed]
    if isinstance(seed, np.random.Generator):
        return list(seed.spawn(n))
    if isinstance(seed, np.random.SeedSequence):
        return [np.random.default_rng(s) for s in seed.spawn(n)]
    if seed is None or (isinstance(seed, (int, np.integer)) and not isinstance(seed, bool)):
        return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]
    raise ValueError(
        "seed: expected an int, None, Generator, SeedSequence or a sequence of them (one per "
        f"video), got {seed!r}"
    )


def _one_rng(s) -> np.random.Generator:
    if isinstance(s, np.random.Generator):
        return s
    if isinstance(s, np.random.SeedSequence) or (
        isinstance(s, (int, np.integer)) and not isinstance(s, bool)
    ):
        return np.random.default_rng(s)
    raise ValueError(f"seed: expected ints, Generators or SeedSequences per video, got {s!r}")


def _window(centres: np.ndarray, radius: float, n: int) -> tuple[np.ndarray, int]:
    """First index (F,) and common length of a pixel window along one axis that holds every
    pixel a disc of ``radius`` around any of each frame's centres ``(F, S)`` may cover.

    A pixel centre ``j + 0.5`` is covered only when it lies within ``radius + 0.5`` of a
    centre; the window is shifted to lie inside ``[0, n)`` (pixels outside it are 0 anyway).
    """
    lo = np.floor(centres.min(axis=1) - radius - 1.0)
    hi = np.ceil(centres.max(axis=1) + radius)
    size = int(min(n, max(1.0, (hi - lo).max() + 1.0)))
    start = np.clip(lo, 0, n - size).astype(np.int64)
    return start, size


def _draw_discs(cols: np.ndarray, rows: np.ndarray, size, radius: float) -> np.ndarray:
    """Anti-aliased disc coverage, averaged over sub-positions.

    Each frame's coverage is computed on a window around its ball only (a 100x50 frame's disc
    covers ~4% of it) and written into zeros: the same float32 operations on the same pixels
    as over the whole frame, so the bytes do not depend on the window.

    Parameters
    ----------
    cols, rows : ndarray, shape (F, S)
        Continuous pixel centres of the ball for F frames and S sub-positions.

    Returns
    -------
    ndarray, shape (F, H, W), float32 in [0, 1]
    """
    h, w = size
    f, s = cols.shape
    out = np.zeros((f, h, w), dtype=np.float32)
    if f == 0:
        return out
    j0, pw = _window(cols, radius, w)
    i0, ph = _window(rows, radius, h)
    jj = j0[:, None] + np.arange(pw)  # (F, Pw) pixel columns of each frame's window
    ii = i0[:, None] + np.arange(ph)  # (F, Ph)
    jc = jj.astype(np.float32) + np.float32(0.5)
    ic = ii.astype(np.float32) + np.float32(0.5)
    r = np.float32(radius + 0.5)
    patch = np.zeros((f, ph, pw), dtype=np.float32)
    for k in range(s):  # S is small (1 without blur); the frames are vectorised
        dx2 = (jc - cols[:, k, None].astype(np.float32)) ** 2  # (F, Pw)
        dy2 = (ic - rows[:, k, None].astype(np.float32)) ** 2  # (F, Ph)
        d = np.sqrt(dy2[:, :, None] + dx2[:, None, :])
        # coverage ~ clip(r - d + 0.5): exact for a straight edge through the pixel centre
        np.subtract(r, d, out=d)
        np.clip(d, 0.0, 1.0, out=d)
        patch += d
    if s > 1:
        patch /= s
    out[np.arange(f)[:, None, None], ii[:, :, None], jj[:, None, :]] = patch
    return out


def render(
    states,
    size=(28, 28),
    *,
    floor=0.0,
    blur: float = 0.0,
    occlusion: float = 0.0,
    drop: float = 0.0,
    noise: float = 0.0,
    floor_offset: float = 0.0,
    seed=None,
    radius: float | None = None,
    dt: float = 0.05,
    return_info: bool = False,
):
    """Draw videos of the ball from its states.

    Parameters
    ----------
    states : ndarray, shape (B, T, 4)
        ``[x, y, vx, vy]`` in metres and m/s (a single video must be passed as ``states[None]``).
    size : (int, int)
        ``(H, W)`` of the frames; ``(28, 28)`` as in the paper's simulated set, ``(50, 100)`` for
        the real-video setup. See the module docstring for how the box maps onto the image.
    floor : float or ndarray, shape (B,)
        Floor height in metres each video's view is framed on.
    blur : float in [0, 1]
        Motion blur: fraction of the frame interval ``dt`` the shutter is open. The ball is
        averaged over 7 positions evenly spread along ``v * dt * blur``, centred on the true
        position (so the blurred blob's centroid stays on it).
    occlusion : float in [0, 1]
        Fraction of frames (each frame independently) on which a black rectangle covers part of
        the image; its height and width are uniform in [30%, 60%] of the image's, its position
        uniform. Blacked-out pixels are exactly 0.
    drop : float in [0, 1]
        Fraction of frames (independently) dropped: the whole frame is 0, the ball is not seen.
    noise : float in [0, 255]
        Standard deviation of additive Gaussian pixel noise in grey levels; clipped to [0, 255].
    floor_offset : float in [0, 10]
        Per-video vertical shift of the view: each video draws ``o ~ U(0, floor_offset)`` metres
        and the ball is drawn ``o`` higher, as if the floor sat ``o`` above the framed floor.
        Tracking such a video with ``floor`` gives ``y + o``; the drawn ``o`` is returned in
        ``info["floor_offset"]`` when ``return_info`` is True.
    seed : int, Generator, SeedSequence, None, or a sequence of these of length B
        Randomness of the nuisances. A single seed is split into one stream per video
        (``SeedSequence.spawn`` / ``Generator.spawn``); a sequence gives each video its own
        stream, so a video's nuisances do not depend on which batch it was drawn in.
    radius : float, optional
        Ball radius in pixels; default ``30/256 * min(H, W)``.
    dt : float
        Seconds between frames (only used by ``blur``).
    return_info : bool
        Also return what the nuisances did.

    Returns
    -------
    frames : ndarray, shape (B, T, H, W), uint8
    info : dict, only if ``return_info``
        ``floor_offset`` (B,) metres, ``dropped`` (B, T) bool, ``occluded`` (B, T) bool,
        ``occlusion_box`` (B, T, 4) int ``[row0, row1, col0, col1)`` (-1 where not occluded).
    """
    st = np.asarray(states)
    if st.ndim != 3 or st.shape[-1] != 4:
        raise ValueError(
            f"states: expected a (B, T, 4) array of [x, y, vx, vy] (pass one video as "
            f"states[None]), got shape {st.shape}"
        )
    st = as_float_array(st, "states", ndim=3, last=4)
    b, t = st.shape[:2]
    geom = view_geometry(size, 0.0, radius)
    h, w = geom.size
    fl = as_float_array(floor, "floor", ndim=(0, 1))
    if fl.ndim == 1 and fl.shape[0] != b:
        raise ValueError(f"floor: expected a scalar or shape ({b},), got shape {fl.shape}")
    fl = np.broadcast_to(fl, (b,))
    blur = _check_fraction(blur, "blur")
    occlusion = _check_fraction(occlusion, "occlusion")
    drop = _check_fraction(drop, "drop")
    noise = _check_fraction(noise, "noise", 255.0)
    floor_offset = _check_fraction(floor_offset, "floor_offset", _BOX)
    dt = float(dt)
    if not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt: expected a finite number > 0, got {dt!r}")

    # -- random draws, one stream per video, in a fixed order ----------------------------------
    offsets = np.zeros(b)
    dropped = np.zeros((b, t), dtype=bool)
    occluded = np.zeros((b, t), dtype=bool)
    boxes = np.full((b, t, 4), -1, dtype=np.int64)
    random_any = floor_offset > 0 or drop > 0 or occlusion > 0 or noise > 0
    rngs = _video_rngs(seed, b) if random_any else None
    if random_any:
        lo_h, lo_w = max(1, round(0.3 * h)), max(1, round(0.3 * w))
        hi_h, hi_w = max(lo_h, round(0.6 * h)), max(lo_w, round(0.6 * w))
        for i, rng in enumerate(rngs):  # only small per-video arrays here; noise comes later
            if floor_offset > 0:
                offsets[i] = rng.uniform(0.0, floor_offset)
            if drop > 0:
                dropped[i] = rng.random(t) < drop
            if occlusion > 0:
                occluded[i] = rng.random(t) < occlusion
                bh = rng.integers(lo_h, hi_h + 1, size=t)
                bw = rng.integers(lo_w, hi_w + 1, size=t)
                r0 = rng.integers(0, h - bh + 1)
                c0 = rng.integers(0, w - bw + 1)
                box = np.stack([r0, r0 + bh, c0, c0 + bw], axis=-1)
                boxes[i] = np.where(occluded[i][:, None], box, -1)

    # -- ball centres (and blur sub-positions) in pixels ---------------------------------------
    n_sub = 7 if blur > 0 else 1
    frac = np.linspace(-0.5, 0.5, n_sub) if blur > 0 else np.zeros(1)
    xy = st[..., :2].copy()
    # each video relative to its own framed floor; an offset lifts the ball (and its floor)
    xy[..., 1] += offsets[:, None] - fl[:, None]
    # sub-positions along the velocity: (B, T, S, 2)
    sub = xy[:, :, None, :] + st[:, :, None, 2:] * (dt * blur) * frac[None, None, :, None]
    cr = geom.to_pixels(sub).reshape(b * t, n_sub, 2)

    out = np.empty((b * t, h, w), dtype=np.uint8)
    step = max(1, _CHUNK_PIXELS // (h * w))
    flat_drop = dropped.reshape(-1)
    flat_occ = occluded.reshape(-1)
    flat_box = boxes.reshape(-1, 4)
    for s0 in range(0, b * t, step):
        s1 = min(b * t, s0 + step)
        img = _draw_discs(cr[s0:s1, :, 0], cr[s0:s1, :, 1], (h, w), geom.radius)
        img *= 255.0
        if noise > 0:
            # noise drawn per video from its own stream; frames of a chunk may span videos
            v0, v1 = s0 // t, (s1 - 1) // t
            for v in range(v0, v1 + 1):
                a0, a1 = max(s0, v * t), min(s1, (v + 1) * t)
                # a video's frames come in increasing order across chunks, so drawing them
                # sequentially from its stream gives the same numbers whatever the chunking
                img[a0 - s0 : a1 - s0] += noise * rngs[v].standard_normal(
                    (a1 - a0, h, w), dtype=np.float32
                )
        np.clip(img, 0.0, 255.0, out=img)
        np.rint(img, out=img)
        chunk = img.astype(np.uint8)
        for k in np.flatnonzero(flat_occ[s0:s1]):
            r0, r1, c0, c1 = flat_box[s0 + k]
            chunk[k, r0:r1, c0:c1] = 0
        chunk[flat_drop[s0:s1]] = 0
        out[s0:s1] = chunk
    frames = out.reshape(b, t, h, w)
    if return_info:
        info = {
            "floor_offset": offsets,
            "dropped": dropped,
            "occluded": occluded,
            "occlusion_box": boxes,
        }
        return frames, info
    return frames
