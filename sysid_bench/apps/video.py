"""Identify a ball's physics from a user's video file (``sysid-bench identify VIDEO``).

Pipeline
--------
1-3. The file is decoded (:func:`read_video`): every frame at the capture's own dt for a method
   that simulates at any step, resampled to 20 frames/s for one built for that rate
   (Vid2Param, its ``frame_rate``), with a note saying so; its
   pixels mapped to the suite's metres (:class:`Geometry`) and the ball followed
   (:func:`find_ball`): the core half, :mod:`sysid_bench.core.footage`, re-exported here.
4. Position methods get the tracked positions in metres (floor at 0). Methods that read frames
   get the frames they were trained on: the renderer draws the ball at each tracked position in
   the method's view (its ``frame_size``: 28x28, or 50x100 for Vid2Param's
   ``--checkpoint camera``); frames where the ball was not found are black, as the renderer's
   dropped frames. See ``docs/video.md`` for why re-drawing rather than cropping the grey
   difference image.
5. :func:`write_outputs` writes ``estimates.csv``, ``estimates.json`` and ``track.png`` into a
   temporary folder beside ``--out`` and renames it into place only when all three exist.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sysid_bench.apps.video_systems import (
    bound_notes,  # noqa: F401  (one for every system)
    show_box,
)
from sysid_bench.core._io import atomic_folder
from sysid_bench.core.box_track import check_box
from sysid_bench.core.estimator import Observation, frame_cap_of, frame_rate_of
from sysid_bench.core.footage import (  # the core half (files, geometry, the tracker), re-exported
    _PROGRESS_FRAMES,
    MODEL_FPS,
    OBJECT_SIZE_RANGE_M,
    OUT_MARKER,
    BallTrack,
    Clip,
    Geometry,
    VideoError,
    camera_for,
    check_out_folder,
    find_ball,
    find_object,
    follow_object_box,
    geometry_from_options,
    knowledge_record,
    loosen_held,
    model_frames,
    observe,
    parse_known,
    parse_prior,
    read_video,
    report_held,
    rotate_frames,
    thin_clip,
    turned_chroma,
    widen_for_scale,
    write_video,
)
from sysid_bench.core.physics import BOX_WIDTH, PARAMS, PRIOR

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
    "identify_video",
    "default_method",
    "ball_method",
    "IdentifyResult",
    "write_outputs",
    "add_arguments",
    "run",
]


# -- identification -------------------------------------------------------------------------------
@dataclass
class IdentifyResult:
    """Everything ``identify`` writes.

    Attributes
    ----------
    mean, std : ndarray, shape (T, 4)
        Per-frame estimates (PARAMS order, physical units); NaN rows before a method's first
        estimate.
    positions : ndarray, shape (T, 2)
        Tracked positions, metres (NaN = not found).
    forecast_mean, forecast_std : ndarray, shape (H, 2) or None
    info : dict
        What goes into ``estimates.json`` besides the rows.
    check : ndarray, shape (T, 3), optional
        Per-frame model check of the estimate (``Posterior.check``): ok (1/0), residual RMS
        (m), assumed noise (m); NaN where the method gave no check (or no estimate yet).
    """

    mean: np.ndarray
    std: np.ndarray
    positions: np.ndarray
    forecast_mean: np.ndarray | None
    forecast_std: np.ndarray | None
    info: dict
    check: np.ndarray | None = None


def _estimator(method: str, checkpoint: str | None, seed: int, known: dict | None = None,
               prior: dict | None = None):
    """The method with ``checkpoint`` (only for a method that takes one) and ``seed``, holding
    ``known``/``prior`` where it takes them (:func:`_takes_knowledge`)."""
    import methods

    params = methods.get_class(method)._param_names()
    opts = {"seed": seed} if "seed" in params else {}
    if (known or prior) and _takes_knowledge(method):
        opts.update(known=dict(known or {}), prior=dict(prior or {}))
    if checkpoint is not None:
        if "checkpoint" not in params:
            takes = [m for m in methods.available()
                     if "checkpoint" in methods.get_class(m)._param_names()]
            raise ValueError(f"checkpoint: only {' and '.join(takes)} take a checkpoint, "
                             f"got {checkpoint!r} with method {method!r}")
        opts["checkpoint"] = checkpoint
    return methods.get(method, **opts)


def _checkpoint_of(est) -> str | None:
    """The checkpoint ``est`` reads (its own default when none was given), None for a method
    without one."""
    if "checkpoint" not in est.get_params():
        return None
    return est.checkpoint or getattr(est, "default_checkpoint", None)


#: how far from 1 a clip's width over height may be and still be the renderer's square view
_SQUARE_TOL = 0.02


def default_method() -> str:
    """The method ``identify`` uses when none is named: the first registered one that
    identifies from frames (registry order; a frame model reads the video as it was trained),
    else the first that identifies."""
    import methods

    names = methods.available()
    for want_frames in (True, False):
        for m in names:
            try:
                sp = methods.spec(m)
            except ImportError:
                continue
            if sp.identifies and (sp.input_kind == "frames" or not want_frames):
                return m
    raise ValueError("method: no registered method identifies")


def _fall_scaled(camera, known, geometry) -> bool:
    """A known g and neither a camera nor the renderer's box given: a camera's clip may take
    its scale from the ball's fall (when it is not the renderer's square view)."""
    return (not camera and "g" in (known or {})
            and not any(v is not None for v in (geometry or {}).values()))


def ball_method(path, *, camera: dict | None = None, known: dict | None = None,
                geometry: dict | None = None, rotate: int = 0) -> str:
    """The method ``identify`` uses on the ball when none is named.

    On the renderer's view, :func:`default_method` (a frame model reads the video as it was
    trained). On a camera's clip (a camera given, or a known g on a clip that is not the
    renderer's square view, so its scale comes from the fall), the same choice as on every
    other system (:func:`sysid_bench.apps.video_systems.camera_method`): a frame model would
    see the track re-drawn in a view it was not trained on, at 20 frames/s.
    """
    from sysid_bench.apps.video_systems import _clip_shape, camera_method

    if _fall_scaled(camera, known, geometry):
        shape = _clip_shape(path, int(rotate))
        camera = shape is not None and abs(shape[1] / shape[0] - 1.0) > _SQUARE_TOL
    return camera_method("ball") if camera else default_method()


def identify_video(path, *, method: str | None = None, checkpoint: str | None = None,
                   geometry: dict | None = None, every: int | None = None, horizon: int = 20,
                   seed: int = 0, progress: bool | None = None, camera: dict | None = None,
                   rotate: int = 0, start: float | None = None, end: float | None = None,
                   capture_fps: float | None = None, known: dict | None = None,
                   prior: dict | None = None, object_box=None) -> IdentifyResult:
    """Identify ``(e, g, d, r)`` frame by frame from a video file.

    Parameters
    ----------
    path : str or Path
    method : str, optional
        A registered identifying method (``methods.available()``); default
        :func:`ball_method` (a frame model on the renderer's view, emcee on a camera's clip).
    checkpoint : str, optional
        The checkpoint of a method that takes one (Vid2Param: ``"28x28"``, its default, or
        ``"camera"``, a 50x100 view).
    geometry : dict, optional
        Keyword options of :func:`geometry_from_options` (``px_per_m``, ``floor_row``,
        ``wall_col``, ``corners``, ``ball_radius_px``).
    every : int, optional
        Frames between estimates of a method without a one-pass ``identify_prefixes``
        (default: about 20 estimates over the clip); a streaming method estimates every frame.
        Rows between estimates repeat the last one (``estimated`` column 0).
    horizon : int
        Frames forecast after the last one (for ``track.png``).
    seed : int
    progress : bool, optional
    camera : dict, optional
        A real camera instead of the renderer's framing: keyword options of
        :func:`sysid_bench.core.footage.camera_for` (``px_per_m`` or ``object_size_m``;
        ``floor_row``, ``walls``), exclusive with ``geometry``. Positions are then the ball's
        true metres (floor at 0; with no walls, the track mid-way in the 10 m box), and the
        scale's uncertainty widens the intervals of g, d and r.
    rotate : {0, 90, 180, 270}
        Degrees clockwise to turn frames stored sideways.
    start, end, capture_fps : float, optional
        The window (seconds) and the capture rate of a slow-motion file
        (:func:`read_video`).
    known, prior : dict, optional
        What the user knows (:func:`sysid_bench.core.footage.parse_known`, ``parse_prior``):
        recorded under ``knowledge`` with whether the method held them.
    object_box : (float, float, float, float), optional
        With a camera: the ball's ``(col, row, width, height)`` px in the first kept frame
        (upright); it is followed by its appearance
        (:func:`~sysid_bench.core.footage.follow_object_box`) instead of by the background,
        and ``track.png`` shows the box over that frame.

    Returns
    -------
    IdentifyResult

    Raises
    ------
    VideoError
        A bad file, or a position method on a video in which the ball is never found.
    ValueError
        Bad options (unknown method, geometry outside the frame).
    """
    import methods
    from sysid_bench.bench.experiment import streams

    if method is None:
        method = ball_method(path, camera=camera, known=known, geometry=geometry,
                             rotate=rotate)
    if method not in methods.available(include_reference=True):
        raise ValueError(f"method: expected one of {', '.join(methods.available())}, got "
                         f"{method!r}")
    # bad options fail before the file is read; known/prior held where the method takes them
    est = _estimator(method, checkpoint, seed, known, prior)
    held = bool(known or prior) and _takes_knowledge(method)
    if camera and geometry and any(v is not None for v in geometry.values()):
        raise ValueError("camera: give a camera (px_per_m, object_size_m, walls) or the "
                         "renderer's box geometry (corners, wall_col), not both")
    # a method that simulates at any step reads every frame at the capture's own dt; one built
    # for a frame rate (Vid2Param) gets the clip resampled to it, and the notes say so
    rate = frame_rate_of(est)
    # a known g and no camera or box given: a camera's clip may take its scale from the fall
    by_fall = _fall_scaled(camera, known, geometry)
    if object_box is not None and not (camera or by_fall):
        raise ValueError("object_box: a box is followed on a camera's clip, and this one's scale "
                         "is not known: give --px-per-m or --object-size-m")
    # a boxed ball is followed in grey: the colour decode is not needed
    clip = read_video(path, rate, progress=progress, start=start, end=end,
                      capture_fps=capture_fps,
                      colour=(bool(camera) or by_fall) and object_box is None)
    resampled = len(clip.frames) != clip.source_frames or abs(clip.fps - clip.source_fps) > 1e-9
    # a method whose cost grows with the observations takes at most its cap (NUTS: 400)
    clip = thin_clip(clip, frame_cap_of(est), method)
    frames = rotate_frames(clip.frames, int(rotate))
    t_n, h, w = frames.shape
    # progress bars on long files, on a terminal (or when asked)
    show = (sys.stderr.isatty() if progress is None else bool(progress)) and t_n > _PROGRESS_FRAMES
    is_video = getattr(type(est), "input_kind", "positions") == "frames"
    size = tuple(est.frame_size) if is_video else None
    notes = list(clip.notes)
    if rate is not None and resampled:
        notes.append(f"{method} is built for {rate:g} frames/s, so the clip was resampled to it "
                     "(a method that simulates at any step, e.g. lsq, reads every frame at the "
                     "capture's own dt)")
    cam = None
    loose: dict = {}  # held values searched within the scale's spread (loosen_held)
    k0 = 0  # the window's frames left out before the ball is first seen (camera clips)
    if by_fall and abs(w / h - 1.0) > _SQUARE_TOL:
        # not the renderer's square view: a camera's clip, its scale from the known g's fall
        camera = {"px_per_m": None, "object_size_m": None, "floor_row": None, "walls": None}
        notes.append(f"the clip is {w}x{h}, not the renderer's square view of the box: read as "
                     "a camera's, its scale from the ball's fall and the known g")
    followed = None
    if camera:
        if object_box is not None:
            box = check_box(object_box, (h, w))
            trk = follow_object_box(frames, box, progress=show)
            followed = {"box": box, "frame": frames[0]}
            notes.append(f"the ball followed by its appearance from the box {box[2]}x{box[3]} px "
                         f"at column {box[0]}, row {box[1]} of the first frame (--object-box): "
                         f"seen in {trk.n_found} of {t_n} frames, not seen where its best match "
                         "was weak")
        else:
            trk = find_object(frames, progress=show, colour=None if clip.colour_frames is None
                              else rotate_frames(clip.colour_frames, int(rotate)),
                              chroma_px=turned_chroma(clip.chroma_px, int(rotate)))
        if trk.n_found < 3:
            raise VideoError(f"{path}: the ball was found in {trk.n_found} of {t_n} frames; "
                             "the camera and the methods need a track (at least 3 frames)")
        k0 = trk.first_seen()
        if k0 > 0:
            # the methods' start is the state at frame 0: extrapolated back across unseen
            # frames (a ball still in the hand) it is no state the ball had (arz.avi: 7 frames
            # before the drop, the fit 1.24 m RMS off a plainly bouncing track; 1.1 cm from here)
            trk, frames, t_n = trk.from_frame(k0), frames[k0:], t_n - k0
            notes.append(f"the track starts where the ball is first seen: frame {k0}, "
                         f"{k0 / clip.fps:.3g} s into the window ({k0} unseen frames before it "
                         "left out)")
        cam = camera_for("ball", trk, (h, w), **camera, known=known, rotate=int(rotate),
                         dt=1.0 / clip.fps)
        if held and known:
            # a held length read through an uncertain scale: searched within the scale's
            # spread of the user's value (reported as held), not pushed into e, d, r
            k2, p2, loose = loosen_held("ball", known, prior or {}, cam.scale_rel_std,
                                        cam.source)
            if loose:
                est = _estimator(method, checkpoint, seed, k2, p2)
        pos = cam.to_metres(trk.pixels)
        if is_video:
            obs = Observation(frames=model_frames(pos, size), dt=1.0 / clip.fps, floor=0.0)
            notes.append(f"{method} saw the tracked ball re-drawn in its {size[1]}x{size[0]} "
                         "view of the 10 m box at the camera's true scale")
        else:
            obs = Observation(positions=np.clip(pos, 0.0, BOX_WIDTH), dt=1.0 / clip.fps,
                              floor=0.0)
        geo = cam
    else:
        obs, pos, trk, geo = observe(frames, size, geometry, dt=1.0 / clip.fps, progress=show)
    found = trk.n_found > 0
    if is_video and not found:
        notes.append("the ball was never found: the model saw black frames only and "
                     "answers its prior")
    if not is_video and trk.n_found < 3:
        raise VideoError(f"{path}: the ball was found in {trk.n_found} of {t_n} frames; "
                         f"{method} needs a track (at least 3 frames)")
    mean = np.full((t_n, 4), np.nan)
    std = np.full((t_n, 4), np.nan)
    estimated = np.zeros(t_n, dtype=bool)
    if streams(est):
        lengths = list(range(1, t_n + 1))
        posts = est.identify_prefixes(obs, lengths)
    else:
        k = every or max(1, int(math.ceil(t_n / 20)))
        lengths = sorted(set(range(k, t_n + 1, k)) | {t_n})
        posts = []
        from tqdm.auto import tqdm

        for n in tqdm(lengths, desc=f"{method}", unit="estimate", leave=False,
                      disable=not show):
            try:
                posts.append(est.identify(obs.prefix(n)))
            except NotImplementedError:
                raise
            except ValueError:
                posts.append(None)  # too short a prefix for this method
    if all(p is None for p in posts):
        raise VideoError(f"{path}: {method} could not identify from any prefix of the "
                         f"{t_n} frames")
    check = np.full((t_n, 3), np.nan)
    last_check = None
    for n, p in zip(lengths, posts):
        if p is not None:
            mean[n - 1], std[n - 1] = p.mean, p.std
            estimated[n - 1] = True
            if p.check is not None:
                check[n - 1] = (float(p.check.ok), p.check.rms_m, p.check.noise_m)
                last_check = {**p.check.as_dict(), "note": p.check.note}
                if not p.check.ok and "support_rms_m" in p.extras:
                    # failed, but a best fit near the answer explains the track: the model
                    # explains the video, the method's answer does not (intervals hold the fit)
                    last_check.update(support_fit=[float(v) for v in p.extras["support_fit"]],
                                      support_rms_m=float(p.extras["support_rms_m"]))
    # rows between estimates carry the last one forward
    for i in range(1, t_n):
        if not estimated[i] and np.isfinite(mean[i - 1]).all():
            mean[i], std[i], check[i] = mean[i - 1], std[i - 1], check[i - 1]
    fmean = fstd = None
    if found:
        try:
            fc = est.forecast(obs, int(horizon))
            fmean, fstd = fc.mean, fc.std
        except (NotImplementedError, ValueError) as exc:
            notes.append(f"no forecast: {exc}")
    info = {
        "method": method,
        "checkpoint": _checkpoint_of(est),
        "file": str(path),
        "fps": clip.source_fps,
        "model_fps": clip.fps,
        # the time base the method saw: the capture's own dt, or its own rate's
        "dt_s": 1.0 / clip.fps,
        "method_frame_rate": rate,
        "resampled": bool(resampled),
        "source_frames": clip.source_frames,
        "frames": t_n,
        "colour": clip.colour,
        "frame_size": [w, h],
        "model_view": None if size is None else [size[1], size[0]],
        "input": "re-drawn model frames" if is_video else "tracked positions",
        "geometry": geo.as_dict(),
        "camera": None if cam is None else cam.as_dict(),
        "rotate": int(rotate),
        "window_s": [start, end],
        # frame 0 of the outputs is this frame of the (resampled) window
        "first_frame": int(k0),
        "capture_fps": capture_fps,
        "knowledge": knowledge_record(known or {}, prior or {}, method, held=held,
                                      why=_knowledge_refused(method)),
        "ball_found": found,
        "frames_with_ball": trk.n_found,
        "ball_radius_px": None if not found else trk.radius,
        "estimated_frames": [int(i) for i in np.flatnonzero(estimated)] if not streams(est)
        else "all",
        "notes": notes,
        "horizon": int(horizon),
        # the last estimate's model check (None: the method cannot tell)
        "check": last_check,
    }
    if held:  # said as on the other systems (video_systems.identify_system_video)
        said = [f"{k} = {v:g} held" for k, v in (known or {}).items()]
        said += [f"{k} searched in {a:g} to {b:g}" for k, (a, b) in (prior or {}).items()]
        notes.append(f"--known/--prior: {method} used them ({'; '.join(said)})")
    if cam is not None and cam.scale_rel_std > 0:
        std = widen_for_scale("ball", PARAMS, mean, std, cam.scale_rel_std)
        notes.append(f"the scale's {100 * cam.scale_rel_std:.2g}% uncertainty is added to the "
                     "std of g, d and r")
        if held and known:  # a held value is the user's, not measured through the scale
            cols = [PARAMS.index(k) for k in known]
            std[:, cols] = np.where(np.isnan(mean[:, cols]), np.nan, 0.0)
    if loose:  # searched within the scale's spread while fitting: reported as held
        notes.append(report_held(PARAMS, mean, known, loose, cam.scale_rel_std))
    notes.extend(bound_notes(mean, known, prior))
    if followed is not None:  # recorded only where given: other runs' files stay as they were
        info["object_box"] = [int(v) for v in followed["box"]]
        info["tracker"] = "appearance (ZNCC template from --object-box)"
    res = IdentifyResult(mean, std, pos, fmean, fstd, info, check)
    res.info["estimated"] = estimated
    if followed is not None:
        res.info["followed"] = followed
    return res


# -- outputs --------------------------------------------------------------------------------------
def _rows(res: IdentifyResult, dt: float) -> list[dict]:
    est = res.info["estimated"]
    rows = []
    for i in range(len(res.mean)):
        r = {"frame": i, "t_s": round(i * dt, 6)}
        for k, p in enumerate(PARAMS):
            r[f"{p}_mean"] = float(res.mean[i, k])
            r[f"{p}_std"] = float(res.std[i, k])
        r["estimated"] = int(bool(est[i]))
        chk = res.check[i] if res.check is not None else np.full(3, np.nan)
        r["check_ok"] = int(chk[0]) if np.isfinite(chk[0]) else None
        r["check_rms_m"], r["check_noise_m"] = float(chk[1]), float(chk[2])
        r["x_m"], r["y_m"] = (float(v) for v in res.positions[i])
        rows.append(r)
    return rows


def _plot(res: IdentifyResult, path: Path, dt: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t_n = len(res.mean)
    t = np.arange(t_n) * dt
    followed = res.info.get("followed")
    fig = plt.figure(figsize=(12, 6.5) if followed is None else (15, 6.5))
    gs = fig.add_gridspec(2, 4 + (followed is not None), height_ratios=[1.1, 1])
    z = 1.6449
    for k, (lab, col) in enumerate((("x (m)", "tab:blue"), ("y (m)", "tab:orange"))):
        ax = fig.add_subplot(gs[0, 2 * k : 2 * k + 2])
        ax.plot(t, res.positions[:, k], ".", ms=3, color=col, label="tracked")
        if res.forecast_mean is not None:
            tf = t_n * dt + np.arange(len(res.forecast_mean)) * dt
            m, s = res.forecast_mean[:, k], res.forecast_std[:, k]
            ax.plot(tf, m, color="k", lw=1.2, label="forecast")
            ax.fill_between(tf, m - z * s, m + z * s, color="k", alpha=0.15, label="90% band")
        ax.set(xlabel="t (s)", ylabel=lab, ylim=(-0.5, 10.5))
        ax.legend(fontsize=7, loc="upper right")
    ax0 = fig.axes[0]
    ax0.set_title(f"{Path(res.info['file']).name}: {res.info['method']}, ball found in "
                  f"{res.info['frames_with_ball']}/{t_n} frames", fontsize=9, loc="left")
    for k, p in enumerate(PARAMS):
        ax = fig.add_subplot(gs[1, k])
        m, s = res.mean[:, k], res.std[:, k]
        ax.plot(t, m, color="tab:red", lw=1.2)
        ax.fill_between(t, m - z * s, m + z * s, color="tab:red", alpha=0.2)
        ax.set(xlabel="t (s)", title=f"{p} (mean, 90% interval)", ylim=PRIOR[p])
        ax.title.set_fontsize(9)
    if followed is not None:  # what was followed: the box over the first frame
        show_box(fig.add_subplot(gs[:, 4]), followed)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_outputs(res: IdentifyResult, out) -> Path:
    """Write ``estimates.csv``, ``estimates.json`` and ``track.png`` into ``out``, all or nothing.

    The three files are written into a temporary folder beside ``out`` that then takes its
    place whole (:func:`sysid_bench.core._io.atomic_folder`). On any error the temporary folder is
    removed and ``out`` is as it was.
    """
    import csv

    out = check_out_folder(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    dt = 1.0 / res.info["model_fps"]

    def write(tmp: Path) -> None:
        rows = _rows(res, dt)
        with open(tmp / "estimates.csv", "w", newline="") as f:
            wr = csv.DictWriter(f, fieldnames=list(rows[0]))
            wr.writeheader()
            wr.writerows(rows)
        info = {"written_by": OUT_MARKER,
                **{k: v for k, v in res.info.items() if k not in ("estimated", "followed")}}
        info["estimates"] = rows
        info["forecast"] = None if res.forecast_mean is None else {
            "after_frame": len(rows) - 1, "mean": res.forecast_mean.tolist(),
            "std": res.forecast_std.tolist()}
        with open(tmp / "estimates.json", "w") as f:
            json.dump(_finite(info), f, indent=1)
        _plot(res, tmp / "track.png", dt)

    # files in an existing ``out`` that this did not write are kept (design: --out never
    # overwrites a file it did not write); the three are replaced together
    atomic_folder(out, write, keep_others=True)
    return out


def _finite(x):
    """JSON without NaN (which is not JSON): NaN and inf become null."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


