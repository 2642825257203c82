"""Two pucks on a track between two walls, colliding: the ``collision`` system.

Physics (the design, ``shared/design.md``, section Systems): two pucks of radius ``R = 0.25`` m slide on
a track from ``x = 0`` to ``x = TRACK = 10`` m with a wall at each end, seen side on. State
``[x1, v1, x2, v2]`` (centres, ``x1 < x2``); the tracked points are ``(x1, R)`` and ``(x2, R)``
(K = 2, in that order). Parameters ``theta = [lq, eb, mu, ew]``:

* ``lq = log2(m2 / m1)``, ``m1 = 1``: the mass ratio;
* ``eb``: restitution between the pucks; ``ew``: restitution at the walls;
* ``mu``: Coulomb friction, a deceleration ``mu`` (m/s^2) of each puck against its velocity; a
  puck whose velocity reaches 0 (an exact event) stays stopped until the other puck hits it.

Contacts, all at their exact times: puck-puck when ``x2 - x1 = 2R`` while approaching,
``v1' = (v1 + m2 v2 + m2 eb (v2 - v1)) / (1 + m2)``,
``v2' = (v1 + m2 v2 + eb (v1 - v2)) / (1 + m2)``; puck 1 at ``x1 = R`` moving left
``v1 <- -ew v1``; puck 2 at ``x2 = TRACK - R`` moving right ``v2 <- -ew v2``.

The simulator is exact, not integrated: between events each puck moves with constant
deceleration, ``x(t) = x + v t - mu sign(v) t^2 / 2``, so within a frame the kernel computes the
earliest event time in closed form among {puck 1 stops, puck 2 stops, puck-puck contact (the
smaller root of the quadratic ``gap(t) = 0`` while approaching), puck 1 at its wall, puck 2 at
its wall}, moves both pucks there exactly, applies that one event and repeats until the frame's
time is used up. Simultaneous events are applied one per pass in a fixed order (pucks, wall 1,
wall 2, stop 1, stop 2), the later ones found again at zero time. Roots are taken in the
cancellation-free form ``t = 2 d / (s + sqrt(s^2 - 2 a d))``. Positions are therefore exact to
rounding and do not depend on ``dt``. One scalar kernel per trajectory, compiled by numba and
cached on disk. The JAX twin (:mod:`sysid_bench.core.systems.collision_jax`) makes the same passes,
a fixed number per frame, masked.

Sequences of contacts: with ``eb, ew < 1`` the light puck can be squeezed between a wall and the
heavy one and bounce back and forth; if both touch the wall at once the sequence is
instantaneous. Over the prior (``|lq| <= 2``, ``eb >= 0.5``, ``ew >= 0.6``) such a sequence has at
most 9 contacts and over the :attr:`Collision.envelope` at most 15 (a scan of the instantaneous
pair/wall map over a dense grid of mass ratios, restitutions and incoming velocities), while
beyond it (e.g. ``lq = 3`` with restitutions of 0.5) it becomes an *inelastic collapse* with
infinitely many contacts, a physics this simulator does not model: the envelope stops there. A
trajectory needing more than :data:`MAX_EVENTS` events in one frame raises ``RuntimeError``. Over
200,000 trajectories from the prior and 100,000 across the envelope no frame had more than 5
events.

Identifiability: the mass ratio ``lq`` enters only through the momentum exchange at a puck-puck
contact, and the restitutions only through their contacts: a video before the first contact says
nothing about them (only ``mu``, from the decelerations, is seen from the first frames); a contact
with a stopped puck, or a wall bounce, shows them sharply.

Video: black background, puck 1 white (grey :data:`LEVEL1` = 255) drawn over puck 2 grey
(:data:`LEVEL2` = 130). The default view is the whole track in x, ``(0, 10, -0.375, 0.875)``,
in 16 x 128 pixels: 12.8 px/m both ways (square pixels, so the discs are round), a puck radius
of 3.2 px, the puck centres' row at exactly 8.0 (the line between rows 7 and 8); 1 px is
7.8 cm. Rendered and tracked back (:meth:`Collision._track`), 20 random prior videos of 200
frames came back within 0.02 px (RMS 0.011 px), touching pucks included, and within 0.09 px
(RMS 0.021 px) with blur 0.5 and pixel noise 8: the 1 px contract holds with a wide margin, and
a narrower strip would only crop the pucks.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sysid_bench.core._validate import (
    as_float_array,
    check_positive_float,
    check_positive_int,
    check_seed,
)
from sysid_bench.core.systems import _draw
from sysid_bench.core.systems._base import System
from sysid_bench.core.systems._scene import CollisionScene

__all__ = ["Collision", "R", "TRACK", "LEVEL1", "LEVEL2", "MAX_EVENTS"]

#: Puck radius, m.
R = 0.25
#: Track length, m (walls at 0 and TRACK).
TRACK = 10.0
#: Where the centres touch the walls.
XL, XR = R, TRACK - R
#: Grey levels of puck 1 (drawn on top) and puck 2.
LEVEL1, LEVEL2 = 255.0, 130.0
#: Events one trajectory may have in one frame before ``simulate`` gives up (RuntimeError).
MAX_EVENTS = 64
#: Largest speed ``simulate`` accepts in ``state0``, m/s.
V_MAX = 20.0
#: Slack on the initial gap ``x2 - x1 >= 2R`` (states read back from a simulation may touch to
#: within rounding).
GAP_SLACK = 1e-9

#: Compiled once per machine (numba's on-disk cache); error_model="numpy": x/0 gives inf.
_njit = numba.njit(cache=True, nogil=True, error_model="numpy")


# --------------------------------------------------------------------------------------------
# the kernel (scalar, one trajectory at a time); collision_jax mirrors it operation for operation
@_njit
def _sign(v):
    return 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)


@_njit
def _event_times(x1, v1, x2, v2, mu, xl, xr, gap):
    """Times from now of (contact, wall 1, wall 2, stop 1, stop 2); inf where none. ``xl``, ``xr``
    are where the centres touch the walls, ``gap`` the centres' distance at contact (the
    design's XL, XR and 2R; other values from a scene)."""
    inf = np.inf
    # puck-puck: gap(t) = g - s t + c t^2 / 2 with closing speed s and c = a2 - a1
    g = max(x2 - x1 - gap, 0.0)
    s = v1 - v2
    c = mu * (_sign(v1) - _sign(v2))
    disc = s * s - 2.0 * c * g
    tp = 2.0 * g / (s + math.sqrt(disc)) if (s > 0.0 and disc >= 0.0) else inf
    # walls: distance d covered at speed |v| decelerating by mu
    d1 = max(x1 - xl, 0.0)
    disc1 = v1 * v1 - 2.0 * mu * d1
    tw1 = 2.0 * d1 / (-v1 + math.sqrt(disc1)) if (v1 < 0.0 and disc1 >= 0.0) else inf
    d2 = max(xr - x2, 0.0)
    disc2 = v2 * v2 - 2.0 * mu * d2
    tw2 = 2.0 * d2 / (v2 + math.sqrt(disc2)) if (v2 > 0.0 and disc2 >= 0.0) else inf
    ts1 = abs(v1) / mu if (v1 != 0.0 and mu > 0.0) else inf
    ts2 = abs(v2) / mu if (v2 != 0.0 and mu > 0.0) else inf
    return tp, tw1, tw2, ts1, ts2


