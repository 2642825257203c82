"""Videos back to ball positions in metres, and the suite's one rule for "is there a ball".

The tracker takes the intensity-weighted centroid of the ball's core (pixels brighter than halfway
between ``threshold`` and white), then the intensity-weighted centroid of the pixels at or above
``threshold`` within two ball radii of that first estimate, so stray bright pixels (noise) far
from the ball do not pull it. The centroid is mapped to metres with the same
:func:`sysid_bench.core.render.view_geometry` the renderer uses.

When is there a ball
--------------------
:func:`ball_seen` is the rule :func:`track` and the video reader
(:func:`sysid_bench.apps.video.find_ball`) both apply to a candidate centre. A pixel *stands out*
when it differs from the background by more than a threshold that is at least ``k`` robust noise
standard deviations (:func:`noise_level`: 1.4826 median absolute deviation); a frame has a ball
when the pixels standing out within ``2 R + 1`` px of the candidate (R: the expected radius)

- cover between half and twice the expected disc's area ``pi R^2`` (a speck of noise is not a
  ball, nor is a bright wall, a lamp or the whole frame), and
- lie mostly (75%) within ``R + 1.5`` px of the candidate: the blob is compact, a disc and not
  the edge of a larger region passing by.

:func:`track` measures the difference from each frame's own background, the frame's median (the
ball covers a few percent of it), and its noise in the same frame; a pixel must stand out by
``threshold`` of white and by 5 noise standard deviations. A white, black or grey frame, random
noise or a still scene without a ball has no pixel or no compact disc standing out: NaN.
A frame also gives NaN when the bright mass near the centroid is below ``min_mass`` of a whole
disc's (dropped or blacked-out frames, a ball mostly hidden by an occluder or mostly out of the
view).

:func:`ball_centre` is the video reader's centre of a ball of any shading: the ball's pixels are
segmented by their difference from the background and filled to their convex hull (a shaded ball
can match the wall's grey along a band across it), then their centroid is taken with each pixel
weighted by the fraction of it the ball covers (1 inside; at the rim, the difference over the
ball's own contrast there, a plane fitted to the inner pixels' differences). A lit top that
barely differs from the wall then counts as much as the dark bottom.

Objects of different colours
----------------------------
:func:`track_colours` follows two (or more) objects told apart by their colour, on a real
camera's RGB frames (the collision's two carts or pucks): each pixel's chromaticity (its RGB
over their sum, so shading keeps it) is matched to each object's; pixels that match in almost
every frame are the scene (a poster of the same red) and never an object; each object is the
matching blob nearest where it was predicted. Objects touching at a contact cannot swap: each
keeps its own colour. A frame where an object's blob is missing or not its size (a hand over
it) gives NaN for that object, never an invented position.
"""

from __future__ import annotations

import numpy as np

from sysid_bench.core._validate import as_float_array
from sysid_bench.core.render import view_geometry

__all__ = ["track", "track_batch", "ball_seen", "ball_centre", "noise_level", "ColourTrack",
           "track_colours"]

#: Frames processed at once (bounds scratch memory to a few arrays of this many pixels). Not
#: smaller: a frame's centre can move in the last bit with its row in a chunk (``@`` is BLAS's
#: gemv), and 1 << 19 moved one of 200k training frames by 1e-7 m.
_CHUNK_PIXELS = 1 << 22
#: A uint8 frame's pixels as ``_centroids`` scales them (``fr / 255`` in float32), by value.
_GREY = np.arange(256, dtype=np.float32) / np.float32(255.0)
#: Robust noise standard deviations a pixel must differ from the background by to stand out.
NOISE_K = 5.0
#: Area of the pixels standing out near a ball, as a fraction of its disc's: accepted range.
AREA_RANGE = (0.5, 2.0)
#: Fraction of those pixels that must lie within R + 1.5 px of the centre (a compact blob).
CORE_FRACTION = 0.75
#: Width of the rim, px, inside and outside the segmented ball, whose pixels are weighted by
#: the fraction the ball covers (anti-aliasing is 1 px wide; motion blur spreads it further).
RIM = 2


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


