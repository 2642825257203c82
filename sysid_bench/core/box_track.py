"""Follow an object by its appearance: a template from a box the user draws on the first frame.

The median-background tracker (:func:`sysid_bench.core.footage.find_object`) finds a round blob
that differs from the background; it loses objects that are neither round nor contrasting, and
objects that rest long enough to leave a ghost in the median (a cart on a lab track, a mass
dwelling at the turns of a vertical spring: ``docs/real-footage.md``, sessions 27-31). This
tracker needs no background: the user gives the object's box in the first frame
(``--object-box C R W H``, as OpenCV's ``selectROI`` or Tracker's template returns it), and
each later frame is searched for the patch most like it.

Per frame:

1. a constant-velocity prediction from the last two frames the object was seen in, and a
   search window around it (the window grows while the object is not seen);
2. zero-mean normalised cross-correlation (ZNCC) of the template at every integer offset of
   the window (a compiled loop; the window's sums from integral images), and a parabola
   through the peak and its neighbours along each axis for the sub-pixel position;
3. the match is refined against the **first** template (the anchor) in a few pixels around
   it: an adapted template drifts a fraction of a pixel a frame onto the background, the
   anchor does not (Matthews, Ishikawa & Baker 2004, "The template update problem");
4. "not seen" (NaN) where the best score is under ``min_score``, or where the peak is on the
   search window's edge after the window was widened (the object may be beyond it): never a
   position the frame does not show;
5. the template is adapted slowly (``adapt``, an exponential average of the patches where
   the anchor agreed within a pixel and the match was strong), so a slow change of light or
   pose is followed without drifting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["BoxTrack", "follow_box", "check_box", "MIN_SCORE"]

#: ZNCC under which a frame's best match is "not seen": 0.5 is a weak match (a hand over the
#: object, the object mostly out of the frame); the object itself scores 0.8-1.0 frame to frame
MIN_SCORE = 0.5
#: ... and above which a match may adapt the template (a partly hidden object is not learnt)
ADAPT_SCORE = 0.8


@dataclass
class BoxTrack:
    """Where the boxed object was matched in each frame.

    Attributes
    ----------
    centres : ndarray, shape (T, 2)
        Sub-pixel centre ``(col, row)`` of the box in each frame (continuous pixel coordinates:
        pixel ``[i, j]``'s centre at ``(j + 0.5, i + 0.5)``); NaN where not seen.
    score : ndarray, shape (T,)
        The best ZNCC found in each frame (1 in frame 0); NaN where no window could be searched.
    box : (int, int, int, int)
        The box ``(col, row, width, height)`` of frame 0 as used (whole pixels).
    """

    centres: np.ndarray
    score: np.ndarray
    box: tuple

    @property
    def found(self) -> np.ndarray:
        """(T,) bool: frames the object was seen in."""
        return np.isfinite(self.centres).all(axis=1)


def check_box(box, size, option: str = "object_box") -> tuple[int, int, int, int]:
    """A box ``(col, row, width, height)`` of a frame of ``size`` ``(H, W)``, in whole pixels.

    Parameters
    ----------
    box : sequence of 4 float
        The top-left corner's column and row, the width and the height, px (OpenCV's
        ``(x, y, w, h)``). Edges are rounded to the nearest whole pixel.
    size : (int, int) or None
        ``(H, W)`` of the frame, after any ``--rotate``; None: the frame's size is not known
        yet (the numbers alone are checked, the corner not left of or above the frame).
    option : str
        The option's name, for the message.

    Returns
    -------
    (int, int, int, int)

    Raises
    ------
    ValueError
        Not four finite numbers, a size under 4 px, or a box not inside the frame; the message
        starts with ``option:``.
    """
    try:
        vals = [float(v) for v in box]
    except (TypeError, ValueError):
        raise ValueError(f"{option}: expected four numbers C R W H, got {box!r}") from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{option}: expected four finite numbers C R W H, got {box!r}")
    c, r, w, h = vals
    if w < 4 or h < 4:
        raise ValueError(f"{option}: expected a width and height of at least 4 px, got "
                         f"{w:g} x {h:g}")
    if size is None:
        if c < 0 or r < 0:
            raise ValueError(f"{option}: expected the box's top-left corner inside the frame "
                             f"(column and row >= 0), got column {c:g}, row {r:g}")
        return int(round(c)), int(round(r)), int(round(c + w)) - int(round(c)), \
            int(round(r + h)) - int(round(r))
    h_f, w_f = int(size[0]), int(size[1])
    if c < 0 or r < 0 or c + w > w_f or r + h > h_f:
        raise ValueError(f"{option}: expected a box inside the {w_f}x{h_f} frame (columns 0 to "
                         f"{w_f}, rows 0 to {h_f}), got columns {c:g} to {c + w:g}, rows {r:g} "
                         f"to {r + h:g}")
    c0, r0 = int(round(c)), int(round(r))
    c1, r1 = min(int(round(c + w)), w_f), min(int(round(r + h)), h_f)
    return c0, r0, c1 - c0, r1 - r0


@numba.njit(cache=True, nogil=True)
def _zncc(frame, tz, tnorm, r0, r1, c0, c1, out):  # pragma: no cover - compiled
    """ZNCC of the zero-mean template ``tz`` (h, w) float64, ``tnorm`` its L2 norm, with the
    patch of ``frame`` (H, W) whose top-left corner is at each ``(r, c)``, ``r0 <= r < r1``,
    ``c0 <= c < c1``; ``out[r - r0, c - c0]``. The template being zero-mean, the patch's mean
    drops out of the numerator; the patch's own norm is from its sum and sum of squares. A
    flat patch (no texture) scores 0."""
    h, w = tz.shape
    n = h * w
    for r in range(r0, r1):
        for c in range(c0, c1):
            s = 0.0
            s1 = 0.0
            s2 = 0.0
            for i in range(h):
                for j in range(w):
                    v = float(frame[r + i, c + j])
                    s += v * tz[i, j]
                    s1 += v
                    s2 += v * v
            var = s2 - s1 * s1 / n
            out[r - r0, c - c0] = s / (tnorm * math.sqrt(var)) if var > 1e-9 else 0.0


def _zero_mean(patch: np.ndarray) -> tuple[np.ndarray, float]:
    """The patch less its mean (float64) and its L2 norm."""
    tz = patch.astype(np.float64) - float(patch.mean())
    return tz, float(np.sqrt((tz * tz).sum()))


def _sub_pixel(m: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """The peak of a parabola through ``m[i, j]`` and its two neighbours along each axis
    (0 along an axis whose neighbour is outside ``m``, or whose curvature is not a peak)."""

    def vertex(a, b, c):
        den = a - 2.0 * b + c
        return 0.0 if den >= 0 else float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))

    di = vertex(m[i - 1, j], m[i, j], m[i + 1, j]) if 0 < i < m.shape[0] - 1 else 0.0
    dj = vertex(m[i, j - 1], m[i, j], m[i, j + 1]) if 0 < j < m.shape[1] - 1 else 0.0
    return di, dj


def _search(frame, tz, tnorm, top_left, radius: int):
    """The best match of ``tz`` with its top-left corner within ``radius`` px of ``top_left``
    ``(row, col)`` (float): ``(score, row, col, on_edge)``, sub-pixel, or None where the window
    is outside the frame. ``on_edge``: the peak is on the window's edge inside the frame (the
    object may be beyond it); the frame's own edge is not the window's."""
    h_f, w_f = frame.shape
    h, w = tz.shape
    pr, pc = int(round(top_left[0])), int(round(top_left[1]))
    r0, r1 = max(pr - radius, 0), min(pr + radius + 1, h_f - h + 1)
    c0, c1 = max(pc - radius, 0), min(pc + radius + 1, w_f - w + 1)
    if r1 <= r0 or c1 <= c0:
        return None
    m = np.empty((r1 - r0, c1 - c0))
    _zncc(frame, tz, tnorm, r0, r1, c0, c1, m)
    i, j = np.unravel_index(int(np.argmax(m)), m.shape)
    di, dj = _sub_pixel(m, i, j)
    edge = ((i == 0 and r0 > 0) or (i == m.shape[0] - 1 and r1 < h_f - h + 1)
            or (j == 0 and c0 > 0) or (j == m.shape[1] - 1 and c1 < w_f - w + 1))
    return float(m[i, j]), r0 + i + di, c0 + j + dj, bool(edge)


#: A box whose smaller side is at least twice this is searched first on k x k block means
#: (``k = smaller side // COARSE_SIDE``), then at full resolution within k px of the coarse peak:
#: a 115x67 box at 1080p tracked at 35 frames/s searched whole, this many times faster
COARSE_SIDE = 24


def _block_mean(a: np.ndarray, k: int) -> np.ndarray:
    """Means of ``k x k`` blocks of a 2-D array (trailing rows/columns dropped), float64."""
    h, w = a.shape[0] // k, a.shape[1] // k
    return a[:h * k, :w * k].reshape(h, k, w, k).mean(axis=(1, 3))


class _Pyramid:
    """A frame, and the two-level search of :func:`_search` on it."""

    def __init__(self, frame: np.ndarray, k: int):
        self.frame, self.k = frame, k

    def search(self, tmpl, top_left, radius: int):
        """:func:`_search` of ``tmpl`` (a :class:`_Template`): at full resolution when
        ``k == 1``; else on ``k x k`` block means of the window's part of the frame, then
        within ``k`` px of the coarse peak at full resolution (the coarse window's edge
        decides ``on_edge``)."""
        k = self.k
        if k == 1:
            return _search(self.frame, tmpl.z, tmpl.norm, top_left, radius)
        hf, wf = self.frame.shape
        h, w = tmpl.z.shape
        pr, pc = int(round(top_left[0])), int(round(top_left[1]))
        # the window's part of the frame, k px wider each side, on the blocks' grid: the
        # coarse window fits inside it except where the frame's own edge cuts it
        r_lo, c_lo = max(0, (pr - radius - k) // k * k), max(0, (pc - radius - k) // k * k)
        r_hi, c_hi = min(hf, pr + radius + h + 2 * k), min(wf, pc + radius + w + 2 * k)
        coarse = _block_mean(self.frame[r_lo:r_hi, c_lo:c_hi], k)
        hit = _search(coarse, tmpl.zc, tmpl.normc, ((top_left[0] - r_lo) / k,
                                                    (top_left[1] - c_lo) / k),
                      int(math.ceil(radius / k)))
        if hit is None:
            return None
        fine = _search(self.frame, tmpl.z, tmpl.norm, (r_lo + hit[1] * k, c_lo + hit[2] * k), k)
        if fine is None:
            return None
        return fine[0], fine[1], fine[2], hit[3]


class _Template:
    """A template zero-meaned, with its norm, at full resolution and on ``k x k`` blocks."""

    def __init__(self, patch: np.ndarray, k: int):
        self.z, self.norm = _zero_mean(patch)
        self.zc, self.normc = _zero_mean(_block_mean(patch, k)) if k > 1 else (None, None)


def follow_box(frames, box, *, min_score: float = MIN_SCORE, margin: int | None = None,
               adapt: float = 0.1, max_radius: int | None = None,
               progress: bool = False) -> BoxTrack:
    """Follow the object boxed in frame 0 through ``frames`` by its appearance.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W), uint8 or float
        Grey frames (after any ``--rotate``).
    box : (float, float, float, float)
        ``(col, row, width, height)`` of the object in frame 0, px (:func:`check_box`).
    min_score : float
        ZNCC under which a frame's best match is "not seen" (:data:`MIN_SCORE`).
    margin : int, optional
        Search radius around the constant-velocity prediction, px; default a quarter of the
        box's larger side, at least 6 px. While the object is not seen the radius grows by
        ``margin`` a frame, up to ``max_radius``.
    adapt : float
        Weight of each new patch in the adapted template (0: the first template only).
    max_radius : int, optional
        Largest search radius, px; default twice the box's larger side.
    progress : bool
        A tqdm bar.

    Returns
    -------
    BoxTrack
        Centres in continuous pixel coordinates, NaN where not seen.
    """
    fr = np.asarray(frames)
    if fr.ndim != 3 or fr.shape[0] < 1:
        raise ValueError(f"frames: expected a (T, H, W) array, got shape {fr.shape}")
    if not 0.0 <= float(adapt) < 1.0:
        raise ValueError(f"adapt: expected a weight in [0, 1), got {adapt!r}")
    c, r, w, h = check_box(box, fr.shape[1:])
    t_n = fr.shape[0]
    margin = int(margin) if margin is not None else max(6, int(math.ceil(max(w, h) / 4)))
    max_radius = int(max_radius) if max_radius is not None else max(margin, 2 * max(w, h))
    blocks = max(1, min(w, h) // COARSE_SIDE)  # the coarse level's block side
    anchor = fr[0, r:r + h, c:c + w].astype(np.float64)
    az, anorm = _zero_mean(anchor)
    if anorm < 1e-6 * math.sqrt(w * h):
        raise ValueError("object_box: the box holds no texture (one grey level): nothing to "
                         "follow; box the object itself")
    tmpl = anchor.copy()
    tl = np.full((t_n, 2), np.nan)  # top-left (row, col) where seen
    score = np.full(t_n, np.nan)
    tl[0], score[0] = (r, c), 1.0
    last = [0]  # frames the object was last seen in (the latest two)
    cur = None  # the adapted template, prepared for the search
    from tqdm.auto import tqdm

    for t in tqdm(range(1, t_n), desc="box", unit="frame", leave=False, disable=not progress):
        k = last[-1]
        vel = (tl[k] - tl[last[-2]]) / (k - last[-2]) if len(last) > 1 else np.zeros(2)
        lost = t - k - 1
        pred = tl[k] + vel * (t - k)
        radius = min(margin * (1 + lost), max_radius)
        if len(last) < 2:
            # no velocity yet, so no prediction: twice the window (a 38 px ball falling from
            # the first frame left a quarter side's window at once, and a patch of the
            # background then matched it at 0.56-0.77)
            radius = min(2 * radius, max_radius)
        if cur is None:
            cur = _Template(tmpl, blocks)
        pyr = _Pyramid(fr[t], blocks)
        hit = pyr.search(cur, pred, radius)
        if hit is not None and hit[3] and radius < max_radius:
            # the peak at the window's edge: the object may be beyond it (a jolt); look wider
            radius = min(3 * radius, max_radius)
            hit = pyr.search(cur, pred, radius)
        if hit is None:
            continue
        s, pr, pc, edge = hit
        score[t] = s
        if s < min_score or edge:
            continue  # a weak match, or one whose peak may lie beyond the widest window
        # the anchor, a few pixels around: drift-free where it still matches
        ref = _search(fr[t], az, anorm, (pr, pc), 2)
        agree = ref is not None and ref[0] >= min_score and not ref[3] \
            and math.hypot(ref[1] - pr, ref[2] - pc) <= 1.0
        if agree:
            pr, pc = ref[1], ref[2]
        tl[t] = (pr, pc)
        last = [last[-1], t]
        if agree and adapt > 0 and s >= ADAPT_SCORE:
            ir, ic = int(round(pr)), int(round(pc))
            tmpl = (1.0 - adapt) * tmpl + adapt * fr[t, ir:ir + h, ic:ic + w]
            cur = None  # re-made (zero mean, norm, blocks) when next needed
    # continuous coordinates of the box's centre: its top-left pixel's corner plus half a side
    centres = tl[:, ::-1] + np.array([w / 2.0, h / 2.0])
    return BoxTrack(centres=centres, score=score, box=(c, r, w, h))