@_njit
def _move(x, v, t, mu):
    """Position and velocity after ``t`` s of deceleration ``mu`` (t never past the stop)."""
    sg = _sign(v)
    sp = abs(v)
    return x + sg * t * (sp - 0.5 * mu * t), sg * max(sp - mu * t, 0.0)


@_njit
def _advance_frame(x1, v1, x2, v2, lq, eb, mu, ew, dt, xl, xr, gap):
    """One frame of exact event stepping; returns the state and the number of passes made
    (MAX_EVENTS + 1 when the frame was not finished)."""
    # fast path: no stop within the frame and both pucks clear of the walls and of each other at
    # its end; within such a frame positions are monotone and the closing speed keeps its sign,
    # so no contact happened in between (the pass below would give the same numbers)
    if (v1 == 0.0 or abs(v1) > mu * dt) and (v2 == 0.0 or abs(v2) > mu * dt):
        y1, u1 = _move(x1, v1, dt, mu)
        y2, u2 = _move(x2, v2, dt, mu)
        if y1 > xl and y2 < xr and y2 - y1 > gap:
            return y1, u1, y2, u2, 1
    rem = dt
    n = 0
    while rem > 0.0:
        if n > MAX_EVENTS:
            return x1, v1, x2, v2, n
        tp, tw1, tw2, ts1, ts2 = _event_times(x1, v1, x2, v2, mu, xl, xr, gap)
        te = min(min(min(tp, tw1), min(tw2, ts1)), ts2)
        if te < rem:
            x1, v1 = _move(x1, v1, te, mu)
            x2, v2 = _move(x2, v2, te, mu)
            if tp <= te:
                m2 = 2.0**lq
                u1 = (v1 + m2 * v2 + m2 * eb * (v2 - v1)) / (1.0 + m2)
                u2 = (v1 + m2 * v2 + eb * (v1 - v2)) / (1.0 + m2)
                v1 = u1
                v2 = u2
            elif tw1 <= te:
                x1 = xl
                v1 = -ew * v1
            elif tw2 <= te:
                x2 = xr
                v2 = -ew * v2
            elif ts1 <= te:
                v1 = 0.0
            else:
                v2 = 0.0
            rem = rem - te
        else:
            x1, v1 = _move(x1, v1, rem, mu)
            x2, v2 = _move(x2, v2, rem, mu)
            rem = 0.0
        n += 1
    return x1, v1, x2, v2, n