# -- command line ---------------------------------------------------------------------------------
#: Each placement or camera option and the systems it means something for; given on another
#: system it is refused with one line, never ignored.
OPTION_SYSTEMS = {
    "px_per_m": ("ball", "pendulum", "spring", "collision"),
    "object_size_m": ("ball", "pendulum", "spring", "collision"),
    "object_box": ("ball", "pendulum", "spring"),
    "floor_row": ("ball",),
    "walls": ("ball",),
    "wall_col": ("ball",),
    "corners": ("ball",),
    "ball_radius_px": ("ball",),
    "pivot": ("pendulum",),
    "anchor": ("spring",),
    "track": ("collision",),
    "checkpoint": ("ball",),
    "horizon": ("ball",),
}
#: Systems whose clips run through :func:`identify_video` (the paper's pipeline: the renderer's
#: box, vid2param's checkpoints, a forecast ``horizon``); the others, a user's included,
#: through :mod:`sysid_bench.apps.video_systems`.
_PAPER_PIPELINE = ("ball",)
#: Options that mean something on a system but are not built there yet, with why.
_NOT_YET: dict[str, str] = {}


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The ``identify VIDEO`` options on a ``sysid-bench`` subcommand parser
    (``sysid_bench.apps.cli.SUBCOMMANDS``)."""
    p.add_argument("video", help="video file (any format FFmpeg reads)")
    p.add_argument("--system", default="ball",
                   help="the system seen (sysid_bench.core.systems.available(); default ball)")
    p.add_argument("--method", default=None,
                   help="identifying method (default: on the renderer's view, the first "
                        "registered one that reads frames; on a camera's clip, emcee, else "
                        "lsq)")
    p.add_argument("--checkpoint", default=None, choices=("28x28", "camera"),
                   help="ball: the model of a method that takes a checkpoint: 28x28 (its "
                        "default) or camera (100x50 view)")
    p.add_argument("--out", default=None,
                   help="output folder (default: runs/identify/<video name>_<method>/); an "
                        "existing non-empty folder is refused unless it holds a previous "
                        "identify's output")
    t = p.add_argument_group("time and orientation")
    t.add_argument("--start", type=float, default=None, help="seconds to skip (a hand in view)")
    t.add_argument("--end", type=float, default=None, help="seconds where the clip ends")
    t.add_argument("--fps", type=float, default=None,
                   help="capture rate of a slow-motion file (overrides the container's)")
    t.add_argument("--rotate", type=float, default=None, metavar="{90,180,270}",
                   help="degrees clockwise to turn a video stored sideways")
    c = p.add_argument_group(
        "camera (any not given is estimated from the clip where physics fixes it, or absent)")
    c.add_argument("--px-per-m", type=number, default=None, help="scale, pixels per metre")
    c.add_argument("--object-size-m", type=float, default=None,
                   help="the tracked object's true diameter (m): the scale frame by frame "
                        "(collision: the carts' length, both the same)")
    c.add_argument("--object-box", type=float, nargs=4, default=None,
                   metavar=("C", "R", "W", "H"),
                   help="the object's box in the first kept frame (after --start and --rotate): "
                        "top-left column and row, width and height, px (OpenCV's x y w h); the "
                        "object is then followed by its appearance, not by the background (one "
                        "object: ball, pendulum, spring)")
    c.add_argument("--floor-row", type=number, default=None, help="ball: row of the floor")
    c.add_argument("--walls", type=number, nargs=2, default=None, metavar=("C1", "C2"),
                   help="ball: columns of the left and right walls")
    c.add_argument("--pivot", type=number, nargs=2, default=None, metavar=("C", "R"),
                   help="pendulum: the pivot's column and row (default: from the bob's arc)")
    c.add_argument("--anchor", type=number, default=None, metavar="C",
                   help="spring: the anchor's column")
    c.add_argument("--track", type=number, nargs=2, default=None, metavar=("C1", "C2"),
                   help="collision: columns of the track's left and right ends (default: "
                        "where the carts turn back, or out of reach)")
    g = p.add_argument_group("the renderer's box (ball; default: framed as the suite's renderer)")
    g.add_argument("--wall-col", type=float, default=None, help="column of the left wall")
    g.add_argument("--corners", type=float, nargs=4, default=None,
                   metavar=("C1", "R1", "C2", "R2"),
                   help="the floor's corners with the left and right walls, px")
    g.add_argument("--ball-radius-px", type=float, default=None,
                   help="ball radius in px (default: measured, or the renderer's)")
    k = p.add_argument_group("what you know")
    k.add_argument("--known", action="append", default=[], metavar="NAME=VALUE",
                   help="a parameter's known value (e.g. g=-9.81, L=0.62); repeatable")
    k.add_argument("--prior", action="append", default=[], metavar="NAME=LO:HI",
                   help="a parameter's range (e.g. w2=20:80); repeatable")
    from sysid_bench.core._validate import SEED_MAX, arg_number
    from sysid_bench.core.estimator import MAX_HORIZON

    p.add_argument("--every", type=arg_number(1, None, integer=True), default=None,
                   help="frames between estimates of a non-streaming method")
    p.add_argument("--horizon", type=arg_number(1, MAX_HORIZON, integer=True), default=None,
                   help=f"ball: frames forecast, 1 to {MAX_HORIZON} (default 20)")
    p.add_argument("--seed", type=arg_number(0, SEED_MAX, integer=True), default=0)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(fn=run)
    return p


def default_out(video, method: str) -> Path:
    """``identify``'s output folder when ``--out`` is not given: under ``runs/`` (ignored by
    git), one per video and method, so no two commands' outputs (or committed files) are
    overwritten."""
    return Path("runs") / "identify" / f"{Path(video).stem}_{method}"


def check_options(args) -> tuple[str, dict, dict]:
    """Refuse every option that means nothing for ``args.system`` or is out of range.

    Returns
    -------
    system : str
        The registered name.
    known, prior : dict
        Parsed ``--known`` and ``--prior``.

    Raises
    ------
    ValueError
        One line naming the option (``--pivot``, ``--rotate``, ...).
    """
    from sysid_bench.core import systems

    name = systems.get(args.system).name  # unknown names: ValueError with "did you mean"
    box = getattr(args, "object_box", None)
    if box is not None and name not in OPTION_SYSTEMS["object_box"]:
        raise ValueError(f"--object-box: follows one object; the {name} system's objects are "
                         "followed by the tracker of their own (give no box)")
    if box is not None:  # its size now; inside the frame once the clip's size is read
        check_box(box, None, "--object-box")
    for dest, where in OPTION_SYSTEMS.items():
        v = getattr(args, dest, None)
        if v is None:
            continue
        if name in where:
            continue
        if name in _NOT_YET and dest not in ("checkpoint", "horizon", "ball_radius_px",
                                             "floor_row", "wall_col", "corners", "walls",
                                             "pivot", "anchor"):
            raise ValueError(f"{_flag(dest)}: not yet for the {name} system: {_NOT_YET[name]}")
        meant = ", ".join(where)
        raise ValueError(f"{_flag(dest)}: means nothing for the {name} system (it is for "
                         f"{meant})")
    if args.rotate is not None and args.rotate not in (90, 180, 270):
        raise ValueError(f"--rotate: expected 90, 180 or 270 (degrees clockwise), got "
                         f"{args.rotate:g}")
    if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
        raise ValueError(f"--fps: expected a capture rate > 0 frames/s, got {args.fps:g}")
    for dest in ("start", "end"):
        v = getattr(args, dest)
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{_flag(dest)}: expected seconds >= 0, got {v:g}")
    if args.start is not None and args.end is not None and args.end <= args.start:
        raise ValueError(f"--end: expected a time after --start {args.start:g} s, got "
                         f"{args.end:g} s")
    if args.px_per_m is not None and args.object_size_m is not None:
        raise ValueError("--object-size-m: give either --px-per-m or --object-size-m, not both")
    for dest in ("px_per_m", "object_size_m"):
        v = getattr(args, dest)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"{_flag(dest)}: expected a number > 0, got {v:g}")
    if args.object_size_m is not None and not (OBJECT_SIZE_RANGE_M[0] <= args.object_size_m
                                               <= OBJECT_SIZE_RANGE_M[1]):
        lo, hi = OBJECT_SIZE_RANGE_M
        raise ValueError(f"--object-size-m: expected an object {lo:g} to {hi:g} m across, got "
                         f"{args.object_size_m:g} m")
    if (args.walls is not None or args.object_size_m is not None) and (
            args.corners is not None or args.wall_col is not None):
        raise ValueError("--walls: give a camera (--px-per-m, --object-size-m, --walls) or the "
                         "renderer's box (--corners, --wall-col), not both")
    known = parse_known(name, args.known)
    prior = parse_prior(name, args.prior, known)
    return name, known, prior


def _box_camera_options(args, system: str, known: dict) -> dict | None:
    """A system in a box (the ball): the renderer's box (``--corners``/``--wall-col``) or a
    camera placed by its floor and walls, which needs the scale."""
    scale = args.px_per_m is not None or args.object_size_m is not None
    legacy = args.wall_col is not None or args.corners is not None
    if legacy or not (scale or args.walls is not None):
        return None
    if not scale:
        raise ValueError("--walls: the scale is not known: give --px-per-m or "
                         "--object-size-m with it")
    return {"px_per_m": args.px_per_m, "object_size_m": args.object_size_m,
            "floor_row": args.floor_row, "walls": args.walls}


def _camera_options(args, system: str, known: dict) -> dict | None:
    """The :func:`camera_for` options given, or None for the renderer's framing."""
    if system in _CAMERA_OPTIONS:
        return _CAMERA_OPTIONS[system](args, system, known)
    scale = args.px_per_m is not None or args.object_size_m is not None
    opts = {"px_per_m": args.px_per_m, "object_size_m": args.object_size_m}
    if system == "pendulum":
        opts["pivot"] = args.pivot
    if system == "spring":
        opts["anchor"] = args.anchor
    if system == "collision":
        opts["track"] = None if args.track is None else tuple(args.track)
    # the pendulum's scale from a known length (the arc's radius); from a known g (its period)
    # only on a clip that is not the renderer's view (identify_system_video decides)
    by_length = system == "pendulum" and "L" in known
    if not any(v is not None for v in opts.values()) and not by_length:
        return None  # framed as the system's renderer draws it
    if not scale and not by_length:
        placed = next(_flag(k) for k, v in opts.items() if v is not None)
        raise ValueError(f"{placed}: the {system}'s scale is not known: give --px-per-m or "
                         "--object-size-m" + (", --known L=... or --known g=..."
                                              if system == "pendulum" else ""))
    return opts


