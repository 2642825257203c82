"""Videos back to ball positions in metres.

The tracker takes the intensity-weighted centroid of the ball's core (pixels brighter than halfway
between ``threshold`` and white), then the intensity-weighted centroid of the pixels at or above
``threshold`` within two ball radii of that first estimate, so stray bright pixels (noise) far
from the ball do not pull it. The centroid is mapped to metres with the same
:func:`sysid_bench.render.view_geometry` the renderer uses.

A frame gives NaN when the ball is not seen: the bright mass near the centroid is below
``min_mass`` of a whole disc's (dropped or blacked-out frames, a ball mostly hidden by an
occluder or mostly out of the view).
"""

from __future__ import annotations

import numpy as np

from sysid_bench._validate import as_float_array
from sysid_bench.render import view_geometry

__all__ = ["track", "track_batch"]

#: Frames processed at once (bounds scratch memory to a few arrays of this many pixels).
_CHUNK_PIXELS = 1 << 22


def _check_frames(frames, ndim: int, shape_text: str) -> np.ndarray:
    fr = np.asarray(frames)
    if fr.ndim != ndim:
        raise ValueError(
            f"frames: expected a {shape_text} array, got shape {fr.shape} dtype {fr.dtype}"
        )
    if fr.dtype != np.uint8:
        fr = as_float_array(fr, "frames", ndim=ndim)
        if fr.size and (fr.min() < 0 or fr.max() > 255):
            raise ValueError(
                f"frames: expected values in [0, 255], got [{fr.min():g}, {fr.max():g}]"
            )
    return fr


def _check_fraction(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a number in (0, 1), got {value!r}") from exc
    if not 0 < v < 1:
        raise ValueError(f"{name}: expected a number in (0, 1), got {value!r}")
    return v


def _centroids(fr: np.ndarray, radius: float, threshold: float, min_mass: float) -> np.ndarray:
    """Sub-pixel ball centres of ``fr`` (F, H, W) as continuous ``(col, row)``, NaN if unseen."""
    f, h, w = fr.shape
    img = fr.astype(np.float32) / np.float32(255.0)
    # first pass on the ball's core only (halfway between threshold and white), so pixel noise
    # spread over the whole image barely moves the first estimate
    wgt = np.where(img >= (1.0 + threshold) / 2, img, np.float32(0.0))
    jc = np.arange(w, dtype=np.float32) + 0.5
    ic = np.arange(h, dtype=np.float32) + 0.5
    colsum = wgt.sum(axis=1)  # (F, W)
    rowsum = wgt.sum(axis=2)  # (F, H)
    mass = colsum.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = colsum @ jc / mass
        r = rowsum @ ic / mass
    # second pass: only pixels within 2 radii of the first estimate (NaN -> mask nothing)
    win = np.float32(2.0 * radius) ** 2
    near = (
        (jc[None, None, :] - c[:, None, None]) ** 2 + (ic[None, :, None] - r[:, None, None]) ** 2
    ) <= win
    wgt = np.where(near & (img >= threshold), img, np.float32(0.0))
    colsum = wgt.sum(axis=1)
    rowsum = wgt.sum(axis=2)
    mass = colsum.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = colsum @ jc / mass
        r = rowsum @ ic / mass
    seen = mass >= min_mass * np.pi * radius**2
    out = np.stack([c, r], axis=-1).astype(np.float64)
    out[~seen] = np.nan
    return out


def track_batch(
    frames,
    floor=0.0,
    *,
    radius: float | None = None,
    threshold: float = 0.25,
    min_mass: float = 0.6,
) -> np.ndarray:
    """Ball positions in metres for a batch of videos.

    Parameters
    ----------
    frames : ndarray, shape (B, T, H, W)
        uint8, or floats in [0, 255].
    floor : float or ndarray, shape (B,)
        Floor height in metres each video's view is framed on (as given to ``render``).
    radius : float, optional
        Ball radius in pixels; default as in ``render``.
    threshold : float in (0, 1)
        Pixels dimmer than this fraction of white are ignored.
    min_mass : float in (0, 1)
        Fraction of a whole disc's brightness that must be found for the ball to count as seen.

    Returns
    -------
    ndarray, shape (B, T, 2)
        ``[x, y]`` in metres, NaN where the ball is not seen.
    """
    fr = _check_frames(frames, 4, "(B, T, H, W)")
    b, t, h, w = fr.shape
    geom = view_geometry((h, w), 0.0, radius)
    fl = as_float_array(floor, "floor", ndim=(0, 1))
    if fl.ndim == 1 and fl.shape[0] != b:
        raise ValueError(f"floor: expected a scalar or shape ({b},), got shape {fl.shape}")
    fl = np.broadcast_to(fl, (b,))
    threshold = _check_fraction(threshold, "threshold")
    min_mass = _check_fraction(min_mass, "min_mass")
    flat = fr.reshape(b * t, h, w)
    cr = np.empty((b * t, 2))
    step = max(1, _CHUNK_PIXELS // (h * w))
    for s0 in range(0, b * t, step):
        cr[s0 : s0 + step] = _centroids(flat[s0 : s0 + step], geom.radius, threshold, min_mass)
    xy = geom.to_metres(cr).reshape(b, t, 2)
    xy[..., 1] += fl[:, None]
    return xy


def track(frames, floor: float = 0.0, **options) -> np.ndarray:
    """Ball positions in metres for one video.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W)
        uint8, or floats in [0, 255].
    floor : float
        Floor height in metres the view is framed on (as given to ``render``).
    **options
        ``radius``, ``threshold``, ``min_mass`` as in :func:`track_batch`.

    Returns
    -------
    ndarray, shape (T, 2)
        ``[x, y]`` in metres, NaN where the ball is not seen.
    """
    fr = _check_frames(frames, 3, "(T, H, W)")
    f = as_float_array(floor, "floor", ndim=0)
    return track_batch(fr[None], float(f), **options)[0]