def noise_level(values, axis=-1) -> np.ndarray:
    """Robust standard deviation of ``values`` along ``axis``: 1.4826 x the median absolute
    deviation from the median (the standard deviation for Gaussian noise; a ball covering a few
    percent of the pixels does not move it).

    Parameters
    ----------
    values : ndarray
    axis : int

    Returns
    -------
    ndarray
        ``values``' shape without ``axis``.
    """
    v = np.asarray(values, dtype=np.float32)
    med = np.median(v, axis=axis, keepdims=True)
    return np.float32(1.4826) * np.median(np.abs(v - med), axis=axis)


def ball_seen(contrast, centres, radius, threshold) -> np.ndarray:
    """Whether a ball is at each candidate centre: the suite's one "is there a ball" rule.

    A pixel stands out when ``contrast > threshold``. The frame has a ball at the candidate when
    the pixels standing out within ``2 R + 1`` px of it cover ``AREA_RANGE`` (0.5 to 2) of the
    disc's area ``pi R^2`` and ``CORE_FRACTION`` (75%) of them lie within ``R + 1.5`` px.

    Parameters
    ----------
    contrast : ndarray, shape (F, H, W)
        How far each pixel is from the background, in grey levels (>= 0 where it matters).
    centres : ndarray, shape (F, 2)
        Candidate centres ``(col, row)`` in continuous pixel coordinates; NaN: no candidate.
    radius : float or ndarray, shape (F,)
        Expected ball radius, px.
    threshold : float or ndarray, shape (F,)
        Grey levels a pixel must differ by to stand out; callers make it well above the noise
        (at least ``NOISE_K`` x :func:`noise_level`).

    Returns
    -------
    ndarray, shape (F,), bool
    """
    c = np.asarray(contrast)
    f, h, w = c.shape
    cen = np.asarray(centres, dtype=np.float32).reshape(f, 2)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float32), (f,))
    thr = np.broadcast_to(np.asarray(threshold, dtype=np.float32), (f,))
    jc = np.arange(w, dtype=np.float32) + np.float32(0.5)
    ic = np.arange(h, dtype=np.float32) + np.float32(0.5)
    d2 = (jc[None, None, :] - cen[:, 0, None, None]) ** 2 + (
        ic[None, :, None] - cen[:, 1, None, None]
    ) ** 2  # NaN centre: comparisons below are False
    out_ = c > thr[:, None, None]
    n_win = (out_ & (d2 <= ((2 * r + 1) ** 2)[:, None, None])).sum(axis=(1, 2))
    n_core = (out_ & (d2 <= ((r + 1.5) ** 2)[:, None, None])).sum(axis=(1, 2))
    disc = np.pi * r.astype(np.float64) ** 2
    return (
        np.isfinite(cen).all(axis=1)
        & (n_win >= AREA_RANGE[0] * disc)
        & (n_win <= AREA_RANGE[1] * disc)
        & (n_core >= CORE_FRACTION * n_win)
    )