#: Systems whose camera options are read their own way (the ball: the renderer's box, or its
#: floor and walls); any other: the scale and its placing option (--pivot, --anchor).
_CAMERA_OPTIONS = {"ball": _box_camera_options}


def _one_line(exc: Exception, args) -> str:
    """The error's line with the option named as the command line spells it."""
    msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    head, sep, rest = msg.partition(":")
    if sep and head in {*OPTION_SYSTEMS, "known", "prior", "out", "rotate", "start", "end",
                        "capture_fps", "every", "horizon"}:
        return f"{_flag('fps' if head == 'capture_fps' else head)}:{rest}"
    if head == "geometry":  # the renderer's box: name the options that placed it
        given = [_flag(d) for d in ("px_per_m", "floor_row", "wall_col", "corners",
                                    "ball_radius_px") if getattr(args, d, None) is not None]
        if given:
            return f"{'/'.join(given)}: {msg}"
    return msg


def _run_system(args, name: str, known: dict, prior: dict, camera: dict | None,
                out: Path) -> int:
    """``identify --system S`` for a system other than the ball (:mod:`video_systems`)."""
    from sysid_bench.apps.video_systems import identify_system_video, write_system_outputs

    res = identify_system_video(args.video, name, method=args.method, every=args.every,
                                progress=None if not args.no_progress else False,
                                camera=camera, rotate=int(args.rotate or 0), start=args.start,
                                end=args.end, capture_fps=args.fps, known=known, prior=prior,
                                object_box=getattr(args, "object_box", None))
    method = res["info"]["method"]
    out = out if args.out else default_out(args.video, f"{name}_{method}")
    write_system_outputs(res, out)
    for n in res["info"]["notes"]:
        print(f"note: {n}", file=sys.stderr)
    chk = res["check"][np.isfinite(res["check"][:, 0])]
    if len(chk) and not chk[-1, 0]:
        print(f"warning: the model does not explain this video: {method}'s fit misses the "
              f"track by {chk[-1, 1]:.3g} m RMS against an assumed noise of {chk[-1, 2]:.3g} m",
              file=sys.stderr)
    last = np.flatnonzero(np.isfinite(res["mean"][:, 0]))[-1]
    where = res["info"].get("camera") or {}
    print(f"{args.video}: {name}, {method} after {last + 1} frames: "
          + ", ".join(f"{p} = {m:.4g} ± {s:.2g}" for p, m, s in
                      zip(res["info"]["params"], res["mean"][last], res["std"][last]))
          + (f"; {where['mapping']}" if where else "") + f"; wrote {out}/")
    return 0