@_njit
def _simulate_kernel(th, s0, dt, out):
    """th (B, T, 4), s0 (B, 4) -> out (B, T, 4) on the design's track; returns the first
    trajectory that needed more than MAX_EVENTS events in a frame, or -1."""
    return _simulate_kernel_scene(th, s0, dt, out, XL, XR, 2.0 * R)


@_njit
def _simulate_kernel_scene(th, s0, dt, out, xl, xr, gap):
    """:func:`_simulate_kernel` with the walls' contact positions ``xl``, ``xr`` and the contact
    distance ``gap`` as arguments (a scene's)."""
    nb, nt = out.shape[0], out.shape[1]
    for b in range(nb):
        x1, v1, x2, v2 = s0[b, 0], s0[b, 1], s0[b, 2], s0[b, 3]
        out[b, 0, 0] = x1
        out[b, 0, 1] = v1
        out[b, 0, 2] = x2
        out[b, 0, 3] = v2
        for t in range(1, nt):
            x1, v1, x2, v2, n = _advance_frame(
                x1, v1, x2, v2, th[b, t - 1, 0], th[b, t - 1, 1], th[b, t - 1, 2],
                th[b, t - 1, 3], dt, xl, xr, gap,
            )
            if n > MAX_EVENTS:
                return b
            out[b, t, 0] = x1
            out[b, t, 1] = v1
            out[b, t, 2] = x2
            out[b, t, 3] = v2
    return -1


# --------------------------------------------------------------------------------------------
# the tracker's pieces, on all frames at once: img (T, H, W), centres (T, 2) as (col, row)
def _coverage(centres, radius, size) -> np.ndarray:
    """Unblurred anti-aliased coverage (T, H, W) of one disc per frame; 0 where the centre is
    NaN."""
    c = np.nan_to_num(np.asarray(centres, dtype=np.float64), nan=-1e6)
    return _draw.draw_discs(c[:, None], radius, size).astype(np.float64)


def _dist2(centres, jc, ic):
    """Squared pixel distances (T, H, W) of every pixel centre to each frame's centre."""
    return ((jc[None, None, :] - centres[:, 0, None, None]) ** 2
            + (ic[None, :, None] - centres[:, 1, None, None]) ** 2)