def ball_centre(diff, threshold: float, guess, radius: float, *,
                origin=(0, 0)) -> tuple[np.ndarray, float]:
    """Sub-pixel centre of a ball of any shading near ``guess``, and its coverage area.

    The ball's pixels are those within ``radius + 2`` px of ``guess`` whose ``|diff|`` exceeds
    ``threshold`` (pieces smaller than a tenth of the disc, specks of noise, left out), filled to
    their convex hull (a shaded ball matches the background's grey along a band where its
    shading crosses it; a ball is convex). Pixels ``RIM`` (2) px or more inside the region weigh
    1; a rim pixel (within ``RIM`` px of the region's border, inside or out) weighs the fraction
    of it the ball covers: ``diff`` over the ball's own difference there, extrapolated from a
    plane fitted to the ``diff`` of the pixels 1 to 3 px inside (clipped to [0, 1]; where the
    ball's own difference is within ``threshold`` of 0, the rim pixel weighs 1 inside the
    region, 0 outside). Measured on a Lambertian ball lit from above on a wall a little
    brighter than its lit top (radius 3-12 px): within 0.17 px of the centre, where weighting
    by ``|diff|`` sits 0.6-2.4 px low (``scripts/measure_tracking.py``); on MuJoCo's renders
    (a ball lit from the camera, 30 px radius) within 0.015 px RMS, as before.

    Parameters
    ----------
    diff : ndarray, shape (H, W)
        Frame minus background, signed grey levels.
    threshold : float
        Grey levels a pixel must differ by to belong to the ball.
    guess : (float, float)
        Rough centre ``(col, row)``, px.
    radius : float
        Expected radius, px (the region is searched within ``radius + 2`` px of ``guess``).
    origin : (int, int)
        ``(col, row)`` of ``diff[0, 0]`` in the frame when ``diff`` is a window of it:
        ``guess`` and the centre are then the frame's coordinates, computed as on the whole
        frame (the same bits) where the window holds the searched region.

    Returns
    -------
    centre : ndarray, shape (2,)
        ``(col, row)``; NaN when no pixel stands out there.
    area : float
        Sum of the weights: the ball's area in px (``pi r^2`` for a whole disc of radius r).
    """
    from sysid_bench.core._ball_region import keep_large_pieces, region_masks

    d = np.asarray(diff, dtype=np.float64)
    oc, orow = int(origin[0]), int(origin[1])
    h, w = d.shape
    gc, gr = float(guess[0]), float(guess[1])
    win = float(radius) + 2.0
    # in the frame's coordinates, then the window's rows and columns
    a0, a1 = max(orow, int(gr - win - 2)), min(orow + h, int(gr + win) + 3)
    b0, b1 = max(oc, int(gc - win - 2)), min(oc + w, int(gc + win) + 3)
    if a0 >= a1 or b0 >= b1:
        return np.full(2, np.nan), 0.0
    sub = d[a0 - orow:a1 - orow, b0 - oc:b1 - oc]
    jj = np.arange(b0, b1) + 0.5
    ii = np.arange(a0, a1) + 0.5
    near = ((jj[None, :] - gc) ** 2 + (ii[:, None] - gr) ** 2) <= win**2
    stand = near & (np.abs(sub) > threshold)
    # specks of noise next to the ball would stretch its hull: keep pieces of a tenth of a disc
    # (compiled: scipy's label and a bincount, the same pieces, were ~0.4 ms of overhead a call)
    stand = keep_large_pieces(stand, max(2.0, 0.1 * np.pi * float(radius) ** 2))
    if not stand.any():
        return np.full(2, np.nan), 0.0
    # filled to the convex hull of its edge pixels; "core" (eroded once) is covered for sure:
    # the ball's own difference; "ring" its outer 3 px: a dome-shaded ball (lit from the
    # camera) is not a plane, but its outer ring is close to one. One compiled call (the
    # scipy erosions and qhull's hull it replaces, same bits, took ~15x its CPU)
    region, inner, rim, ring = region_masks(np.ascontiguousarray(stand), RIM)
    wgt = inner.astype(np.float64)
    ri, ci = np.nonzero(ring)
    re_, ce_ = np.nonzero(rim)
    if len(ri) >= 4:  # the ball's own difference: a plane through the covered pixels
        x, y = ci - ci.mean(), ri - ri.mean()
        coef = np.linalg.lstsq(np.stack([np.ones_like(x), x, y], axis=1).astype(np.float64),
                               sub[ri, ci], rcond=None)[0]
        own = coef[0] + coef[1] * (ce_ - ci.mean()) + coef[2] * (re_ - ri.mean())
    elif len(ri):
        own = np.full(len(re_), sub[ri, ci].mean())
    else:
        own = np.zeros(len(re_))
    known = np.abs(own) > threshold
    frac = np.where(known, sub[re_, ce_] / np.where(known, own, 1.0), 0.0)
    wgt[re_, ce_] = np.where(known, np.clip(frac, 0.0, 1.0), region[re_, ce_])
    m = wgt.sum()
    centre = np.array([(wgt.sum(axis=0) @ jj) / m, (wgt.sum(axis=1) @ ii) / m])
    return centre, float(m)