def run(args) -> int:
    """Run ``identify``; bad input prints one line to stderr and returns 2."""
    geometry = {"px_per_m": args.px_per_m, "floor_row": args.floor_row,
                "wall_col": args.wall_col, "corners": args.corners,
                "ball_radius_px": args.ball_radius_px}
    try:
        if args.every is not None and args.every < 1:
            raise ValueError(f"every: expected an int >= 1, got {args.every}")
        if args.horizon is not None and args.horizon < 1:
            raise ValueError(f"horizon: expected an int >= 1, got {args.horizon}")
        name, known, prior = check_options(args)
        camera = _camera_options(args, name, known)
        box = getattr(args, "object_box", None)
        if box is not None:
            if camera is None and "g" not in known:
                raise ValueError("object_box: a box is followed on a camera's clip, and this "
                                 "one's scale is not known: give --px-per-m or --object-size-m")
            from sysid_bench.apps.video_systems import _clip_shape

            shape = _clip_shape(args.video, int(args.rotate or 0))
            if shape is not None:  # inside the frame, before the clip is decoded
                check_box(box, shape)
        out = Path(args.out) if args.out else None
        if out is not None:
            check_out_folder(out)  # before any work: a folder of other files is refused
        if name not in _PAPER_PIPELINE:
            return _run_system(args, name, known, prior, camera, out)
        if args.method is None:
            args.method = ball_method(args.video, camera=camera, known=known,
                                      geometry=None if camera else geometry,
                                      rotate=int(args.rotate or 0))
        out = out or default_out(args.video, args.method)
        horizon = 20 if args.horizon is None else args.horizon
        res = identify_video(args.video, method=args.method, checkpoint=args.checkpoint,
                             geometry=None if camera else geometry, every=args.every,
                             horizon=horizon, seed=args.seed,
                             progress=None if not args.no_progress else False, camera=camera,
                             rotate=int(args.rotate or 0), start=args.start, end=args.end,
                             capture_fps=args.fps, known=known, prior=prior,
                             object_box=getattr(args, "object_box", None))
        write_outputs(res, out)
    except VideoError as exc:
        print(f"sysid-bench identify: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"sysid-bench identify: {args.video}: {_one_line(exc, args)}", file=sys.stderr)
        return 2
    except NotImplementedError as exc:  # dmd: no parameters to identify
        print(f"sysid-bench identify: {args.video}: {args.method} cannot identify: {exc}",
              file=sys.stderr)
        return 2
    except ImportError as exc:  # a method's optional dependency
        print(f"sysid-bench identify: {args.video}: {exc}", file=sys.stderr)
        return 3
    for n in res.info["notes"]:
        print(f"note: {n}", file=sys.stderr)
    kn = res.info.get("knowledge") or {}
    if kn.get("note"):
        print(f"note: --known/--prior {kn['note']}", file=sys.stderr)
    chk = res.info.get("check")
    if chk is not None and not chk["check_ok"] and "support_fit" in chk:
        fit = ", ".join(f"{p} = {v:.4g}" for p, v in zip(PARAMS, chk["support_fit"]))
        print(f"warning: {res.info['method']}'s answer does not explain this video: its fit "
              f"misses the track by {chk['check_rms_m']:.3g} m RMS against an assumed noise of "
              f"{chk['check_noise_m']:.3g} m, and the best fit near it ({fit}) explains it "
              f"({chk['support_rms_m']:.3g} m RMS); intervals widened to hold that fit",
              file=sys.stderr)
    elif chk is not None and not chk["check_ok"] and not np.isfinite(chk["check_rms_m"]):
        # nothing to compare with: the object was seen in too few frames for a fit
        print(f"warning: {res.info['method']}'s answer could not be checked: the object was not "
              "seen in enough frames to compare a fit with; intervals widened to at least the "
              "prior's", file=sys.stderr)
    elif chk is not None and not chk["check_ok"]:
        print(f"warning: the model does not explain this video: {res.info['method']}'s fit "
              f"misses the track by {chk['check_rms_m']:.3g} m RMS against an assumed noise of "
              f"{chk['check_noise_m']:.3g} m; intervals widened to at least the prior's, or read "
              "them as unreliable", file=sys.stderr)
    last = res.mean[-1]
    sd = res.std[-1]
    print(f"{args.video}: {res.info['method']} after {len(res.mean)} frames: "
          + ", ".join(f"{p} = {m:.4g} ± {s:.2g}" for p, m, s in zip(PARAMS, last, sd))
          + f"; geometry {res.info['geometry']['mapping']}; wrote {out}/")
    return 0


def number(text: str):
    """argparse's type of the scale and placement options: a float that keeps how it was
    written (:class:`sysid_bench.core.footage.Given`), so its rounding reaches the intervals."""
    from sysid_bench.core.footage import Given

    return Given(text)


def _takes_knowledge(method: str) -> bool:
    """Whether ``method`` holds ``known``/``prior`` on the ball (it takes both
    hyperparameters: lsq, bo, emcee, nuts and prior do)."""
    import methods

    return {"known", "prior"} <= set(methods.get_class(method, "ball")._param_names())


def _knowledge_refused(method: str) -> str:
    """Why ``method`` holds no known values or prior ranges on the ball (its declared reason);
    empty for a method that holds them (:func:`_takes_knowledge`)."""
    import methods

    if _takes_knowledge(method):
        return ""
    return getattr(methods.get_class(method, "ball"), "knowledge_refused",
                   "it does not take known values or prior ranges")
