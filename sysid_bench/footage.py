"""Video files to the suite's inputs: decode, encode, map pixels to metres, find the ball.

The core half of ``sysid-bench identify`` (:mod:`sysid_bench.video`, the command, builds on it),
used as well by the MuJoCo scenes (:mod:`sysid_bench.mujoco_scene`) and the benchmark's
experiment on them; it knows no method.

1. :func:`read_video` decodes the file with **PyAV** (``av``: FFmpeg's libraries in the wheel,
   libx264 included), converts every frame to grey and resamples to the model's 20 frames/s
   by taking, for each 50 ms tick, the source frame nearest in time (blending frames would show
   two half-bright balls). PyAV rather than imageio-ffmpeg because it gives each frame's own
   presentation time and the stream's rate from the container, in process (imageio-ffmpeg
   pipes raw frames from an ``ffmpeg`` subprocess and parses its rate from the log text), and
   because the same wheel writes H.264 (:func:`write_video`) without any system FFmpeg.
2. :class:`Geometry` maps source pixels to the suite's metres. By default the frame is framed
   as :mod:`sysid_bench.render` frames its videos, at the file's resolution: the box
   ``[0, 10] m`` spans the width with the ball's radius as margin and the floor contact is at
   the bottom edge. Other footage gives the pixel scale, the floor row and the left wall's
   column, or the two floor corners of the box (:func:`geometry_from_options`).
3. :func:`find_ball` follows the ball at the file's resolution: a median background over the
   clip is subtracted, pixels that differ by more than the noise (or a floor of contrast) form
   blobs, and each frame keeps the blob nearest the position predicted from the last two
   (constant velocity), of a size consistent with the ball's; a track is (re)acquired on the
   roundest blob. Static clutter is in the background, so it never becomes "the ball".
4. :func:`observe` turns the track into the Observation a method takes: tracked positions in
   metres (floor at 0), or frames re-drawn at them in a video model's view
   (:func:`model_frames`; see ``docs/video.md`` for why re-drawing rather than cropping).
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from sysid_bench._io import atomic_write
from sysid_bench.physics import BOX_WIDTH
from sysid_bench.render import RADIUS_FRACTION, view_geometry
from sysid_bench.tracking import ball_centre, ball_seen, noise_level

__all__ = [
    "MODEL_FPS",
    "VideoError",
    "Clip",
    "read_video",
    "write_video",
    "Geometry",
    "geometry_from_options",
    "find_ball",
    "BallTrack",
    "model_frames",
    "observe",
]

#: frame rate of every model in the suite (physics.dt = 0.05 s)
MODEL_FPS = 20.0
#: decoded frames above which the reader shows a progress bar (when stderr is a terminal)
_PROGRESS_FRAMES = 300


class VideoError(ValueError):
    """A video file that cannot be used; the message names the file and the problem."""


# -- reading and writing ------------------------------------------------------------------------
@dataclass
class Clip:
    """A decoded video, grey and resampled to the model's frame rate.

    Attributes
    ----------
    frames : ndarray, shape (T, H, W), uint8
        Grey frames at ``fps`` (``MODEL_FPS`` after resampling).
    times : ndarray, shape (T,)
        Source presentation time of each kept frame, seconds from the first frame.
    source_fps : float
        The file's frame rate (from the stream, else from the frame times).
    source_frames : int
        Frames decoded from the file.
    colour : bool
        The file stored colour (it was converted to grey: ITU-R BT.601 luma, FFmpeg's "gray").
    notes : list of str
        What was done to the file (resampling), one sentence each.
    """

    frames: np.ndarray
    times: np.ndarray
    source_fps: float
    source_frames: int
    colour: bool
    fps: float = MODEL_FPS
    notes: list = field(default_factory=list)
    path: str = ""


def _fail(path, problem: str) -> VideoError:
    return VideoError(f"{path}: {problem}")


def read_video(path, fps: float = MODEL_FPS, *, progress: bool | None = None) -> Clip:
    """Decode a video file to grey frames at ``fps``.

    Parameters
    ----------
    path : str or Path
        Any container and codec FFmpeg reads (mp4, avi, mkv, mov, webm, gif, ...).
    fps : float
        Frame rate to resample to (nearest source frame in time for each output tick).
    progress : bool, optional
        tqdm bar while decoding; default: only for files over 300 frames, on a terminal.

    Returns
    -------
    Clip

    Raises
    ------
    VideoError
        Missing, unreadable, empty or zero-frame file, not a video, or no readable frame rate;
        the message starts with the path.
    """
    try:
        import av
    except ImportError as exc:  # pragma: no cover - av is a core dependency
        raise VideoError(f"{path}: reading videos needs PyAV (pip install av): {exc}") from exc
    fps = float(fps)
    if not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps: expected a frame rate > 0, got {fps!r}")
    p = Path(path)
    if not p.exists():
        raise _fail(path, "no such file")
    if p.is_dir():
        raise _fail(path, "is a directory, not a video file")
    if not os.access(p, os.R_OK):
        raise _fail(path, "cannot be read (permission denied)")
    if p.stat().st_size == 0:
        raise _fail(path, "empty file (0 bytes)")
    try:
        container = av.open(str(p), mode="r")
    except av.error.EOFError:
        raise _fail(path, "the video has zero frames (the file ends before its first frame)") from None
    except av.error.FFmpegError as exc:
        raise _fail(path, f"not a readable video ({_av_reason(exc)})") from None
    except OSError as exc:
        raise _fail(path, f"cannot be read ({exc.strerror or exc})") from None
    try:
        if not container.streams.video:
            raise _fail(path, "no video stream in the file")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rate = stream.average_rate or stream.guessed_rate or stream.base_rate
        rate = float(rate) if rate else float("nan")
        colour = not str(stream.codec_context.pix_fmt or "").startswith("gray")
        n_hint = int(stream.frames or 0)
        show = (n_hint > _PROGRESS_FRAMES) if progress is None else bool(progress)
        frames, times = [], []
        from tqdm.auto import tqdm

        with tqdm(total=n_hint or None, desc=f"reading {p.name}", unit="frame",
                  disable=not show or (progress is None and not sys.stderr.isatty()),
                  leave=False) as bar:
            try:
                for fr in container.decode(stream):
                    frames.append(fr.to_ndarray(format="gray"))
                    times.append(np.nan if fr.time is None else float(fr.time))
                    bar.update(1)
            except av.error.EOFError:
                pass  # a stream declared but holding no frames: "zero frames" below
            except av.error.FFmpegError as exc:
                if not frames:
                    raise _fail(path, f"not a readable video ({_av_reason(exc)})") from None
                # a truncated file: keep the frames decoded before the damage
    finally:
        container.close()
    if not frames:
        raise _fail(path, "the video has zero frames")
    t = np.asarray(times, dtype=np.float64)
    if np.isfinite(t).all() and len(t) > 1 and np.all(np.diff(t) > 0):
        t = t - t[0]
        if not math.isfinite(rate) or rate <= 0:
            rate = (len(t) - 1) / t[-1]
    elif math.isfinite(rate) and rate > 0:
        t = np.arange(len(frames)) / rate  # timestamps missing or out of order: trust the rate
    elif len(frames) == 1:
        rate, t = fps, np.zeros(1)
    else:
        raise _fail(path, "the frame rate cannot be read (no stream rate, no frame times)")
    raw = np.stack(frames)
    notes = []
    if abs(rate - fps) > 1e-3 * fps:
        ticks = np.arange(0.0, t[-1] + 0.5 / rate + 1e-9, 1.0 / fps)
        # nearest source frame to each tick
        j = np.clip(np.searchsorted(t, ticks), 1, len(t) - 1)
        j = np.where(np.abs(t[j - 1] - ticks) <= np.abs(t[j] - ticks), j - 1, j)
        if len(t) == 1:
            j = np.zeros(1, dtype=int)
        raw_kept, t_kept = raw[j], t[j]
        notes.append(f"resampled from {rate:.4g} to {fps:g} frames/s (nearest frame in time): "
                     f"{len(frames)} -> {len(j)} frames"
                     + ("; the source is slower than the model, so frames repeat" if rate < fps
                        else ""))
    else:
        raw_kept, t_kept = raw, t
    return Clip(frames=np.ascontiguousarray(raw_kept), times=t_kept, source_fps=float(rate),
                source_frames=len(frames), colour=colour, fps=fps, notes=notes, path=str(path))


def _av_reason(exc) -> str:
    s = str(getattr(exc, "strerror", None) or exc)
    return s.split(":")[0].strip() if ": '" in s else s.strip()


def write_video(path, frames, fps: float = MODEL_FPS, *, codec: str = "libx264",
                crf: int = 18) -> Path:
    """Write frames to a video file with PyAV (no system FFmpeg needed), atomically.

    Parameters
    ----------
    path : str or Path
        Output file; the container follows its suffix (``.mp4``, ``.mkv``, ``.avi``).
    frames : ndarray, shape (T, H, W) grey or (T, H, W, 3) RGB, uint8
    fps : float
        Frame rate (an exact fraction for common rates: 20, 25, 30000/1001, ...).
    codec : str
        ``"libx264"`` (H.264, yuv420p, even sizes), ``"ffv1"`` (lossless; keeps grey as grey),
        or any encoder PyAV has.
    crf : int
        H.264 quality (0 lossless .. 51; 18 is visually lossless).

    Returns
    -------
    Path
    """
    from fractions import Fraction

    import av

    fr = np.asarray(frames)
    if fr.dtype != np.uint8 or fr.ndim not in (3, 4) or (fr.ndim == 4 and fr.shape[-1] != 3):
        raise ValueError("frames: expected uint8 (T, H, W) or (T, H, W, 3), got "
                         f"{fr.dtype} shape {fr.shape}")
    if fr.shape[0] < 1:
        raise ValueError("frames: expected at least one frame, got 0")
    path = Path(path)
    rate = Fraction(float(fps)).limit_denominator(1001)
    grey = fr.ndim == 3

    def encode(tmp: Path) -> None:
        with av.open(str(tmp), mode="w") as out:
            st = out.add_stream(codec, rate=rate)
            st.width, st.height = fr.shape[2], fr.shape[1]
            if codec in ("libx264", "h264"):
                st.pix_fmt = "yuv420p"
                # no macroblock-tree rate control: with it (x264's default, asm on) two writes
                # of the same noisy camera-like frames came out different every time, one
                # thread or several, and so did every estimate read back; without it (or
                # without asm) the bytes repeat
                st.options = {"crf": str(int(crf)), "preset": "medium", "x264-params": "mbtree=0"}
            elif grey and codec in ("ffv1", "png", "rawvideo"):
                st.pix_fmt = "gray"
            for img in fr:
                vf = av.VideoFrame.from_ndarray(img, format="gray" if grey else "rgb24")
                for pkt in st.encode(vf):
                    out.mux(pkt)
            for pkt in st.encode():
                out.mux(pkt)

    atomic_write(path, encode)
    return path


# -- geometry -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Geometry:
    """Source pixels <-> the suite's metres (ball centre; floor at y = 0).

    Continuous pixel coordinates put pixel ``[i, j]``'s centre at ``(j + 0.5, i + 0.5)``. A ball
    of radius ``radius`` px whose centre is at ``x = 0`` touches the left wall (column
    ``wall_col``); at ``y = 0`` it touches the floor (row ``floor_row``).

    Attributes
    ----------
    size : (int, int)
        ``(H, W)`` of the source frames.
    wall_col, floor_row : float
        Column of the left wall's surface and row of the floor's surface, px.
    px_per_m : (float, float)
        Pixels per metre across and up.
    radius : float
        Ball radius, px.
    source : str
        ``"renderer"`` (default framing) or what the options were.
    """

    size: tuple
    wall_col: float
    floor_row: float
    px_per_m: tuple
    radius: float
    source: str = "renderer"

    def to_metres(self, cr) -> np.ndarray:
        """``[..., (col, row)]`` px to ``[..., (x, y)]`` m."""
        cr = np.asarray(cr, dtype=np.float64)
        sx, sy = self.px_per_m
        x = (cr[..., 0] - self.wall_col - self.radius) / sx
        y = (self.floor_row - self.radius - cr[..., 1]) / sy
        return np.stack([x, y], axis=-1)

    def to_pixels(self, xy) -> np.ndarray:
        """``[..., (x, y)]`` m to ``[..., (col, row)]`` px."""
        xy = np.asarray(xy, dtype=np.float64)
        sx, sy = self.px_per_m
        return np.stack([self.wall_col + self.radius + xy[..., 0] * sx,
                         self.floor_row - self.radius - xy[..., 1] * sy], axis=-1)

    def box_px(self) -> tuple[float, float, float, float]:
        """``(col0, col1, row0, row1)`` of the area the ball can cover (walls, floor, top)."""
        sx, sy = self.px_per_m
        return (self.wall_col, self.wall_col + BOX_WIDTH * sx + 2 * self.radius,
                self.floor_row - BOX_WIDTH * sy - 2 * self.radius, self.floor_row)

    def describe(self) -> str:
        sx, sy = self.px_per_m
        return (f"{self.source}: x = (col - {self.wall_col:.4g} - {self.radius:.3g}) / {sx:.4g}, "
                f"y = ({self.floor_row:.4g} - {self.radius:.3g} - row) / {sy:.4g} "
                f"(metres of the ball's centre; px per metre {sx:.4g} across, {sy:.4g} up; "
                f"frame {self.size[1]}x{self.size[0]} WxH)")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["size"] = list(self.size)
        d["px_per_m"] = list(self.px_per_m)
        d["box_px"] = list(self.box_px())
        d["mapping"] = self.describe()
        return d


def geometry_from_options(size, *, px_per_m=None, floor_row=None, wall_col=None, corners=None,
                          ball_radius_px=None) -> Geometry:
    """The mapping of ``size`` frames: the renderer's framing, or the user's numbers.

    Parameters
    ----------
    size : (int, int)
        ``(H, W)`` of the source frames.
    px_per_m : float, optional
        Pixels per metre (square pixels). Default: the box's 10 m span the width.
    floor_row : float, optional
        Row of the floor's surface (default: the bottom edge, ``H``).
    wall_col : float, optional
        Column of the left wall's surface (default: the left edge, 0).
    corners : (c1, r1, c2, r2), optional
        Two clicked points, the floor's corners with the left and the right wall, px. They
        give ``wall_col = c1``, ``floor_row = (r1 + r2) / 2`` and the scale that puts the right
        wall at ``c2``; exclusive with the three options above.
    ball_radius_px : float, optional
        The ball's radius in the source, px; default ``30/256`` of the smaller side (the
        renderer's).

    Raises
    ------
    ValueError
        Options that put the box (walls and floor) outside the frame, or inconsistent ones.
    """
    h, w = int(size[0]), int(size[1])
    radius = RADIUS_FRACTION * min(h, w) if ball_radius_px is None else float(ball_radius_px)
    if not math.isfinite(radius) or radius <= 0 or 2 * radius >= min(h, w):
        raise ValueError(f"ball_radius_px: expected pixels in (0, {min(h, w) / 2:g}), got "
                         f"{ball_radius_px!r}")
    custom = any(v is not None for v in (px_per_m, floor_row, wall_col))
    if corners is not None:
        if custom:
            raise ValueError("corners: give either corners or px_per_m / floor_row / wall_col, "
                             "not both")
        try:
            c1, r1, c2, r2 = (float(v) for v in corners)
        except (TypeError, ValueError):
            raise ValueError(f"corners: expected four numbers c1 r1 c2 r2, got {corners!r}") from None
        if not all(map(math.isfinite, (c1, r1, c2, r2))) or c2 - c1 <= 2 * radius:
            raise ValueError("corners: expected the right corner more than a ball's width right "
                             f"of the left one, got ({c1:g}, {r1:g}) and ({c2:g}, {r2:g})")
        s = (c2 - c1 - 2 * radius) / BOX_WIDTH
        geo = Geometry((h, w), c1, (r1 + r2) / 2, (s, s), radius,
                       source=f"corners ({c1:g}, {r1:g}) ({c2:g}, {r2:g})")
    elif custom:
        for name, v in (("px_per_m", px_per_m), ("floor_row", floor_row), ("wall_col", wall_col)):
            if v is not None and not math.isfinite(float(v)):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
        s = (w - 2 * radius) / BOX_WIDTH if px_per_m is None else float(px_per_m)
        # the box must be wider than two balls, or every position maps far outside it (a scale
        # of 1e-6 px/m put each tracked ball ~1e6 m away, clipped, and answered the prior)
        if s * BOX_WIDTH < 4 * radius:
            raise ValueError(f"px_per_m: expected at least {4 * radius / BOX_WIDTH:.3g} (the "
                             f"{BOX_WIDTH:g} m box at least two balls of {radius:.3g} px wide), "
                             f"got {px_per_m!r}")
        geo = Geometry((h, w), 0.0 if wall_col is None else float(wall_col),
                       float(h) if floor_row is None else float(floor_row), (s, s), radius,
                       source=f"options px_per_m={s:g} floor_row="
                              f"{h if floor_row is None else floor_row} wall_col="
                              f"{0 if wall_col is None else wall_col}")
    else:
        vg = view_geometry((h, w), radius=radius)
        geo = Geometry((h, w), 0.0, float(h), vg.px_per_m, vg.radius, source="renderer")
    c0, c1, r0, r1 = geo.box_px()
    tol = 1.0  # a pixel of slack for rounding in clicked points
    if c0 < -tol or c1 > w + tol or r1 > h + tol or r1 <= 0 or c0 >= w:
        raise ValueError(
            f"geometry: the box (walls at columns {c0:.1f} and {c1:.1f}, floor at row {r1:.1f}) "
            f"is outside the {w}x{h} frame; walls and floor must be in view")
    if r1 - max(r0, 0.0) < 0.25 * (r1 - r0):
        raise ValueError(f"geometry: less than a quarter of the box's height is in view "
                         f"(rows {r0:.1f}..{r1:.1f} of a {h}-row frame)")
    return geo


# -- finding the ball -----------------------------------------------------------------------------
@dataclass
class BallTrack:
    """Where the ball was found in each frame.

    Attributes
    ----------
    pixels : ndarray, shape (T, 2)
        Sub-pixel centre ``(col, row)`` in the source frame; NaN where not found.
    radius : float
        Median radius of the found blobs, px (NaN if never found).
    found : ndarray, shape (T,), bool
    """

    pixels: np.ndarray
    radius: float
    found: np.ndarray

    @property
    def n_found(self) -> int:
        return int(self.found.sum())


def _background(frames: np.ndarray, max_frames: int = 150) -> np.ndarray:
    """Per-pixel median over (up to ``max_frames`` evenly spread) frames: the static scene."""
    idx = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), max_frames)).astype(int))
    return np.median(frames[idx], axis=0).astype(np.float32)


def find_ball(frames, *, min_contrast: float = 20.0, noise_k: float = 5.0,
              max_gap: int = 5, progress: bool = False) -> BallTrack:
    """Follow the ball through ``frames`` by background subtraction.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W)
        Grey frames, uint8 or floats in [0, 255].
    min_contrast : float
        Fewest grey levels a pixel must differ from the background to belong to a blob.
    noise_k : float
        ... or this many robust standard deviations of the difference image, if more.
    max_gap : int
        Frames without the ball after which the prediction is dropped and the track is
        acquired afresh (on the roundest blob of plausible size).
    progress : bool
        tqdm bar over the frames.

    Returns
    -------
    BallTrack
    """
    fr = np.asarray(frames, dtype=np.float32)
    if fr.ndim != 3 or fr.shape[0] < 1:
        raise ValueError(f"frames: expected a (T, H, W) array, got shape {fr.shape}")
    t_n, h, w = fr.shape
    bg = _background(fr)
    # the noise of the signed difference (robust: 1.4826 MAD), as tracking.track measures it
    sigma = float(noise_level((fr[:: max(1, t_n // 20)] - bg).ravel()))
    thr = max(float(min_contrast), noise_k * sigma)
    pix, radii = _follow(fr, bg, thr, max_gap, progress)
    # A ball that sits or rolls slowly over the same pixels for more than half the clip is in
    # the median, and then invisible there. When the ball is consistently brighter (darker)
    # than the scene, a low (high) quantile over time is the scene wherever the ball covered a
    # pixel in less than 90% of the frames; where that background differs from the median
    # over a twentieth of a ball or more, the ball is followed again against it.
    found = np.isfinite(pix).all(axis=1)
    if found.sum() >= 3:
        # the ball's sign at its centre and at 0.6 radii up, down, left and right of it: a lit,
        # shaded ball can be brighter than the scene at its top and darker at its bottom
        r_f = 0.6 * radii[found]
        offs = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.float64)
        pts = pix[found][:, None, :] + offs[None] * r_f[:, None, None]  # (N, 5, 2)
        c = np.clip(pts.astype(int), 0, [w - 1, h - 1])
        tt = np.broadcast_to(np.flatnonzero(found)[:, None], c.shape[:2])
        sign = np.sign(fr[tt, c[..., 1], c[..., 0]] - bg[c[..., 1], c[..., 0]])
        if abs(sign.mean()) > 0.8:
            idx = np.unique(np.linspace(0, t_n - 1, min(t_n, 150)).astype(int))
            q = np.percentile(fr[idx], 10 if sign.mean() > 0 else 90, axis=0).astype(np.float32)
            r = float(np.nanmedian(radii))
            if (np.abs(q - bg) > thr).sum() >= 0.05 * np.pi * r * r:
                pix, radii = _follow(fr, q, thr, max_gap, progress)
    found = np.isfinite(pix).all(axis=1)
    radius = float(np.nanmedian(radii)) if found.any() else float("nan")
    return BallTrack(pixels=pix, radius=radius, found=found)


def _follow(fr, bg, thr, max_gap, progress):
    """One tracking pass over ``fr`` against background ``bg``: centres (T, 2), radii (T,)."""
    from scipy import ndimage
    from tqdm.auto import tqdm

    t_n, h, w = fr.shape
    pix = np.full((t_n, 2), np.nan)
    radii = np.full(t_n, np.nan)
    areas: list[float] = []
    last: list[tuple[int, np.ndarray]] = []  # (frame, centre) of the last detections
    for t in tqdm(range(t_n), desc="finding the ball", unit="frame", disable=not progress,
                  leave=False):
        signed = fr[t] - bg
        diff = np.abs(signed)
        mask = diff > thr
        if not mask.any():
            continue
        lab, n = ndimage.label(mask)
        if n == 0:
            continue
        idx = np.arange(1, n + 1)
        area = ndimage.sum_labels(np.ones_like(diff), lab, idx)
        cen = np.array(ndimage.center_of_mass(diff, lab, idx))[:, ::-1] + 0.5  # (col, row)
        if areas:
            ref = float(np.median(areas[-20:]))
            ok = (area >= 0.2 * ref) & (area <= 5.0 * ref)
        else:
            ok = area >= 3
        if not ok.any():
            continue
        pred = None
        if last and t - last[-1][0] <= max_gap:
            pred = last[-1][1].copy()
            if len(last) >= 2:
                (t1, p1), (t2, p2) = last[-2], last[-1]
                pred = p2 + (p2 - p1) * (t - t2) / max(1, t2 - t1)
        cand = np.flatnonzero(ok)
        if pred is not None:
            r_ref = math.sqrt(float(np.median(areas[-20:])) / math.pi) if areas else 3.0
            dist = np.hypot(*(cen[cand] - pred).T)
            gate = 4.0 * r_ref + 2.0 * (t - last[-1][0]) * r_ref
            near = dist <= max(gate, 0.1 * min(h, w))
            if not near.any():
                continue
            k = cand[near][np.argmin(dist[near])]
        else:
            # roundness: blob area against the disc spanned by its bounding box
            sl = ndimage.find_objects(lab)
            score = []
            for c in cand:
                s = sl[c]
                ext = max(s[0].stop - s[0].start, s[1].stop - s[1].start)
                score.append(area[c] / (math.pi * (ext / 2) ** 2 + 1e-9) * math.sqrt(area[c]))
            k = cand[int(np.argmax(score))]
        # centre and size: the ball's pixels segmented by |difference| and filled to their hull,
        # each weighted by the fraction of it the ball covers (tracking.ball_centre): a lit top
        # that barely differs from the wall counts as much as the dark bottom. The expected
        # radius is the recent balls'; on (re)acquisition the blob's (and its pieces') own,
        # then the covered area's.
        found_r = radii[np.isfinite(radii)][-20:]
        if found_r.size:
            r_exp, centre = float(np.median(found_r)), cen[k]
        else:
            # a shaded ball can fall apart where its shading crosses the wall's grey: blobs
            # within two of the chosen blob's radii are its other pieces
            own = math.sqrt(area[k] / math.pi)
            part = np.hypot(*(cen - cen[k]).T) <= 2.0 * own + 1.0
            r_exp = math.sqrt(area[part].sum() / math.pi)
            centre = (cen[part] * area[part, None]).sum(axis=0) / area[part].sum()
        for _ in range(3):  # re-centred, the search window takes in the whole ball
            new, cov = ball_centre(signed, thr, centre, r_exp)
            if cov <= 0:
                break
            moved = float(np.hypot(*(new - centre)))
            centre = new
            if not found_r.size:
                r_exp = math.sqrt(cov / math.pi)
            if moved < 0.01:
                break
        # the suite's one rule (tracking.ball_seen), as tracking.track applies it; a disc wider
        # than half the frame's smaller side is no ball in flight
        if (cov <= 0 or r_exp > min(h, w) / 4
                or not ball_seen(diff[None], centre[None], r_exp, thr)[0]):
            continue
        c0, r0 = float(centre[0]), float(centre[1])
        radii[t] = math.sqrt(cov / math.pi)
        pix[t] = (c0, r0)
        areas.append(float(area[k]))
        last = (last + [(t, np.array([c0, r0]))])[-2:]
    return pix, radii


def model_frames(positions, size) -> np.ndarray:
    """The frames a video model was trained on, drawn at the tracked positions.

    Parameters
    ----------
    positions : ndarray, shape (T, 2)
        Metres, NaN where the ball was not found (those frames stay black, as the renderer's
        dropped frames).
    size : (int, int)
        ``(H, W)`` of the model's view.

    Returns
    -------
    ndarray, shape (T, H, W), uint8
    """
    from sysid_bench.render import render

    pos = np.asarray(positions, dtype=np.float64)
    seen = np.isfinite(pos).all(axis=1)
    states = np.zeros((1, len(pos), 4))
    states[0, seen, :2] = pos[seen]
    states[0, ~seen, :2] = -100.0  # far outside the view: nothing drawn
    out = render(states, size=tuple(size))[0]
    out[~seen] = 0
    return out


def observe(frames, model_size=None, geometry: dict | None = None, dt: float = 0.05,
            progress: bool = False):
    """A video's frames as the Observation a method takes, via the ball's track.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W)
        Grey source frames at the model's rate.
    model_size : (int, int), optional
        ``(H, W)`` of a video model's view: the Observation holds frames re-drawn there
        (:func:`model_frames`). None: it holds the tracked positions (clipped onto the box:
        a ball at a wall or on the floor is tracked a few mm outside it).
    geometry : dict, optional
        Options of :func:`geometry_from_options`; with any of them, the ball's radius is the
        measured one unless given.
    dt : float

    Returns
    -------
    obs : Observation
        ``floor = 0`` (the geometry puts the floor there).
    positions : ndarray, shape (T, 2)
        Tracked positions in metres (NaN where not found), not clipped.
    track : BallTrack
    geometry : Geometry
    """
    from sysid_bench.estimator import Observation

    fr = np.asarray(frames)
    t_n, h, w = fr.shape
    geo_opts = dict(geometry or {})
    trk = find_ball(fr, progress=progress)
    if (geo_opts.get("ball_radius_px") is None and trk.n_found
            and any(geo_opts.get(k) is not None for k in ("px_per_m", "floor_row", "wall_col",
                                                         "corners"))):
        geo_opts["ball_radius_px"] = trk.radius  # real footage: the ball's own size
    geo = geometry_from_options((h, w), **geo_opts)
    pos = geo.to_metres(trk.pixels)
    if model_size is not None:
        obs = Observation(frames=model_frames(pos, model_size), dt=dt, floor=0.0)
    else:
        clipped = pos.copy()
        clipped[:, 0] = np.clip(clipped[:, 0], 0.0, BOX_WIDTH)
        clipped[:, 1] = np.clip(clipped[:, 1], 0.0, BOX_WIDTH)
        obs = Observation(positions=clipped, dt=dt, floor=0.0)
    return obs, pos, trk, geo