def _at_least(img: np.ndarray, fr: np.ndarray, level: float) -> np.ndarray:
    """``img >= level`` (bool, ``img``'s shape), from the grey levels when ``fr`` is uint8:
    ``img`` is then a non-decreasing function of ``fr`` (:data:`_GREY`), so the comparison is
    one integer cut-off on 1-byte pixels."""
    if fr.dtype != np.uint8:
        return img >= level
    cut = np.flatnonzero(_GREY >= level)  # the same comparison on the 256 possible values
    return fr >= cut[0] if cut.size else np.zeros(fr.shape, dtype=bool)


def _kept(img: np.ndarray, fr: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``np.where(mask, img, 0)`` in float32 (for uint8 frames a product by the mask: ``img`` is
    finite and >= 0 there, so bitwise the same and cheaper)."""
    if fr.dtype == np.uint8:
        return img * mask
    return np.where(mask, img, np.float32(0.0))


def _background(img: np.ndarray, fr: np.ndarray, k: int) -> np.ndarray:
    """The ``k``-th smallest pixel (0-based) of each frame of ``img`` (F, H, W), float32 (F,).

    uint8 frames: where more than ``k`` pixels equal the frame's darkest (a rendered wall),
    that is it; the others' grey level by ``np.partition`` of the bytes, scaled as ``img``
    (the same value as sorting ``img``: the scaling does not decrease)."""
    f = img.shape[0]
    if fr.dtype != np.uint8:
        return np.sort(img.reshape(f, -1), axis=1)[:, k]
    flat = fr.reshape(f, -1)
    v = flat.min(axis=1)
    rest = np.flatnonzero((flat == v[:, None]).sum(axis=1) <= k)
    if rest.size:
        v[rest] = np.partition(flat[rest], k, axis=1)[:, k]
    return _GREY[v]


def _stand_out(contrast: np.ndarray, threshold: float, k: int) -> np.ndarray:
    """``max(threshold, NOISE_K * 1.4826 * (k-th smallest |contrast|))`` of each frame, float32
    (F,): the grey levels a pixel must stand out by.

    Where more than ``k`` pixels are within ``q`` of the background, ``q`` the largest value
    whose noise bound is still at most ``threshold``, the answer is ``threshold`` without a
    sort (clean renders: most pixels are the wall); the others' k-th value by sorting."""
    f = contrast.shape[0]
    thr = np.float32(threshold)
    q = np.float32(threshold / (NOISE_K * 1.4826))
    while np.float32(NOISE_K) * (np.float32(1.4826) * q) > thr:
        q = np.nextafter(q, np.float32(0.0))
    absc = np.abs(contrast.reshape(f, -1))
    tau = np.full(f, thr, dtype=np.float32)
    rest = np.flatnonzero((absc <= q).sum(axis=1) <= k)
    if rest.size:
        noise = np.float32(1.4826) * np.sort(absc[rest], axis=1)[:, k]
        tau[rest] = np.maximum(thr, np.float32(NOISE_K) * noise)
    return tau


def _centroids(fr: np.ndarray, radius: float, threshold: float, min_mass: float) -> np.ndarray:
    """Sub-pixel ball centres of ``fr`` (F, H, W) as continuous ``(col, row)``, NaN if unseen."""
    f, h, w = fr.shape
    img = fr.astype(np.float32) / np.float32(255.0)
    # first pass on the ball's core only (halfway between threshold and white), so pixel noise
    # spread over the whole image barely moves the first estimate
    wgt = _kept(img, fr, _at_least(img, fr, (1.0 + threshold) / 2))
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
    wgt = _kept(img, fr, near & _at_least(img, fr, threshold))
    colsum = wgt.sum(axis=1)
    rowsum = wgt.sum(axis=2)
    mass = colsum.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = colsum @ jc / mass
        r = rowsum @ ic / mass
    seen = mass >= min_mass * np.pi * radius**2
    # the suite's rule: a compact disc standing out from the frame's own background (its median)
    # by threshold and by NOISE_K noise standard deviations, not a white, grey or noise frame
    # (in units of white; the lower median, as of a sorted copy: np.median costs several times
    # more on a single frame, and track runs once per frame in the control loop)
    k = (h * w - 1) // 2
    contrast = img - _background(img, fr, k)[:, None, None]
    tau = _stand_out(contrast, threshold, k)
    seen &= ball_seen(contrast, np.stack([c, r], axis=-1), radius, tau)
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
        Pixels dimmer than this fraction of white are ignored, and the ball must stand out from
        the frame's median by this fraction of white (and by ``NOISE_K`` noise standard
        deviations) to be seen (:func:`ball_seen`).
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


