"""Compiled masks of :func:`sysid_bench.core.tracking.ball_centre`'s region (bool arrays).

Each kernel gives the bits of the scipy calls it replaces (``ndimage.binary_erosion`` and
``binary_dilation`` with the 4-neighbour cross and ``border_value=0``, and the fill to
``scipy.spatial.ConvexHull``'s hull of the edge pixels) on a crop of a few hundred to a few
thousand pixels, where scipy's per-call overhead and qhull's set-up were most of the cost
(``tests/test_tracking_rule.py`` checks them against scipy on random masks).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _erode(mask, k):  # pragma: no cover - compiled
    """``ndimage.binary_erosion(mask, iterations=k)``: a pixel stays if every pixel within
    L1 distance ``k`` is inside the array and set (the cross applied ``k`` times)."""
    h, w = mask.shape
    cur = mask.copy()
    nxt = np.zeros((h, w), dtype=np.bool_)
    for _ in range(k):
        for i in range(h):
            for j in range(w):
                nxt[i, j] = (cur[i, j] and i > 0 and i < h - 1 and j > 0 and j < w - 1
                             and cur[i - 1, j] and cur[i + 1, j] and cur[i, j - 1]
                             and cur[i, j + 1])
        cur, nxt = nxt, cur
    return cur


@numba.njit(cache=True, nogil=True)
def _dilate(mask, k):  # pragma: no cover - compiled
    """``ndimage.binary_dilation(mask, iterations=k)``: set where a set pixel lies within
    L1 distance ``k`` (the cross applied ``k`` times, nothing from outside the array)."""
    h, w = mask.shape
    cur = mask.copy()
    nxt = np.zeros((h, w), dtype=np.bool_)
    for _ in range(k):
        for i in range(h):
            for j in range(w):
                nxt[i, j] = (cur[i, j] or (i > 0 and cur[i - 1, j])
                             or (i < h - 1 and cur[i + 1, j]) or (j > 0 and cur[i, j - 1])
                             or (j < w - 1 and cur[i, j + 1]))
        cur, nxt = nxt, cur
    return cur


@numba.njit(cache=True, nogil=True)
def _cross(o0, o1, a0, a1, b0, b1):  # pragma: no cover - compiled
    return (a0 - o0) * (b1 - o1) - (a1 - o1) * (b0 - o0)


@numba.njit(cache=True, nogil=True)
def hull_fill(mask):  # pragma: no cover - compiled
    """``mask`` with every pixel whose centre lies in (or on) the convex hull of its edge
    pixels (``mask & ~erosion``); ``mask`` itself when there are fewer than 3 or they lie
    on one line (qhull's flat simplex).

    The hull is Andrew's monotone chain on the integer (row, col) indices (collinear points
    dropped) and "inside or on" is the sign of integer cross products: exact, where qhull's
    float facets with a 1e-9 tolerance gave the same set on the clips' masks (an integer point
    off a facet through integer vertices lies at least 1 / (facet length) px from it)."""
    h, w = mask.shape
    edge = mask & ~_erode(mask, 1)
    n = 0
    for i in range(h):
        for j in range(w):
            if edge[i, j]:
                n += 1
    out = mask.copy()
    if n < 3:
        return out
    pr = np.empty(n, dtype=np.int64)  # row-major order: sorted by row, then column
    pc = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(h):
        for j in range(w):
            if edge[i, j]:
                pr[m] = i
                pc[m] = j
                m += 1
    hr = np.empty(2 * n, dtype=np.int64)
    hc = np.empty(2 * n, dtype=np.int64)
    k = 0
    for p in range(n):  # lower chain
        while k >= 2 and _cross(hr[k - 2], hc[k - 2], hr[k - 1], hc[k - 1], pr[p], pc[p]) <= 0:
            k -= 1
        hr[k] = pr[p]
        hc[k] = pc[p]
        k += 1
    lo = k + 1
    for p in range(n - 2, -1, -1):  # upper chain
        while k >= lo and _cross(hr[k - 2], hc[k - 2], hr[k - 1], hc[k - 1], pr[p], pc[p]) <= 0:
            k -= 1
        hr[k] = pr[p]
        hc[k] = pc[p]
        k += 1
    k -= 1  # the last point is the first
    if k < 3:  # all on a line: nothing to fill
        return out
    r0, r1 = pr.min(), pr.max()
    c0, c1 = pc.min(), pc.max()
    for i in range(r0, r1 + 1):
        for j in range(c0, c1 + 1):
            if out[i, j]:
                continue
            inside = True
            for e in range(k):  # counter-clockwise in (row, col): inside is on the left
                if _cross(hr[e], hc[e], hr[e + 1], hc[e + 1], i, j) < 0:
                    inside = False
                    break
            if inside:
                out[i, j] = True
    return out


@numba.njit(cache=True, nogil=True)
def region_masks(stand, rim_px):  # pragma: no cover - compiled
    """``ball_centre``'s masks from the pixels that stand out, shape (h, w) bool each:
    ``region`` (filled to the hull), ``inner`` (``rim_px`` eroded), ``rim`` (within ``rim_px``
    of the region's border, inside or out) and ``ring`` (the outer 3 px of the once-eroded
    region)."""
    region = hull_fill(stand)
    core = _erode(region, 1)
    inner = _erode(region, rim_px)
    rim = _dilate(region, rim_px) & ~inner
    ring = core & ~_erode(core, 3)
    return region, inner, rim, ring



@numba.njit(cache=True, nogil=True)
def keep_large_pieces(stand, min_size):  # pragma: no cover - compiled
    """``stand`` with only its 4-connected pieces of ``min_size`` pixels or more when it has
    more than one piece and one of them is that large; otherwise ``stand`` itself (a copy).

    ``ndimage.label``'s pieces (the cross), each found by a flood fill from its first pixel in
    row-major order, their sizes compared as ``np.bincount`` of the labels was."""
    h, w = stand.shape
    lab = np.zeros((h, w), dtype=np.int64)
    size = np.zeros(h * w + 1, dtype=np.int64)
    stack = np.empty(h * w, dtype=np.int64)
    n = 0
    for i0 in range(h):
        for j0 in range(w):
            if not stand[i0, j0] or lab[i0, j0]:
                continue
            n += 1
            lab[i0, j0] = n
            top = 0
            stack[0] = i0 * w + j0
            top = 1
            while top:
                top -= 1
                i, j = divmod(stack[top], w)
                size[n] += 1
                for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    a, b = i + di, j + dj
                    if 0 <= a < h and 0 <= b < w and stand[a, b] and not lab[a, b]:
                        lab[a, b] = n
                        stack[top] = a * w + b
                        top += 1
    out = stand.copy()
    if n <= 1:
        return out
    any_kept = False
    for k in range(1, n + 1):
        if size[k] >= min_size:
            any_kept = True
    if any_kept:
        for i in range(h):
            for j in range(w):
                out[i, j] = lab[i, j] > 0 and size[lab[i, j]] >= min_size
    return out