def _blob(mask, jc, ic, reach):
    """Centre (T, 2) and count (T,) of the pixels of ``mask`` (T, H, W) in the band of columns
    ``reach`` either side of where they are densest; NaN where fewer than 90% of the mask's
    pixels are there (scattered pixels: noise, not a puck) or there are none."""
    t, _, w = mask.shape
    cols = mask.sum(axis=1).astype(np.float64)  # (T, W)
    k = int(math.floor(reach))
    cs = np.concatenate([np.zeros((t, 1)), np.cumsum(cols, axis=1)], axis=1)
    lo = np.clip(np.arange(w) - k, 0, w)
    hi = np.clip(np.arange(w) + k + 1, 0, w)
    band = cs[:, hi] - cs[:, lo]  # pixels within k columns of each column
    j0 = np.argmax(band, axis=1)
    inband = np.abs(jc[None, :] - jc[j0][:, None]) <= k  # (T, W)
    m = mask & inband[:, None, :]
    n = m.sum(axis=(1, 2)).astype(np.float64)
    total = mask.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.stack([m.sum(axis=1) @ jc / n, m.sum(axis=2) @ ic / n], axis=-1)
    c[(n == 0) | (n < 0.9 * total)] = np.nan
    return c, n


def _weighted_centre(wgt, jc, ic, centres, reach):
    """Centroid (T, 2) of weights ``wgt`` (T, H, W) within ``reach`` of each centre, and the
    weights' total (T,); NaN where the centre is NaN or the total is 0."""
    ww = np.where(_dist2(centres, jc, ic) <= reach * reach, wgt, 0.0)
    mass = ww.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.stack([ww.sum(axis=1) @ jc / mass, ww.sum(axis=2) @ ic / mass], axis=-1)
    c[~(mass > 0)] = np.nan
    return c, mass


def _soft(c):
    """Coverage estimate to a centroid weight: pixel noise (a few % of a level) counts nothing;
    a monotone map keeps a symmetric disc's centroid where it is."""
    return np.clip((c - 0.15) / 0.85, 0.0, 1.0)


