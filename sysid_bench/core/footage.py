"""Video files to the suite's inputs: decode, encode, map pixels to metres, find the ball.

The core half of ``sysid-bench identify`` (:mod:`sysid_bench.apps.video`, the command, builds on it),
used as well by the MuJoCo scenes (:mod:`sysid_bench.core.mujoco_scene`) and the benchmark's
experiment on them; it knows no method.

1. :func:`read_video` decodes the file with **PyAV** (``av``: FFmpeg's libraries in the wheel,
   libx264 included) and converts every frame to grey. Methods that simulate at any step take
   every frame at the capture's own ``dt`` (``fps=None``; a variable frame rate put on a grid
   at its median interval); a method built for one rate (Vid2Param: 20 frames/s) gets the
   clip resampled by taking, for each tick, the source frame nearest in time (blending frames
   would show two half-bright balls). PyAV rather than imageio-ffmpeg because it gives each frame's own
   presentation time and the stream's rate from the container, in process (imageio-ffmpeg
   pipes raw frames from an ``ffmpeg`` subprocess and parses its rate from the log text), and
   because the same wheel writes H.264 (:func:`write_video`) without any system FFmpeg.
2. :class:`Geometry` maps source pixels to the suite's metres. By default the frame is framed
   as :mod:`sysid_bench.core.render` frames its videos, at the file's resolution: the box
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
5. A real camera's clip of any system (issue 38): :func:`find_object` follows the object at
   any resolution ("not seen" where it is not, or where a blob is not its size), and
   :func:`camera_for` builds the :class:`Camera` (pixels to metres in the system's world
   frame) from a given scale, the object's known size frame by frame, or a pendulum's known
   length and the arc its bob sweeps; the scale's uncertainty widens the intervals
   (:func:`widen_for_scale`). :func:`parse_known` and :func:`parse_prior` read what the user
   knows; :func:`check_out_folder` keeps ``--out`` from overwriting files identify did not
   write.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numba
import numpy as np

from sysid_bench.core._io import atomic_write
from sysid_bench.core.physics import BOX_WIDTH
from sysid_bench.core.render import RADIUS_FRACTION, view_geometry
from sysid_bench.core.tracking import ball_centre, ball_seen, noise_level

__all__ = [
    "MODEL_FPS",
    "VideoError",
    "Clip",
    "read_video",
    "thin_clip",
    "write_video",
    "Geometry",
    "geometry_from_options",
    "find_ball",
    "BallTrack",
    "model_frames",
    "observe",
    "ROTATIONS",
    "OBJECT_SIZE_RANGE_M",
    "LENGTH_POWER",
    "rotate_frames",
    "turned_chroma",
    "chroma_spacing",
    "fit_circle",
    "find_object",
    "follow_object_box",
    "Camera",
    "camera_for",
    "widen_for_scale",
    "loosen_held",
    "report_held",
    "track_noise",
    "camera_check",
    "TRACK_CHECK_FACTOR",
    "parse_known",
    "parse_prior",
    "knowledge_record",
    "OUT_MARKER",
    "OUT_FILES",
    "check_out_folder",
    "CAMERA_SYSTEMS",
    "CameraClip",
    "clip_options",
    "observe_clip",
    "TrackCamera",
    "camera_for_track",
    "ABSENT_END_M",
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
    """A decoded video, grey, at the capture's own rate or resampled to a method's.

    Attributes
    ----------
    frames : ndarray, shape (T, H, W), uint8
        Grey frames, ``1 / fps`` seconds apart.
    times : ndarray, shape (T,)
        Source presentation time of each kept frame, seconds from the first frame (after
        ``--fps`` and the window).
    source_fps : float
        The file's frame rate (from the stream, else from the frame times).
    source_frames : int
        Frames decoded from the file.
    colour : bool
        The file stored colour (it was converted to grey: ITU-R BT.601 luma, FFmpeg's "gray").
    fps : float
        Rate of ``frames``: the one asked of :func:`read_video`, or the capture's own (the
        median interval's for a variable frame rate).
    notes : list of str
        What was done to the file (capture rate, window, resampling), one sentence each.
    colour_frames : ndarray, shape (T, h, w, 3), uint8, optional
        The same frames in RGB, area-averaged so that the larger side is at most
        :data:`COLOUR_SIDE` (what :func:`find_object` follows a real object by); None unless
        :func:`read_video` was asked for them and the file stores colour.
    chroma_px : (float, float)
        Source pixels ``(across, down)`` between the file's colour samples: ``(2, 2)`` for the
        4:2:0 of H.264, HEVC and VP9 as phones write them, ``(1, 1)`` for full colour or grey.
        The colour is as blurred as its samples are coarse (:func:`find_object`).
    """

    frames: np.ndarray
    times: np.ndarray
    source_fps: float
    source_frames: int
    colour: bool
    fps: float = MODEL_FPS
    notes: list = field(default_factory=list)
    path: str = ""
    colour_frames: np.ndarray | None = None
    chroma_px: tuple = (1.0, 1.0)


def chroma_spacing(pix_fmt) -> tuple[float, float]:
    """Source pixels ``(across, down)`` between a pixel format's colour samples.

    ``"yuv420p"`` (H.264's usual) -> ``(2.0, 2.0)``, ``"yuv422p"`` -> ``(2.0, 1.0)``; a
    format without subsampled colour (RGB, 4:4:4, grey) or one FFmpeg does not name ->
    ``(1.0, 1.0)``.
    """
    import av

    try:
        comps = av.VideoFormat(str(pix_fmt), 64, 64).components
    except (ValueError, TypeError):  # a name FFmpeg does not know
        return 1.0, 1.0
    if len(comps) < 3:
        return 1.0, 1.0
    w = min(int(c.width) for c in comps[1:3]) or 64
    h = min(int(c.height) for c in comps[1:3]) or 64
    return 64.0 / w, 64.0 / h


#: Larger side (px) of :attr:`Clip.colour_frames`: the tracker's working size on real footage.
COLOUR_SIDE = 640


def _fail(path, problem: str) -> VideoError:
    return VideoError(f"{path}: {problem}")


def read_video(path, fps: float | None = MODEL_FPS, *, progress: bool | None = None,
               start: float | None = None, end: float | None = None,
               capture_fps: float | None = None, colour: bool = False,
               rgb: bool = False) -> Clip:
    """Decode a video file to grey frames at ``fps``, or at the capture's own rate.

    Parameters
    ----------
    path : str or Path
        Any container and codec FFmpeg reads (mp4, avi, mkv, mov, webm, gif, ...).
    fps : float or None
        Frame rate to resample to (nearest source frame in time for each output tick), for a
        method built for one rate (:func:`sysid_bench.core.estimator.frame_rate_of`). None:
        the capture's own rate, every frame kept (the container's rate, or ``capture_fps``);
        a variable-frame-rate file (intervals differing by more than 10% of their median) is
        put on a uniform grid at its median interval by the nearest frame in time, and a
        note says so and how far a frame lies from its tick.
    progress : bool, optional
        tqdm bar while decoding; default: only for files over 300 frames, on a terminal.
    start, end : float, optional
        Seconds of capture time (from the first frame) to keep: frames before ``start`` (a
        hand still holding the object) and after ``end`` are dropped; ``times`` then count
        from the first frame kept.
    capture_fps : float, optional
        The rate the frames were captured at, when it is not the container's (a slow-motion
        file: captured at 240 frames/s, stored at 30). Every frame time is stretched by the
        container rate over ``capture_fps``; the frames' own spacing (variable frame rate)
        is kept.
    colour : bool
        Also keep each frame in RGB at a working size (:attr:`Clip.colour_frames`), when the
        file stores colour: a real object is told from a wall of the same grey by its hue.
    rgb : bool
        Keep colour: ``Clip.frames`` is then (T, H, W, 3) RGB (objects told apart by colour,
        :func:`sysid_bench.core.tracking.track_colours`).

    Returns
    -------
    Clip

    Raises
    ------
    VideoError
        Missing, unreadable, empty or zero-frame file, not a video, or no readable frame rate;
        the message starts with the path.
    ValueError
        ``start``/``end`` outside the clip or not in order, ``capture_fps`` not > 0; the
        message names the argument.
    """
    try:
        import av
    except ImportError as exc:  # pragma: no cover - av is a core dependency
        raise VideoError(f"{path}: reading videos needs PyAV (pip install av): {exc}") from exc
    if fps is not None:
        if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)) \
                or not math.isfinite(float(fps)) or float(fps) <= 0:
            raise ValueError(f"fps: expected None or a frame rate > 0, got {fps!r}")
        fps = float(fps)
    for name, v in (("capture_fps", capture_fps), ("start", start), ("end", end)):
        if v is not None and (not math.isfinite(float(v)) or float(v) < 0
                              or (name == "capture_fps" and float(v) <= 0)):
            raise ValueError(f"{name}: expected a finite number "
                             f"{'> 0' if name == 'capture_fps' else '>= 0'} (seconds"
                             f"{'' if name != 'capture_fps' else ' -> frames/s'}), got {v!r}")
    if start is not None and end is not None and float(end) <= float(start):
        raise ValueError(f"end: expected a time after start = {start:g} s, got {end:g} s")
    p = Path(path)
    if not p.exists():
        raise _fail(path, "no such file")
    if p.is_dir():
        raise _fail(path, "is a directory, not a video file")
    if not os.access(p, os.R_OK):
        raise _fail(path, "cannot be read (permission denied)")
    if p.stat().st_size == 0:
        raise _fail(path, "empty file (0 bytes)")
    for skip in (True, False):  # the plain decode again where a window's shortcut cannot hold
        dec = _decode(av, p, path, progress, colour, rgb, start, end, capture_fps, skip)
        if dec is not None:
            break
    frames, small, times, rate, tick, colour_file, chroma, n_skip, lut = dec
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
        rate, t = fps or MODEL_FPS, np.zeros(1)
    else:
        raise _fail(path, "the frame rate cannot be read (no stream rate, no frame times)")
    notes = []
    if capture_fps is not None:
        stretch = rate / float(capture_fps)
        t, tick = t * stretch, tick * stretch
        notes.append(f"capture rate {float(capture_fps):g} frames/s (the container says "
                     f"{rate:.4g}): time runs {stretch:.4g}x the file's")
        rate = float(capture_fps)
    if start is not None or end is not None:
        lo = 0.0 if start is None else float(start)
        hi = math.inf if end is None else float(end)
        keep = (t >= lo - 1e-9) & (t <= hi + 1e-9)
        if keep.sum() < 1:
            name = "start" if lo > t[-1] else "end" if end is not None and hi < t[0] else "start"
            raise ValueError(f"{name}: the window {lo:g} to {hi:g} s holds no frame of the clip "
                             f"(0 to {t[-1]:.4g} s, {len(t)} frames)")
        first = int(np.flatnonzero(keep)[0])
        # the frames decoded before the window were not kept (_decode): none of them is in it
        frames, small = frames.subset(keep[n_skip:]), small.subset(keep[n_skip:])
        t = t[keep] - t[first]
        notes.append(f"window {lo:g} to {min(hi, float(t[-1]) + lo):.4g} s: {len(frames)} frames")
    gaps = np.diff(t)
    mean_gap = float(t[-1] / (len(t) - 1)) if len(t) > 1 else 1.0 / rate
    # a browser's or phone's variable frame rate: an interval off the mean by more than 10%
    # beyond one tick of the container's clock (16/17 ms at 60 frames/s in 1/1000 s is not)
    vfr = len(gaps) > 1 and float(np.max(np.abs(gaps - mean_gap))) > 0.1 * mean_gap + tick
    if fps is None and not vfr:
        # the capture's own rate, every frame kept; a container rate its frames contradict
        # (by more than 1%) gives way to their own spacing
        own = rate if len(gaps) == 0 or abs(rate * mean_gap - 1.0) <= 0.01 else 1.0 / mean_gap
        if own != rate:
            notes.append(f"the frames are {1e3 * mean_gap:.4g} ms apart, not the {rate:.4g} "
                         f"frames/s the container says: read at {own:.4g} frames/s")
        # only the frames kept become grey
        return Clip(frames=frames.take(np.arange(len(frames)), path, lut), times=t,
                    source_fps=float(rate),
                    source_frames=len(frames), colour=colour_file, fps=float(own), notes=notes,
                    path=str(path),
                    colour_frames=small.take(np.arange(len(small)), path) if len(small) else None,
                    chroma_px=chroma)
    med = float(np.median(gaps)) if len(gaps) else mean_gap
    if fps is None:
        # the grid: the median interval (blind to dropped frames' long gaps), refined as the
        # mean of the intervals near it (undoing the clock's rounding: 33/34 ms -> 33.3 ms)
        near = gaps[np.abs(gaps - med) <= 0.25 * med]
        target = 1.0 / float(np.mean(near))
    else:
        target = fps
    if vfr or abs(rate - target) > 1e-3 * target:
        ticks = np.arange(0.0, t[-1] + 0.5 / rate + 1e-9, 1.0 / target)
        # nearest source frame to each tick (blending two would show two half-bright objects)
        j = np.clip(np.searchsorted(t, ticks), 1, len(t) - 1)
        j = np.where(np.abs(t[j - 1] - ticks) <= np.abs(t[j] - ticks), j - 1, j)
        if len(t) == 1:
            j = np.zeros(1, dtype=int)
        t_kept = t[j]
        if vfr:
            off = float(np.max(np.abs(t_kept - ticks[:len(j)]))) if len(j) else 0.0
            how = (f"its typical interval, {1e3 / target:.4g} ms" if fps is None
                   else f"the method's {fps:g} frames/s")
            notes.append(f"variable frame rate (frames {1e3 * gaps.min():.3g} to "
                         f"{1e3 * gaps.max():.3g} ms apart, median {1e3 * med:.3g} ms): put on a "
                         f"uniform grid at {how} by the nearest frame in time, {len(frames)} -> "
                         f"{len(j)} frames, each at most {1e3 * off:.3g} ms from its tick")
        else:
            notes.append(f"resampled from {rate:.4g} to {target:g} frames/s (nearest frame in "
                         f"time): {len(frames)} -> {len(j)} frames"
                         + ("; the source is slower than the model, so frames repeat"
                            if rate < target else ""))
    else:
        j, t_kept = np.arange(len(frames)), t
    # only the frames kept become grey (a 30 frames/s file resampled to 20 keeps 2 in 3)
    return Clip(frames=frames.take(j, path, lut), times=t_kept, source_fps=float(rate),
                source_frames=len(frames), colour=colour_file, fps=float(target), notes=notes,
                path=str(path), colour_frames=small.take(j, path) if len(small) else None,
                chroma_px=chroma)


def _decode(av, p: Path, path, progress, colour, rgb, start, end, capture_fps, skip: bool):
    """:func:`read_video`'s decoding: the frames (grey, or ``rgb``), their colour copies
    (``colour``), every decoded frame's time, the container's rate and clock tick, whether the
    file stores colour, its chroma spacing, how many frames before the window were decoded
    without being kept (``skip``) and the luma -> grey table (:func:`_luma_table`). None:
    decode again without ``skip`` (the shortcut met times it cannot trust, or kept nothing)."""
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
        # one tick of the container's clock: timestamps are rounded to it (1 ms in mkv/webm)
        tick = float(stream.time_base) if stream.time_base else 0.0
        colour_file = not str(stream.codec_context.pix_fmt or "").startswith("gray")
        chroma = chroma_spacing(stream.codec_context.pix_fmt) if colour_file else (1.0, 1.0)
        n_hint = int(stream.frames or 0)
        show = (n_hint > _PROGRESS_FRAMES) if progress is None else bool(progress)
        # each decoded frame written once into one array (a list stacked afterwards copied a
        # 1080p clip's frames a second time: 0.5-0.8 s of its 2.3 s)
        frames, small, times = _FrameStore(n_hint), _FrameStore(n_hint), []
        want_rgb = bool(colour) and colour_file
        # one scaler for the clip (a frame's own reformat() sets up swscale for every frame:
        # 8% of the colour copy's CPU), the same bytes
        scaler = av.video.reformatter.VideoReformatter() if want_rgb else None
        lut = None  # the luma -> grey table (False: FFmpeg converts every frame)
        # a window (start, end) read from the frames' own times as they come: the frames
        # before it are not kept (nor converted), and decoding stops after it; where the
        # times turn out unusable (missing, out of order), the caller decodes it all again
        lo = 0.0 if start is None else float(start)
        hi = math.inf if end is None else float(end)
        stretch = 1.0 if capture_fps is None else rate / float(capture_fps)
        window = skip and (lo > 0 or math.isfinite(hi)) and math.isfinite(rate) and rate > 0
        ordered, inside, stopped, n_skip = True, False, False, 0
        from tqdm.auto import tqdm

        with tqdm(total=n_hint or None, desc=f"reading {p.name}", unit="frame",
                  disable=not show or (progress is None and not sys.stderr.isatty()),
                  leave=False) as bar:
            try:
                for fr in container.decode(stream):
                    tm = np.nan if fr.time is None else float(fr.time)
                    if window:
                        ordered = ordered and math.isfinite(tm) and (not times or tm > times[-1])
                        if ordered:
                            rel = (tm - times[0] if times else 0.0) * stretch
                            if rel > hi + 1e-9 and inside:
                                stopped = True  # every later frame is later still
                                break
                            if rel < lo - 1e-9 and not frames:
                                times.append(tm)  # before the window: its time only
                                n_skip += 1
                                bar.update(1)
                                continue
                            inside = inside or lo - 1e-9 <= rel <= hi + 1e-9
                    if rgb:  # full colour frames (told apart by colour), kept as they are
                        frames.put(fr.to_ndarray(format="rgb24"))
                    else:
                        key = (fr.format.name, fr.color_range, fr.colorspace)
                        if lut is None:
                            lut, lut_key = _luma_table(fr), key
                        y = _luma(fr, copy=False) if lut is not False and key == lut_key \
                            else None
                        # the luma plane, made grey by the table after decoding (kept frames
                        # only, on threads); a frame whose format is not the first's: FFmpeg's
                        frames.put(y if y is not None else fr.to_ndarray(format="gray"),
                                   raw=y is not None)
                    if want_rgb:  # FFmpeg's area filter: the mean colour of each block
                        k = max(1, math.ceil(max(fr.width, fr.height) / COLOUR_SIDE))
                        small.put(scaler.reformat(fr, width=max(1, fr.width // k),
                                                  height=max(1, fr.height // k),
                                                  format="rgb24",
                                                  interpolation="AREA").to_ndarray())
                    times.append(tm)
                    bar.update(1)
            except av.error.EOFError:
                pass  # a stream declared but holding no frames: "zero frames" below
            except av.error.FFmpegError as exc:
                if not frames:
                    if n_skip:
                        return None  # the frames before the window may be all there is
                    raise _fail(path, f"not a readable video ({_av_reason(exc)})") from None
                # a truncated file: keep the frames decoded before the damage
    finally:
        container.close()
    if skip and (n_skip or stopped) and (not ordered or not frames):
        return None
    return frames, small, times, rate, tick, colour_file, chroma, n_skip, lut


def thin_clip(clip: Clip, max_frames: int | None, method: str = "the method") -> Clip:
    """Every k-th frame of ``clip``, the fewest k that leaves at most ``max_frames``.

    For a method whose cost grows with the observations (:func:`sysid_bench.core.estimator.
    frame_cap_of`): a 10 s clip at 240 frames/s is 2400 of them. The frames kept are still
    evenly spaced, at k times the dt.

    Parameters
    ----------
    clip : Clip
    max_frames : int or None
        None: the clip as it is.
    method : str
        Named in the note.

    Returns
    -------
    Clip
        ``frames`` (ceil(T / k), H, W), ``fps`` divided by k, a note saying so; the same
        object when nothing was dropped.
    """
    if max_frames is None or len(clip.frames) <= max_frames:
        return clip
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) \
            or max_frames < 1:
        raise ValueError(f"max_frames: expected None or an int >= 1, got {max_frames!r}")
    k = -(-len(clip.frames) // int(max_frames))
    keep = slice(None, None, k)
    note = (f"{method} takes at most {int(max_frames)} observations: one frame in {k} kept "
            f"({len(clip.frames)} -> {len(clip.frames[keep])} frames, "
            f"{clip.fps / k:.4g} frames/s)")
    return replace(clip, frames=np.ascontiguousarray(clip.frames[keep]), times=clip.times[keep],
                   fps=clip.fps / k, notes=[*clip.notes, note],
                   colour_frames=None if clip.colour_frames is None
                   else np.ascontiguousarray(clip.colour_frames[keep]))


def _av_reason(exc) -> str:
    s = str(getattr(exc, "strerror", None) or exc)
    return s.split(":")[0].strip() if ": '" in s else s.strip()


#: 8-bit pixel formats whose first plane is the luma FFmpeg's "gray" is computed from, pixel by
#: pixel (a table of 256 values: limited-range luma is stretched to 0-255, full range kept)
_LUMA_FORMATS = frozenset({"yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p",
                           "yuv440p", "yuvj440p", "yuv411p", "yuv410p", "nv12", "nv21", "gray"})


def _luma(fr, copy: bool = True) -> np.ndarray | None:
    """The luma plane of a decoded frame as a (H, W) uint8 copy (``copy=False``: a view of the
    decoder's buffer, valid until the next frame); None for other formats."""
    if fr.format.name not in _LUMA_FORMATS:
        return None
    pl = fr.planes[0]
    if pl.width != fr.width or pl.height != fr.height:
        return None
    view = np.frombuffer(pl, dtype=np.uint8).reshape(pl.height, pl.line_size)
    return view[:, : pl.width].copy() if copy else view[:, : pl.width]  # buffers are reused


def _luma_table(fr):
    """FFmpeg's luma -> grey conversion for ``fr``'s format and range as a (256,) uint8 table,
    or False where it is not one (or a frame of fewer than 256 pixels cannot show it).

    FFmpeg's "gray" (BT.601 luma; limited-range 16-235 stretched to 0-255) depends on each
    pixel's luma alone, so one table gives the same bytes as ``to_ndarray(format="gray")`` at a
    fraction of the cost (swscale's conversion was 4.7 ms of CPU per 1080p frame, the table 1.4
    ms, the plane's copy 0.3 ms). The table is read from FFmpeg itself: a frame of the same size,
    format, range and colour space whose luma runs through all 256 values in every column is
    converted, and the table is kept only when each value gave one grey level and the table
    reproduces FFmpeg's grey of ``fr`` byte for byte.
    """
    try:
        import av

        y = _luma(fr)
        if y is None:
            return False
        syn = av.VideoFrame(fr.width, fr.height, fr.format.name)
        syn.color_range, syn.colorspace = fr.color_range, fr.colorspace
        pl = syn.planes[0]
        # the 256 levels in raster order (every level in a frame of 256 pixels or more)
        ramp = np.zeros((pl.height, pl.line_size), dtype=np.uint8)
        ramp[:, : pl.width] = np.resize(np.arange(256, dtype=np.uint8),
                                        (pl.height, pl.width))
        pl.update(ramp.tobytes())
        for q in syn.planes[1:]:  # neutral chroma (grey does not read it)
            q.update(np.full(q.buffer_size, 128, dtype=np.uint8).tobytes())
        grey = syn.to_ndarray(format="gray")
        if grey.size < 256:
            return False
        table = np.ascontiguousarray(grey.ravel()[:256])  # level v at raster position v
        # one grey level per luma level wherever it stands, and FFmpeg's grey of this frame
        if not np.array_equal(table[ramp[:, : pl.width]], grey):
            return False
        return table if np.array_equal(table[y], fr.to_ndarray(format="gray")) else False
    except Exception:  # noqa: BLE001 - any surprise: FFmpeg converts every frame, as before
        return False


@numba.njit(cache=True, nogil=True)
def _apply_table(src, table, out):  # pragma: no cover - compiled
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            out[i, j] = table[src[i, j]]


class _FrameStore:
    """Decoded frames of one shape, each copied once into one growing array.

    :meth:`put` copies the next frame into its row (a frame of another shape is kept aside),
    :meth:`subset` narrows to a window, and :meth:`take` returns frames by index: a view for a
    run of consecutive frames that fills most of the array, else a copy. A luma plane stored
    ``raw`` becomes grey through the table in :meth:`take`, for the frames taken only, on
    threads. Frames of another shape are refused only when taken with the others ("frames change
    size within the video"), as the list stacked before was.
    """

    def __init__(self, n_hint: int = 0):
        self.buf: np.ndarray | None = None
        self.n = 0
        self.hint = max(int(n_hint), 8)
        self.aside: dict[int, np.ndarray] = {}
        self.raw: list[bool] = []  # a luma plane still to go through the table
        self.index: np.ndarray | None = None  # a window's frames (subset), else all

    def __len__(self) -> int:
        return self.n if self.index is None else len(self.index)

    def put(self, frame: np.ndarray, raw: bool = False) -> None:
        """Store a copy of ``frame`` (``raw``: a luma plane the table has not seen)."""
        if self.buf is None:
            self.buf = np.empty((self.hint, *frame.shape), dtype=frame.dtype)
        if frame.shape != self.buf.shape[1:] or frame.dtype != self.buf.dtype:
            self.aside[self.n] = np.array(frame)
        else:
            if self.n == len(self.buf):  # more frames than the stream declared
                self.buf = np.concatenate([self.buf, np.empty_like(self.buf)])
            self.buf[self.n] = frame
        self.raw.append(bool(raw))
        self.n += 1

    def subset(self, keep: np.ndarray) -> _FrameStore:
        """The store narrowed to the frames where ``keep`` (len(self),) bool is True (an empty
        store, the colour copy not asked for, stays empty)."""
        if self.n:
            self.index = np.flatnonzero(keep) if self.index is None else self.index[keep]
        return self

    def take(self, idx, path, table=None) -> np.ndarray:
        """Frames ``idx`` (of this store's frames, after :meth:`subset`), (len(idx), ...); the
        raw luma planes among them through ``table`` first (in place, once each)."""
        idx = np.asarray(idx, dtype=np.int64)
        if self.index is not None:
            idx = self.index[idx]
        rows = [int(i) for i in np.unique(idx) if self.raw[int(i)]]
        if rows:
            arrays = [self.aside[i] if i in self.aside else self.buf[i] for i in rows]

            def part(lo, hi):
                for a in arrays[lo:hi]:
                    _apply_table(a, table, a)

            _over_frames(part, len(arrays))
            for i in rows:
                self.raw[i] = False
        odd = [int(i) for i in idx if int(i) in self.aside]
        if odd:
            shapes = sorted({self.aside[i].shape for i in odd}
                            | ({self.buf.shape[1:]} if len(odd) < len(idx) else set()))
            if len(shapes) > 1:
                raise _fail(path, f"frames change size within the video: {shapes}")
            return np.stack([self.aside[int(i)] for i in idx])
        if len(idx) and np.array_equal(idx, np.arange(idx[0], idx[0] + len(idx))) \
                and len(idx) >= 0.75 * self.n:
            # a view: no second copy (the rows never written were never resident either)
            return self.buf[idx[0]: idx[0] + len(idx)]
        return self.buf[idx]


def _kernel_threads() -> int:
    """Threads a compiled per-frame kernel splits a clip over: the cores this process may
    use, at most 4."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        n = os.cpu_count() or 1
    return max(1, min(4, n))


def _over_frames(fn, n_frames: int, min_part: int = 8) -> None:
    """``fn(lo, hi)`` for contiguous parts of ``range(n_frames)``, each on its own thread.

    For kernels that release the GIL and treat each frame alone (the grey table, the colour
    distance): the same bytes however the frames are split; on two free cores the step takes
    about half the wall time (its CPU is the same). Parts of fewer than ``min_part`` frames are
    not worth a thread.
    """
    k = min(_kernel_threads(), max(1, n_frames // int(min_part)))
    if k <= 1:
        fn(0, n_frames)
        return
    from concurrent.futures import ThreadPoolExecutor

    bounds = np.linspace(0, n_frames, k + 1).astype(int)
    with ThreadPoolExecutor(k) as ex:
        for f in [ex.submit(fn, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]:
            f.result()  # an error in a part is raised here


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
    radii : ndarray, shape (T,), optional
        Each frame's radius, px (NaN where not found): the object's apparent size frame by
        frame, from which ``--object-size-m`` reads the scale.
    """

    pixels: np.ndarray
    radius: float
    found: np.ndarray
    radii: np.ndarray | None = None

    @property
    def n_found(self) -> int:
        return int(self.found.sum())

    def first_seen(self) -> int:
        """Index of the first frame the object was found in (0 when never found)."""
        idx = np.flatnonzero(self.found)
        return int(idx[0]) if idx.size else 0

    def from_frame(self, k: int) -> BallTrack:
        """This track without its first ``k`` frames (``k >= 0``)."""
        k = int(k)
        if not 0 <= k <= len(self.pixels):
            raise ValueError(f"k: expected a frame index in [0, {len(self.pixels)}], got {k}")
        return BallTrack(pixels=self.pixels[k:], radius=self.radius, found=self.found[k:],
                         radii=None if self.radii is None else self.radii[k:])


@numba.njit(cache=True, nogil=True)
def _transpose(src, out):  # pragma: no cover - compiled
    """``out[:] = src.T`` in 64 x 64 blocks (numpy's copy of the transposed view walks a
    whole row of ``src`` between two writes: 4x the CPU on a (150, 230400) stack)."""
    n, p = src.shape
    for j0 in range(0, p, 64):
        for i0 in range(0, n, 64):
            for j in range(j0, min(p, j0 + 64)):
                for i in range(i0, min(n, i0 + 64)):
                    out[j, i] = src[i, j]


def _sorted_over_time(stack: np.ndarray) -> np.ndarray:
    """Each pixel's samples of ``stack`` (n, ...) contiguous and sorted: shape (pixels, n)."""
    n = stack.shape[0]
    flat = stack.reshape(n, -1)
    if flat.size >= 1 << 16 and flat.dtype in (np.float32, np.uint8):  # a clip's background
        y = np.empty(flat.shape[::-1], dtype=flat.dtype)
        _transpose(flat, y)
    else:
        y = np.ascontiguousarray(flat.T)
    y.sort(axis=1)
    return y


def _median_of_sorted(y: np.ndarray, shape) -> np.ndarray:
    """The median of each row of sorted ``y`` (pixels, n) (the middle one, or the mean of the
    two middle ones by ``np.mean`` as ``np.median`` takes it), reshaped to ``shape``."""
    n = y.shape[1]
    mid = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
    return np.mean(y[:, mid], axis=1).reshape(shape)


def _median_over_time(stack: np.ndarray) -> np.ndarray:
    """``np.median(stack, axis=0)``, the same values, 3x faster on a (150, 360, 640) stack.

    The samples of each pixel are made contiguous and sorted in place; the middle one (or the
    mean of the two middle ones, by ``np.mean`` as ``np.median`` takes it) is the median.
    ``np.median`` partitions along the first axis, a stride of a whole frame between samples.
    """
    return _median_of_sorted(_sorted_over_time(stack), stack.shape[1:])


def _background_samples(frames: np.ndarray, max_frames: int = 150) -> np.ndarray:
    """The samples :func:`_background` takes the median of, sorted (:func:`_sorted_over_time`):
    each pixel's value in up to ``max_frames`` evenly spread frames."""
    idx = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), max_frames)).astype(int))
    return _sorted_over_time(frames[idx])


