"""Footage as a camera would film it, for the four systems, with its ground truth (issue 38, 5).

Our physics (:mod:`sysid_bench.core.systems`) simulated at a true size in a room-scale scene (a 7 cm
ball dropped from 1-1.8 m, a 0.5-1 m pendulum, a cart on a spring about 1-1.5 m long, two 10 cm
pucks on a 2 m track), drawn through a **pinhole camera** with NumPy:

- perspective: a point at depth ``Z`` in front of the camera lands ``f X / Z`` px from the image
  centre, so the ball, which also drifts towards or away from the camera, changes its apparent
  size and its floor contact row over the clip; the camera may be rolled a few degrees (tilt)
  and the file stored sideways (``rotate``: turned counter-clockwise, so ``--rotate`` undoes it);
- a textured wall (smooth noise, a lighting gradient, a vignette), clutter (posters, a shelf,
  a door frame, printed text), a wood-grain floor meeting the wall behind the motion;
- shaded objects: Lambert light from above left with a specular highlight on spheres, a
  gradient on the cart; a thin string, a low-contrast coil;
- a hand (palm, fingers and forearm): it holds the ball or the bob still before releasing it,
  or sweeps across the room for a second;
- motion blur: each frame is the mean of ``subframes`` renders over the open shutter;
- sensor noise, then H.264 through :func:`sysid_bench.core.footage.write_video` (30, 60 or 120
  frames/s; a slow-motion file may be stored at a lower container rate).

The MuJoCo renderer (:mod:`sysid_bench.core.mujoco_scene`) was not used: it needs an OpenGL library
(EGL or OSMesa) that a CI machine with pip packages lacks, and its pixels depend on the GL driver,
while this module's raw frames are the same bytes for the same seed on every machine.

Everything is seeded: :func:`film` with the same :class:`Shot` returns the same bytes of raw
frames. :func:`write_clip` writes ``<name>.mp4`` and ``<name>.json`` (the ground truth: theta,
the scene, the camera, the true positions and pixels per frame, and ``options``, what a user
would give ``sysid-bench identify``), each atomically.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from sysid_bench.core._io import atomic_write

__all__ = ["SYSTEMS", "FPS", "ROTATIONS", "Shot", "Footage", "film", "write_clip", "shots",
           "generate_set"]

#: the systems a camera films here
SYSTEMS = ("ball", "pendulum", "spring", "collision")
#: capture rates offered
FPS = (30, 60, 120)
#: how a file may be stored: turned this many degrees counter-clockwise (``--rotate`` undoes it)
ROTATIONS = (0, 90, 180, 270)
#: standard gravity, m/s^2 (what a camera on Earth films)
G = -9.81
_SKIN = np.array([0.87, 0.67, 0.55], dtype=np.float32)
#: light direction (towards the light) in the camera's frame: from above left, in front
_LIGHT = np.array([-0.45, 0.65, 0.62], dtype=np.float32) / np.float32(
    np.linalg.norm([-0.45, 0.65, 0.62]))


@dataclass(frozen=True)
class Shot:
    """One clip to film.

    Attributes
    ----------
    system : {"ball", "pendulum", "spring", "collision"}
    seed : int
        Seeds the truth (theta, start, scene), the camera's placement, the room and the noise.
    fps : int
        Capture rate, one of :data:`FPS`.
    duration_s : float
        Length of the clip, s (0.2 to 30).
    size : (int, int)
        ``(H, W)`` of the picture as filmed (even, 32 to 2160); stored ``(W, H)`` when
        ``rotate`` is 90 or 270.
    rotate : int
        Stored turned this many degrees counter-clockwise (a phone held sideways);
        ``sysid-bench identify --rotate`` with the same number turns it back.
    tilt_deg : float
        Roll of the camera, degrees (-10 to 10): the room's vertical leans in the picture.
    subframes : int
        Renders averaged per frame (1 = no motion blur; 1 to 16).
    exposure : float
        Fraction of the frame interval the shutter is open (0 to 1].
    hand : bool
        Draw the hand (holding and releasing the ball or the bob; a sweep for the others).
    stored_fps : float, optional
        Container rate when it differs from ``fps`` (a slow-motion file: captured at 120,
        played at 30); the user then gives ``--fps``.
    noise : float
        Sensor noise, grey levels (standard deviation, 0 to 20).
    crf : int
        H.264 quality of the written file (0 to 51).
    """

    system: str
    seed: int = 0
    fps: int = 30
    duration_s: float = 4.0
    size: tuple = (360, 640)
    rotate: int = 0
    tilt_deg: float = 0.0
    subframes: int = 4
    exposure: float = 0.5
    hand: bool = True
    stored_fps: float | None = None
    noise: float = 2.0
    crf: int = 20

    def __post_init__(self):
        if self.system not in SYSTEMS:
            raise ValueError(f"system: expected one of {', '.join(SYSTEMS)}, got {self.system!r}")
        for name in ("seed", "fps", "rotate", "subframes", "crf"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"{name}: expected an int, got {type(v).__name__} {v!r}")
        if self.seed < 0:
            raise ValueError(f"seed: expected an int >= 0, got {self.seed}")
        if self.fps not in FPS:
            raise ValueError(f"fps: expected one of {FPS} frames/s, got {self.fps}")
        if self.rotate not in ROTATIONS:
            raise ValueError(f"rotate: expected one of {ROTATIONS} (degrees counter-clockwise), "
                             f"got {self.rotate}")
        d = float(self.duration_s)
        if not (math.isfinite(d) and 0.2 <= d <= 30.0):
            raise ValueError(f"duration_s: expected 0.2 to 30 s, got {self.duration_s!r}")
        size = tuple(self.size)
        if (len(size) != 2 or not all(isinstance(v, (int, np.integer)) for v in size)
                or not all(32 <= v <= 2160 and v % 2 == 0 for v in size)):
            raise ValueError(f"size: expected (H, W), even ints from 32 to 2160, got {self.size!r}")
        if not (math.isfinite(float(self.tilt_deg)) and abs(float(self.tilt_deg)) <= 10.0):
            raise ValueError(f"tilt_deg: expected -10 to 10 degrees, got {self.tilt_deg!r}")
        if not 1 <= self.subframes <= 16:
            raise ValueError(f"subframes: expected 1 to 16, got {self.subframes}")
        if not (math.isfinite(float(self.exposure)) and 0.0 < float(self.exposure) <= 1.0):
            raise ValueError(f"exposure: expected a fraction in (0, 1], got {self.exposure!r}")
        if self.stored_fps is not None and not (math.isfinite(float(self.stored_fps))
                                                and 1.0 <= float(self.stored_fps) <= self.fps):
            raise ValueError(f"stored_fps: expected 1 to fps = {self.fps} frames/s, got "
                             f"{self.stored_fps!r}")
        if not (math.isfinite(float(self.noise)) and 0.0 <= float(self.noise) <= 20.0):
            raise ValueError(f"noise: expected 0 to 20 grey levels, got {self.noise!r}")
        if not 0 <= self.crf <= 51:
            raise ValueError(f"crf: expected 0 to 51, got {self.crf}")
        object.__setattr__(self, "size", (int(size[0]), int(size[1])))


@dataclass
class Footage:
    """A filmed clip and its truth.

    Attributes
    ----------
    frames : ndarray, shape (T, H, W, 3), uint8
        RGB frames as stored (turned by ``shot.rotate``).
    truth : dict
        What :func:`write_clip` writes as JSON (see there).
    """

    frames: np.ndarray
    truth: dict = field(default_factory=dict)


# -- the pinhole camera ---------------------------------------------------------------------------
@dataclass(frozen=True)
class _Pinhole:
    """World metres ``(x, y)`` in the plane of motion at depth ``z`` to upright pixels.

    The camera looks along +z at ``(cx, cy)`` of the plane, focal length ``f`` px, rolled by
    ``tilt`` radians (counter-clockwise in the picture). Continuous pixel coordinates (pixel
    ``[i, j]``'s centre at ``(j + 0.5, i + 0.5)``), as :mod:`sysid_bench.core.footage` reads them.
    """

    f: float
    cx: float
    cy: float
    size: tuple
    tilt: float

    def project(self, x, y, z):
        """``(col, row)`` arrays, and the px per metre at that depth."""
        x, y, z = (np.asarray(v, dtype=np.float64) for v in (x, y, z))
        du, dv = self.f * (x - self.cx) / z, -self.f * (y - self.cy) / z
        c, s = math.cos(self.tilt), math.sin(self.tilt)
        h, w = self.size
        # a camera rolled clockwise by tilt shows the world turned counter-clockwise: rows run
        # down, so a counter-clockwise turn in the picture is (du, dv) -> (c du + s dv, -s du + c dv)
        return (w / 2 + c * du + s * dv, h / 2 - s * du + c * dv), self.f / z


# -- drawing (float RGB in [0, 1], coverage from signed distances, in a window) -----------------------
def _window(img, c0, c1, r0, r1):
    h, w = img.shape[:2]
    c0, r0 = max(0, int(math.floor(c0))), max(0, int(math.floor(r0)))
    c1, r1 = min(w, int(math.ceil(c1)) + 1), min(h, int(math.ceil(r1)) + 1)
    if c1 <= c0 or r1 <= r0:
        return None
    yy, xx = np.mgrid[r0:r1, c0:c1].astype(np.float32) + np.float32(0.5)
    return (slice(r0, r1), slice(c0, c1)), xx, yy


#: the windows drawn into since the list was last cleared (a frame's sub-frames redraw only there)
_DIRTY: list = []


def _blend(img, win, alpha, colour):
    sl = win[0]
    _DIRTY.append(sl)
    a = np.clip(alpha, 0.0, 1.0)[..., None]
    img[sl] = img[sl] * (1 - a) + colour * a


def _sphere(img, cu, cv, rad, rgb, spec=0.45):
    """A shaded ball (Lambert from :data:`_LIGHT` plus a highlight), anti-aliased edge."""
    if not (math.isfinite(cu) and math.isfinite(cv)) or rad < 0.3:
        return
    win = _window(img, cu - rad - 1, cu + rad + 1, cv - rad - 1, cv + rad + 1)
    if win is None:
        return
    _, xx, yy = win
    nx, ny = (xx - cu) / rad, -(yy - cv) / rad
    rr = nx * nx + ny * ny
    nz = np.sqrt(np.clip(1 - rr, 0, 1))
    lam = np.clip(nx * _LIGHT[0] + ny * _LIGHT[1] + nz * _LIGHT[2], 0, 1)
    half = _LIGHT + np.array([0, 0, 1], dtype=np.float32)
    half /= np.linalg.norm(half)
    hl = np.clip(nx * half[0] + ny * half[1] + nz * half[2], 0, 1) ** 40
    col = np.asarray(rgb, np.float32) * (0.3 + 0.7 * lam)[..., None] + (spec * hl)[..., None]
    alpha = rad - np.sqrt(rr) * rad + 0.5
    _blend(img, win, alpha, np.clip(col, 0, 1))


def _ellipse(img, cu, cv, a, b, ang, rgb):
    """A flat-shaded ellipse (semi-axes ``a``, ``b`` px, turned ``ang`` rad), lit from above."""
    m = max(a, b) + 1
    win = _window(img, cu - m, cu + m, cv - m, cv + m)
    if win is None:
        return
    _, xx, yy = win
    c, s = math.cos(ang), math.sin(ang)
    u, v = (xx - cu) * c + (yy - cv) * s, -(xx - cu) * s + (yy - cv) * c
    q = np.sqrt((u / a) ** 2 + (v / b) ** 2)
    alpha = (1 - q) * min(a, b) + 0.5
    shade = (0.85 - 0.15 * np.clip((yy - cv) / m, -1, 1))[..., None]
    _blend(img, win, alpha, np.asarray(rgb, np.float32) * shade)


def _segment(img, p0, p1, width, rgb, opacity=1.0):
    """A line of ``width`` px from ``p0`` to ``p1`` (col, row), round caps."""
    (u0, v0), (u1, v1) = p0, p1
    m = width / 2 + 1
    win = _window(img, min(u0, u1) - m, max(u0, u1) + m, min(v0, v1) - m, max(v0, v1) + m)
    if win is None:
        return
    _, xx, yy = win
    du, dv = u1 - u0, v1 - v0
    ll = du * du + dv * dv
    t = np.clip(((xx - u0) * du + (yy - v0) * dv) / ll, 0, 1) if ll > 0 else 0.0
    dist = np.hypot(xx - (u0 + t * du), yy - (v0 + t * dv))
    _blend(img, win, (width / 2 - dist + 0.5) * opacity, np.asarray(rgb, np.float32))


def _box(img, cu, cv, hw, hh, ang, rgb, corner=0.25):
    """A cart: a rounded rectangle (half sizes ``hw``, ``hh`` px), lit from above."""
    m = math.hypot(hw, hh) + 1
    win = _window(img, cu - m, cu + m, cv - m, cv + m)
    if win is None:
        return
    _, xx, yy = win
    c, s = math.cos(ang), math.sin(ang)
    u, v = (xx - cu) * c + (yy - cv) * s, -(xx - cu) * s + (yy - cv) * c
    rc = corner * min(hw, hh)
    qu, qv = np.abs(u) - (hw - rc), np.abs(v) - (hh - rc)
    sdf = np.hypot(np.maximum(qu, 0), np.maximum(qv, 0)) + np.minimum(np.maximum(qu, qv), 0) - rc
    shade = (0.95 - 0.35 * np.clip((v + hh) / (2 * hh), 0, 1))[..., None]
    _blend(img, win, 0.5 - sdf, np.asarray(rgb, np.float32) * shade)


def _hand(img, cam, x, y, z, reach):
    """A hand at world ``(x, y)``, depth ``z``: palm, four fingers pointing at ``reach`` (a unit
    world direction), the forearm running out the other way."""
    (pu, pv), s = cam.project(x, y, z)
    pu, pv, s = float(pu), float(pv), float(s)
    dx, dy = reach
    ang = math.atan2(-dy, dx) - cam.tilt  # picture angle of the reach (rows run down)
    # forearm first (behind the palm), out of the picture
    back = (pu - math.cos(ang) * 0.5 * s, pv - math.sin(ang) * 0.5 * s)
    _segment(img, (pu, pv), back, 0.07 * s, _SKIN * 0.92)
    _ellipse(img, pu, pv, 0.055 * s, 0.045 * s, ang, _SKIN)
    for k in range(4):
        off = (k - 1.5) * 0.02 * s
        bu = pu + math.cos(ang) * 0.04 * s - math.sin(ang) * off
        bv = pv + math.sin(ang) * 0.04 * s + math.cos(ang) * off
        _segment(img, (bu, bv), (bu + math.cos(ang) * 0.06 * s, bv + math.sin(ang) * 0.06 * s),
                 0.016 * s, _SKIN * 0.97)


# -- the room ---------------------------------------------------------------------------------------
def _noise(rng, shape, cells):
    """Smooth noise in [0, 1]: a coarse random grid, bilinearly enlarged."""
    from scipy.ndimage import zoom

    h, w = shape
    gh, gw = max(2, int(h / cells) + 2), max(2, int(w / cells) + 2)
    g = rng.random((gh, gw)).astype(np.float32)
    z = zoom(g, (h / (gh - 1) + 1e-3, w / (gw - 1) + 1e-3), order=1, prefilter=False)
    return z[:h, :w]


def _room(rng, cam, floor_y, wall_z, size):
    """The background: wall, clutter and (when ``floor_y`` is given) a floor, float RGB (H, W, 3)."""
    h, w = size
    wall = rng.choice([np.array([0.86, 0.83, 0.76]), np.array([0.72, 0.76, 0.80]),
                       np.array([0.80, 0.80, 0.78]), np.array([0.62, 0.66, 0.60])])
    tex = 0.6 * _noise(rng, (h, w), 40) + 0.4 * _noise(rng, (h, w), 6)
    img = np.broadcast_to(wall.astype(np.float32), (h, w, 3)) * (0.9 + 0.2 * tex)[..., None]
    img = np.ascontiguousarray(img, dtype=np.float32)
    # clutter: posters, a shelf, a door frame, a row of printed text
    for _ in range(int(rng.integers(3, 7))):
        pw, ph = rng.uniform(0.06, 0.22) * w, rng.uniform(0.08, 0.3) * h
        pc, pr = rng.uniform(0, w), rng.uniform(0, 0.7 * h)
        col = rng.uniform(0.15, 0.95, 3).astype(np.float32)
        _box(img, pc, pr, pw / 2, ph / 2, 0.0, col, corner=0.02)
        if rng.random() < 0.5:  # a picture in the frame
            _box(img, pc, pr, 0.4 * pw, 0.4 * ph, 0.0, rng.uniform(0.1, 0.9, 3), corner=0.05)
    for _ in range(int(rng.integers(1, 3))):  # printed text: rows of dark dashes
        c0, r0 = rng.uniform(0, 0.8 * w), rng.uniform(0, 0.6 * h)
        step = max(2.0, 0.012 * h)
        for line in range(int(rng.integers(2, 5))):
            c = c0
            for _word in range(int(rng.integers(3, 7))):
                ln = rng.uniform(2, 6) * step
                _segment(img, (c, r0 + 2 * line * step), (c + ln, r0 + 2 * line * step),
                         0.6 * step, (0.12, 0.12, 0.14))
                c += ln + 1.5 * step
    door = rng.uniform(0, w)
    _segment(img, (door, -10), (door, h + 10), 0.02 * w, (0.55, 0.45, 0.35))
    if floor_y is not None:  # the floor meets the wall behind the motion
        (_, junction), _ = cam.project(0.0, floor_y, wall_z)
        junction = float(junction)
        rows = np.arange(h, dtype=np.float32)[:, None] + 0.5
        cols = np.arange(w, dtype=np.float32)[None, :] + 0.5
        grain = 0.5 + 0.5 * np.sin(0.35 * np.maximum(rows - junction, 0) ** 1.1
                                    + 6 * _noise(rng, (h, w), 25))
        planks = (np.abs(np.sin(cols / (0.09 * w) + 0.3 * rows / h)) < 0.03).astype(np.float32)
        wood = np.array([0.58, 0.40, 0.24], np.float32) * (0.8 + 0.25 * grain
                                                           - 0.3 * planks)[..., None]
        mask = np.clip(rows - junction, 0, 1)[..., None]
        img = img * (1 - mask) + wood * mask
        _segment(img, (-10, junction), (w + 10, junction), 0.006 * h, (0.95, 0.95, 0.92))
    # light from above left, darker corners
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    grad = 1.05 - 0.25 * (xx / w) * 0.5 - 0.25 * (yy / h) * 0.5
    vig = 1 - 0.25 * (((xx - w / 2) / w) ** 2 + ((yy - h / 2) / h) ** 2) * 2
    return np.clip(img * (grad * vig)[..., None], 0, 1).astype(np.float32)


def _tilted(img, tilt):
    """The room as a camera rolled by ``tilt`` sees it (the projection's turn, about the centre)."""
    if tilt == 0:
        return img
    from scipy.ndimage import map_coordinates

    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    du, dv = xx - w / 2, yy - h / 2
    c, s = math.cos(tilt), math.sin(tilt)
    # invert (du, dv) -> (c du + s dv, -s du + c dv)
    su, sv = c * du - s * dv, s * du + c * dv
    out = np.empty_like(img)
    for k in range(3):
        out[..., k] = map_coordinates(img[..., k], [sv + h / 2 - 0.5, su + w / 2 - 0.5],
                                      order=1, mode="reflect")
    return out


# -- the systems at true size ------------------------------------------------------------------------
def _truth_ball(sys_, rng):
    theta = np.array([rng.uniform(0.65, 0.9), G, rng.uniform(0.005, 0.03),
                      rng.uniform(0.05, 0.5)])
    vx = rng.choice([-1, 1]) * rng.uniform(0.15, 0.6)
    state0 = np.array([0.0, rng.uniform(1.0, 1.8), vx, 0.0])
    scene = sys_.scene(floor=0.0, walls=None)
    draw = {"radius_m": 0.035, "colour": rng.choice([(0.25, 0.75, 0.2), (0.95, 0.55, 0.1),
                                                     (0.85, 0.85, 0.15)])}
    return theta, state0, scene, draw


def _truth_pendulum(sys_, rng):
    theta = np.array([G, rng.uniform(0.5, 1.0), rng.uniform(0.02, 0.2),
                      rng.uniform(0.0, 0.1)])
    state0 = np.array([rng.choice([-1, 1]) * rng.uniform(0.3, 0.8), 0.0])
    scene = sys_.scene(pivot=(0.0, 0.0))
    draw = {"radius_m": float(rng.uniform(0.03, 0.05)),
            "colour": rng.choice([(0.8, 0.15, 0.1), (0.15, 0.3, 0.85), (0.9, 0.75, 0.1)])}
    return theta, state0, scene, draw


def _truth_spring(sys_, rng):
    theta = np.array([rng.uniform(6.0, 20.0), rng.uniform(0.0, 5.0), rng.uniform(0.05, 0.3),
                      rng.uniform(1.0, 1.5)])
    state0 = np.array([theta[3] + rng.choice([-1, 1]) * rng.uniform(0.15, 0.35), 0.0])
    scene = sys_.scene(anchor=(0.0, 0.0))
    draw = {"half_m": 0.06, "colour": rng.choice([(0.2, 0.35, 0.8), (0.85, 0.2, 0.2)])}
    return theta, state0, scene, draw


def _truth_collision(sys_, rng):
    theta = np.array([rng.uniform(-1.5, 1.5), rng.uniform(0.6, 0.95), rng.uniform(0.02, 0.2),
                      rng.uniform(0.7, 0.95)])
    half = 0.05
    state0 = np.array([rng.uniform(0.25, 0.6), rng.uniform(0.3, 0.8), rng.uniform(1.4, 1.75),
                       -rng.uniform(0.3, 0.8)])
    scene = sys_.scene(ends=(0.0, 2.0), half_sizes=(half, half))
    draw = {"half_m": half, "colours": [(0.85, 0.15, 0.15), (0.15, 0.3, 0.85)]}
    return theta, state0, scene, draw


@dataclass(frozen=True)
class _Staging:
    """How a system is staged in front of the camera (the knowledge is this module's: a table
    with an entry per system of :data:`SYSTEMS`, not a branch on its name).

    Attributes
    ----------
    truth : callable
        ``(system, rng) -> (theta, state0, scene, draw)``: the motion filmed and its drawing.
    hand : str or None
        ``"above"`` (holds the object from above, then lets go), ``"side"`` (holds it from the
        side it swings away from) or None (no hold: a hand sweeps through the picture).
    margin_m : float
        Room around the motion in the picture, m.
    drift : (float, float) or None
        Speed range (m/s) of the object's drift in depth while it moves (either way); None:
        it keeps its distance.
    floor_below : bool
        A floor under the object: the ball's radius below its centre's floor.
    """

    truth: object
    hand: str | None
    margin_m: float
    drift: tuple | None = None
    floor_below: bool = False

    @property
    def held(self) -> bool:
        """A hand holds the object still for a while before the release."""
        return self.hand is not None


_STAGING = {
    "ball": _Staging(_truth_ball, "above", 0.15, drift=(0.05, 0.15), floor_below=True),
    "pendulum": _Staging(_truth_pendulum, "side", 0.12),
    "spring": _Staging(_truth_spring, None, 0.2),
    "collision": _Staging(_truth_collision, None, 0.15),
}


def _truth(shot: Shot, rng):
    """theta, state0, scene, the hold before release and the drawing's sizes for ``shot``."""
    from sysid_bench.core import systems

    sys_ = systems.get(shot.system)
    stage = _STAGING[shot.system]
    # a hand holds the ball or the bob still for a while (at most a quarter of the clip)
    hold = (min(float(rng.uniform(0.3, 0.7)), 0.25 * float(shot.duration_s))
            if stage.held else 0.0)
    theta, state0, scene, draw = stage.truth(sys_, rng)
    draw["colour"] = tuple(float(v) for v in draw.get("colour", (0, 0, 0)))
    return sys_, theta, state0, scene, hold, draw


def film(shot: Shot) -> Footage:
    """Film ``shot``: simulate the system at true size and draw it through the camera.

    Parameters
    ----------
    shot : Shot

    Returns
    -------
    Footage
        ``frames`` (T, H, W, 3) uint8 as stored, T = round(duration_s * fps); ``truth`` as
        :func:`write_clip` writes it.
    """
    if not isinstance(shot, Shot):
        raise TypeError(f"shot: expected a Shot, got {type(shot).__name__}")
    rng = np.random.default_rng([int(shot.seed), SYSTEMS.index(shot.system), 38])
    sys_, theta, state0, scene, hold, draw = _truth(shot, rng)
    fps, n_sub = int(shot.fps), int(shot.subframes)
    n_frames = int(round(shot.duration_s * fps))
    ticks = 8  # simulation steps per frame interval; the shutter's sub-frames fall on them
    dt_f = 1.0 / (fps * ticks)
    hold_ticks = int(round(hold / dt_f))
    hold = hold_ticks * dt_f
    n_fine = n_frames * ticks + ticks
    states = sys_.simulate(theta[None], state0[None], n_frames=max(2, n_fine - hold_ticks + 2),
                           dt=dt_f, scene=scene)
    points = sys_.observe(states, theta[None], scene=scene)[0]  # (n, K, 2)

    def at(tick):
        """Tracked points (K, 2) at a fine tick (held still before the release)."""
        return points[min(max(tick - hold_ticks, 0), len(points) - 1)]

    # -- the camera: frame the whole motion with a margin, at a room's distance
    allp = points[: max(2, n_fine - hold_ticks)].reshape(-1, 2)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    h, w = shot.size
    stage = _STAGING[shot.system]
    extra = stage.margin_m
    if shot.system == "pendulum":  # the string to the pivot, which may be above the frame
        lo, hi = np.minimum(lo, [0, 0]), np.maximum(hi, [0, 0])
    if shot.system == "spring":  # the anchor wall
        lo = np.minimum(lo, [scene.anchor[0] - 0.1, scene.anchor[1] - 0.1])
    if shot.system == "collision":
        lo, hi = np.minimum(lo, [scene.ends[0], 0]), np.maximum(hi, [scene.ends[1], 0.1])
    span = (hi - lo) + 2 * extra
    centre = (lo + hi) / 2
    distance = float(rng.uniform(2.2, 3.5))
    f = float(min(w / span[0], h / span[1])) * distance * float(rng.uniform(0.8, 0.95))
    if shot.system == "pendulum" and rng.random() < 0.5:  # the pivot above the frame
        centre = centre + [0, 0.12 * (hi[1] - lo[1])]
    centre = centre + rng.uniform(-0.04, 0.04, 2) * span
    tilt = math.radians(float(shot.tilt_deg))
    cam = _Pinhole(f=f, cx=float(centre[0]), cy=float(centre[1]), size=(h, w), tilt=tilt)
    # the ball drifts in depth (towards or away from the camera) while it moves
    vz = (float(rng.choice([-1, 1]) * rng.uniform(*stage.drift)) if stage.drift is not None
          else 0.0)

    def depth(tick):
        return distance + vz * max(tick - hold_ticks, 0) * dt_f

    floor_y = None
    if stage.floor_below:
        floor_y = scene.floor - draw["radius_m"]  # the floor surface under the ball's centre
    elif shot.system == "collision":
        floor_y = 0.0
    room = _tilted(_room(rng, cam, floor_y, distance + 0.8, (h, w)), tilt)
    if shot.system == "collision":  # the track: a rail under the pucks
        (u0, v0), _ = cam.project(scene.ends[0], -0.01, distance)
        (u1, v1), _ = cam.project(scene.ends[1], -0.01, distance)
        _segment(room, (float(u0), float(v0)), (float(u1), float(v1)), 0.02 * f / distance,
                 (0.55, 0.55, 0.58))
        for e in scene.ends:
            (ue, ve), _ = cam.project(e, 0.05, distance)
            _segment(room, (float(ue), float(ve) + 0.05 * f / distance),
                     (float(ue), float(ve) - 0.05 * f / distance), 0.015 * f / distance,
                     (0.3, 0.3, 0.32))
    if shot.system == "spring":  # the anchor's wall block
        (ua, va), _ = cam.project(scene.anchor[0] - 0.03, scene.anchor[1], distance)
        _box(room, float(ua), float(va), 0.03 * f / distance, 0.12 * f / distance, -tilt,
             (0.35, 0.3, 0.28), corner=0.05)

    # the hand: holds the ball or the bob until release, then pulls away; else a sweep
    t_total = n_frames / fps
    if stage.held:
        hand_win = (0.0, hold + 0.45)
    else:
        a = float(rng.uniform(0.2, max(0.25, t_total - 1.2)))
        hand_win = (a, min(t_total, a + 1.0))
    sweep_y = float(hi[1] + extra * 0.6)
    sweep_dir = float(rng.choice([-1, 1]))

    def draw_hand(img, tick):
        t = tick * dt_f
        if not (shot.hand and hand_win[0] <= t <= hand_win[1]):
            return
        if stage.held:
            p = at(hold_ticks)[0]
            rad = draw["radius_m"]
            away = max(0.0, t - hold) / 0.45  # 0 holding, 1 gone
            if stage.hand == "above":
                hx, hy = p[0] + 0.02, p[1] + rad + 0.03 + 0.9 * away ** 1.5
                _hand(img, cam, hx, hy, depth(hold_ticks) - 0.06, (0.0, -1.0))
            else:  # from the side the bob swings away from
                side = -np.sign(p[0]) if p[0] != 0 else 1.0
                hx = p[0] + side * (rad + 0.06 + 0.8 * away ** 1.5)
                _hand(img, cam, hx, p[1], depth(hold_ticks) - 0.06, (-side, 0.0))
        else:
            u = (t - hand_win[0]) / (hand_win[1] - hand_win[0])
            x0, x1 = (lo[0] - 0.3, hi[0] + 0.3)[:: int(sweep_dir)]
            _hand(img, cam, x0 + (x1 - x0) * u, sweep_y + 0.05 * math.sin(6 * u),
                  distance - 0.3, (sweep_dir, 0.0))

    def draw_objects(img, tick):
        z = depth(tick)
        pts = at(tick)
        if shot.system == "pendulum":
            (pu, pv), s = cam.project(scene.pivot[0], scene.pivot[1], z)
            (u, v), _ = cam.project(pts[0, 0], pts[0, 1], z)
            # a thin dark string, half-covering its pixels
            _segment(img, (float(pu), float(pv)), (float(u), float(v)), 1.2, (0.2, 0.2, 0.2),
                     opacity=0.5)
            _sphere(img, float(u), float(v), draw["radius_m"] * float(s), draw["colour"])
        elif shot.system == "spring":
            (u, v), s = cam.project(pts[0, 0], pts[0, 1], z)
            (ua, va), _ = cam.project(scene.anchor[0], scene.anchor[1], z)
            s = float(s)
            # a silver coil from the anchor to the cart: low contrast against the wall
            n_turn = 14
            xs = np.linspace(float(ua), float(u) - draw["half_m"] * s, 2 * n_turn + 1)
            ys = np.linspace(float(va), float(v), 2 * n_turn + 1)
            amp = 0.025 * s * np.where(np.arange(2 * n_turn + 1) % 2 == 0, 1, -1)
            amp[0] = amp[-1] = 0
            base = img[int(np.clip(v, 0, h - 1)), int(np.clip(u, 0, w - 1))].copy()
            coil = np.clip(base * 0.9 + 0.08, 0, 1)
            for k in range(2 * n_turn):
                _segment(img, (xs[k], ys[k] + amp[k]), (xs[k + 1], ys[k + 1] + amp[k + 1]), 1.0,
                         coil, opacity=0.6)
            _box(img, float(u), float(v), draw["half_m"] * s, 0.8 * draw["half_m"] * s, -tilt,
                 draw["colour"])
        elif shot.system == "collision":
            for k in range(2):
                (u, v), s = cam.project(pts[k, 0], pts[k, 1], z)
                _sphere(img, float(u), float(v), draw["half_m"] * float(s), draw["colours"][k],
                        spec=0.3)
        else:  # the ball, and the default: a sphere at each tracked point
            for k in range(len(pts)):
                (u, v), s = cam.project(pts[k, 0], pts[k, 1], z)
                _sphere(img, float(u), float(v), draw["radius_m"] * float(s), draw["colour"])

    # -- the frames: each the mean of the shutter's sub-frames, then sensor noise
    offs = [int(round((j + 0.5) / n_sub * shot.exposure * ticks - shot.exposure * ticks / 2))
            for j in range(n_sub)]
    out = np.empty((n_frames, h, w, 3), dtype=np.uint8)
    noise_rng = np.random.default_rng([int(shot.seed), SYSTEMS.index(shot.system), 39])
    img = room.copy()
    room_n = room * np.float32(n_sub)
    for i in range(n_frames):
        acc = room_n.copy()
        for o in offs:
            tick = max(i * ticks + o, 0)
            _DIRTY.clear()
            draw_objects(img, tick)
            draw_hand(img, tick)
            if _DIRTY:  # add what this sub-frame drew over the room, then wipe it
                r0 = min(sl[0].start for sl in _DIRTY)
                r1 = max(sl[0].stop for sl in _DIRTY)
                c0 = min(sl[1].start for sl in _DIRTY)
                c1 = max(sl[1].stop for sl in _DIRTY)
                acc[r0:r1, c0:c1] += img[r0:r1, c0:c1] - room[r0:r1, c0:c1]
                img[r0:r1, c0:c1] = room[r0:r1, c0:c1]
        acc *= np.float32(255.0 / n_sub)
        if shot.noise > 0:
            acc += noise_rng.standard_normal(acc.shape, dtype=np.float32) * np.float32(shot.noise)
        out[i] = np.clip(np.rint(acc), 0, 255).astype(np.uint8)
    stored = out if shot.rotate == 0 else np.ascontiguousarray(
        np.rot90(out, k=shot.rotate // 90, axes=(1, 2)))

    # -- the truth at the frame times
    frame_ticks = np.arange(n_frames) * ticks
    true_pts = np.stack([at(int(k)) for k in frame_ticks])  # (T, K, 2)
    zs = np.array([depth(int(k)) for k in frame_ticks])
    (pc, pr), scale = cam.project(true_pts[..., 0], true_pts[..., 1], zs[:, None])
    pix = np.stack([pc, pr], axis=-1)
    truth = _truth_record(shot, sys_, theta, state0, scene, hold, draw, cam, distance, vz,
                          true_pts, pix, scale, hand_win, n_frames)
    return Footage(frames=stored, truth=truth)


def _round_up(x, step=0.1):
    return round(math.ceil(x / step - 1e-9) * step, 6)


def _truth_record(shot, sys_, theta, state0, scene, hold, draw, cam, distance, vz, pts, pix,
                  scale, hand_win, n_frames) -> dict:
    """The ground truth and the options a user would give identify, as plain JSON values."""
    params = list(sys_.params)
    start = _round_up(hand_win[1] + 0.05) if _STAGING[shot.system].held else None
    scale0 = float(scale[0, 0])
    opts = ["--system", shot.system, "--method", "lsq"]
    if shot.rotate:
        opts += ["--rotate", str(shot.rotate)]
    if shot.stored_fps is not None:
        opts += ["--fps", f"{shot.fps:g}"]
    if start is not None:
        opts += ["--start", f"{start:g}"]
    size_m = None
    if shot.system == "pendulum":
        size_m = 2 * draw["radius_m"]
        if shot.seed % 2 == 0:  # the string's length is known
            opts += ["--known", f"L={theta[1]:.3g}"]
        else:  # g is known and the bob's size
            opts += ["--known", f"g={G:g}", "--object-size-m", f"{size_m:.3g}"]
    elif shot.system == "spring":
        size_m = 2 * draw["half_m"]
        # a ruler on the track: the scale to three figures, and the anchor's column
        (ua, _), _ = cam.project(scene.anchor[0], scene.anchor[1], distance)
        opts += ["--px-per-m", f"{scale0:.3g}", "--anchor", f"{float(ua):.0f}"]
    elif shot.system == "collision":
        size_m = 2 * draw["half_m"]
        (u0, _), _ = cam.project(scene.ends[0], 0.0, distance)
        (u1, _), _ = cam.project(scene.ends[1], 0.0, distance)
        opts += ["--px-per-m", f"{scale0:.3g}", "--track", f"{float(u0):.0f}", f"{float(u1):.0f}"]
    else:  # the ball, and the default: the scale from the sphere's known size
        size_m = 2 * draw["radius_m"]
        opts += ["--object-size-m", f"{size_m:g}"]
    h, w = shot.size
    scene_d = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(scene).items()}
    return {
        "written_by": "sysid_bench.core.camera_footage",
        "shot": {**asdict(shot), "size": [h, w]},
        "system": shot.system, "params": params,
        "theta": {p: float(v) for p, v in zip(params, theta)},
        "state0": [float(v) for v in state0], "scene": scene_d,
        "release_s": float(hold),
        "fps": shot.fps, "container_fps": float(shot.stored_fps or shot.fps),
        "n_frames": int(n_frames),
        "size_filmed": [h, w], "size_stored": [w, h] if shot.rotate in (90, 270) else [h, w],
        "rotate": shot.rotate, "tilt_deg": float(shot.tilt_deg),
        "camera": {"f_px": float(cam.f), "looks_at_m": [cam.cx, cam.cy], "distance_m": distance,
                   "depth_speed_m_s": vz, "px_per_m_start": scale0,
                   "px_per_m_range": [float(scale.min()), float(scale.max())],
                   "model": "pinhole, rolled by tilt_deg; pixels of the upright picture"},
        "object_size_m": size_m, "hand_s": [float(hand_win[0]), float(hand_win[1])]
        if shot.hand else None,
        "positions_m": np.round(pts, 6).tolist(),
        "pixels": np.round(pix, 3).tolist(),
        "options": opts,
    }


def write_clip(shot: Shot, out_dir, name: str | None = None) -> tuple[Path, Path]:
    """Film ``shot`` and write ``<name>.mp4`` (H.264) and ``<name>.json`` (its truth).

    Parameters
    ----------
    shot : Shot
    out_dir : str or Path
        Folder (created when missing).
    name : str, optional
        File stem; default ``<system>_s<seed>_<fps>fps``.

    Returns
    -------
    video, truth : Path
        Each written atomically; the JSON last (it marks a complete clip).
    """
    from sysid_bench.core.footage import write_video

    fo = film(shot)
    out = Path(out_dir)
    name = name or f"{shot.system}_s{shot.seed}_{shot.fps}fps"
    vpath, jpath = out / f"{name}.mp4", out / f"{name}.json"
    write_video(vpath, fo.frames, float(shot.stored_fps or shot.fps), crf=shot.crf)
    atomic_write(jpath, json.dumps({**fo.truth, "file": vpath.name}, indent=1))
    return vpath, jpath


def shots(system: str, n: int = 5, seed: int = 0, duration_s: float | None = None,
          size: tuple | None = None) -> list[Shot]:
    """``n`` varied shots of ``system``: 30/60/120 frames/s in turn, sizes 360p/720p/540p,
    stored sideways (90, 270) in the second and fourth, rolled 2-3 degrees in the third and
    fifth, a slow-motion file (120 captured, 30 stored) in every sixth."""
    if system not in SYSTEMS:
        raise ValueError(f"system: expected one of {', '.join(SYSTEMS)}, got {system!r}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n: expected an int >= 1, got {n!r}")
    sizes = [(360, 640), (720, 1280), (540, 960)]
    dur = {"ball": 3.5, "pendulum": 5.0, "spring": 5.0, "collision": 4.0}[system]
    out = []
    for i in range(n):
        rot = {1: 90, 3: 270}.get(i % 6, 0)
        tilt = {2: 2.5, 4: -2.0}.get(i % 6, 0.0)
        fps = FPS[i % 3]
        slow = i % 6 == 5
        out.append(Shot(system=system, seed=seed + i, fps=120 if slow else fps,
                        duration_s=duration_s or dur, size=size or sizes[i % 3], rotate=rot,
                        tilt_deg=tilt, stored_fps=30.0 if slow else None))
    return out


def generate_set(out_dir, n: int = 5, seed: int = 0, systems=SYSTEMS, **kw) -> list[Path]:
    """:func:`write_clip` for :func:`shots` of each system; returns the JSON paths."""
    paths = []
    for s in systems:
        for shot in shots(s, n, seed, **kw):
            paths.append(write_clip(shot, out_dir)[1])
    return paths


def main(argv=None) -> int:
    import argparse
    import time

    p = argparse.ArgumentParser(prog="python -m sysid_bench.camera_footage",
                                description="Film camera-like clips of the four systems, with "
                                            "their ground truth.")
    p.add_argument("--out", default="runs/camera_footage")
    p.add_argument("-n", type=int, default=5, help="clips per system")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--system", action="append", choices=SYSTEMS, default=None)
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    for j in generate_set(args.out, args.n, args.seed, tuple(args.system or SYSTEMS)):
        print(j)
    print(f"{time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