class Collision(System):
    """Two pucks on a 10 m track with walls: parameters lq, eb, mu, ew; state [x1, v1, x2, v2];
    K = 2 (puck 1, puck 2).

    See the module docstring for the physics, the exact event-driven simulator, the envelope,
    what a video identifies, and the view.
    """

    name = "collision"
    params = ("lq", "eb", "mu", "ew")
    prior = {"lq": (-2.0, 2.0), "eb": (0.5, 1.0), "mu": (0.0, 0.3), "ew": (0.6, 1.0)}
    #: experiment 4's simplified physics: track friction and wall restitution held in training
    simplified_params = ("mu", "ew")
    #: wider than the prior where the physics stays finite: more friction, mass ratios up to
    #: 2^2.5, wall restitution down to 0.5 (lower restitutions or larger ratios reach the
    #: inelastic collapse, see the module docstring)
    envelope = {"lq": (-2.5, 2.5), "eb": (0.5, 1.0), "mu": (0.0, 1.0), "ew": (0.5, 1.0)}
    state = ("x1", "v1", "x2", "v2")
    state_bounds = {
        "x1": (XL, XR - 2.0 * R),
        "v1": (-V_MAX, V_MAX),
        "x2": (XL + 2.0 * R, XR),
        "v2": (-V_MAX, V_MAX),
    }
    n_points = 2
    extent = (0.0, TRACK, -0.375, 0.875)
    size = (16, 128)
    noise_m = 0.01
    jax_twin = "sysid_bench.core.systems.collision_jax:simulate"
    scene_type = CollisionScene
    #: below 6 x 48 the pucks (0.5 m in 10 m) are under 2.4 px and the tracker loses them
    min_size = (6, 48)

    @staticmethod
    def _contacts(scene) -> tuple[float, float, float]:
        """(xl, xr, gap): where the centres touch the walls, and each other, in ``scene``."""
        (a, b), (r1, r2) = scene.ends, scene.half_sizes
        return a + r1, b - r2, r1 + r2

    def state_bounds_for(self, scene):
        if scene == self.default_scene:
            return self.state_bounds
        xl, xr, gap = self._contacts(scene)
        return dict(self.state_bounds, x1=(xl, xr - gap), x2=(xl + gap, xr))

    # ------------------------------------------------------------------------------------------
    def _check_state0_extra(self, state0, name, scene=None):
        contact = 2.0 * R if scene is None else self._contacts(scene)[2]
        gap = state0[:, 2] - state0[:, 0]
        if gap.size and gap.min() < contact - GAP_SLACK:
            i = int(np.argmin(gap))
            raise ValueError(
                f"{name}: expected x2 - x1 >= r1 + r2 = {contact:g} m (the pucks do not overlap) "
                f"for the {self.name} system, got x2 - x1 = {gap[i]:g} in row {i}"
            )

    def _simulate(self, theta, state0, n_frames, dt, scene=None):
        out = np.empty((state0.shape[0], n_frames, 4), dtype=np.float64)
        if scene is None or scene == self.default_scene:
            bad = _simulate_kernel(theta, state0, float(dt), out)
        else:
            bad = _simulate_kernel_scene(theta, state0, float(dt), out, *self._contacts(scene))
        if bad >= 0:
            raise RuntimeError(
                f"{self.name}: trajectory {bad} needs more than {MAX_EVENTS} contacts in one frame "
                f"(theta={theta[bad, 0].tolist()}): an inelastic collapse outside this simulator"
            )
        return out

    def sample_state0(self, n, rng=None, theta=None):
        """Initial states (n, 4): x1 in [1, 4], v1 in [1, 4], x2 in [6, 9], v2 in [-4, -1]
        (uniform, independent of ``theta``, which is accepted and ignored)."""
        n = check_positive_int(n, "n")
        rng = check_seed(rng)
        u = rng.random((n, 4))
        lo = np.array([1.0, 1.0, 6.0, -4.0])
        return lo + 3.0 * u

    def _observe(self, states, theta, scene=None):
        b, t = states.shape[:2]
        out = np.empty((b, t, 2, 2), dtype=np.float64)
        out[..., 0, 0] = states[..., 0]
        out[..., 1, 0] = states[..., 2]
        # each tracked point is a puck's centre, its half-size above the track
        out[..., :, 1] = R if scene is None else np.asarray(scene.half_sizes)
        return out

    # ------------------------------------------------------------------------------------------
    def _render(self, points, states, theta, size, **nuisance):
        nz = _draw.check_nuisance(nuisance)
        view = _draw.View(self.extent, size)
        radius = R * view.px_per_m[0]
        sub = view.to_pixels(_draw.blur_positions(points, nz["dt"], nz["blur"]))  # (B,T,S,K,2)
        b, t = points.shape[:2]
        img = np.empty((b, t) + tuple(size), dtype=np.float32)
        for i in range(b):
            c1 = _draw.draw_discs(sub[i, :, :, 0], radius, size)
            c2 = _draw.draw_discs(sub[i, :, :, 1], radius, size)
            # puck 1 drawn over puck 2 (they overlap only in the anti-aliased rim at contact)
            img[i] = np.float32(LEVEL1) * c1 + np.float32(LEVEL2) * c2 * (1.0 - c1)
        return _draw.finish(img, occlusion=nz["occlusion"], drop=nz["drop"],
                            noise=nz["noise"], seed=nz["seed"])

    def _track(self, frames):
        """Both pucks in each frame, by their grey levels.

        Per frame: puck 1 from its core (pixels above the levels' midpoint, which only puck 1
        reaches); puck 2 from the mid-grey pixels farther than its rim from puck 1; then three
        rounds of refinement in which each puck's coverage is read from the image with the other
        puck's rendered disc taken out (``img = L1 c1 + L2 c2 (1 - c1)`` solved for one
        coverage given the other), and its centre is the centroid of that coverage within a
        window around it. So the touching discs' shared rim pixels are split between them as the
        renderer mixed them, and each centre stays within a tenth of a pixel on clean frames.
        A puck is unseen (NaN) when its core is missing, scattered (noise), far too large (a
        white frame) or its coverage mass is not that of one disc.
        """
        img = np.asarray(frames, dtype=np.float64)
        t, h, w = img.shape
        size = (h, w)
        view = _draw.View(self.extent, size)
        radius = R * view.px_per_m[0]
        jc = np.arange(w, dtype=np.float64) + 0.5
        ic = np.arange(h, dtype=np.float64) + 0.5
        area = math.pi * radius * radius
        reach = radius + 2.5
        mid = 0.5 * (LEVEL1 + LEVEL2)
        # first estimates: puck 1's core, then the mid-grey pixels beyond puck 1's rim
        p1, n1 = _blob(img >= mid, jc, ic, reach)
        p1[~((n1 >= 0.3 * area) & (n1 <= 2.0 * area))] = np.nan
        far = ~(_dist2(p1, jc, ic) <= (radius + 2.0) ** 2)  # True where p1 is NaN
        p2, n2 = _blob((img >= 0.5 * LEVEL2) & (img < mid) & far, jc, ic, reach)
        p2[~((n2 >= 0.25 * area) & (n2 <= 2.0 * area))] = np.nan
        m1 = m2 = np.zeros(t)
        for _ in range(3):
            cov2 = _coverage(p2, radius, size)
            c1 = (img - LEVEL2 * cov2) / (LEVEL1 - LEVEL2 * cov2)
            q, m1 = _weighted_centre(_soft(c1), jc, ic, p1, reach)
            p1 = np.where(np.isfinite(q), q, p1)
            cov1 = _coverage(p1, radius, size)
            # where puck 1 covers most of a pixel the division would amplify its rounding and
            # the image's; puck 2 covers under half of such a pixel anyway (discs do not overlap)
            c2 = np.where(cov1 < 0.5, (img - LEVEL1 * cov1)
                          / (LEVEL2 * np.maximum(1.0 - cov1, 0.5)), 0.0)
            q, m2 = _weighted_centre(_soft(c2), jc, ic, p2, reach)
            p2 = np.where(np.isfinite(q), q, p2)
        # the soft weights of a whole disc sum to about its area; a puck half hidden or a blob
        # of another size is not this puck
        p1[~((m1 >= 0.6 * area) & (m1 <= 1.6 * area))] = np.nan
        p2[~((m2 >= 0.6 * area) & (m2 <= 1.6 * area))] = np.nan
        return view.to_metres(np.stack([p1, p2], axis=1))

    # ------------------------------------------------------------------------------------------
    def state0_from_track(self, positions, dt=0.05):
        """Rough initial state from the first frames of a track, before any contact.

        The pucks start at least 1.5 m apart closing at most at 8 m/s, so nothing happens in the
        first 0.18 s: a straight line through each puck's seen positions there gives its
        position and velocity at frame 0 (friction bends it by at most 5 mm). A puck seen in
        fewer than two of those frames falls back on the middle of the initial-state ranges.

        Parameters
        ----------
        positions : ndarray, shape (T, 2, 2)
            Observed points (metres), NaN where unseen.
        dt : float

        Returns
        -------
        state0 : ndarray, shape (4,)
        scale : ndarray, shape (4,)
            Half-widths of a box around ``state0`` that holds the true one with high
            probability (position noise of a few cm).
        """
        pos = as_float_array(positions, "positions", ndim=3, allow_nan=True)
        if pos.shape[1:] != (2, 2):
            raise ValueError(f"positions: expected (T, 2, 2) for the {self.name} system, got "
                             f"shape {pos.shape}")
        dt = check_positive_float(dt, "dt")
        t = np.arange(pos.shape[0]) * dt
        early = t <= 0.18
        fallback = ((2.5, 1.5, 2.5, 1.5), (7.5, 1.5, -2.5, 1.5))
        s0 = np.empty(4)
        scale = np.empty(4)
        for j in range(2):
            x = pos[early, j, 0]
            tt = t[early]
            ok = np.isfinite(x)
            if ok.sum() >= 2:
                a, b = np.polyfit(tt[ok], x[ok], 1)[::-1]
                spread = tt[ok].std()
                s0[2 * j], s0[2 * j + 1] = a, b
                scale[2 * j] = 0.05
                scale[2 * j + 1] = min(0.3 + 0.05 / max(spread, 1e-3), 3.0)
            else:
                x0, hx, v0, hv = fallback[j]
                s0[2 * j] = x[ok][0] if ok.any() else x0
                scale[2 * j] = 0.05 if ok.any() else hx
                s0[2 * j + 1], scale[2 * j + 1] = v0, hv
        lo = np.array([self.state_bounds[q][0] for q in self.state])
        hi = np.array([self.state_bounds[q][1] for q in self.state])
        s0 = np.clip(s0, lo, hi)
        if s0[2] - s0[0] < 2 * R:  # keep the estimate a valid state: pucks apart
            mid = 0.5 * (s0[0] + s0[2])
            s0[0], s0[2] = mid - R, mid + R
        return s0, scale

    # ------------------------------------------------------------------------------------------
    def reference(self, theta, state0, n_frames=200, dt=0.05):
        """Event-driven ``solve_ivp`` (DOP853, rtol = atol = 1e-12) of one trajectory.

        The right-hand side is ``x' = v, v' = -mu sign(v)`` with each puck's sign fixed per
        segment (0 once stopped); terminal events: each moving puck's velocity reaching 0,
        the gap closing to 0, each puck reaching its wall. At each event the rule is applied and
        the integration restarted; contacts due at the restart time itself (touching pucks
        against a wall) are applied first, one at a time, as the design's rules say.

        Parameters
        ----------
        theta : ndarray, shape (4,)
        state0 : ndarray, shape (4,)
        n_frames : int
        dt : float

        Returns
        -------
        ndarray, shape (n_frames, 4)
        """
        from scipy.integrate import solve_ivp

        n_frames, dt = self._check_frames_dt(n_frames, dt)
        th = self.check_theta(np.asarray(theta, dtype=np.float64)[None])[0]
        y = self.check_state0(np.asarray(state0, dtype=np.float64)[None])[0].copy()
        lq, eb, mu, ew = th
        m2 = 2.0**lq
        times = np.arange(n_frames) * dt
        t_end = times[-1]
        out = np.empty((n_frames, 4))
        out[0] = y
        filled = 1
        t = 0.0
        tol = 1e-10

        def contact(y):
            v1, v2 = y[1], y[3]
            y[1] = (v1 + m2 * v2 + m2 * eb * (v2 - v1)) / (1.0 + m2)
            y[3] = (v1 + m2 * v2 + eb * (v1 - v2)) / (1.0 + m2)

        for _ in range(100_000):
            # contacts due now (after an event the other bodies may already touch)
            for _ in range(1000):
                if y[2] - y[0] - 2 * R <= tol and y[1] > y[3]:
                    contact(y)
                elif y[0] - XL <= tol and y[1] < 0:
                    y[0], y[1] = XL, -ew * y[1]
                elif XR - y[2] <= tol and y[3] > 0:
                    y[2], y[3] = XR, -ew * y[3]
                else:
                    break
            if t >= t_end or filled >= n_frames:
                break
            a1 = -mu * np.sign(y[1])
            a2 = -mu * np.sign(y[3])

            def rhs(_t, z, a1=a1, a2=a2):
                return np.array([z[1], a1, z[3], a2])

            def ev_gap(_t, z):
                return z[2] - z[0] - 2 * R

            def ev_w1(_t, z):
                return z[0] - XL

            def ev_w2(_t, z):
                return XR - z[2]

            def ev_s1(_t, z):
                return z[1]

            def ev_s2(_t, z):
                return z[3]

            events = [ev_gap, ev_w1, ev_w2, ev_s1, ev_s2]
            dirs = [-1, -1, -1, -np.sign(y[1]), -np.sign(y[3])]
            for f, d in zip(events, dirs):
                f.terminal = True
                f.direction = d
            active = [True, True, True, a1 != 0, a2 != 0]
            evs = [f for f, a in zip(events, active) if a]
            kinds = [k for k, a in enumerate(active) if a]
            t_eval = times[filled:]
            sol = solve_ivp(rhs, (t, t_end), y, method="DOP853", rtol=1e-12, atol=1e-12,
                            events=evs, t_eval=t_eval)
            n_new = len(sol.t)  # a list, not an array, when no t_eval point was reached
            if n_new:
                out[filled : filled + n_new] = np.asarray(sol.y).T
                filled += n_new
            if sol.status != 1:
                break
            hit = [i for i, te in enumerate(sol.t_events) if te.size]
            i = min(hit, key=lambda i: sol.t_events[i][0])
            t = float(sol.t_events[i][0])
            y = sol.y_events[i][0].copy()
            kind = kinds[i]
            if kind == 0:
                contact(y)
            elif kind == 1:
                y[0], y[1] = XL, -ew * y[1]
            elif kind == 2:
                y[2], y[3] = XR, -ew * y[3]
            else:
                y[2 * (kind - 3) + 1] = 0.0
        if filled < n_frames:  # the last segment ended at t_end on an event: hold the state
            out[filled:] = y
        return out