def _background(frames: np.ndarray, max_frames: int = 150) -> np.ndarray:
    """Per-pixel median over (up to ``max_frames`` evenly spread) frames: the static scene."""
    return _median_of_sorted(_background_samples(frames, max_frames),
                             frames.shape[1:]).astype(np.float32)


def find_ball(frames, *, min_contrast: float = 20.0, noise_k: float = 5.0,
              max_gap: int = 5, progress: bool = False, reset_on_loss: bool = False,
              round_power: float = 1.0, window: bool = True) -> BallTrack:
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
    reset_on_loss : bool
        Forget the sizes seen when the track is lost for more than ``max_gap`` frames (real
        footage: a hand followed before the ball is let go). Off by default: the suite's
        renders and MuJoCo scenes are tracked as they always were.
    round_power : float
        How much a blob's roundness (its area over its bounding disc's) outweighs its size
        when the track is (re)acquired: the score is ``roundness**round_power * sqrt(area)``.
        Real footage uses 2, so that a thrown ball beats the larger arm that threw it.
    window : bool
        While the track holds, search each frame only in a window around the predicted
        position (the same answer as the whole frame's, bit for bit, several times faster on
        large frames; the whole frame when a blob crosses the window's edge or the track is
        lost). False: every frame searched whole, as before.

    Returns
    -------
    BallTrack
    """
    fr = np.asarray(frames, dtype=np.float32)
    if fr.ndim != 3 or fr.shape[0] < 1:
        raise ValueError(f"frames: expected a (T, H, W) array, got shape {fr.shape}")
    t_n, h, w = fr.shape
    # the background's samples, kept sorted for the quantile below (the same frames)
    samples = _background_samples(fr)
    bg = _median_of_sorted(samples, (h, w)).astype(np.float32)
    # the noise of the signed difference (robust: 1.4826 MAD), as tracking.track measures it
    sigma = float(noise_level((fr[:: max(1, t_n // 20)] - bg).ravel()))
    thr = max(float(min_contrast), noise_k * sigma)
    pix, radii = _follow(fr, bg, thr, max_gap, progress, reset_on_loss, window,
                         round_power=round_power)
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
            # np.percentile(fr[idx], 10 or 90, axis=0) over the background's frames idx, the
            # same values from their samples already sorted (1.5 s of CPU -> 0.1 s at 640x360)
            q = np.percentile(samples, 10 if sign.mean() > 0 else 90,
                              axis=1).reshape(h, w).astype(np.float32)
            r = float(np.nanmedian(radii))
            if (np.abs(q - bg) > thr).sum() >= 0.05 * np.pi * r * r:
                pix, radii = _follow(fr, q, thr, max_gap, progress, reset_on_loss, window,
                                     round_power=round_power)
    found = np.isfinite(pix).all(axis=1)
    radius = float(np.nanmedian(radii)) if found.any() else float("nan")
    return BallTrack(pixels=pix, radius=radius, found=found, radii=radii)


def _follow(fr, bg, thr, max_gap, progress, reset_on_loss=False, window=True, stats=None,
            round_power=1.0):
    """One tracking pass over ``fr`` against background ``bg``: centres (T, 2), radii (T,).

    ``reset_on_loss``: a track lost for more than ``max_gap`` frames forgets the sizes seen so
    far, so an object of another size followed for a while (a hand holding the ball) does not
    gate the ball out for the rest of the clip (:func:`find_object`).

    ``window``: while the track holds (a detection within ``max_gap`` frames), a frame is
    searched only in a window around the predicted position that holds the search gate, the
    centring and the "is there a ball" test (:func:`_follow_window`); the answer is the whole
    frame's, bit for bit, and the whole frame is searched when a blob crosses the window's
    edge or the track is lost. ``stats`` (a dict) counts the frames searched each way.
    """
    if stats is None:
        stats = {}
    stats.setdefault("window", 0)
    stats.setdefault("full", 0)
    from scipy import ndimage
    from tqdm.auto import tqdm

    t_n, h, w = fr.shape
    pix = np.full((t_n, 2), np.nan)
    radii = np.full(t_n, np.nan)
    areas: list[float] = []
    last: list[tuple[int, np.ndarray]] = []  # (frame, centre) of the last detections
    since = 0  # sizes are taken from frames since (reset_on_loss: the last re-acquisition)
    for t in tqdm(range(t_n), desc="finding the ball", unit="frame", disable=not progress,
                  leave=False):
        if window and last and t - last[-1][0] <= max_gap:
            got = _follow_window(fr[t], bg, thr, t, last, areas, radii[since:])
            if got is not None:  # else the whole frame decides (a blob cut by the window)
                stats["window"] += 1
                if got is not False:
                    centre, cov, area_k = got
                    radii[t] = math.sqrt(cov / math.pi)
                    pix[t] = (float(centre[0]), float(centre[1]))
                    areas.append(area_k)
                    last = (last + [(t, np.array(pix[t]))])[-2:]
                continue
        stats["full"] += 1
        signed = fr[t] - bg
        diff = np.abs(signed)
        mask = diff > thr
        if not mask.any():
            continue
        lab, n = ndimage.label(mask)
        if n == 0:
            continue
        if reset_on_loss and areas and (not last or t - last[-1][0] > max_gap):
            areas, since = [], t
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
                score.append((area[c] / (math.pi * (ext / 2) ** 2 + 1e-9)) ** round_power
                             * math.sqrt(area[c]))
            k = cand[int(np.argmax(score))]
        # centre and size: the ball's pixels segmented by |difference| and filled to their hull,
        # each weighted by the fraction of it the ball covers (tracking.ball_centre): a lit top
        # that barely differs from the wall counts as much as the dark bottom. The expected
        # radius is the recent balls'; on (re)acquisition the blob's (and its pieces') own,
        # then the covered area's.
        found_r = radii[since:][np.isfinite(radii[since:])][-20:]
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


def _follow_window(frame, bg, thr, t, last, areas, radii_since):
    """One frame of :func:`_follow` while the track holds, searched in a window only.

    The window (a box around the position predicted from the last two detections) holds the
    gate's circle, three re-centrings of :func:`~sysid_bench.core.tracking.ball_centre` and
    the disc :func:`~sysid_bench.core.tracking.ball_seen` counts. Blobs are labelled in the
    window; when none touches an edge of the window that is not the frame's, each is a whole
    blob of the frame, with the frame's area and (summed in the same order, in the frame's
    coordinates) centroid, and the answer is the one the whole frame gives.

    Returns
    -------
    None
        A blob crosses the window's edge (or the window is most of the frame): search the
        whole frame.
    False
        Not seen in this frame.
    (centre, coverage, area)
        The ball's centre ``(col, row)``, its covered area (px) and its blob's area.
    """
    from scipy import ndimage

    h, w = frame.shape
    (t1, p1), (t2, p2) = (last[-2], last[-1]) if len(last) >= 2 else (last[-1], last[-1])
    pred = p2 + (p2 - p1) * (t - t2) / max(1, t2 - t1) if len(last) >= 2 else p2.copy()
    ref = float(np.median(areas[-20:]))
    r_ref = math.sqrt(ref / math.pi)
    gate = max(4.0 * r_ref + 2.0 * (t - t2) * r_ref, 0.1 * min(h, w))
    found_r = radii_since[np.isfinite(radii_since)][-20:]
    if not areas or not found_r.size or not np.isfinite(pred).all():
        return None
    r_exp = float(np.median(found_r))
    # per axis: the gate, three re-centrings that each move at most r + 5 px, the last
    # centring's window (r + 5) or the disc test's (2 r + 2)
    reach = gate + 5.0 * r_exp + 24.0
    r0, r1 = max(0, int(pred[1] - reach)), min(h, int(pred[1] + reach) + 2)
    c0, c1 = max(0, int(pred[0] - reach)), min(w, int(pred[0] + reach) + 2)
    if r0 >= r1 or c0 >= c1:
        return False  # predicted far outside the frame: as the frame, no blob near it
    if (r1 - r0) * (c1 - c0) > 0.5 * h * w:
        return None
    signed = frame[r0:r1, c0:c1] - bg[r0:r1, c0:c1]
    diff = np.abs(signed)
    mask = diff > thr
    if not mask.any():
        return False
    lab, n = ndimage.label(mask)
    edges = [lab[0, :] if r0 > 0 else (), lab[-1, :] if r1 < h else (),
             lab[:, 0] if c0 > 0 else (), lab[:, -1] if c1 < w else ()]
    if any(np.any(np.asarray(e) > 0) for e in edges):
        return None
    # scipy's center_of_mass, in the frame's coordinates: bincount sums each blob's pixels in
    # the frame's raster order, as on the whole frame
    flat = lab.ravel()
    dd = diff.astype(np.float64)
    area = np.bincount(flat, minlength=n + 1)[1:].astype(np.float64)
    mass = np.bincount(flat, weights=diff.ravel(), minlength=n + 1)[1:]
    rows = np.arange(r0, r1, dtype=np.float64)[:, None]
    cols = np.arange(c0, c1, dtype=np.float64)[None, :]
    cr = np.bincount(flat, weights=(dd * rows).ravel(), minlength=n + 1)[1:] / mass
    cc = np.bincount(flat, weights=(dd * cols).ravel(), minlength=n + 1)[1:] / mass
    cen = np.stack([cc, cr], axis=1) + 0.5  # (col, row)
    ok = (area >= 0.2 * ref) & (area <= 5.0 * ref)
    if not ok.any():
        return False
    cand = np.flatnonzero(ok)
    dist = np.hypot(*(cen[cand] - pred).T)
    near = dist <= gate
    if not near.any():
        return False
    k = cand[near][np.argmin(dist[near])]

    def held(c, m):  # the window holds everything within m px of c (or the frame's edge does)
        return ((c[1] - m >= r0 or r0 == 0) and (c[1] + m + 1 <= r1 or r1 == h)
                and (c[0] - m >= c0 or c0 == 0) and (c[0] + m + 1 <= c1 or c1 == w))

    centre = cen[k]
    for _ in range(3):
        if not held(centre, r_exp + 6.0):
            return None
        new, cov = ball_centre(signed, thr, centre, r_exp, origin=(c0, r0))
        if cov <= 0:
            break
        moved = float(np.hypot(*(new - centre)))
        centre = new
        if moved < 0.01:
            break
    if cov <= 0 or r_exp > min(h, w) / 4:
        return False
    if not held(centre, 2.0 * r_exp + 3.0):
        return None
    # the disc test in window coordinates: float32 centre minus whole pixels is exact
    cw = np.asarray(centre, dtype=np.float32) - np.array([c0, r0], dtype=np.float32)
    if not ball_seen(diff[None], cw[None], r_exp, thr)[0]:
        return False
    return np.asarray(centre, dtype=np.float64), cov, float(area[k])


# -- a camera per video ---------------------------------------------------------------------------
#: Rotations ``--rotate`` accepts, degrees clockwise.
ROTATIONS = (0, 90, 180, 270)
#: Sizes (m) an identified object may have: a tracked object outside this range means the scale
#: cannot be right for the clip (a ball "10 m wide", or 30 nm wide at 1e9 px/m).
OBJECT_SIZE_RANGE_M = (0.003, 3.0)
#: Power of length in each parameter's unit: a scale read ``1 + s`` times too large reads each
#: parameter ``(1 + s) ** power`` times too large (g in m/s^2: 1; the ball's drag d in 1/m: -1).
LENGTH_POWER = {
    "ball": {"e": 0, "g": 1, "d": -1, "r": 1},
    "pendulum": {"g": 1, "L": 1, "b": 0, "mu": 0},
    "spring": {"w2": 0, "k3": -2, "c": 0, "L0": 1},
    "collision": {"lq": 0, "eb": 0, "mu": 1, "ew": 0},
}


def rotate_frames(frames, rotate: int) -> np.ndarray:
    """Frames stored sideways, turned upright.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W)
    rotate : {0, 90, 180, 270}
        Degrees clockwise to turn each frame.

    Returns
    -------
    ndarray, shape (T, H, W) or (T, W, H) for 90 and 270
    """
    if rotate not in ROTATIONS:
        raise ValueError(f"rotate: expected one of 90, 180, 270 (degrees clockwise), got "
                         f"{rotate!r}")
    fr = np.asarray(frames)
    if rotate == 0:
        return fr
    # np.rot90 turns counter-clockwise for positive k
    return np.ascontiguousarray(np.rot90(fr, k=-(rotate // 90), axes=(1, 2)))


def turned_chroma(chroma_px, rotate: int) -> tuple[float, float]:
    """:attr:`Clip.chroma_px` of frames turned ``rotate`` degrees (90 and 270 swap the axes)."""
    a, b = (float(v) for v in chroma_px)
    return (b, a) if int(rotate) % 180 == 90 else (a, b)


def fit_circle(points) -> tuple[np.ndarray, float, float, float]:
    """The circle through tracked points: a pendulum's pivot and radius from its bob's arc.

    An algebraic fit (Kasa's linear least squares) starts a geometric one
    (``scipy.optimize.least_squares`` on the distances), whose Jacobian gives the radius's
    standard error. The centre may lie outside the frame (a pivot above it).

    Parameters
    ----------
    points : ndarray, shape (N, 2)
        ``(col, row)`` px; rows with NaN are skipped.

    Returns
    -------
    centre : ndarray, shape (2,)
        ``(col, row)`` px.
    radius : float
        px.
    radius_std : float
        Standard error of the radius, px (inf when the arc does not fix it).
    rms : float
        RMS distance of the points from the circle, px.
    """
    from scipy.optimize import least_squares

    p = np.asarray(points, dtype=np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < 5:
        raise ValueError(f"points: expected at least 5 tracked points for a circle, got {len(p)}")
    a = np.column_stack([2 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(a, (p ** 2).sum(axis=1), rcond=None)
    c0 = sol[:2]
    r0 = math.sqrt(max(sol[2] + c0 @ c0, 1e-12))

    def resid(z):
        return np.hypot(*(p - z[:2]).T) - z[2]

    fit = least_squares(resid, np.array([c0[0], c0[1], r0]), method="lm")
    centre, radius = fit.x[:2], float(abs(fit.x[2]))
    res = fit.fun
    dof = max(len(p) - 3, 1)
    s2 = float(res @ res) / dof
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * s2
        r_std = float(math.sqrt(max(cov[2, 2], 0.0)))
    except np.linalg.LinAlgError:
        r_std = float("inf")
    return centre, radius, r_std, float(math.sqrt(np.mean(res ** 2)))


@dataclass(frozen=True)
class Camera:
    """Source pixels -> metres in the plane of motion, in the system's world frame.

    ``x = (col - origin_col) / s * flip``, ``y = (origin_row - row) / s`` (rows run down, y up),
    with ``s`` the scale in px per metre: one number, or one per frame where it came from the
    tracked object's apparent size (an object moving in depth keeps a true scale). Pixel
    coordinates are continuous (pixel ``[i, j]``'s centre at ``(j + 0.5, i + 0.5)``) and taken
    after the frames were turned by ``rotate`` degrees clockwise.

    Attributes
    ----------
    px_per_m : float
        The scale (the median of the per-frame scales when there are several).
    origin : (float, float)
        ``(col, row)`` of the world's origin: the pendulum's pivot, the ball's floor under the
        ball's centre (``y = 0`` is the centre of a ball resting on the floor), the spring's
        anchor.
    scale_rel_std : float
        Relative standard deviation of the scale (a 24 px ball read a pixel wrong: 0.042);
        carried into the intervals of every parameter with a length in its unit.
    per_frame : ndarray, shape (T,), optional
        Per-frame scale, px per metre (NaN where the object was not seen: ``px_per_m`` there).
    rotate : int
        Degrees clockwise the frames were turned before tracking.
    flip : float
        ``+1``, or ``-1`` when the world's x runs right to left (a spring anchored on the right).
    offset : (float, float)
        Metres added after the mapping (the ball's x placed mid-box when no walls are given).
    source : str
        Where the scale came from, in words.
    placement : dict
        What fixed the origin: each item given (``"given"``), estimated (how) or absent.
    param_std : dict
        Standard deviation a given number's rounding adds to a parameter, in the parameter's
        unit (the spring's anchor column written to a pixel is +- 0.5 px: ``L0`` gains 0.29 px
        over the scale); added in quadrature by :func:`widen_for_placement`.
    """

    px_per_m: float
    origin: tuple
    scale_rel_std: float = 0.0
    per_frame: np.ndarray | None = None
    rotate: int = 0
    flip: float = 1.0
    offset: tuple = (0.0, 0.0)
    source: str = ""
    placement: dict = field(default_factory=dict)
    param_std: dict = field(default_factory=dict)

    def scales(self, n: int) -> np.ndarray:
        """px per metre of each of ``n`` frames, shape (n,)."""
        if self.per_frame is None:
            return np.full(n, float(self.px_per_m))
        s = np.asarray(self.per_frame, dtype=np.float64)[:n]
        return np.where(np.isfinite(s), s, self.px_per_m)

    def to_metres(self, cr) -> np.ndarray:
        """``(T, ..., 2)`` px ``(col, row)`` to metres ``(x, y)``, frame by frame."""
        cr = np.asarray(cr, dtype=np.float64)
        s = self.scales(cr.shape[0]).reshape((-1,) + (1,) * (cr.ndim - 2))
        x = self.flip * (cr[..., 0] - self.origin[0]) / s + self.offset[0]
        y = (self.origin[1] - cr[..., 1]) / s + self.offset[1]
        return np.stack([x, y], axis=-1)

    def describe(self) -> str:
        """The mapping in one line."""
        sign = "" if self.flip > 0 else "-"
        rel = f" ± {100 * self.scale_rel_std:.2g}%" if self.scale_rel_std else ""
        per = " (per frame, from the object's size; median shown)" if self.per_frame is not None \
            else ""
        rot = f"; frames turned {self.rotate} deg clockwise" if self.rotate else ""
        return (f"camera: x = {sign}(col - {self.origin[0]:.5g}) / s + {self.offset[0]:.4g}, "
                f"y = ({self.origin[1]:.5g} - row) / s + {self.offset[1]:.4g}, "
                f"s = {self.px_per_m:.5g} px/m{rel}{per} [{self.source}]{rot}")

    def as_dict(self) -> dict:
        """What ``estimates.json`` records under ``camera``."""
        return {"px_per_m": float(self.px_per_m), "origin": [float(v) for v in self.origin],
                "scale_rel_std": float(self.scale_rel_std), "rotate": int(self.rotate),
                "flip": float(self.flip), "offset": [float(v) for v in self.offset],
                "per_frame_px_per_m": None if self.per_frame is None
                else [float(v) for v in self.per_frame],
                "source": self.source, "placement": dict(self.placement),
                "param_std": {k: float(v) for k, v in self.param_std.items()},
                "mapping": self.describe()}


def _fit_inverse_size(inv, t_all, seen):
    """A robust line through ``inv[seen]`` against ``t_all[seen]``: ``(coef, keep)``.

    Repeated medians (Siegel: up to half the frames may be off) start the line; then least
    squares on the frames within 3 MADs of it."""
    from scipy.stats import siegelslopes

    sl = siegelslopes(inv[seen], t_all[seen])
    coef, keep = np.array([sl.slope, sl.intercept]), seen
    for _ in range(3):
        res = inv[seen] - np.polyval(coef, t_all[seen])
        rk = res[np.isin(seen, keep)]
        mid = float(np.median(rk))
        mad = 1.4826 * float(np.median(np.abs(rk - mid)))
        new = seen[np.abs(res - mid) <= 3.0 * max(mad, 1e-12)]
        if len(new) < 6:
            break
        keep = new
        coef = np.polyfit(t_all[keep], inv[keep], 1)
    return coef, keep


#: Ball diameters above the lowest point of its track from which :func:`_scale_from_size` reads
#: the ball's size: nearer the floor the 7 cm ball read 3-7% small (the floor behind it, of
#: its own colour, and the blur across a bounce: docs/camera-footage.md, session 27).
FLOOR_CLEAR_DIAMETERS = 3.0


def _scale_from_size(track: BallTrack, object_size_m: float,
                     centre_row: float | None = None) -> tuple[np.ndarray, float, float]:
    """Per-frame px per metre from the object's apparent diameter, its median and relative std.

    A pinhole camera shows an object of diameter ``D`` at depth ``z`` ``f D / z`` px across, and
    an object drifting in depth at a steady speed has ``z`` linear in time: the inverse of the
    apparent diameter is fitted as a line in the frame index, robustly (a repeated-medians line,
    then least squares on the frames within 3 MADs of it), and each frame's scale is read off
    the line. A frame's own size is not used: at 640x360 the 7 cm ball is 10-16 px across and a single frame's size is
    5-40% off where the ball crosses a background of its own grey (measured in
    ``docs/camera-footage.md``), which a running median followed. The relative std is a pixel's
    error on the median diameter (the size's own bias, which averaging over frames does not
    remove) combined with the fitted level's standard error (the scatter about the line over
    the frames kept).

    ``centre_row`` (a ball over a floor: the picture's centre row, about which a pinhole
    scales): the line is fitted again on the frames where the ball is at least
    :data:`FLOOR_CLEAR_DIAMETERS` of its diameters above the lowest point of its track (heights
    read at the first line's scale), where there are at least 6 spanning a third of the
    track's frames; near the floor the ball reads small, and a clip whose later part is
    mostly small bounces and rolling would read a drift in depth that is not there.
    """
    radii = np.asarray(track.radii if track.radii is not None else
                       np.where(track.found, track.radius, np.nan), dtype=np.float64)
    seen = np.flatnonzero(np.isfinite(radii) & (radii > 0))
    diam = 2.0 * radii
    t_all = np.arange(len(radii), dtype=np.float64)
    d_med = float(np.median(diam[seen]))
    keep = seen
    coef = np.array([0.0, 1.0 / d_med])
    spread = 0.0
    if len(seen) >= 6:
        inv = 1.0 / diam
        coef, keep = _fit_inverse_size(inv, t_all, seen)
        rows = np.asarray(track.pixels, dtype=np.float64)[:, 1]
        if centre_row is not None and np.all(np.polyval(coef, t_all[seen]) > 0):
            height = (float(centre_row) - rows) * np.polyval(coef, t_all) * float(object_size_m)
            clear = seen[np.isfinite(height[seen])
                         & (height[seen] - np.nanmin(height[seen])
                            >= FLOOR_CLEAR_DIAMETERS * float(object_size_m))]
            if len(clear) >= 6 and t_all[clear[-1]] - t_all[clear[0]] >= (
                    t_all[seen[-1]] - t_all[seen[0]]) / 3:
                coef, keep = _fit_inverse_size(inv, t_all, clear)
        res = inv[keep] - np.polyval(coef, t_all[keep])
        level = float(np.polyval(coef, np.median(t_all[keep])))
        spread = float(np.std(res)) / level / math.sqrt(max(len(keep) - 2, 1))
    inv_fit = np.polyval(coef, t_all)
    if not np.all(inv_fit > 0):  # a line through zero: no steady drift to read, one scale
        coef, inv_fit = np.array([0.0, 1.0 / d_med]), np.full(len(radii), 1.0 / d_med)
    per_frame = 1.0 / inv_fit / float(object_size_m)
    d_level = float(np.median(1.0 / inv_fit[seen]))
    rel = math.hypot(1.0 / d_level, spread)
    return per_frame, d_level / float(object_size_m), rel


#: Weight of the colour (chroma) difference against the grey one in :func:`colour_difference`:
#: a shadow or a lighting change moves the grey level and barely the hue.
CHROMA_WEIGHT = 2.0
#: A pixel that differs from the background in more than this share of the frames, and in one
#: unbroken stretch of more than :data:`STATIC_RUN` of them, is part of a still scene or the
#: ghost an object leaves where it rested (it is in the median there).
STATIC_SHARE = 0.3
#: ... the stretch: an object that passes the same place often (the middle of a spring's or a
#: pendulum's swing) differs there in 30-60% of the frames but a few at a time, never more than
#: 19% in one stretch on section 9's clips; zeroed by the total share alone, a spring's cart was
#: lost in 46% of its frames and its track off by up to 6 cm (issue 38). A ball rolling to rest
#: at the end of arz.avi's window differs in one stretch of 20-33%: still zeroed.
STATIC_RUN = 0.2


@numba.njit(cache=True, nogil=True)
def _counted_median(c, idx, lo, hi, out):  # pragma: no cover - compiled
    """``out[i] = np.median(c[idx, i], axis=0)`` for rows ``lo:hi`` of uint8 frames ``c``
    (T, h, w, 3): each value's count over the sampled frames, then the middle one (the mean
    of the middle two, in float64, for an even number): np.median's exact values, without its
    copy of the samples and its partition of each pixel's (``out`` float64, (h, w, 3))."""
    n = idx.shape[0]
    w, ch = c.shape[2], c.shape[3]
    step = 32  # columns counted at once: their counts (96 KB) stay in the cache
    counts = np.zeros((step, ch, 256), dtype=np.int32)
    first = np.empty((step, ch), dtype=np.int64)  # each pixel's lowest and highest value
    last = np.empty((step, ch), dtype=np.int64)
    a_rank, b_rank = (n - 1) // 2, n // 2  # the middle one or two, 0-based, ascending
    for i in range(lo, hi):
        for j0 in range(0, w, step):
            m = min(step, w - j0)
            first[:] = 255
            last[:] = 0
            for t in range(n):
                row = c[idx[t], i]
                for j in range(m):
                    for k in range(ch):
                        v = row[j0 + j, k]
                        counts[j, k, v] += 1
                        first[j, k] = min(first[j, k], v)
                        last[j, k] = max(last[j, k], v)
            for j in range(m):
                for k in range(ch):
                    seen = 0
                    a = -1
                    for v in range(first[j, k], last[j, k] + 1):
                        seen += counts[j, k, v]
                        if a < 0 and seen > a_rank:
                            a = v
                        if seen > b_rank:
                            out[i, j0 + j, k] = (np.float64(a) + np.float64(v)) / 2.0
                            break
                    counts[j, k, first[j, k]:last[j, k] + 1] = 0  # zero for the next pixels


@numba.njit(cache=True, nogil=True)
def _colour_distance(c, bg_y, bg_c, weight, out):  # pragma: no cover - compiled
    """``out[t] = sqrt((y - bg_y)**2 + weight * |(c[t] - y) - bg_c|**2)`` per pixel, ``y`` the
    mean of ``c[t]``'s three channels: in float32, in numpy's order of operations (``f.mean(
    axis=-1)``, ``(dc * dc).sum(axis=-1)`` sum the channels left to right), so the same bits
    as the array expression :func:`colour_difference` used before."""
    three = np.float32(3.0)
    for t in range(c.shape[0]):
        for i in range(c.shape[1]):
            for j in range(c.shape[2]):
                r = np.float32(c[t, i, j, 0])
                g = np.float32(c[t, i, j, 1])
                b = np.float32(c[t, i, j, 2])
                y = ((r + g) + b) / three
                d0 = (r - y) - bg_c[i, j, 0]
                d1 = (g - y) - bg_c[i, j, 1]
                d2 = (b - y) - bg_c[i, j, 2]
                dy = y - bg_y[i, j]
                out[t, i, j] = np.sqrt(dy * dy + weight * ((d0 * d0 + d1 * d1) + d2 * d2))


def colour_difference(colour, max_frames: int = 150) -> np.ndarray:
    """How far each pixel of each frame is from the static scene, in colour.

    The scene is the per-pixel median colour; the difference weighs the hue's change
    (:data:`CHROMA_WEIGHT`) above the grey level's, so that a red bob on a beige wall of the
    same grey stands out and its shadow does not. Pixels that differ in more than
    :data:`STATIC_SHARE` of the frames and in one unbroken stretch of more than
    :data:`STATIC_RUN` of them (a scene that changed, the ghost of an object that rested there)
    are set to 0: an object is followed where it moves, also where it passes often, a few
    frames at a time (the middle of a swing).

    Parameters
    ----------
    colour : ndarray, shape (T, h, w, 3), uint8
        RGB frames (:attr:`Clip.colour_frames`).
    max_frames : int
        Frames (evenly spread) the median and the static share are taken over.

    Returns
    -------
    ndarray, shape (T, h, w), float32
        The difference in grey levels (0 to ~440), as :func:`find_ball` takes frames.
    """
    c = np.asarray(colour)
    if c.ndim != 4 or c.shape[-1] != 3 or c.shape[0] < 1:
        raise ValueError(f"colour: expected a (T, h, w, 3) array, got shape {c.shape}")
    t_n = c.shape[0]
    idx = np.unique(np.linspace(0, t_n - 1, min(t_n, max_frames)).astype(int))
    if c.dtype == np.uint8 and c.flags.c_contiguous:  # np.median's values, ~4x less CPU
        med = np.empty(c.shape[1:], dtype=np.float64)
        _over_frames(lambda a, b: _counted_median(c, idx.astype(np.int64), a, b, med),
                     c.shape[1])
        bg = med.astype(np.float32)
    else:
        bg = np.median(c[idx], axis=0).astype(np.float32)
    bg_y = bg.mean(axis=-1)
    bg_c = bg - bg_y[..., None]
    out = np.empty(c.shape[:3], dtype=np.float32)
    # one pass over the pixels (numpy's chunked version, float32 temporaries of the clip's size,
    # took 23 ms of CPU a 640x360 frame; this 2.5 ms, the same bits)
    src = np.ascontiguousarray(c if c.dtype == np.uint8 else c.astype(np.float32))
    _over_frames(lambda a, b: _colour_distance(src[a:b], bg_y, bg_c, np.float32(CHROMA_WEIGHT),
                                               out[a:b]), t_n)
    sample = out[idx[:: max(1, len(idx) // 20)]]
    sigma = float(noise_level((sample - np.median(sample)).ravel()))
    thr = max(20.0, 5.0 * sigma)
    above = out[idx] > thr
    # the longest run of consecutive (sampled) frames in which each pixel differs
    run = np.zeros(out.shape[1:], dtype=np.int32)
    longest = np.zeros_like(run)
    for a in above:
        run = np.where(a, run + 1, 0)
        np.maximum(longest, run, out=longest)
    static = (above.mean(axis=0) > STATIC_SHARE) & (longest > STATIC_RUN * len(idx))
    out[:, static] = 0.0
    return out


def find_object(frames, *, max_side: int = 640, progress: bool = False,
                window: bool = True, colour=None, chroma_px=(1.0, 1.0)) -> BallTrack:
    """:func:`find_ball` on large frames: followed on a block-averaged copy, in source pixels.

    A 1080p frame is averaged over 3 x 3 blocks (the larger side brought to at most
    ``max_side``), so the background, the blobs and each frame's search are 9 times smaller;
    centres and radii are scaled back to the source's pixels (continuous coordinates scale by
    the block size exactly). Frames this size or smaller are followed as they are.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W), uint8
    max_side : int
        Largest side the tracker works at, px.
    progress : bool
    window : bool
        Search a window around the predicted position while the track holds
        (:func:`find_ball`); the same track as searching every frame whole.
    colour : ndarray, shape (T, h, w, 3), uint8, optional
        The same frames in colour (:attr:`Clip.colour_frames`): the object is followed in
        :func:`colour_difference` at that size (a real camera's object on a wall of its own
        grey, its shadow, the ghost where it rested); sizes are still measured on ``frames``.
    chroma_px : (float, float)
        Source pixels ``(across, down)`` between the file's colour samples, as the frames are
        turned (:attr:`Clip.chroma_px`): the blur the colour's sizes are measured through.

    Returns
    -------
    BallTrack
        In the source frame's pixels; "not seen" frames NaN, as are frames whose blob is not
        the object's size (a hand: more than half the median radius off it). A lost track
        forgets the sizes seen before (``find_ball(..., reset_on_loss=True)``).
    """
    fr = np.asarray(frames)
    if fr.ndim != 3 or fr.shape[0] < 1:
        raise ValueError(f"frames: expected a (T, H, W) array, got shape {fr.shape}")
    if colour is not None:
        col = np.asarray(colour)
        if col.ndim != 4 or col.shape[0] != fr.shape[0] or col.shape[-1] != 3:
            raise ValueError(f"colour: expected a ({fr.shape[0]}, h, w, 3) array, got shape "
                             f"{col.shape}")
        diff = colour_difference(col)
        sx, sy = fr.shape[2] / col.shape[2], fr.shape[1] / col.shape[1]
        cx, cy = (float(v) for v in chroma_px)
        if not (cx >= 1.0 and cy >= 1.0):
            raise ValueError(f"chroma_px: expected source pixels >= 1, got {chroma_px!r}")
        # a colour pixel is sx source pixels wide and its colour a chroma_px wide sample:
        # whichever is coarser is the box each colour pixel averages over
        trk = _minor_radii(diff, find_ball(diff, progress=progress, reset_on_loss=True,
                                           round_power=2.0),
                           blur_var=(max(1.0, cx / sx) ** 2 / 12.0, max(1.0, cy / sy) ** 2 / 12.0))
        # continuous coordinates scale by the block size; the radius by the mean of the two
        s = 0.5 * (sx + sy)
        trk = BallTrack(pixels=trk.pixels * np.array([sx, sy]), radius=trk.radius * s,
                        found=trk.found, radii=trk.radii * s)
        # sizes at the source's resolution where its grey shows the object (a bright ball on a
        # dark wall), else the colour's: whichever is steadier over the frames
        fine = _minor_radii(fr, trk)
        return _consistent(fine if _spread(fine.radii) < _spread(trk.radii) else trk)
    k = max(1, math.ceil(max(fr.shape[1:]) / int(max_side)))
    if k == 1:
        trk = find_ball(fr, progress=progress, reset_on_loss=True, window=window)
        return _consistent(_minor_radii(fr, trk))
    small = _block_means(fr, k)
    trk = find_ball(small, progress=progress, reset_on_loss=True, window=window)
    trk = BallTrack(pixels=trk.pixels * k, radius=trk.radius * k, found=trk.found,
                    radii=None if trk.radii is None else trk.radii * k)
    return _consistent(_minor_radii(fr, trk))


def follow_object_box(frames, box, *, progress: bool = False) -> BallTrack:
    """The object boxed in the first frame, followed by its appearance (``--object-box``).

    For objects :func:`find_object` loses: not round, not contrasting with the background, or
    resting long enough to leave a ghost in the median background (a cart on a lab track).
    :func:`sysid_bench.core.box_track.follow_box` matches the box's patch frame by frame
    (zero-mean normalised cross-correlation around a constant-velocity prediction, refined
    against the first frame's patch); frames whose best match is weak are "not seen".

    Parameters
    ----------
    frames : ndarray, shape (T, H, W), uint8
        Grey frames, turned upright (:func:`rotate_frames`).
    box : (float, float, float, float)
        ``(col, row, width, height)`` px of the object in ``frames[0]``: the top-left corner,
        as OpenCV's ``selectROI`` gives it (:func:`sysid_bench.core.box_track.check_box`).
    progress : bool

    Returns
    -------
    BallTrack
        The box's centre, NaN where not seen. ``radius`` and ``radii`` (where seen) are half
        the box's side along the motion (its width where the track spreads more over the
        columns than the rows, else its height): ``--object-size-m`` is the object's true
        length along its motion.
    """
    from sysid_bench.core.box_track import follow_box

    bt = follow_box(frames, box, progress=progress)
    pix, found = bt.centres, bt.found
    _, _, w, h = bt.box
    seen = pix[found]
    spread = seen.max(axis=0) - seen.min(axis=0) if len(seen) else np.zeros(2)
    half = 0.5 * float(w if spread[0] >= spread[1] else h)
    return BallTrack(pixels=pix, radius=half, found=found,
                     radii=np.where(found, half, np.nan))


def _block_means(fr: np.ndarray, k: int) -> np.ndarray:
    """Means of ``k x k`` blocks of each frame (T, H, W) -> (T, H // k, W // k) float32.

    Summed exactly in integers (rows of a block first, whole contiguous rows at a time, then
    the columns), then divided once: the same float32 values as ``reshape(...).mean``, 10x
    faster than summing the reshaped blocks over two strided axes (1.4 against 14 ms of CPU
    a 1080p frame)."""
    t_n = fr.shape[0]
    h, w = (fr.shape[1] // k) * k, (fr.shape[2] // k) * k
    small = np.empty((t_n, h // k, w // k), dtype=np.float32)
    acc = np.uint16 if k * k * 255 < 2 ** 16 else np.uint32
    for i in range(0, t_n, 16):  # in chunks: scratch memory of 16 frames
        blk = fr[i:i + 16, :h, :w]
        rows = blk[:, 0::k].astype(acc)
        for a in range(1, k):
            rows += blk[:, a::k]
        tot = rows[:, :, 0::k].copy()
        for b in range(1, k):
            tot += rows[:, :, b::k]
        small[i:i + 16] = tot.astype(np.float32) / float(k * k)
    return small


#: Variance (px**2) a pixel's own area adds along each axis: its value is the mean over a
#: 1 px box, a uniform distribution of variance 1 / 12.
PIXEL_VAR = 1.0 / 12.0


def _minor_radii(frames, trk: BallTrack, blur_var=(PIXEL_VAR, PIXEL_VAR)) -> BallTrack:
    """Each frame's radius from the object's narrowest extent, at the source's resolution.

    Motion blur stretches a moving ball along its path (a 21 px ball at 3 m/s and 1/30 s
    exposure looks 30 px long), so its area overstates its size; across the path it keeps its
    width. A uniform disc of radius r has variance r**2 / 4 along every axis, so the radius is
    ``2 sqrt(smallest eigenvalue)`` of the covariance of the pixels covered, each weighted by
    the fraction covered (its difference from the background over the object's own, the
    faint texture below a tenth of it left out).

    A blur adds its own variance to that of the disc's coverage along every axis (a
    convolution's variances add): ``blur_var``, ``(across, down)`` in px**2, is taken out of
    the smallest eigenvalue along its axis before the square root. A pixel's area is 1 / 12;
    colour decoded from H.264's 4:2:0 (one colour sample per 2 x 2 pixels) is a 2 px box,
    4 / 12, which read the 7 cm ball's diameter 3-4% large at 10 px across
    (``docs/camera-footage.md``, session 27).
    """
    fr = np.asarray(frames)
    t_n, h, w = fr.shape
    bx, by = (float(v) for v in blur_var)
    found = np.flatnonzero(trk.found)
    if found.size == 0:
        return trk
    idx = np.unique(np.linspace(0, t_n - 1, min(t_n, 31)).astype(int))
    radii = np.array(trk.radii, dtype=np.float64, copy=True)
    boxes = {}
    for t in found:
        c, r = trk.pixels[t]
        half = int(math.ceil(2.0 * float(trk.radii[t]) + 3))
        c0, c1 = max(0, int(c) - half), min(w, int(c) + half + 1)
        r0, r1 = max(0, int(r) - half), min(h, int(r) + half + 1)
        if r1 > r0 and c1 > c0:
            boxes[t] = (r0, r1, c0, c1)
    # the background where the windows lie only (a median of 31 whole 1080p frames took
    # seconds), once per 64 px tile: windows of consecutive frames overlap
    tile = 64
    need = np.zeros((-(-h // tile), -(-w // tile)), dtype=bool)
    for r0, r1, c0, c1 in boxes.values():
        need[r0 // tile:(r1 - 1) // tile + 1, c0 // tile:(c1 - 1) // tile + 1] = True
    bg_all = np.zeros((h, w), dtype=np.float32)
    sample = fr[idx]
    for ti, tj in zip(*np.nonzero(need)):
        rs, cs = slice(ti * tile, (ti + 1) * tile), slice(tj * tile, (tj + 1) * tile)
        bg_all[rs, cs] = _median_over_time(sample[:, rs, cs]).astype(np.float32)
    for t, (r0, r1, c0, c1) in boxes.items():
        c, r = trk.pixels[t]
        rad = float(trk.radii[t])
        bg = bg_all[r0:r1, c0:c1]
        d = np.abs(fr[t, r0:r1, c0:c1].astype(np.float32) - bg)
        yy, xx = np.mgrid[r0:r1, c0:c1] + 0.5
        inner = np.hypot(xx - c, yy - r) <= 0.5 * rad
        if not inner.any():
            continue
        peak = float(np.median(d[inner]))
        if peak <= 0:
            continue
        wgt = np.where(d > 0.1 * peak, np.clip(d / peak, 0.0, 1.0), 0.0)
        # only the blob around the centre: texture elsewhere in the window is not the object
        from scipy import ndimage

        lab, _ = ndimage.label(wgt > 0)
        centre_lab = lab[min(max(int(r) - r0, 0), r1 - r0 - 1), min(max(int(c) - c0, 0),
                                                                    c1 - c0 - 1)]
        if centre_lab == 0:
            continue
        wgt = np.where(lab == centre_lab, wgt, 0.0)
        sw = wgt.sum()
        mx, my = (wgt * xx).sum() / sw, (wgt * yy).sum() / sw
        cxx = (wgt * (xx - mx) ** 2).sum() / sw
        cyy = (wgt * (yy - my) ** 2).sum() / sw
        cxy = (wgt * (xx - mx) * (yy - my)).sum() / sw
        lam = 0.5 * (cxx + cyy) - math.sqrt(0.25 * (cxx - cyy) ** 2 + cxy ** 2)
        # the blur's variance along the narrow axis (the smaller eigenvalue's vector)
        ax, ay = (lam - cyy, cxy) if abs(cxy) > 1e-12 else ((1.0, 0.0) if cxx <= cyy
                                                             else (0.0, 1.0))
        nrm = ax * ax + ay * ay
        lam -= (ax * ax * bx + ay * ay * by) / nrm if nrm > 0 else 0.5 * (bx + by)
        if lam > 0:
            radii[t] = 2.0 * math.sqrt(lam)
    return BallTrack(pixels=trk.pixels, radius=float(np.nanmedian(radii)), found=trk.found,
                     radii=radii)


def _spread(radii) -> float:
    """Relative robust spread of a track's radii over its frames (inf with fewer than 3)."""
    r = np.asarray(radii, dtype=np.float64)
    r = r[np.isfinite(r)]
    if r.size < 3 or np.median(r) <= 0:
        return math.inf
    med = float(np.median(r))
    return float(np.median(np.abs(r - med))) / med


def _consistent(trk: BallTrack, tol: float = 0.5) -> BallTrack:
    """Frames whose blob is not the object's size (off the track's median radius by more than
    ``tol`` of it: a hand, a person crossing) become "not seen" rather than a position."""
    r = np.asarray(trk.radii, dtype=np.float64)
    if not trk.found.any():
        return trk
    med = float(np.nanmedian(r))
    ok = trk.found & (np.abs(r - med) <= tol * med)
    pix = np.where(ok[:, None], trk.pixels, np.nan)
    radii = np.where(ok, r, np.nan)
    return BallTrack(pixels=pix, radius=float(np.nanmedian(radii)) if ok.any() else float("nan"),
                     found=ok, radii=radii)


def _floor_from_bounces(pix, radii, min_height: float | None = None) -> tuple[float, int]:
    """The floor's row from where the ball's bounces turn: ``(row, n_bounces)``.

    The track is cut at its turns (its lowest points) into arcs. Each arc is fitted as a
    parabola on its frames in the upper half of its height only, and two arcs' parabolas meet
    at the contact between them, between frames (at 20 frames/s a ball at 4 m/s is 20 cm above
    the floor in the frame nearest its bounce). The frames near the floor are left out because
    there the centre is read worst: the ball is over the floor (of nearly its own colour), and
    blurred across the contact, so its lower part may not be seen and its centre reads high
    (``docs/camera-footage.md``, session 27). The floor is the median contact's row plus the
    ball's radius, over the bounces between arcs at least ``min_height`` tall (default: three
    of the ball's median diameters; all bounces when none is); NaN when no arc has three
    frames in its upper half.
    """
    seen = np.flatnonzero(np.isfinite(pix).all(axis=1))
    t_all, row = seen.astype(np.float64), pix[seen, 1]
    rad = np.where(np.isfinite(radii[seen]), radii[seen], np.nanmedian(radii))
    turns = [j for j in range(1, len(seen) - 1)
             if row[j] >= row[j - 1] and row[j] >= row[j + 1] and row[j] > min(row[j - 1],
                                                                                row[j + 1])]
    if min_height is None:
        med = float(np.nanmedian(rad)) if np.isfinite(rad).any() else 0.0
        min_height = 6.0 * med if math.isfinite(med) else 0.0
    ends = [0, *turns, len(seen) - 1]

    def arc(a, b):  # the parabola through the arc's upper half, and the arc's height
        r = row[a:b + 1]
        height = max(r[0], r[-1]) - r.min()  # rows run down: the apex is the smallest row
        keep = np.arange(a, b + 1)[r <= r.min() + 0.5 * height]
        if len(keep) < 3 or t_all[b] - t_all[a] > 2 * (b - a) + 1:  # a gap in the track
            return None
        return np.polyfit(t_all[keep], row[keep], 2), height

    contacts = []
    for i, j in enumerate(turns):
        before, after = arc(ends[i], j), arc(j, ends[i + 2])
        if before is None or after is None:
            continue
        roots = np.roots(before[0] - after[0])
        roots = roots[np.isreal(roots)].real
        roots = roots[(roots >= t_all[j - 1] - 1e-9) & (roots <= t_all[j + 1] + 1e-9)]
        if roots.size == 0:
            continue
        c = float(np.polyval(before[0], roots[0]))
        contacts.append((min(before[1], after[1]), c + float(rad[j])))
    if not contacts:
        return float("nan"), 0
    tall = [c for h, c in contacts if h >= min_height]
    use = tall or [c for _, c in contacts]
    return float(np.median(use)), len(use)


def _check_size(diam_m: float, option: str, how: str) -> None:
    lo, hi = OBJECT_SIZE_RANGE_M
    if not (lo <= diam_m <= hi):
        raise ValueError(f"{option}: puts the tracked object {diam_m:.3g} m across ({how}); "
                         f"expected {lo:g} to {hi:g} m: the scale cannot be right for this clip")


def swing_frequency(pix, pivot, dt: float) -> tuple[float, float, float]:
    """A pendulum's undamped angular frequency from its bob's track: ``(omega0, rel_std, amp)``.

    The angle about ``pivot`` is fitted with a damped cosine (its frequency first read off a
    Lomb-Scargle periodogram, which takes the frames the tracker lost), ``omega0**2 =
    omega_d**2 + lambda**2`` undoes the viscous damping, and the large-angle period is
    corrected to the small-angle one (``T = T0 (1 + A**2/16 + 11 A**4/3072)`` at the median
    amplitude ``A``). With the pendulum's ``g`` known, ``L = |g| / omega0**2``.

    Parameters
    ----------
    pix : ndarray, shape (T, 2)
        The bob's ``(col, row)`` per frame, NaN where not seen.
    pivot : (float, float)
        The pivot's ``(col, row)``.
    dt : float
        Seconds between frames.

    Returns
    -------
    omega0 : float
        rad/s.
    rel_std : float
        Its relative standard deviation (the fit's).
    amp : float
        The median amplitude, rad.

    Raises
    ------
    ValueError
        Fewer than two swings seen, or no period found (named ``known``).
    """
    from scipy.optimize import curve_fit
    from scipy.signal import lombscargle

    pix = np.asarray(pix, dtype=np.float64)
    seen = np.isfinite(pix).all(axis=1)
    t = np.flatnonzero(seen) * float(dt)
    ang = np.arctan2(pix[seen, 0] - pivot[0], pix[seen, 1] - pivot[1])
    span = t[-1] - t[0] if t.size else 0.0
    if t.size < 8 or span <= 0:
        raise ValueError(f"known: g gives the scale through the swing's period; the bob was seen "
                         f"in {t.size} frames (at least 8 over two swings needed)")
    a0 = ang - ang.mean()
    nyq = math.pi / float(dt)
    freqs = np.linspace(2 * math.pi / span, nyq, 4000)
    w_pk = float(freqs[np.argmax(lombscargle(t, a0, freqs))])
    # the turns seen give the period as well: where they disagree with the periodogram the
    # swing was seen in part (the bob out of the frame, or lost, on one side: the seen side's
    # arcs alone fit a sinusoid at twice the swing's frequency, their drifting mean one far
    # below it), and the turns, which never need the unseen side, are kept
    t_turn = _turn_period(np.flatnonzero(seen), ang) * float(dt)
    if not math.isfinite(t_turn):
        raise ValueError(f"known: g gives the scale through the swing's period; fewer than two "
                         f"turns of one side of the swings were seen in {t.size} frames over "
                         f"{span:.3g} s (the bob out of the frame or lost where it turns): give "
                         "px_per_m, object_size_m or known L")
    partial = abs(w_pk * t_turn / (2 * math.pi) - 1) > 0.25
    if partial:
        w_pk = 2 * math.pi / t_turn
    if span * w_pk / (2 * math.pi) < 1.5:
        raise ValueError(f"known: g gives the scale through the swing's period; {span:.3g} s of "
                         f"track hold {span * w_pk / (2 * math.pi):.2g} swings (at least 1.5 "
                         "needed): give px_per_m, object_size_m or known L")

    def model(tt, amp, lam, w, ph, c):
        return amp * np.exp(-lam * tt) * np.cos(w * tt + ph) + c

    amp0 = float(np.percentile(np.abs(a0), 95))
    ph0 = float(np.arctan2(-np.sum(a0 * np.sin(w_pk * t)), np.sum(a0 * np.cos(w_pk * t))))
    bounds = ([0, 0, 0.5 * w_pk, -np.inf, -np.pi], [np.pi, 5.0, 1.5 * w_pk, np.inf, np.pi])
    # a swing seen in part: the seen arcs fix the phase only together, so the fit starts from
    # eight phases and keeps the closest (the whole swing's single start is kept as it was)
    starts = [ph0] if not partial else list(np.linspace(-math.pi, math.pi, 8, endpoint=False))
    best = None
    for ph in starts:
        try:
            par, cov = curve_fit(model, t - t[0], ang, p0=(amp0, 0.05, w_pk, ph, ang.mean()),
                                 bounds=bounds, maxfev=20000)
        except (RuntimeError, ValueError) as exc:
            err = exc
            continue
        cost = float(np.sum((model(t - t[0], *par) - ang) ** 2))
        if best is None or cost < best[0]:
            best = (cost, par, cov)
    if best is None:
        raise ValueError(f"known: the swing's period could not be fitted ({err})") from None
    _, par, cov = best
    amp, lam, w = float(par[0]), float(par[1]), float(par[2])
    w_std = float(np.sqrt(max(cov[2, 2], 0.0))) if np.all(np.isfinite(cov)) else w
    a_med = float(amp * np.exp(-lam * 0.5 * (t[-1] - t[0])))
    w_d = math.sqrt(w * w + lam * lam)
    w0 = w_d * (1 + a_med ** 2 / 16 + 11 * a_med ** 4 / 3072)
    return w0, w_std / w, a_med


def _turn_period(frames, ang, k: int = 3) -> float:
    """The swing's period in frames from the turns seen on either side: NaN when no side shows
    two.

    A turn is a seen frame whose angle is the strict extreme of the seen frames within ``k``
    of it, with a frame seen within ``k`` on either side (the edge of a gap, where the bob left
    the frame, is not a turn); turns of one side closer than ``k`` frames are one. The period is the median interval between a side's
    consecutive turns (a turn the tracker lost makes one interval twice as long).

    Parameters
    ----------
    frames : ndarray, shape (N,), int
        Indices of the seen frames, increasing.
    ang : ndarray, shape (N,)
        The bob's angle in those frames, rad.
    k : int
        Half-window, frames.
    """
    frames = np.asarray(frames)
    ang = np.asarray(ang, dtype=np.float64)
    gaps = []
    for side in (1.0, -1.0):
        turns = []
        for i in range(1, len(frames) - 1):
            near = np.abs(frames - frames[i]) <= k
            if frames[i] - frames[i - 1] > k or frames[i + 1] - frames[i] > k:
                continue  # no frame seen within k on one side: the edge of a gap
            others = side * ang[near & (frames != frames[i])]
            if side * ang[i] > others.max() and (not turns or frames[i] - turns[-1] > k):
                turns.append(frames[i])
        gaps += list(np.diff(turns))
    return float(np.median(gaps)) if gaps else float("nan")


#: Systems whose object falls freely between contacts, so that a known g gives the scale
#: (:func:`scale_from_fall`).
FALL_SCALED = ("ball",)
#: Systems whose object swings about a pivot, so that a known length (the arc's radius) or a
#: known g (the swing's period, :func:`swing_frequency`) gives the scale.
PERIOD_SCALED = ("pendulum",)
#: Systems whose object bounces on a floor seen behind it, so that its size is read clear of
#: the floor (:data:`FLOOR_CLEAR_DIAMETERS`; a pendulum's bob or a cart has no floor behind it).
FLOOR_SIZED = ("ball",)


def scale_from_fall(pix, g: float, dt: float, radius_px: float) -> tuple[float, float]:
    """A camera's scale from a falling object's curvature and a known g: ``(px_per_m, rel_std)``.

    In flight the row's second difference is ``|g| s dt**2`` pixels a frame squared; the median
    over every three consecutive seen frames away from the floor (the track's lowest two
    radii: bounces and rolling) is robust to the few triples that straddle a bounce, and air
    drag, which adds to g on the way down and takes from it on the way up, cancels to first
    order over rises and falls.

    Parameters
    ----------
    pix : ndarray, shape (T, 2)
        The object's ``(col, row)`` per frame, rows down, NaN where not seen.
    g : float
        Gravity, m/s^2 (its sign is ignored).
    dt : float
        Seconds between frames.
    radius_px : float
        The object's radius, px.

    Returns
    -------
    px_per_m : float
    rel_std : float
        Relative standard deviation of the scale (the median's, from the spread).

    Raises
    ------
    ValueError
        Fewer than 4 triples in flight, or no downward curvature (named ``known``).
    """
    pix = np.asarray(pix, dtype=np.float64)
    if not math.isfinite(g) or g == 0:
        raise ValueError(f"known: expected g != 0 m/s^2, got {g!r}")
    row = pix[:, 1]
    dd = row[2:] - 2 * row[1:-1] + row[:-2]
    low = np.nanmax(row) if np.isfinite(row).any() else np.nan
    ok = np.isfinite(dd) & (row[1:-1] < low - 2.0 * float(radius_px))
    if ok.sum() < 4:
        raise ValueError(f"known: g gives the scale through the ball's fall; {int(ok.sum())} "
                         "runs of three frames in flight were seen (at least 4 needed): give "
                         "px_per_m or object_size_m")
    d = dd[ok]
    med = float(np.median(d))
    if med <= 0:
        raise ValueError(f"known: the ball's track does not fall (median curvature "
                         f"{med:.3g} px/frame^2): give px_per_m or object_size_m")
    mad = 1.4826 * float(np.median(np.abs(d - med)))
    rel = 1.2533 * mad / math.sqrt(d.size) / med  # the median's standard error
    return med / (abs(g) * dt * dt), rel


def camera_for(system: str, track: BallTrack, size, *, px_per_m=None, object_size_m=None,
               known: dict | None = None, floor_row=None, walls=None, pivot=None, anchor=None,
               rotate: int = 0, dt: float | None = None) -> Camera:
    """The camera of a clip: its scale and the system's origin, given or estimated.

    Parameters
    ----------
    system : {"ball", "pendulum", "spring"}
    track : BallTrack
        The object followed through the (turned) frames, source pixels.
    size : (int, int)
        ``(H, W)`` of the (turned) frames.
    px_per_m : float, optional
        The scale, given.
    object_size_m : float, optional
        The object's true diameter (or length), m: each frame's scale is its apparent size
        over this, with a pixel's error on the size as the scale's uncertainty.
    known : dict, optional
        Known parameters; when neither of the above is given, the pendulum's ``L`` fixes the
        scale from the arc's radius, else its ``g`` from the swing's period
        (:func:`swing_frequency`: ``L = |g| / omega0**2``, then the arc's radius); the ball's
        ``g`` from the fall's curvature (:func:`scale_from_fall`).
    floor_row : float, optional
        Ball: the floor's row; default the lowest the ball's bottom reached (where bounces
        turn).
    walls : (float, float), optional
        Ball: the left and right walls' columns. Absent: the ball's track is placed mid-way
        in the suite's 10 m box (its walls out of reach).
    pivot : (float, float), optional
        Pendulum: the pivot's ``(col, row)``; default the centre of the circle fitted to the
        bob's track (:func:`fit_circle`), which may lie outside the frame.
    anchor : float, optional
        Spring: the anchor's column; absent, the oscillation's centre is placed at 1.5 m (the
        middle of ``L0``'s prior), so ``L0`` is not measured.
    rotate : int
        Degrees clockwise the frames were turned (recorded).
    dt : float, optional
        Seconds between the track's frames (the scale from a known ``g`` needs it).

    Returns
    -------
    Camera

    Raises
    ------
    ValueError
        A camera that cannot be right for the clip (an object outside
        :data:`OBJECT_SIZE_RANGE_M`, a pivot the bob does not circle, walls the object does not
        fit between, too few tracked frames); the message names the argument.
    """
    known = dict(known or {})
    h, w = int(size[0]), int(size[1])
    pix = np.asarray(track.pixels, dtype=np.float64)
    seen = np.isfinite(pix).all(axis=1)
    if seen.sum() < 3:
        raise ValueError(f"object: found in {int(seen.sum())} of {len(pix)} frames; the camera "
                         "and the methods need a track (at least 3 frames)")
    r_px = float(track.radius)
    given = {k: v for k, v in (("px_per_m", px_per_m), ("object_size_m", object_size_m))
             if v is not None}
    if len(given) > 1:
        raise ValueError("object_size_m: give either px_per_m or object_size_m, not both")
    for k, v in given.items():
        if not math.isfinite(float(v)) or float(v) <= 0:
            raise ValueError(f"{k}: expected a number > 0, got {v!r}")
    per_frame, rel, placement = None, 0.0, {}
    if px_per_m is not None:
        s, src = float(px_per_m), f"px_per_m={float(px_per_m):g} given"
        _check_size(2 * r_px / s, "px_per_m", f"its {2 * r_px:.3g} px at {s:g} px/m")
        rel = rounding_std(px_per_m) / s  # a scale written to three figures is +- half a unit
    elif object_size_m is not None:
        d = float(object_size_m)
        _check_size(d, "object_size_m", "as given")
        # an object's size read clear of the floor it bounces on (FLOOR_SIZED)
        per_frame, s, rel = _scale_from_size(track, d,
                                             centre_row=h / 2 if system in FLOOR_SIZED else None)
        src = (f"object_size_m={d:g}: the object's median {2 * r_px:.3g} px across, frame by "
               f"frame (its inverse a line in time: a steady drift in depth)")
    elif system in PERIOD_SCALED and ("L" in known or "g" in known):
        s, src = None, "known L" if "L" in known else "known g"
    elif system in FALL_SCALED and "g" in known:  # the fall's curvature in px/s^2 over g
        if dt is None:
            raise ValueError("dt: the scale from known g needs the clip's frame interval")
        s, rel = scale_from_fall(pix, float(known["g"]), float(dt), r_px)
        rel = math.hypot(rel, rounding_std(known["g"]) / abs(float(known["g"])))
        src = (f"known g={float(known['g']):g}: the ball's fall, {s * abs(float(known['g'])):.4g} "
               "px/s^2 between bounces")
        _check_size(2 * r_px / s, "known", f"its {2 * r_px:.3g} px at {s:.4g} px/m")
        if system in FLOOR_SIZED:
            # the fall gives the scale, the ball's apparent size its drift in depth: the size
            # line of any diameter (its shape does not depend on it) brought to the fall's scale
            # (a 640x360 ball drifting in depth, read at one scale, had its later bounces
            # mis-scaled: e 3 stds off with the check passing)
            pf1, s1, _ = _scale_from_size(track, 1.0, centre_row=h / 2)
            if np.all(np.isfinite(pf1)) and s1 > 0:
                per_frame = pf1 * (s / s1)
                src += ("; frame by frame from the ball's apparent size (its inverse a line in "
                        "time: a steady drift in depth)")
    else:
        raise ValueError(f"px_per_m: the {system}'s scale is not known: give px_per_m, "
                         "object_size_m" + {"pendulum": ", known L or known g",
                                            "ball": " or known g"}.get(system, ""))
    flip, offset = 1.0, (0.0, 0.0)
    origin = (0.0, 0.0)

    # how a camera places each system's world in the picture: this function's knowledge, one
    # entry per system it builds a camera for
    def place_ball():  # the floor at the bounces (or given), the walls given or out of reach
        nonlocal origin, offset
        rad_m = r_px / s
        if per_frame is not None and floor_row is None and walls is None:
            # a scale per frame (the ball drifting in depth) is a scale about the pinhole's
            # principal point, the picture's centre: a height is (h/2 - row) / s_t there, and
            # the floor a fixed height in metres (a floor row scaled about itself would drift
            # with the depth, by cm over a clip)
            sc = np.asarray(per_frame, dtype=np.float64)
            m_x = (pix[:, 0] - w / 2) / sc
            m_y = (h / 2 - pix[:, 1]) / sc
            down = np.column_stack([m_x, -m_y])
            y_c, n_b = _floor_from_bounces(down, np.zeros(len(pix)), min_height=6.0 * rad_m)
            low = float(np.nanmax(-m_y[seen]))
            if math.isfinite(y_c) and y_c >= low - 1.0 / s:
                placement["floor_row"] = (f"estimated: the ball's centre {-y_c:.4g} m from the "
                                          f"picture's centre at contact, where the track's "
                                          f"parabolas meet at {n_b} bounces (heights scaled "
                                          "about the picture's centre, frame by frame)")
            else:
                y_c = low
                placement["floor_row"] = (f"estimated: the lowest the ball's centre reached, "
                                          f"{-y_c:.4g} m from the picture's centre (no bounce "
                                          "with three frames either side)")
            mid = 0.5 * (np.min(m_x[seen]) + np.max(m_x[seen]))
            span = float(np.max(m_x[seen]) - np.min(m_x[seen]))
            if span > BOX_WIDTH - 2.0:
                raise ValueError(f"walls: the ball travels {span:.3g} m across with no walls "
                                 f"given; the suite's box is {BOX_WIDTH:g} m wide")
            origin, offset = (w / 2, h / 2), (BOX_WIDTH / 2 - float(mid), float(y_c))
            placement["walls"] = (f"absent: the track's middle placed at x = {BOX_WIDTH / 2:g} m, "
                                  "the simulated walls out of its reach")
            return
        if floor_row is None:
            radii = np.asarray(track.radii if track.radii is not None
                               else np.full(len(pix), r_px), dtype=np.float64)
            fr_row, n_b = _floor_from_bounces(pix, radii)
            bottom = float(np.nanmax(pix[seen, 1] + np.where(np.isfinite(radii[seen]),
                                                              radii[seen], r_px)))
            if math.isfinite(fr_row) and fr_row >= bottom - 1.0:
                placement["floor_row"] = (f"estimated {fr_row:.1f}: where the track's parabolas "
                                          f"meet at {n_b} bounces")
            else:
                fr_row = bottom
                placement["floor_row"] = (f"estimated {fr_row:.1f}: the lowest the ball's bottom "
                                          "reached (no bounce with three frames either side)")
        else:
            fr_row = float(floor_row)
            if not math.isfinite(fr_row):
                raise ValueError(f"floor_row: expected a finite row, got {floor_row!r}")
            low = float(np.max(pix[seen, 1]))
            if fr_row < low - 1.0:
                raise ValueError(f"floor_row: the ball's centre is tracked down to row "
                                 f"{low:.1f}, below the floor given at row {fr_row:g}")
            placement["floor_row"] = "given"
        if walls is not None:
            c1, c2 = (float(v) for v in walls)
            cols = pix[seen, 0]
            if not (math.isfinite(c1) and math.isfinite(c2) and c2 - c1 > 2 * r_px):
                raise ValueError(f"walls: expected the right wall more than the ball's "
                                 f"{2 * r_px:.3g} px right of the left one, got {c1:g} {c2:g}")
            if cols.min() < c1 - r_px or cols.max() > c2 + r_px:
                raise ValueError(f"walls: the ball is tracked from column {cols.min():.1f} to "
                                 f"{cols.max():.1f}, outside the walls {c1:g} {c2:g}")
            width = (c2 - c1) / s - 2 * rad_m
            if abs(width - BOX_WIDTH) > 0.05 * BOX_WIDTH:
                raise ValueError(
                    f"walls: the walls are {width:.3g} m apart at this scale; the methods "
                    f"simulate the suite's {BOX_WIDTH:g} m box until a scene of any size is held "
                    "(issue 38, part 1): leave out walls (the walls are then out of reach)")
            origin, offset = (c1, fr_row), (-rad_m, -rad_m)
            placement["walls"] = "given"
        else:
            mid = 0.5 * (np.min(pix[seen, 0]) + np.max(pix[seen, 0]))
            span = (np.max(pix[seen, 0]) - np.min(pix[seen, 0])) / s
            if span > BOX_WIDTH - 2.0:
                raise ValueError(f"walls: the ball travels {span:.3g} m across with no walls "
                                 f"given; the suite's box is {BOX_WIDTH:g} m wide")
            origin, offset = (float(mid), fr_row), (BOX_WIDTH / 2, -rad_m)
            placement["walls"] = (f"absent: the track's middle placed at x = {BOX_WIDTH / 2:g} m, "
                                  "the simulated walls out of its reach")

    def place_pendulum():  # the pivot at the centre of the bob's arc (or given)
        nonlocal s, rel, src, origin
        if pivot is not None:
            pc, pr = (float(v) for v in pivot)
            if not (math.isfinite(pc) and math.isfinite(pr)):
                raise ValueError(f"pivot: expected a finite (col, row), got {pivot!r}")
            dist = np.hypot(pix[seen, 0] - pc, pix[seen, 1] - pr)
            r_arc = float(np.median(dist))
            spread = float(np.percentile(dist, 95) - np.percentile(dist, 5))
            if r_arc < 2 * r_px or spread > 0.2 * r_arc:
                raise ValueError(
                    f"pivot: the bob's distance from ({pc:g}, {pr:g}) runs from "
                    f"{dist.min():.1f} to {dist.max():.1f} px; a rod keeps it fixed, so the pivot "
                    "is not the centre of the bob's arc (inside the bob's path?)")
            r_std = float(np.std(dist)) / math.sqrt(len(dist))
            placement["pivot"] = "given"
        else:
            centre, r_arc, r_std, rms = fit_circle(pix[seen])
            pc, pr = float(centre[0]), float(centre[1])
            if not math.isfinite(r_arc) or rms > 0.1 * r_arc or r_arc < 2 * r_px:
                raise ValueError(f"pivot: the bob's track is not an arc about one pivot (circle "
                                 f"fit radius {r_arc:.1f} px, RMS off it {rms:.2g} px); give "
                                 "pivot")
            if r_arc > 50 * max(h, w):
                raise ValueError(f"pivot: the bob's arc is too flat to place the pivot (radius "
                                 f"{r_arc:.3g} px); give pivot")
            placement["pivot"] = (f"estimated ({pc:.1f}, {pr:.1f}): the centre of the circle "
                                  f"fitted to the bob's track, radius {r_arc:.1f} ± {r_std:.2g} "
                                  f"px, RMS off it {rms:.2g} px")
        if s is None and "L" in known:
            L = float(known["L"])
            if not math.isfinite(L) or L <= 0:
                raise ValueError(f"known: expected L > 0 m, got {known['L']!r}")
            s = r_arc / L
            # the arc's fit and L as written (0.74: +- 0.005), which every length carries
            rel = math.hypot(r_std / r_arc, rounding_std(known["L"]) / L)
            src = f"known L={L:g}: the arc's radius {r_arc:.1f} px"
        elif s is None:  # known g: the swing's period gives L = |g| / omega0**2
            g = float(known["g"])
            if not math.isfinite(g) or g == 0:
                raise ValueError(f"known: expected g != 0 m/s^2, got {known['g']!r}")
            if dt is None:
                raise ValueError("dt: the scale from known g needs the clip's frame interval")
            w0, w_rel, amp = swing_frequency(pix, (pc, pr), float(dt))
            L = abs(g) / w0 ** 2
            s = r_arc / L
            rel = math.hypot(r_std / r_arc, 2.0 * w_rel, rounding_std(known["g"]) / abs(g))
            src = (f"known g={g:g}: the swing's period {2 * math.pi / w0:.4g} s (amplitude "
                   f"{math.degrees(amp):.3g} deg) gives L = {L:.4g} m, the arc's radius "
                   f"{r_arc:.1f} px")
        _check_size(2 * r_px / s, "known" if src.startswith("known") else next(iter(given)),
                    f"its {2 * r_px:.3g} px at {s:.4g} px/m")
        origin = (pc, pr)

    def place_spring():  # the anchor given, or the oscillation's centre placed
        nonlocal origin, flip, offset
        row0 = float(np.median(pix[seen, 1]))
        if anchor is not None:
            a = float(anchor)
            cols = pix[seen, 0]
            if not math.isfinite(a) or cols.min() - r_px < a < cols.max() + r_px:
                raise ValueError(f"anchor: expected a column outside the block's path (columns "
                                 f"{cols.min():.1f} to {cols.max():.1f}), got {anchor!r}")
            flip = 1.0 if np.median(cols) > a else -1.0
            origin = (a, row0)
            placement["anchor"] = "given" + ("" if flip > 0 else " (right of the block: x runs "
                                                                  "right to left)")
        else:
            mid = float(np.median(pix[seen, 0]))
            origin, offset = (mid, row0), (1.5, 0.0)
            placement["anchor"] = ("absent: the oscillation's centre placed at x = 1.5 m, so L0 "
                                   "is not measured")

    place = {"ball": place_ball, "pendulum": place_pendulum, "spring": place_spring}.get(system)
    if place is None:
        raise ValueError(f"system: a camera is built for ball, pendulum and spring clips, got "
                         f"{system!r}")
    place()
    # a placement written to a pixel moves a length measured from it by up to half a pixel
    param_std = {}
    if system == "spring" and anchor is not None and rounding_std(anchor) > 0:
        param_std["L0"] = rounding_std(anchor) / float(s)
    if system == "pendulum" and pivot is not None and rounding_std(pivot[1]) > 0:
        param_std["L"] = rounding_std(pivot[1]) / float(s)  # the row: L below the pivot
    return Camera(px_per_m=float(s), origin=(float(origin[0]), float(origin[1])),
                  scale_rel_std=float(rel), per_frame=per_frame, rotate=int(rotate),
                  flip=flip, offset=offset, source=src, placement=placement,
                  param_std=param_std)


#: Where an end not given and not seen (no cart turned there) is placed: this far beyond the
#: farthest a cart reached, m, so no fit's trajectory reaches it
ABSENT_END_M = 5.0


@dataclass
class TrackCamera:
    """The camera of a clip of objects on a straight track (the collision), and what it fixed.

    Attributes
    ----------
    camera : Camera
        Levelled pixels to metres: ``x`` along the track from its left end, ``y`` up from the
        track's surface.
    pixels : ndarray, shape (T, K, 2)
        The tracked centres turned level (the track's tilt in the picture taken out), px.
    ends_m : (float, float)
        The track's ends, m (``(0, length)``, or an end placed out of reach).
    half_sizes_m : tuple of float, length K
        Each object's half-length, m.
    tilt_deg : float
        The track's slope in the picture, degrees (read from the centres' line).
    """

    camera: Camera
    pixels: np.ndarray
    ends_m: tuple
    half_sizes_m: tuple
    tilt_deg: float


def _turn(cols: np.ndarray, sign: float, min_speed: float) -> float:
    """Column of the first turn of a track where it moved ``-sign`` then ``+sign`` (a cart
    thrown back by an end), from lines fitted to 3 frames either side: NaN if none."""
    t = np.flatnonzero(np.isfinite(cols))
    x = cols[t]
    for j in range(2, len(t) - 2):
        if sign * (x[j] - x[j - 1]) > 0 or sign * (x[j + 1] - x[j]) < 0:
            continue
        if not sign * (x[j - 1] - x[j]) >= 0:
            continue
        best = None
        for split in (j, j + 1):
            lft, rgt = np.arange(max(0, split - 3), split), np.arange(split, min(len(t), split + 3))
            if len(lft) < 2 or len(rgt) < 2 or t[rgt[-1]] - t[lft[0]] > len(lft) + len(rgt) + 1:
                continue
            a1, b1 = np.polyfit(t[lft], x[lft], 1)
            a2, b2 = np.polyfit(t[rgt], x[rgt], 1)
            if sign * a1 > -min_speed or sign * a2 < min_speed:
                continue
            tc = (b2 - b1) / (a1 - a2)
            if t[lft[-1]] - 1 <= tc <= t[rgt[0]] + 1:
                c = a1 * tc + b1
                best = c if best is None else (min(best, c) if sign > 0 else max(best, c))
        if best is not None:
            return float(best)
    return float("nan")


def camera_for_track(track, size, *, px_per_m=None, object_size_m=None, track_ends=None,
                     rotate: int = 0) -> TrackCamera:
    """The camera of a clip of objects sliding on a straight track (the collision's carts).

    The track's line is read from the objects' centres (a straight line through them; its
    slope, a camera rolled a few degrees, is taken out); ``x`` runs along it from the left
    end, ``y`` up from the track's surface (each centre sits its half-length above it).

    Parameters
    ----------
    track : sysid_bench.core.tracking.ColourTrack
        The objects followed, left to right in the first frames, source pixels (upright).
    size : (int, int)
        ``(H, W)`` of the (turned) frames.
    px_per_m : float, optional
        The scale, given; each object's half-length is then its apparent radius over it.
    object_size_m : float, optional
        The objects' true length (or diameter), m, the same for all: the scale is their
        median apparent size over it (they keep their distance from the camera on a track).
    track_ends : (float, float), optional
        Columns of the track's left and right ends (where a cart would hit), px. Not given:
        each end is read from where a cart turned back from it (the first object's turns
        from moving left to moving right, the last's the other way); an end no cart reached
        is placed :data:`ABSENT_END_M` beyond the farthest one went (out of reach).
    rotate : int
        Degrees clockwise the frames were turned (recorded).

    Returns
    -------
    TrackCamera

    Raises
    ------
    ValueError
        No scale, both scales, an end inside the carts' path, ends not in order, objects
        that cannot fit between the ends or whose size is outside
        :data:`OBJECT_SIZE_RANGE_M`; the message names the argument.
    """
    pix = np.asarray(track.pixels, dtype=np.float64)
    t_n, k = pix.shape[:2]
    seen = np.isfinite(pix).all(axis=-1)
    if (seen.sum(axis=0) < 3).any():
        j = int(np.argmin(seen.sum(axis=0)))
        raise ValueError(f"object: object {j + 1} found in {int(seen[:, j].sum())} of {t_n} "
                         "frames; the camera and the methods need each object's track (at "
                         "least 3 frames)")
    if px_per_m is not None and object_size_m is not None:
        raise ValueError("object_size_m: give either px_per_m or object_size_m, not both")
    r_px = np.asarray(track.radius, dtype=np.float64)
    if not np.isfinite(r_px).all():  # an object never seen apart from the others
        r_px = np.where(np.isfinite(r_px), r_px, np.nanmedian(r_px))
    rel = 0.0
    if px_per_m is not None:
        s = float(px_per_m)
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"px_per_m: expected a number > 0, got {px_per_m!r}")
        src = f"px_per_m={s:g} given"
        rel = rounding_std(px_per_m) / s  # a scale written to three figures: +- half a unit
        for j in range(k):
            _check_size(2 * r_px[j] / s, "px_per_m", f"object {j + 1}'s {2 * r_px[j]:.3g} px at "
                                                     f"{s:g} px/m")
        half = tuple(float(r / s) for r in r_px)
    elif object_size_m is not None:
        d = float(object_size_m)
        if not (math.isfinite(d) and d > 0):
            raise ValueError(f"object_size_m: expected a number > 0, got {object_size_m!r}")
        _check_size(d, "object_size_m", "as given")
        diam = 2.0 * np.asarray(track.radii, dtype=np.float64)
        d_med = float(np.nanmedian(diam))
        s = d_med / d
        n_read = int(np.isfinite(diam).sum())
        spread = float(np.nanstd(diam)) / math.sqrt(max(n_read, 1))
        rel = math.hypot(1.0 / d_med, spread / d_med)
        src = f"object_size_m={d:g}: the objects' median {d_med:.3g} px across"
        half = tuple(0.5 * d for _ in range(k))
    else:
        raise ValueError("px_per_m: the collision's scale is not known: give px_per_m or "
                         "object_size_m")
    # the track's line through the centres, and the picture turned level about its left end
    cs, rs = pix[..., 0][seen], pix[..., 1][seen]
    slope, icpt = np.polyfit(cs, rs, 1) if np.ptp(cs) > 0 else (0.0, float(np.median(rs)))
    norm = math.hypot(1.0, slope)
    c0 = float(np.min(cs))
    r0 = float(slope * c0 + icpt)

    def level(c, r):
        dc, dr = c - c0, r - r0
        return c0 + (dc + slope * dr) / norm, r0 + (dr - slope * dc) / norm

    lc, lr = level(pix[..., 0], pix[..., 1])
    lev = np.stack([lc, lr], axis=-1)
    placement = {"tilt": f"read {math.degrees(math.atan(slope)):.3g} deg: the slope of the line "
                         "through the centres, taken out"}
    first, last = lev[:, 0, 0], lev[:, -1, 0]
    reach = (float(np.nanmin(lev[:, :, 0] - r_px)), float(np.nanmax(lev[:, :, 0] + r_px)))
    if track_ends is not None:
        e1, e2 = (float(v) for v in track_ends)
        if not (math.isfinite(e1) and math.isfinite(e2) and e1 < e2):
            raise ValueError(f"track: expected two columns, left < right, got {track_ends!r}")
        e1, e2 = (c0 + (e - c0) * norm for e in (e1, e2))  # their points on the line, levelled
        tol = 0.5 * float(np.min(r_px)) + 1.0
        lo1 = float(np.nanmin(first)) - r_px[0]
        hi2 = float(np.nanmax(last)) + r_px[-1]
        if e1 > lo1 + tol:
            raise ValueError(f"track: the left end at column {track_ends[0]:g} is inside the "
                             f"carts' path (cart 1's edge seen at column {lo1:.1f})")
        if e2 < hi2 - tol:
            raise ValueError(f"track: the right end at column {track_ends[1]:g} is inside the "
                             f"carts' path (cart {k}'s edge seen at column {hi2:.1f})")
        ends_px = (e1, e2)
        placement["track"] = "given"
    else:
        speed = 0.3 * float(np.min(r_px))  # px a frame: slower turns are a stopped cart's jitter
        t1 = _turn(first, 1.0, speed)
        t2 = _turn(last, -1.0, speed)
        ends_px = (t1 - r_px[0] if math.isfinite(t1) else reach[0] - ABSENT_END_M * s,
                   t2 + r_px[-1] if math.isfinite(t2) else reach[1] + ABSENT_END_M * s)
        placement["track"] = (
            "estimated: "
            + ("left end where cart 1 turned back" if math.isfinite(t1) else
               f"left end absent (no cart turned there: placed {ABSENT_END_M:g} m out of reach)")
            + ", "
            + ("right end where the last cart turned back" if math.isfinite(t2) else
               f"right end absent (placed {ABSENT_END_M:g} m out of reach)"))
    length = (ends_px[1] - ends_px[0]) / s
    if 2.0 * sum(half) > length:
        opt = "object_size_m" if object_size_m is not None else "px_per_m"
        raise ValueError(f"{opt}: objects of half-lengths {', '.join(f'{h:.3g}' for h in half)} m "
                         f"cannot fit the {length:.3g} m track side by side with room to move")
    # y = 0 on the track's surface: each centre its half-length above it
    row_track = float(np.nanmedian(lev[..., 1] + r_px[None, :]))
    cam = Camera(px_per_m=float(s), origin=(float(ends_px[0]), row_track),
                 scale_rel_std=float(rel), rotate=int(rotate), source=src, placement=placement)
    return TrackCamera(camera=cam, pixels=lev, ends_m=(0.0, float(length)), half_sizes_m=half,
                       tilt_deg=float(math.degrees(math.atan(slope))))


def widen_for_scale(system: str, params, mean, std, scale_rel_std: float) -> np.ndarray:
    """Standard deviations with the scale's uncertainty added.

    A parameter with length to the power ``q`` in its unit (:data:`LENGTH_POWER`) read at a
    scale ``1 + s`` times the true one is ``(1 + s) ** -q`` times the true value (positions in
    metres are ``1 / (1 + s)`` times the true ones); to first order its std gains
    ``|q| * |mean| * scale_rel_std``, added in quadrature.

    Parameters
    ----------
    system : str
    params : sequence of str, length P
    mean, std : ndarray, shape (..., P)
    scale_rel_std : float

    Returns
    -------
    ndarray, shape (..., P)
    """
    q = np.array([LENGTH_POWER.get(system, {}).get(p, 0) for p in params], dtype=np.float64)
    m = np.asarray(mean, dtype=np.float64)
    return np.hypot(np.asarray(std, dtype=np.float64), np.abs(q * m) * float(scale_rel_std))


#: a held value with a length in its unit is searched within this many of the scale's
#: standard deviations of it (:func:`loosen_held`)
HELD_SCALE_Z = 2.0
#: ... when the scale's uncertainty moves it by at least this fraction (a ruler's rounding,
#: 0.02%, leaves it held)
HELD_SCALE_MIN = 0.005
#: held lengths a scale is measured across, which the positions then hold by construction
#: (the pendulum's L: the arc's radius in pixels over it); :func:`loosen_held` keeps them held
SCALE_EXACT = {"pendulum": ("L",)}


def loosen_held(system, known: dict, prior: dict, scale_rel_std: float,
                scale_source: str = "") -> tuple[dict, dict, dict]:
    """What a method holds and searches when a held value is read through an uncertain scale.

    A value with length to the power ``q`` in its unit (:data:`LENGTH_POWER`: the pendulum's g
    or L, the ball's g) held exactly while the positions in metres are ``1 + s`` times the true
    ones contradicts them by ``|q| s``: the fit cannot move it, so the contradiction goes into
    the parameters that can (a pendulum held at g = -9.81 with its scale from the bob's size,
    6.7% uncertain: the period's mismatch read as pivot friction, b and mu 6 stds off with the
    check passing). Such a value is searched instead within ``HELD_SCALE_Z |q| s`` of it (its
    relative range, kept inside the physics' envelope); the caller reports it as held (the
    user's value, std 0). A length the scale was measured across (:data:`SCALE_EXACT`: the
    pendulum's L over the arc's radius, so the positions hold it by construction) stays held,
    as does a value the scale moves by less than :data:`HELD_SCALE_MIN`. A g the scale was
    read from (the ball's fall, the pendulum's period) is loosened like any other: the scale's
    fit is not the methods' model (a parabola without drag), so the positions need not agree
    with it (a 640x360 ball, scale from its fall 7.3% uncertain, g held: d read 0.048 +- 0.006
    against 0.018 with the check passing).

    Parameters
    ----------
    system : str or System
    known : dict of str -> float
    prior : dict of str -> (float, float)
    scale_rel_std : float
    scale_source : str
        :attr:`Camera.source`.

    Returns
    -------
    known : dict
        What stays held.
    prior : dict
        The user's ranges plus the loosened values' ranges.
    loosened : dict of str -> (float, float)
        The ranges given to values the user held.
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system) if isinstance(system, str) else system
    keep, rng, loose = dict(known or {}), dict(prior or {}), {}
    for name, value in (known or {}).items():
        q = abs(LENGTH_POWER.get(sys_.name, {}).get(name, 0))
        half = HELD_SCALE_Z * q * float(scale_rel_std)
        exact = name in SCALE_EXACT.get(sys_.name, ()) and \
            str(scale_source).startswith(f"known {name}=")
        if q == 0 or exact or q * float(scale_rel_std) < HELD_SCALE_MIN or float(value) == 0.0:
            continue
        elo, ehi = sys_.envelope[name]
        a, b = sorted((float(value) * (1.0 - half), float(value) * (1.0 + half)))
        a, b = max(a, float(elo)), min(b, float(ehi))
        if not a < b:
            continue
        del keep[name]
        rng[name] = loose[name] = (a, b)
    return keep, rng, loose


def report_held(params, mean: np.ndarray, known: dict, loose: dict,
                scale_rel_std: float) -> str:
    """The loosened values (:func:`loosen_held`) reported as held, in place: their column of
    ``mean`` (T, P) set to the user's value where there is an estimate; returns the note that
    says so (empty when nothing was loosened)."""
    for k in loose:
        j = list(params).index(k)
        mean[:, j] = np.where(np.isnan(mean[:, j]), np.nan, float(known[k]))
    if not loose:
        return ""
    return ("held within the scale's uncertainty while fitting (reported as held): "
            + ", ".join(f"{k} = {known[k]:g} searched in {a:.4g} to {b:.4g}"
                        for k, (a, b) in loose.items())
            + f" (the scale is {100 * scale_rel_std:.2g}% uncertain; held exactly, its error "
            "would be read into the other parameters)")


def widen_for_placement(params, std, param_std: dict) -> np.ndarray:
    """Standard deviations with a given placement's rounding added in quadrature
    (:attr:`Camera.param_std`).

    Parameters
    ----------
    params : sequence of str, length P
    std : ndarray, shape (..., P)
    param_std : dict of str -> float

    Returns
    -------
    ndarray, shape (..., P)
    """
    add = np.array([float(param_std.get(p, 0.0)) for p in params], dtype=np.float64)
    return np.hypot(np.asarray(std, dtype=np.float64), add)


#: a camera answer fails when its fit misses the track by more than this many times the
#: track's own noise (:func:`camera_check`); the same tolerance ``Posterior.check`` gives the
#: method's assumed noise. Provisional: not yet chosen by the measurement issue 38 asks for.
TRACK_CHECK_FACTOR = 2.0
#: third differences more than this many robust stds from zero are motion (a bounce, a
#: contact), not noise, and are left out of :func:`track_noise`'s second pass
_TRACK_NOISE_CLIP = 4.0
#: variance of a third difference of white noise, in units of the noise's variance (1+9+9+1)
_THIRD_DIFF_VAR = 20.0


def track_noise(positions) -> float:
    """The track's own measurement noise (m, per coordinate), robust to bounces and contacts.

    A third difference ``x[t+3] - 3 x[t+2] + 3 x[t+1] - x[t]`` is zero on a parabola (free
    flight) and small on any smooth motion sampled finely, so on a smooth track it is the
    noise's alone, with variance 20 sigma^2. Its scale is the MAD's (1.4826 * median |d|);
    differences farther than 4 such stds from zero (a bounce, a collision) are dropped and
    the scale taken again. Windows with an unseen (NaN) position are left out.

    Parameters
    ----------
    positions : array_like, shape (T, D) or (T, K, D)
        Observed positions (m) of one or K objects at uniform times; NaN where unseen.

    Returns
    -------
    float
        The noise's standard deviation (m); NaN when fewer than 8 windows of 4 seen frames.
    """
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim not in (2, 3) or x.shape[0] < 1:
        raise ValueError(f"positions: expected an array of shape (T, D) or (T, K, D), "
                         f"got shape {x.shape}")
    d3 = np.diff(x, n=3, axis=0).ravel()
    d3 = d3[np.isfinite(d3)]
    if d3.size < 8:
        return float("nan")
    scale = 1.4826 * float(np.median(np.abs(d3)))
    if scale > 0:
        kept = d3[np.abs(d3) <= _TRACK_NOISE_CLIP * scale]
        if kept.size >= 8:
            scale = 1.4826 * float(np.median(np.abs(kept)))
    return scale / math.sqrt(_THIRD_DIFF_VAR)


def camera_check(check, noise_m: float, factor: float = TRACK_CHECK_FACTOR):
    """A method's model check judged again against the track's own noise (issue 38).

    A camera's track is often far less noisy than the noise a method assumes (about a pixel:
    ~5 mm on a 640x360 ball clip, against the ball's 10 mm), so a fit that misses the track
    by 2-4 times its real noise passes ``Posterior.check`` while its narrow interval misses the
    truth. The answer passes here only when it passed there and its residual RMS is within
    ``Check.bound(n, factor)`` times ``noise_m`` too.

    Parameters
    ----------
    check : sysid_bench.core.estimator.Check
        The method's check (``post.check``).
    noise_m : float
        The track's own noise (m), e.g. :func:`track_noise`'s; NaN: not known, ``check``
        is returned as it is.
    factor : float
        Largest passing ratio of the residual RMS to ``noise_m`` (for many residuals).

    Returns
    -------
    Check
        ``check`` itself when it stands; else a failed copy whose note says why in one sentence.
    """
    from sysid_bench.core.estimator import Check

    if not isinstance(check, Check):
        raise TypeError(f"check: expected a Check (post.check), got {type(check).__name__}")
    if isinstance(noise_m, bool) or not isinstance(noise_m, (int, float, np.integer, np.floating)):
        raise TypeError(f"noise_m: expected a number of metres, got {noise_m!r}")
    if not (np.isnan(noise_m) or noise_m >= 0):
        raise ValueError(f"noise_m: expected >= 0 m or NaN, got {noise_m!r}")
    if not (isinstance(factor, (int, float)) and not isinstance(factor, bool) and factor > 0):
        raise ValueError(f"factor: expected a positive number, got {factor!r}")
    if not check.ok or np.isnan(noise_m) or check.n < 1 or not np.isfinite(check.rms_m):
        return check
    limit = Check.bound(check.n, float(factor)) * max(float(noise_m), 1e-12)
    if check.rms_m <= limit:
        return check
    note = (f"the fit misses the track by {check.rms_m:.3g} m RMS, "
            f"{check.rms_m / max(float(noise_m), 1e-12):.3g} times the track's own noise "
            f"({float(noise_m):.3g} m; at most {Check.bound(check.n, float(factor)):.3g} passes)")
    return replace(check, ok=False, note=note)


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
    from sysid_bench.core.render import render

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
    from sysid_bench.core.estimator import Observation

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


# -- what the user knows --------------------------------------------------------------------------
def _param_name(system, name: str, option: str) -> str:
    import difflib

    if name not in system.params:
        close = difflib.get_close_matches(name, system.params, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"{option}: {name!r} is no parameter of the {system.name} system; "
                         f"expected one of {', '.join(system.params)}{hint}")
    return name


class Given(float):
    """A number as the user wrote it: ``resolution`` is one unit of its last written digit
    (``"306"``: 1, ``"0.62"``: 0.01, ``"1.53e+03"``: 10), so its rounding can be carried into
    the answer (a value rounded to that unit is off by up to half of it: uniform, std
    ``resolution / sqrt(12)``, :func:`rounding_std`).

    Parameters
    ----------
    text : str
        The number as written; ``float(text)`` must read it.
    """

    resolution: float

    def __new__(cls, text):
        if isinstance(text, Given):
            return text
        v = super().__new__(cls, text)
        v.resolution = _written_resolution(str(text)) if isinstance(text, str) else 0.0
        return v


def _written_resolution(text: str) -> float:
    """One unit of the last digit written in ``text`` (0 when it is not a plain decimal)."""
    from decimal import Decimal, InvalidOperation

    try:
        d = Decimal(text.strip())
    except InvalidOperation:
        return 0.0
    if not d.is_finite():
        return 0.0
    return float(Decimal(1).scaleb(d.as_tuple().exponent))


def rounding_std(value) -> float:
    """Standard deviation of a :class:`Given` number's rounding (0 for any other number)."""
    return float(getattr(value, "resolution", 0.0)) / math.sqrt(12.0)


def _number(text: str, option: str, what: str) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{option}: expected {what}, got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{option}: expected {what} (finite), got {text!r}")
    return v


def parse_known(system, items) -> dict[str, float]:
    """``NAME=VALUE`` strings to ``{name: value}``, checked against ``system``.

    Parameters
    ----------
    system : str or System
        A registered system (:func:`sysid_bench.core.systems.get`).
    items : sequence of str
        ``"g=-9.81"``, ``"L=0.62"``, ...

    Returns
    -------
    dict of str -> Given
        Floats that keep their written resolution (``L=0.74``: 0.01): a scale taken from a
        known value carries its rounding (:func:`rounding_std`).

    Raises
    ------
    ValueError
        A name that is no parameter of the system, a value that is not a number or lies
        outside what the physics allows (the system's ``envelope``), a name given twice; the
        message starts with ``known``.
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system) if isinstance(system, str) else system
    out: dict[str, float] = {}
    for it in items or ():
        name, sep, val = str(it).partition("=")
        if not sep:
            raise ValueError(f"known: expected NAME=VALUE, got {it!r}")
        name = _param_name(sys_, name.strip(), "known")
        v = _number(val.strip(), "known", f"a number for {name}")
        lo, hi = sys_.envelope[name]
        if not lo <= v <= hi:
            raise ValueError(f"known: {name} = {v:g} is outside what the {sys_.name} system's "
                             f"physics allows ({lo:g} to {hi:g})")
        if name in out:
            raise ValueError(f"known: {name} given twice")
        out[name] = Given(val.strip())  # its written resolution: the rounding a scale carries
    return out


def parse_prior(system, items, known: dict | None = None) -> dict[str, tuple[float, float]]:
    """``NAME=LO:HI`` strings to ``{name: (lo, hi)}``, checked against ``system``.

    Parameters
    ----------
    system : str or System
    items : sequence of str
        ``"w2=20:80"``, ...
    known : dict, optional
        Parameters held fixed: a range for one of them is refused.

    Returns
    -------
    dict of str -> (float, float)

    Raises
    ------
    ValueError
        An unknown name, ``LO >= HI``, a range outside the system's ``envelope``, a name given
        twice or also known; the message starts with ``prior``.
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system) if isinstance(system, str) else system
    out: dict[str, tuple[float, float]] = {}
    for it in items or ():
        name, sep, rng = str(it).partition("=")
        lo_s, sep2, hi_s = rng.partition(":")
        if not sep or not sep2:
            raise ValueError(f"prior: expected NAME=LO:HI, got {it!r}")
        name = _param_name(sys_, name.strip(), "prior")
        lo = _number(lo_s.strip(), "prior", f"a number LO for {name}")
        hi = _number(hi_s.strip(), "prior", f"a number HI for {name}")
        elo, ehi = sys_.envelope[name]
        if not lo < hi:
            raise ValueError(f"prior: {name} = {lo:g}:{hi:g}: expected LO < HI")
        if lo < elo or hi > ehi:
            raise ValueError(f"prior: {name} = {lo:g}:{hi:g} reaches outside what the "
                             f"{sys_.name} system's physics allows ({elo:g} to {ehi:g})")
        if name in out or name in (known or {}):
            raise ValueError(f"prior: {name} given twice (or also known)")
        out[name] = (lo, hi)
    return out


def check_knowledge(system, known=None, prior=None) -> tuple[dict, dict]:
    """A method's ``known``/``prior`` options (Python dicts) checked as ``--known``/``--prior``.

    Parameters
    ----------
    system : str or System
    known : dict of str -> float, optional
        ``{name: value}``; None or empty: nothing held.
    prior : dict of str -> (float, float), optional
        ``{name: (lo, hi)}``; None or empty: the system's ranges.

    Returns
    -------
    known : dict of str -> float
    prior : dict of str -> (float, float)

    Raises
    ------
    ValueError
        Not a dict, a pair that is not ``(lo, hi)``, or what :func:`parse_known` /
        :func:`parse_prior` refuse; the message starts with ``known`` or ``prior``.
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system) if isinstance(system, str) else system
    for opt, v in (("known", known), ("prior", prior)):
        if v is not None and not isinstance(v, dict):
            raise ValueError(f"{opt}: expected a dict of parameter names, got "
                             f"{type(v).__name__} {v!r}")

    def text(x):  # a number as parse_known reads it back exactly; anything else as given
        return repr(float(x)) if isinstance(x, (int, float, np.number)) else str(x)

    k = parse_known(sys_, [f"{n}={text(x)}" for n, x in (known or {}).items()])
    items = []
    for n, r in (prior or {}).items():
        if isinstance(r, (str, bytes)) or np.shape(r) != (2,):
            raise ValueError(f"prior: expected a (lo, hi) pair for {n}, got {r!r}")
        items.append(f"{n}={text(r[0])}:{text(r[1])}")
    return k, parse_prior(sys_, items, k)


def knowledge_record(known: dict, prior: dict, method: str, held: bool = False,
                     why: str = "") -> dict:
    """What ``estimates.json`` says under ``knowledge``: the user's known values and ranges,
    and whether the method held them (``why``: the method's reason when it cannot).

    Returns
    -------
    dict
        ``known`` ``{name: value}``, ``prior`` ``{name: [lo, hi]}``, ``held`` (bool) and
        ``note`` (a sentence; empty when nothing was given).
    """
    note = ""
    if (known or prior) and not held:
        note = (f"not yet held: {method} does not take known values or prior ranges here"
                f"{f' ({why})' if why else ''}; its estimates above are its own, over its "
                "default prior (lsq, bo, emcee, nuts and prior hold them)")
    return {"known": {k: float(v) for k, v in (known or {}).items()},
            "prior": {k: [float(a), float(b)] for k, (a, b) in (prior or {}).items()},
            "held": bool(held), "note": note}


# -- identify's output folder ---------------------------------------------------------------------
#: ``estimates.json``'s ``written_by``: the marker that tells identify's own output folder
OUT_MARKER = "sysid-bench identify"
#: the files identify writes into ``--out``
OUT_FILES = ("estimates.csv", "estimates.json", "track.png")


def check_out_folder(out) -> Path:
    """Refuse an output folder identify may not write into.

    ``out`` may be missing, an empty folder, or a folder holding a previous identify's output
    (its ``estimates.json`` carries ``written_by`` = :data:`OUT_MARKER`); only the three
    :data:`OUT_FILES` are then replaced, anything else there is left as it is. Anything else
    (a file, a folder of other files: a committed ``docs/`` folder) is refused, so identify
    never overwrites a file it did not write.

    Returns
    -------
    Path

    Raises
    ------
    ValueError
        The message starts with ``out``.
    """
    import json

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: expected a folder, got the file {out}")
    if not out.exists():
        return out
    names = sorted(p.name for p in out.iterdir())
    if not names:
        return out
    ours = False
    try:
        ours = json.loads((out / "estimates.json").read_text()).get("written_by") == OUT_MARKER
    except (OSError, ValueError, AttributeError):
        ours = False
    if not ours:
        shown = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
        raise ValueError(f"out: {out} exists and holds files identify did not write ({shown}); "
                         "give a new or empty folder")
    return out


# -- a camera clip to an Observation --------------------------------------------------------------
#: Systems a camera is built for: one object followed in grey (:func:`find_object`,
#: :func:`camera_for`), or several told apart by colour on a track (:data:`TRACK_OBJECTS`).
CAMERA_SYSTEMS = ("ball", "pendulum", "spring", "collision")
#: Systems whose objects slide on a straight track, followed by colour
#: (:func:`sysid_bench.core.tracking.track_colours`, :func:`camera_for_track`): how many
#: objects, and the names of the scene's fields for the track's ends and their half-lengths.
TRACK_OBJECTS = {"collision": (2, "ends", "half_sizes")}
#: ``identify`` options a clip's record may give (:func:`clip_options`): the values each takes
#: and where it goes (``None``: checked, then not needed to observe the clip)
#: options whose rounding reaches the answer (:class:`Given`): the scale and the placement
_WRITTEN = ("px_per_m", "floor_row", "walls", "pivot", "anchor", "track")

_CLIP_OPTIONS = {
    "--system": (1, None), "--method": (1, None), "--rotate": (1, "rotate"),
    "--fps": (1, "capture_fps"), "--start": (1, "start"), "--end": (1, "end"),
    "--px-per-m": (1, "px_per_m"), "--object-size-m": (1, "object_size_m"),
    "--floor-row": (1, "floor_row"), "--walls": (2, "walls"), "--pivot": (2, "pivot"),
    "--anchor": (1, "anchor"), "--track": (2, "track"), "--known": (1, "known"),
    "--prior": (1, "prior"), "--object-box": (4, "object_box"),
}


@dataclass
class CameraClip:
    """A camera's clip as a method takes it: the tracked object in metres, and the camera.

    Attributes
    ----------
    observation : Observation
        ``positions`` (T, K, 2) metres in the system's world frame (NaN where the object was
        not seen), ``dt`` the capture's own frame interval (or the asked ``fps``'s), the
        system's known geometry (the ball's floor at 0, where the camera put it).
    camera : Camera
        The pixels-to-metres mapping, its scale and the scale's relative std.
    lost : ndarray, shape (T,), bool
        Frames where the tracker did not see the object.
    known : dict of str -> float
        ``--known`` values, checked against the system.
    prior : dict of str -> (float, float)
        ``--prior`` ranges, checked against the system.
    notes : list of str
        What was done to the file (resampling, the camera), one sentence each.
    source_fps : float
        The file's frame rate (or ``--fps``).
    followed : dict, optional
        Where the object was followed from a box (``--object-box``): ``box`` ``(col, row,
        width, height)`` px and ``frame`` (H, W) uint8, the first kept frame it was drawn on
        (what ``track.png`` shows); None when the object was found by the background.
    """

    observation: object
    camera: Camera
    lost: np.ndarray
    known: dict
    prior: dict
    notes: list = field(default_factory=list)
    source_fps: float = float("nan")
    followed: dict | None = None

    @property
    def lost_share(self) -> float:
        """Share of frames the tracker did not see the object in."""
        return float(np.mean(self.lost)) if len(self.lost) else float("nan")


def clip_options(options) -> dict:
    """``identify``'s options for a clip (as a clip's record lists them) to keyword arguments.

    Parameters
    ----------
    options : sequence of str
        ``["--system", "pendulum", "--known", "L=0.8", "--start", "0.6", ...]``: the time
        window, ``--fps``, ``--rotate``, the scale and placement options, ``--known`` and
        ``--prior`` (repeatable).

    Returns
    -------
    dict
        ``system`` and ``method`` when given, ``rotate``, ``capture_fps``, ``start``, ``end``,
        ``px_per_m``, ``object_size_m``, ``floor_row``, ``walls``, ``pivot``, ``anchor``,
        ``track``, ``object_box`` (numbers; pairs and the box as tuples), ``known`` and
        ``prior`` (lists of the raw
        ``NAME=VALUE`` / ``NAME=LO:HI`` strings); only the options given.

    Raises
    ------
    ValueError
        An option identify does not take, a missing or non-numeric value; the message names
        the option.
    """
    if isinstance(options, (str, bytes)) or not hasattr(options, "__iter__"):
        raise TypeError(f"options: expected a sequence of strings, got {type(options).__name__}")
    toks = [str(t) for t in options]
    out: dict = {}
    i = 0
    while i < len(toks):
        flag = toks[i]
        if flag not in _CLIP_OPTIONS:
            raise ValueError(f"options: expected one of {', '.join(_CLIP_OPTIONS)}, got {flag!r}")
        n, dest = _CLIP_OPTIONS[flag]
        vals = toks[i + 1:i + 1 + n]
        if len(vals) < n or any(v.startswith("--") for v in vals):
            raise ValueError(f"{flag}: expected {n} value{'s' if n > 1 else ''}, got "
                             f"{' '.join(vals) or 'none'}")
        i += 1 + n
        if flag in ("--system", "--method"):
            out[flag[2:]] = vals[0]
        elif dest in ("known", "prior"):
            out.setdefault(dest, []).append(vals[0])
        else:
            nums = [_number(v, flag, "a number") for v in vals]
            if dest in _WRITTEN:  # the scale and placement keep how they were written
                nums = [Given(v) for v in vals]
            out[dest] = nums[0] if n == 1 else tuple(nums)
    if "rotate" in out:
        r = out["rotate"]
        if r not in ROTATIONS:
            raise ValueError(f"--rotate: expected 90, 180 or 270 (degrees clockwise), got {r:g}")
        out["rotate"] = int(r)
    return out


def observe_clip(path, system: str, options=(), *, progress: bool | None = False,
                 fps: float | None = None, max_frames: int | None = None,
                 **given) -> CameraClip:
    """A camera's clip of ``system`` and the options a user would give, as a method takes it.

    Decodes the file (:func:`read_video`: the window, the capture rate; every frame at the
    capture's own ``dt``, or resampled to ``fps``), turns it upright (:func:`rotate_frames`), follows the object at the
    file's resolution (:func:`find_object`), builds the camera (:func:`camera_for`: the scale
    given, from the object's size frame by frame, or from a known length) and maps the track
    to metres in the system's world frame. What ``sysid-bench identify --system S`` does
    before a method runs, for every system with a camera.

    Parameters
    ----------
    path : str or Path
        The video file.
    system : str
        A registered system; one of :data:`CAMERA_SYSTEMS`.
    options : sequence of str
        ``identify``'s options (:func:`clip_options`); a ``--system`` among them must name
        ``system``.
    progress : bool, optional
        tqdm bars while decoding (None: :func:`read_video`'s default) and tracking.
    fps : float, optional
        The rate of the method that will read the observation
        (:func:`sysid_bench.core.estimator.frame_rate_of`): the clip is resampled to it. None
        (default): the capture's own ``dt``, for a method that simulates at any step.
    max_frames : int, optional
        The most observations the method takes (:func:`sysid_bench.core.estimator.
        frame_cap_of`): a longer clip is thinned (:func:`thin_clip`).
    **given
        The same options as keywords (``rotate``, ``capture_fps``, ``start``, ``end``,
        ``px_per_m``, ``object_size_m``, ``floor_row``, ``walls``, ``pivot``, ``anchor``,
        ``object_box`` (the object's ``(col, row, width, height)`` in the first kept frame,
        upright: followed by its appearance, :func:`follow_object_box`, instead of
        :func:`find_object`); ``known`` and ``prior`` as dicts, as :func:`parse_known` and :func:`parse_prior`
        return them); a keyword that is not None overrides the option.

    Returns
    -------
    CameraClip

    Raises
    ------
    NotImplementedError
        A system without a camera (the collision: two pucks, the track's ends), with why.
    ValueError
        Bad options (named), a camera that cannot be right for the clip.
    VideoError
        A bad file, or an object found in fewer than 3 frames.
    """
    from sysid_bench.core import systems
    from sysid_bench.core.estimator import Observation

    sys_ = systems.get(system)
    opts = clip_options(options)
    dests = {d for _, d in _CLIP_OPTIONS.values() if d is not None}
    for k, v in given.items():
        if k not in dests:
            raise TypeError(f"{k}: expected one of {', '.join(sorted(dests))} as a keyword")
        if v is None:
            continue
        if k == "known":  # back to NAME=VALUE (repr round-trips a float exactly)
            v = [f"{n}={float(x)!r}" for n, x in dict(v).items()]
        elif k == "prior":
            v = [f"{n}={float(a)!r}:{float(b)!r}" for n, (a, b) in dict(v).items()]
        opts[k] = v
    if opts.get("system", sys_.name) != sys_.name:
        raise ValueError(f"options: --system {opts['system']} given for a clip of the "
                         f"{sys_.name} system")
    if sys_.name not in CAMERA_SYSTEMS:
        raise NotImplementedError(
            f"no camera is built for the {sys_.name} system yet (cameras: "
            f"{', '.join(CAMERA_SYSTEMS)}): its objects and placement (--track) are not "
            "followed from a camera's clip (issue 38, parts 2-3)")
    known = parse_known(sys_, opts.get("known", ()))
    prior = parse_prior(sys_, opts.get("prior", ()), known)
    if sys_.name in TRACK_OBJECTS:
        return _observe_track_clip(path, sys_, opts, known, prior, progress, fps, max_frames)
    if "track" in opts:
        raise ValueError(f"--track: means nothing for the {sys_.name} system (collision only)")
    box = opts.get("object_box")
    # a boxed object is followed in grey: the colour decode is not needed
    clip = read_video(path, fps, progress=progress, start=opts.get("start"), end=opts.get("end"),
                      capture_fps=opts.get("capture_fps"), colour=box is None)
    clip = thin_clip(clip, max_frames)
    rotate = int(opts.get("rotate", 0))
    frames = rotate_frames(clip.frames, rotate)
    followed = None
    if box is not None:
        from sysid_bench.core.box_track import check_box

        box = check_box(box, frames.shape[1:])
        trk = follow_object_box(frames, box, progress=bool(progress))
        followed = {"box": box, "frame": frames[0]}
    else:
        trk = find_object(frames, progress=bool(progress),
                          colour=None if clip.colour_frames is None
                          else rotate_frames(clip.colour_frames, rotate),
                          chroma_px=turned_chroma(clip.chroma_px, rotate))
    if trk.n_found < 3:
        raise VideoError(f"{path}: the {sys_.name}'s object was found in {trk.n_found} of "
                         f"{len(frames)} frames; the camera and the methods need a track (at "
                         "least 3 frames)")
    place = {k: opts[k] for k in ("px_per_m", "object_size_m", "floor_row", "walls", "pivot",
                                  "anchor") if k in opts}
    cam = camera_for(sys_.name, trk, frames.shape[1:], **place, known=known, rotate=rotate,
                     dt=1.0 / clip.fps)
    pos = cam.to_metres(trk.pixels)[:, None, :]  # (T, 1, 2): one tracked object
    obs = Observation(positions=pos, dt=1.0 / clip.fps, system=sys_.name,
                      **sys_.known_geometry())
    notes = [*clip.notes, f"the tracked object in metres ({cam.describe()})"]
    turn = axis_note(sys_, trk.pixels)
    if turn:
        notes.insert(len(clip.notes), turn)
    if followed is not None:
        c, r, w, h = followed["box"]
        notes.insert(len(clip.notes),
                     f"the object followed by its appearance from the box {w}x{h} px at column "
                     f"{c}, row {r} of the first frame (--object-box): seen in {trk.n_found} of "
                     f"{len(frames)} frames, not seen where its best match was weak")
    return CameraClip(observation=obs, camera=cam, lost=~np.isfinite(trk.pixels).all(axis=1),
                      known=known, prior=prior, notes=notes, source_fps=float(clip.source_fps),
                      followed=followed)


def axis_note(sys_, pixels: np.ndarray) -> str | None:
    """A note when a system that moves along its x axis was followed moving up and down.

    A spring hung vertically and filmed upright moves along the picture's rows; the spring
    system moves along x, so without ``--rotate`` its fit sees a block at rest and answers
    the prior (honest, and no use). The system's own axis is read from its simulation (8 prior
    draws, 100 steps: the spread of y under 5% of x's), the track's from the 5th-95th
    percentile spread of its seen pixels.

    Parameters
    ----------
    sys_ : System
    pixels : ndarray, shape (T, 2)
        Tracked (column, row), NaN where unseen.

    Returns
    -------
    str or None
    """
    seen = np.isfinite(pixels).all(axis=1)
    if seen.sum() < 3 or not _moves_along_x(sys_):
        return None  # too little seen, or the system moves in the plane (or not along x)
    lo, hi = np.percentile(pixels[seen], [5, 95], axis=0)
    cols, rows = hi - lo
    if rows >= 10 and rows > 3 * max(cols, 1.0):
        return (f"the object moved up and down ({rows:.0f} px over the rows) far more than "
                f"across ({cols:.0f} px), but the {sys_.name} system moves along the "
                "picture's x axis: a clip filmed with that motion vertical needs --rotate 90 "
                "or 270 (otherwise its fit sees an object at rest)")
    return None


_ALONG_X: dict = {}


def _moves_along_x(sys_) -> bool:
    """Whether ``sys_`` moves along its x axis only (:func:`axis_note`): the spread of y under
    5% of x's over 8 prior draws of 100 steps, simulated once per system class."""
    key = type(sys_)
    if key not in _ALONG_X:
        theta, s0 = sys_.sample_cases(8, rng=0)
        pts = sys_.observe(sys_.simulate(theta, s0, 100), theta)  # (8, 100, K, 2)
        spread = np.nanstd(pts, axis=1).mean(axis=(0, 1))  # (2,): x, y
        _ALONG_X[key] = bool(spread[0] > 0 and spread[1] <= 0.05 * spread[0])
    return _ALONG_X[key]


def _observe_track_clip(path, sys_, opts: dict, known: dict, prior: dict,
                        progress, fps: float | None = None,
                        max_frames: int | None = None) -> CameraClip:
    """:func:`observe_clip` for objects on a track told apart by colour (the collision): the
    clip decoded in colour (at the capture's own ``dt``, or resampled to ``fps``; thinned to
    ``max_frames``, as :func:`observe_clip` reads the others), the objects followed
    (:func:`~sysid_bench.core.tracking.track_colours`), the camera and the scene (the track's
    ends, each object's half-length) from :func:`camera_for_track`."""
    from sysid_bench.core.estimator import Observation
    from sysid_bench.core.tracking import track_colours

    n_obj, ends_field, sizes_field = TRACK_OBJECTS[sys_.name]
    if "object_box" in opts:
        raise ValueError(f"--object-box: follows one object; the {sys_.name}'s {n_obj} objects "
                         "are told apart by their colours (give no box)")
    for opt in ("floor_row", "walls", "pivot", "anchor"):
        if opt in opts:
            raise ValueError(f"--{opt.replace('_', '-')}: means nothing for the {sys_.name} "
                             "system (give --track C1 C2)")
    clip = read_video(path, fps, progress=progress, start=opts.get("start"), end=opts.get("end"),
                      capture_fps=opts.get("capture_fps"), rgb=True)
    clip = thin_clip(clip, max_frames)
    rotate = int(opts.get("rotate", 0))
    frames = rotate_frames(clip.frames, rotate)
    try:
        trk = track_colours(frames, n_obj, progress=bool(progress))
    except ValueError as exc:
        raise VideoError(f"{path}: the {sys_.name}'s {n_obj} objects were not found: "
                         f"{str(exc).partition(': ')[2]}") from None
    n_seen = trk.found.sum(axis=0)
    if (n_seen < 3).any():
        raise VideoError(f"{path}: the {sys_.name}'s objects were found in "
                         f"{', '.join(str(int(n)) for n in n_seen)} of {len(frames)} frames; the "
                         "camera and the methods need each object's track (at least 3 frames)")
    tc = camera_for_track(trk, frames.shape[1:3], px_per_m=opts.get("px_per_m"),
                          object_size_m=opts.get("object_size_m"), track_ends=opts.get("track"),
                          rotate=rotate)
    try:
        scene = sys_.scene(**{ends_field: tc.ends_m, sizes_field: tc.half_sizes_m})
    except ValueError as exc:
        opt = "object_size_m" if "object_size_m" in opts else "px_per_m"
        raise ValueError(f"{opt}: {exc}") from None
    pos = tc.camera.to_metres(tc.pixels)  # (T, K, 2)
    obs = Observation(positions=pos, dt=1.0 / clip.fps, system=sys_.name, scene=scene,
                      **sys_.known_geometry(scene))
    notes = [*clip.notes,
             f"scene: track ends {tc.ends_m[0]:.4g} to {tc.ends_m[1]:.4g} m, half-lengths "
             + ", ".join(f"{h:.3g}" for h in tc.half_sizes_m) + " m",
             f"the tracked objects in metres ({tc.camera.describe()}; track tilt "
             f"{tc.tilt_deg:.3g} deg taken out)"]
    return CameraClip(observation=obs, camera=tc.camera, lost=~trk.found.all(axis=1),
                      known=known, prior=prior, notes=notes, source_fps=float(clip.source_fps))