# -- objects of different colours (a real camera's RGB frames) -------------------------------------
#: Chromaticity distance (RGB over its sum) within which a pixel counts as an object's colour.
COLOUR_TOL = 0.1
#: Darkest pixel (R + G + B, of 765) whose chromaticity is read (darker ones are all noise).
COLOUR_MIN_SUM = 60.0
#: A pixel matching an object's colour in more than this share of the frames is the scene.
STATIC_SHARE = 0.8
#: Accepted area of an object's blob, as a fraction of its median area over the clip.
COLOUR_AREA_RANGE = (0.35, 2.5)


class ColourTrack:
    """Where each coloured object was seen in each frame (:func:`track_colours`).

    Attributes
    ----------
    pixels : ndarray, shape (T, K, 2)
        Sub-pixel centre ``(col, row)`` of object k, NaN where it was not seen.
    radii : ndarray, shape (T, K)
        Each object's radius from its blob's narrowest extent, px (NaN where not seen, or
        where it touched another object and its size could not be read alone).
    colours : ndarray, shape (K, 3)
        Each object's chromaticity (RGB over their sum).
    """

    def __init__(self, pixels, radii, colours):
        self.pixels = np.asarray(pixels, dtype=np.float64)
        self.radii = np.asarray(radii, dtype=np.float64)
        self.colours = np.asarray(colours, dtype=np.float64)

    @property
    def found(self) -> np.ndarray:
        """(T, K) bool: object k seen in frame t."""
        return np.isfinite(self.pixels).all(axis=-1)

    @property
    def radius(self) -> np.ndarray:
        """(K,) median radius of each object, px (NaN if never seen)."""
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                return np.nanmedian(self.radii, axis=0)


