"""Drawing helpers every system's renderer shares: a view, anti-aliased discs and rods, and the
camera nuisances of the ball's renderer (blur, occlusion, dropped frames, pixel noise).

Pixel convention as :mod:`sysid_bench.core.render`: continuous ``(col, row)`` puts pixel ``[i, j]``'s
centre at ``(j + 0.5, i + 0.5)``; rows run downwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["View", "draw_discs", "draw_segments", "blur_positions", "finish", "video_rngs",
           "NUISANCES"]

#: The camera nuisances every system's ``render`` accepts (as the ball's), all off by default.
NUISANCES = ("blur", "occlusion", "drop", "noise")


@dataclass(frozen=True)
class View:
    """Linear map between metres and continuous pixel coordinates.

    Attributes
    ----------
    extent : (float, float, float, float)
        ``(x0, x1, y0, y1)`` metres shown; ``x0`` at the left edge, ``y1`` at the top edge.
    size : (int, int)
        ``(H, W)`` pixels.
    """

    extent: tuple[float, float, float, float]
    size: tuple[int, int]

    @property
    def px_per_m(self) -> tuple[float, float]:
        """Pixels per metre ``(across, up)``."""
        x0, x1, y0, y1 = self.extent
        h, w = self.size
        return w / (x1 - x0), h / (y1 - y0)

    def to_pixels(self, xy) -> np.ndarray:
        """Metres ``[..., (x, y)]`` to pixels ``[..., (col, row)]``."""
        xy = np.asarray(xy, dtype=np.float64)
        x0, _, _, y1 = self.extent
        sx, sy = self.px_per_m
        return np.stack([(xy[..., 0] - x0) * sx, (y1 - xy[..., 1]) * sy], axis=-1)

    def to_metres(self, cr) -> np.ndarray:
        """Pixels ``[..., (col, row)]`` to metres ``[..., (x, y)]``."""
        cr = np.asarray(cr, dtype=np.float64)
        x0, _, _, y1 = self.extent
        sx, sy = self.px_per_m
        return np.stack([x0 + cr[..., 0] / sx, y1 - cr[..., 1] / sy], axis=-1)


def _grid(size):
    h, w = size
    ic = np.arange(h, dtype=np.float32)[:, None] + np.float32(0.5)  # (H, 1)
    jc = np.arange(w, dtype=np.float32)[None, :] + np.float32(0.5)  # (1, W)
    return ic, jc


def draw_discs(centres, radius_px, size) -> np.ndarray:
    """Anti-aliased coverage of discs, averaged over sub-positions.

    Parameters
    ----------
    centres : ndarray, shape (F, S, 2)
        Pixel centres ``(col, row)`` of one disc in F frames at S sub-positions (S = 1 unblurred).
    radius_px : float
    size : (int, int)

    Returns
    -------
    ndarray, shape (F, H, W), float32 in [0, 1]
    """
    c = np.asarray(centres, dtype=np.float32)
    ic, jc = _grid(size)
    out = np.zeros((c.shape[0],) + tuple(size), dtype=np.float32)
    r = np.float32(radius_px + 0.5)
    for s in range(c.shape[1]):
        dx2 = (jc[None] - c[:, s, 0, None, None]) ** 2
        dy2 = (ic[None] - c[:, s, 1, None, None]) ** 2
        d = np.sqrt(dx2 + dy2)
        # coverage ~ clip(r - d + 0.5): exact for a straight edge through the pixel centre
        out += np.clip(r - d, 0.0, 1.0)
    out /= np.float32(c.shape[1])
    return out


def draw_segments(a, b, width_px, size) -> np.ndarray:
    """Anti-aliased coverage of line segments (rods), averaged over sub-positions.

    Parameters
    ----------
    a, b : ndarray, shape (F, S, 2)
        Pixel end points.
    width_px : float
    size : (int, int)

    Returns
    -------
    ndarray, shape (F, H, W), float32 in [0, 1]
    """
    a = np.asarray(a, dtype=np.float32)
    b = np.asarray(b, dtype=np.float32)
    ic, jc = _grid(size)
    out = np.zeros((a.shape[0],) + tuple(size), dtype=np.float32)
    half = np.float32(width_px / 2 + 0.5)
    for s in range(a.shape[1]):
        ax, ay = a[:, s, 0, None, None], a[:, s, 1, None, None]
        ux, uy = b[:, s, 0, None, None] - ax, b[:, s, 1, None, None] - ay
        ll = np.maximum(ux * ux + uy * uy, np.float32(1e-12))
        t = np.clip(((jc[None] - ax) * ux + (ic[None] - ay) * uy) / ll, 0.0, 1.0)
        d = np.sqrt((jc[None] - ax - t * ux) ** 2 + (ic[None] - ay - t * uy) ** 2)
        out += np.clip(half - d, 0.0, 1.0)
    out /= np.float32(a.shape[1])
    return out


def blur_positions(points, dt: float, blur: float) -> np.ndarray:
    """Sub-positions of moving points over an open shutter.

    Parameters
    ----------
    points : ndarray, shape (B, T, K, 2)
    dt : float
    blur : float in [0, 1]
        Fraction of the frame interval the shutter is open; 0 gives one sub-position.

    Returns
    -------
    ndarray, shape (B, T, S, K, 2)
        S = 7 positions evenly spread along the velocity (finite differences of the points),
        centred on the point, or S = 1 without blur.
    """
    p = np.asarray(points, dtype=np.float64)
    if blur <= 0 or p.shape[1] < 2:
        return p[:, :, None]
    v = np.gradient(p, dt, axis=1)
    frac = np.linspace(-0.5, 0.5, 7)
    return p[:, :, None] + v[:, :, None] * (dt * blur) * frac[None, None, :, None, None]


def video_rngs(seed, n: int) -> list[np.random.Generator]:
    """One independent Generator per video, so a video's nuisances do not depend on its batch."""
    if isinstance(seed, np.random.Generator):
        return list(seed.spawn(n))
    if seed is None or (isinstance(seed, (int, np.integer)) and not isinstance(seed, bool)):
        return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]
    raise ValueError(f"seed: expected an int, None or numpy.random.Generator, got {seed!r}")


