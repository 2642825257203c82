"""A shaded, lit ball on a grey wall, for the tracking tests (not a test module itself).

The ball is a Lambertian sphere lit by one distant light from above and slightly to the left,
with an ambient term; pixels are averaged over ``ss x ss`` sub-pixel samples (anti-aliasing,
as a camera integrates over its pixels).
"""

from __future__ import annotations

import numpy as np

#: light direction (x right, y up, z towards the camera): above, a little to the left, in front
LIGHT = np.array([-0.35, 1.0, 0.45]) / np.linalg.norm([-0.35, 1.0, 0.45])


def shaded_frames(centres, radius, size, *, wall=215.0, ambient=25.0, gain=170.0, noise=2.0,
                  ss=8, seed=0) -> np.ndarray:
    """Frames of a shaded ball at sub-pixel ``centres`` on a uniform grey wall.

    Parameters
    ----------
    centres : ndarray, shape (T, 2)
        Continuous ``(col, row)`` of the ball's centre (pixel ``[i, j]``'s centre is at
        ``(j + 0.5, i + 0.5)``).
    radius : float
        Ball radius, px.
    size : (int, int)
        ``(H, W)``.
    wall : float
        The wall's grey level.
    ambient, gain : float
        The ball's grey is ``ambient + gain * max(0, n . LIGHT)`` (n: the sphere's normal).
    noise : float
        Standard deviation of Gaussian pixel noise, grey levels.
    ss : int
        Sub-pixel samples per pixel side.
    seed : int

    Returns
    -------
    ndarray, shape (T, H, W), uint8
    """
    h, w = size
    cen = np.asarray(centres, dtype=np.float64)
    sub = (np.arange(ss) + 0.5) / ss
    xs = (np.arange(w)[:, None] + sub[None, :]).ravel()  # (W*ss,)
    ys = (np.arange(h)[:, None] + sub[None, :]).ravel()  # (H*ss,)
    rng = np.random.default_rng(seed)
    out = np.empty((len(cen), h, w), dtype=np.uint8)
    for t, (c, r) in enumerate(cen):
        nx = (xs[None, :] - c) / radius
        ny = -(ys[:, None] - r) / radius  # up is minus rows
        rho2 = nx**2 + ny**2
        inside = rho2 < 1.0
        nz = np.sqrt(np.clip(1.0 - rho2, 0.0, None))
        lam = np.clip(nx * LIGHT[0] + ny * LIGHT[1] + nz * LIGHT[2], 0.0, None)
        img = np.where(inside, ambient + gain * lam, wall)
        img = img.reshape(h, ss, w, ss).mean(axis=(1, 3))
        img += noise * rng.standard_normal(img.shape)
        out[t] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return out


def path(n, radius, size, seed=0) -> np.ndarray:
    """``n`` sub-pixel ball centres ``(col, row)`` along a smooth path over the frame (left to
    right, up and down), the ball fully in view; ``seed`` shifts the path by a random sub-pixel
    amount and phase."""
    h, w = size
    rng = np.random.default_rng(seed)
    m = radius + 1.5
    s = np.linspace(0.0, 1.0, n)
    ph = rng.uniform(0, 2 * np.pi)
    col = m + rng.uniform(0, 1) + (w - 2 * m - 1) * s
    row = h / 2 + rng.uniform(-0.5, 0.5) + (h / 2 - m - 0.5) * np.sin(2.5 * np.pi * s + ph)
    return np.stack([col, row], axis=-1)