def _chroma(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chromaticity (H, W, 3) and brightness sum (H, W) of an RGB frame."""
    f = img.astype(np.float32)
    tot = f.sum(axis=-1)
    return f / np.maximum(tot, 1.0)[..., None], tot


def _matches(img: np.ndarray, colours: np.ndarray, tol: float) -> np.ndarray:
    """Per object, a soft membership (K, H, W) in [0, 1]: 1 within half ``tol`` of its
    chromaticity, falling to 0 at ``tol``; 0 on pixels too dark to read."""
    ch, tot = _chroma(img)
    d = np.sqrt(((ch[None] - colours[:, None, None, :].astype(np.float32)) ** 2).sum(axis=-1))
    w = np.clip((tol - d) / (0.5 * tol), 0.0, 1.0)
    w[:, tot < COLOUR_MIN_SUM] = 0.0
    return w


def _object_colours(frames: np.ndarray, k: int, bg: np.ndarray) -> np.ndarray:
    """The ``k`` objects' chromaticities from the first frames where ``k`` blobs of similar
    size and of a colour (not grey) stand out from the background, left to right."""
    from scipy import ndimage

    diff_thr = 60.0
    for t in range(min(len(frames), 15)):
        img = frames[t].astype(np.float32)
        mask = np.abs(img - bg).sum(axis=-1) > diff_thr
        mask = ndimage.binary_opening(mask)
        lab, n = ndimage.label(mask)
        if n < k:
            continue
        # only pixels of a colour count (a stopped object is in the median background: where
        # it stood, the wall differs from the background too, in the wall's grey)
        ch, tot = _chroma(img)
        vivid = ((ch.max(axis=-1) - ch.min(axis=-1)) > 0.15) & (tot >= COLOUR_MIN_SUM)
        idx = np.arange(1, n + 1)
        area = ndimage.sum_labels(vivid, lab, idx)
        order = np.argsort(area)[::-1][:k]
        if area[order[-1]] < 6 or area[order[0]] > 4 * area[order[-1]]:
            continue
        cols, out = [], []
        for j in order:
            sel = (lab == j + 1) & vivid
            cols.append(ndimage.center_of_mass(sel)[1])
            out.append(np.median(ch[sel], axis=0))
        out = np.array(out)[np.argsort(cols)]
        gaps = [np.linalg.norm(out[i] - out[j]) for i in range(k) for j in range(i + 1, k)]
        if min(gaps) >= COLOUR_TOL:
            return out
    raise ValueError(f"colours: found no frame among the first {min(len(frames), 15)} with "
                     f"{k} objects of different colours standing out from the scene")


def _size_from_scene(img: np.ndarray, bg: np.ndarray, centre, r_core: float) -> float:
    """An object's radius (px) from the pixels around ``centre`` that differ from the scene
    ``bg``, each weighted by the share of it the object covers (its difference over the
    object's own at its core), in the connected piece holding the centre."""
    from scipy import ndimage

    h, w = img.shape[:2]
    half = int(np.ceil(2.5 * r_core + 3))
    c0, c1 = max(0, int(centre[0]) - half), min(w, int(centre[0]) + half + 1)
    r0, r1 = max(0, int(centre[1]) - half), min(h, int(centre[1]) + half + 1)
    if c1 - c0 < 3 or r1 - r0 < 3:
        return float("nan")
    d = np.abs(img[r0:r1, c0:c1].astype(np.float32) - bg[r0:r1, c0:c1]).sum(axis=-1)
    rr, cc = np.mgrid[r0:r1, c0:c1].astype(np.float64) + 0.5
    inner = np.hypot(cc - centre[0], rr - centre[1]) <= 0.5 * r_core
    if not inner.any():
        return float("nan")
    peak = float(np.median(d[inner]))
    if peak <= 30.0:
        return float("nan")
    wgt = np.where(d > 0.15 * peak, np.clip(d / peak, 0.0, 1.0), 0.0)
    lab, _ = ndimage.label(wgt > 0)
    own = lab[min(max(int(centre[1]) - r0, 0), r1 - r0 - 1),
              min(max(int(centre[0]) - c0, 0), c1 - c0 - 1)]
    if own == 0:
        return float("nan")
    wgt = np.where(lab == own, wgt, 0.0)
    if (wgt[0].any() or wgt[-1].any() or wgt[:, 0].any() or wgt[:, -1].any()) and \
            wgt.sum() > 4 * np.pi * r_core ** 2:
        return float("nan")  # the piece runs out of the window: merged with something else
    return _blob_radius(wgt, rr, cc)


def _blob_radius(wgt: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> float:
    """Radius (px) of a disc from the weighted pixels' smallest second moment (a disc of radius
    r has variance r**2 / 4 along every axis; motion blur stretches only the other one)."""
    sw = wgt.sum()
    if sw <= 0:
        return float("nan")
    my, mx = (wgt * rows).sum() / sw, (wgt * cols).sum() / sw
    cyy = (wgt * (rows - my) ** 2).sum() / sw
    cxx = (wgt * (cols - mx) ** 2).sum() / sw
    cxy = (wgt * (rows - my) * (cols - mx)).sum() / sw
    lam = 0.5 * (cxx + cyy) - np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy ** 2)
    return float(2.0 * np.sqrt(lam)) if lam > 0 else float("nan")


def track_colours(frames, n_objects: int = 2, colours=None, *, tol: float = COLOUR_TOL,
                  max_side: int = 640, progress: bool = False) -> ColourTrack:
    """Follow ``n_objects`` objects of different colours through a camera's RGB frames.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W, 3), uint8
        RGB frames (upright).
    n_objects : int
        Objects to follow (2 for the collision).
    colours : array_like, shape (K, 3), optional
        Each object's colour (RGB, any scale: only its chromaticity counts), in the order the
        objects are reported. Default: read from the first frames where ``n_objects`` blobs
        of similar size stand out from the median background, left to right.
    tol : float
        Chromaticity distance within which a pixel is an object's colour.
    max_side : int
        Larger frames are followed on a block-averaged copy (the larger side at most this,
        px); centres and radii are given back in the source's pixels.
    progress : bool
        tqdm bar over the frames.

    Returns
    -------
    ColourTrack

    Raises
    ------
    ValueError
        Frames that are not (T, H, W, 3) uint8, colours not (K, 3), or objects whose colours
        cannot be read or told apart; the message names the argument.
    """
    from scipy import ndimage
    from tqdm.auto import tqdm

    fr = np.asarray(frames)
    if fr.ndim != 4 or fr.shape[-1] != 3 or fr.dtype != np.uint8 or fr.shape[0] < 1:
        raise ValueError(f"frames: expected RGB frames (T, H, W, 3) uint8, got {fr.dtype} "
                         f"shape {fr.shape}")
    if isinstance(n_objects, bool) or not isinstance(n_objects, (int, np.integer)) \
            or n_objects < 1:
        raise ValueError(f"n_objects: expected an int >= 1, got {n_objects!r}")
    blk = max(1, int(np.ceil(max(fr.shape[1:3]) / int(max_side))))
    if blk > 1:  # averaged over blk x blk blocks: continuous coordinates scale by blk exactly
        hh, ww = (fr.shape[1] // blk) * blk, (fr.shape[2] // blk) * blk
        small = np.empty((fr.shape[0], hh // blk, ww // blk, 3), np.uint8)
        for i in range(0, fr.shape[0], 32):
            tot = fr[i:i + 32, :hh, :ww].reshape(-1, hh // blk, blk, ww // blk, blk, 3).sum(
                axis=(2, 4), dtype=np.uint32)
            small[i:i + 32] = np.rint(tot / (blk * blk)).astype(np.uint8)
        out = track_colours(small, n_objects, colours, tol=tol, max_side=max_side,
                            progress=progress)
        return ColourTrack(out.pixels * blk, out.radii * blk, out.colours)
    t_n, h, w, _ = fr.shape
    idx = np.unique(np.linspace(0, t_n - 1, min(t_n, 31)).astype(int))
    bg = np.median(fr[idx], axis=0).astype(np.float32)
    if colours is None:
        col = _object_colours(fr, int(n_objects), bg)
    else:
        c = np.asarray(colours, dtype=np.float64)
        if c.shape != (n_objects, 3) or not np.isfinite(c).all() or (c < 0).any() \
                or (c.sum(axis=1) <= 0).any():
            raise ValueError(f"colours: expected ({n_objects}, 3) non-negative RGB values, got "
                             f"{colours!r}")
        col = c / c.sum(axis=1, keepdims=True)
    k = len(col)
    # the scene: pixels of an object's colour in most frames (a poster of the same red)
    count = np.zeros((k, h, w), dtype=np.float32)
    for t in idx:
        count += _matches(fr[t], col, tol) > 0.5
    bg = bg.astype(np.float32)
    static = count > STATIC_SHARE * len(idx)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    pix = np.full((t_n, k, 2), np.nan)
    radii = np.full((t_n, k), np.nan)
    areas = np.full((t_n, k), np.nan)
    last: list[list] = [[] for _ in range(k)]  # (frame, centre) of each object's last sightings
    for t in tqdm(range(t_n), desc="following the objects", unit="frame", disable=not progress,
                  leave=False):
        m = _matches(fr[t], col, tol)
        m[static] = 0.0
        for j in range(k):
            lab, n = ndimage.label(m[j] > 0.5)
            if n == 0:
                continue
            ids = np.arange(1, n + 1)
            area = ndimage.sum_labels(m[j], lab, ids)
            cen = np.array(ndimage.center_of_mass(m[j], lab, ids))[:, ::-1] + 0.5  # (col, row)
            ok = area >= 3.0
            seen_a = areas[:t, j][np.isfinite(areas[:t, j])][-20:]
            if seen_a.size:
                ref = float(np.median(seen_a))
                ok &= (area >= 0.2 * ref) & (area <= 5.0 * ref)
            if not ok.any():
                continue
            cand = np.flatnonzero(ok)
            hist = last[j]
            if hist and t - hist[-1][0] <= 5:
                pred = hist[-1][1]
                if len(hist) >= 2:
                    (t1, p1), (t2, p2) = hist[-2], hist[-1]
                    pred = p2 + (p2 - p1) * (t - t2) / max(1, t2 - t1)
                r_ref = np.sqrt(np.median(seen_a) / np.pi) if seen_a.size else 3.0
                dist = np.hypot(*(cen[cand] - pred).T)
                near = dist <= max(6.0 * r_ref, 0.05 * min(h, w))
                if not near.any():
                    continue
                b = cand[near][np.argmin(dist[near])]
            else:
                b = cand[np.argmax(area[cand])]
            # the blob's soft pixels (in its bounding box): centroid, then its size from how
            # far it differs from the scene around it (the colour's core misses the blurred rim)
            sl = ndimage.find_objects(lab, max_label=b + 1)[b]
            wgt = np.where(lab[sl] == b + 1, m[j][sl], 0.0)
            rr, cc = rows[sl], cols[sl]
            sw = wgt.sum()
            c = np.array([(wgt * cc).sum() / sw, (wgt * rr).sum() / sw])
            pix[t, j] = c
            areas[t, j] = area[b]
            radii[t, j] = _size_from_scene(fr[t], bg, c, np.sqrt(area[b] / np.pi))
            last[j] = (hist + [(t, c)])[-2:]
    # blobs not the object's size (a hand over it, a piece of it) are not seen
    for j in range(k):
        a = areas[:, j]
        if np.isfinite(a).any():
            med = float(np.nanmedian(a))
            bad = np.isfinite(a) & ((a < COLOUR_AREA_RANGE[0] * med)
                                    | (a > COLOUR_AREA_RANGE[1] * med))
            pix[bad, j] = np.nan
            radii[bad, j] = np.nan
    # sizes read only where the objects stood apart (touching, blur merges their rims)
    if k > 1:
        for t in range(t_n):
            for j in range(k):
                others = [i for i in range(k) if i != j]
                d = np.hypot(*(pix[t, others] - pix[t, j]).T)
                r = np.nansum([radii[t, j]] + [radii[t, i] for i in others])
                if np.isfinite(d).any() and np.nanmin(d) < 1.5 * r:
                    radii[t, j] = np.nan
    return ColourTrack(pixels=pix, radii=radii, colours=col)