def _fraction(value, name: str, hi: float = 1.0) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}: expected a number in [0, {hi:g}], got {value!r}")
    v = float(value)
    if not np.isfinite(v) or v < 0 or v > hi:
        raise ValueError(f"{name}: expected a number in [0, {hi:g}], got {value!r}")
    return v


def check_nuisance(nuisance: dict) -> dict:
    """Validate nuisance options; unknown names raise ``ValueError`` listing the known ones."""
    unknown = sorted(set(nuisance) - set(NUISANCES) - {"seed", "dt"})
    if unknown:
        raise ValueError(
            f"nuisance: unknown option(s) {unknown}; known: {', '.join(NUISANCES)}, seed, dt"
        )
    out = {k: _fraction(nuisance.get(k, 0.0), k, 255.0 if k == "noise" else 1.0) for k in NUISANCES}
    dt = nuisance.get("dt", 0.05)
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt: expected a number of seconds > 0, got {dt!r}")
    out["dt"] = float(dt)
    out["seed"] = nuisance.get("seed")
    return out


def finish(images, *, occlusion: float = 0.0, drop: float = 0.0, noise: float = 0.0,
           seed=None) -> np.ndarray:
    """Grey levels (B, T, H, W) in [0, 255] to uint8 frames with the camera nuisances.

    Per video, in this order from its own stream: the occluded frames and their black
    rectangles (30-60% of each side, uniform position), the dropped frames (all black), then
    additive Gaussian pixel noise of std ``noise`` grey levels; clipped and rounded.
    """
    img = np.array(images, dtype=np.float32, copy=True)
    b, t, h, w = img.shape
    if occlusion > 0 or drop > 0 or noise > 0:
        rngs = video_rngs(seed, b)
        lo_h, lo_w = max(1, round(0.3 * h)), max(1, round(0.3 * w))
        hi_h, hi_w = max(lo_h, round(0.6 * h)), max(lo_w, round(0.6 * w))
        for i, rng in enumerate(rngs):
            if noise > 0:
                img[i] += noise * rng.standard_normal((t, h, w), dtype=np.float32)
            if occlusion > 0:
                occ = rng.random(t) < occlusion
                bh = rng.integers(lo_h, hi_h + 1, size=t)
                bw = rng.integers(lo_w, hi_w + 1, size=t)
                r0 = rng.integers(0, h - bh + 1)
                c0 = rng.integers(0, w - bw + 1)
                for k in np.flatnonzero(occ):
                    img[i, k, r0[k] : r0[k] + bh[k], c0[k] : c0[k] + bw[k]] = 0.0
            if drop > 0:
                img[i, rng.random(t) < drop] = 0.0
    np.clip(img, 0.0, 255.0, out=img)
    np.rint(img, out=img)
    return img.astype(np.uint8)
