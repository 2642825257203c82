"""``sysid-bench identify VIDEO --system S`` for a system other than the ball.

The clip is read as the ball's (:func:`sysid_bench.core.footage.read_video`: any FFmpeg format, grey,
resampled to 20 frames/s), then taken to be framed as the system's own renderer draws it (its
``extent`` fills the frame) and resized to the system's default size. Position methods get the
system's tracker's points, frame methods the frames. Estimates every ``every`` frames go to
``estimates.csv`` (a row per frame: ``frame, t_s, <p>_mean, <p>_std`` for each of the system's
parameters, the model check, the tracked points), ``estimates.json`` and ``track.png``, all or
nothing.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from sysid_bench.core._io import atomic_folder

__all__ = ["identify_system_video", "write_system_outputs", "resize_frames"]


def resize_frames(frames: np.ndarray, size) -> np.ndarray:
    """Grey frames (T, h, w) uint8 to (T, H, W) by area averaging (PIL's BOX filter)."""
    from PIL import Image

    h, w = size
    if frames.shape[1:] == (h, w):
        return frames
    return np.stack([np.asarray(Image.fromarray(f).resize((w, h), Image.BOX)) for f in frames])


def _first_method(system: str, *, frames: bool) -> str:
    """The first registered contender that runs on ``system`` and identifies: with ``frames``,
    frame methods first (a learned model shipped for the system), then the position methods;
    without, position methods only (a camera's track)."""
    import methods

    names = methods.available()
    ordered = [n for n in names if methods.spec(n).input_kind != "frames"]
    if frames:
        ordered = [n for n in names if methods.spec(n).input_kind == "frames"] + ordered
    for n in ordered:
        if not methods.spec(n).identifies:
            continue
        try:
            methods.get(n, system=system).fit(None)
        except (NotImplementedError, ValueError, ImportError):
            continue
        return n
    kind = "" if frames else "position "
    raise ValueError(f"system: no registered {kind}method identifies the {system} system")


def _default_method(system: str) -> str:
    """:func:`_first_method`, frame methods first."""
    return _first_method(system, frames=True)


def _position_method(system: str) -> str:
    """:func:`_first_method` among the position methods."""
    return _first_method(system, frames=False)


#: The methods ``identify`` uses on a camera's clip when none is named, the first that runs on
#: the system: an ensemble-MCMC posterior in seconds (section 9's lowest error with calibrated
#: intervals on every system), then maximum likelihood. Registry order would give ``nuts``, the
#: reference posterior, which costs minutes per estimate (180 s against emcee's 13 s for one
#: pendulum clip of 6 s), and frame models read only the renderer's view.
CAMERA_DEFAULTS = ("emcee", "lsq")


def camera_method(system: str) -> str:
    """The method ``identify`` uses on a camera's clip of ``system`` when none is named: the
    first of :data:`CAMERA_DEFAULTS` that is registered, installed and identifies ``system``,
    else the first registered position method that does (:func:`_position_method`)."""
    import methods

    for n in CAMERA_DEFAULTS:
        if n not in methods.available():
            continue
        try:
            if methods.spec(n).identifies:
                methods.get(n, system=system).fit(None)
                return n
        except (NotImplementedError, ValueError, ImportError):
            continue
    return _position_method(system)


def _clip_shape(path, rotate: int) -> tuple[int, int] | None:
    """``(H, W)`` of the clip's frames once turned upright, from its stream (None: unreadable;
    :func:`~sysid_bench.core.footage.read_video` then says why)."""
    try:
        import av

        with av.open(str(path)) as c:
            st = c.streams.video[0]
            h, w = int(st.height), int(st.width)
    except Exception:  # noqa: BLE001 - any failure: read_video names it properly
        return None
    return (w, h) if int(rotate) in (90, 270) else (h, w)


def _renderer_framed(sys_, shape) -> bool:
    """Whether a frame of ``shape`` ``(H, W)`` can be the system's render (its aspect)."""
    h, w = int(shape[0]), int(shape[1])
    rh, rw = (int(v) for v in sys_.size)
    return abs(w / h - rw / rh) <= 0.02 * (rw / rh)


def _check_renderer_framing(sys_, shape, path) -> None:
    """Refuse, with the options that would read it, a clip that cannot be the system's render.

    Without a camera a clip is read as the system's renderer frames it (its view, any size);
    a frame of another shape (a phone's 1080x1920, a lab camera's 640x352) is a camera's, and
    read as a render it would be followed nowhere ("seen in 0 frames")."""
    h, w = int(shape[0]), int(shape[1])
    rh, rw = (int(v) for v in sys_.size)
    if _renderer_framed(sys_, shape):
        return
    how = "--px-per-m or --object-size-m"
    if "L" in sys_.params and "g" in sys_.params:  # a pendulum-like scale from L or g
        how += ", --known L=... or --known g=..."
    raise ValueError(f"px_per_m: the clip is {w}x{h}, not the {sys_.name} renderer's {rw}x{rh} "
                     f"view, so it is a camera's and its scale is not known: give {how}")


def identify_system_video(path, system: str, *, method: str | None = None,
                          every: int | None = None,
                          progress=None, camera: dict | None = None, rotate: int = 0,
                          start: float | None = None, end: float | None = None,
                          capture_fps: float | None = None, known: dict | None = None,
                          prior: dict | None = None, object_box=None) -> dict:
    """Identify the parameters of ``system`` from a video file.

    Parameters
    ----------
    path : str or Path
    system : str
    method : str, optional
        Default: the first identifying contender (frame methods first); with a camera,
        :func:`camera_method`.
    every : int, optional
        Frames between estimates; default: half a second of capture (10 frames at 20 frames/s,
        30 at 60).
    progress : bool, optional
    camera : dict, optional
        A real camera (:func:`sysid_bench.core.footage.camera_for`'s ``px_per_m``,
        ``object_size_m``, ``pivot``, ``anchor``): the object is followed at the file's
        resolution (:func:`~sysid_bench.core.footage.find_object`) and its track mapped to the
        system's world (the pendulum relative to its pivot, y up; the spring from its anchor).
        None: the clip is framed as the system's renderer draws it.
    rotate : {0, 90, 180, 270}
    start, end, capture_fps : float, optional
        :func:`~sysid_bench.core.footage.read_video`'s window and capture rate.
    known, prior : dict, optional
        What the user knows; the pendulum's ``L`` fixes the scale from the bob's arc.
        Recorded under ``knowledge``.
    object_box : (float, float, float, float), optional
        The object's ``(col, row, width, height)`` px in the first kept frame (upright), on a
        camera's clip: the object is followed by its appearance
        (:func:`~sysid_bench.core.footage.follow_object_box`) instead of by the background;
        ``track.png`` shows the box over that frame.

    Returns
    -------
    dict
        ``mean``, ``std`` (T, P) with NaN rows between estimates, ``check`` (T, 3) (ok, RMS m,
        noise m), ``points`` (T, K, 2) tracked, ``info`` (what ``estimates.json`` records).
    """
    import methods
    from sysid_bench.core import systems
    from sysid_bench.core.estimator import Observation, frame_cap_of, frame_rate_of
    from sysid_bench.core.footage import (
        PERIOD_SCALED,
        knowledge_record,
        loosen_held,
        observe_clip,
        read_video,
        report_held,
        rotate_frames,
        thin_clip,
        widen_for_placement,
        widen_for_scale,
    )

    sys_ = systems.get(system)
    if camera is not None and method is not None and methods.spec(method).input_kind == "frames":
        raise ValueError(f"method: {method} reads frames drawn as the {sys_.name}'s renderer "
                         "draws them; on a camera's clip give a position method (e.g. lsq)")
    cam = None
    followed = None
    if camera is None and "g" in (known or {}) and sys_.name in PERIOD_SCALED:
        shape = _clip_shape(path, rotate)
        if shape is not None and not _renderer_framed(sys_, shape):
            # a camera's clip with nothing but g known: its period gives the scale
            camera = {"px_per_m": None, "object_size_m": None, "pivot": None}
    # the method first: its frame rate decides the clip's time base (None: the capture's own dt)
    name = method or (_default_method(sys_.name) if camera is None
                      else camera_method(sys_.name))
    klass = methods.get_class(name, system=sys_.name)
    rate, cap = frame_rate_of(klass), frame_cap_of(klass)
    if camera is None and object_box is not None:
        raise ValueError("object_box: a box is followed on a camera's clip, and this one's scale "
                         "is not known: give --px-per-m or --object-size-m")
    if camera is None:
        clip = read_video(path, rate, progress=progress, start=start, end=end,
                          capture_fps=capture_fps)
        resampled = len(clip.frames) != clip.source_frames or abs(clip.fps - clip.source_fps) > 1e-9
        clip = thin_clip(clip, cap, name)  # a method whose cost grows with the observations
        notes = list(clip.notes)
        model_fps, source_fps = clip.fps, clip.source_fps
        turned = rotate_frames(clip.frames, int(rotate))
        _check_renderer_framing(sys_, turned.shape[1:], path)
        frames = resize_frames(turned, sys_.size)
        obs = Observation(frames=frames, system=sys_.name, dt=1.0 / clip.fps)
        points = sys_.track(frames)
    else:  # the core's camera pipeline, as the benchmark's camera section runs it
        cc = observe_clip(path, sys_.name, progress=progress, fps=rate, max_frames=cap,
                          rotate=int(rotate), start=start, end=end, capture_fps=capture_fps,
                          known=known, prior=prior, object_box=object_box, **camera)
        cam, obs, followed = cc.camera, cc.observation, cc.followed
        points = obs.points
        notes = [*cc.notes[:-1], f"{name} saw {cc.notes[-1]}"]
        model_fps, source_fps = 1.0 / obs.dt, cc.source_fps
        resampled = any(n.startswith(("resampled", "variable")) for n in cc.notes)
    if rate is not None and resampled:
        notes.append(f"{name} is built for {rate:g} frames/s, so the clip was resampled to it "
                     "(a method that simulates at any step, e.g. lsq, reads every frame at the "
                     "capture's own dt)")
    # a method that takes the user's knowledge holds it (issue 38 §4); the others say they did not
    takes = {"known", "prior"} <= set(methods.get(name, system=sys_.name).get_params())
    loose: dict = {}
    give = {"known": dict(known or {}), "prior": dict(prior or {})} if takes else {}
    if takes and cam is not None and known:
        # a held length read through an uncertain scale: searched within the scale's spread
        # of the user's value, so its error does not land in the other parameters
        k2, p2, loose = loosen_held(sys_, known, prior or {}, cam.scale_rel_std, cam.source)
        give = {"known": k2, "prior": p2}
    est = methods.get(name, system=sys_.name, **give)
    est.fit(None)
    t = obs.n_frames
    if every is None:  # an estimate every half second of capture (10 frames at 20 frames/s)
        every = max(1, int(round(0.5 / float(obs.dt))))
    lengths = sorted({*range(every, t + 1, every), t})
    lengths = [n for n in lengths if n >= max(3, getattr(est.spec(), "min_frames", 3))]
    if not lengths:
        raise ValueError(f"video: expected at least 3 frames at {model_fps:.4g} frames/s, "
                         f"got {t}")
    if methods.spec(name).input_kind != "frames":
        # a position method needs the object seen in 3 frames of a prefix: the first
        # half-second may hold it in 1 (a fast 20 cm pull lost in its blur), which refused the
        # whole clip; its estimates start at the first prefix that has them
        seen = np.cumsum(np.isfinite(points).all(axis=(1, 2)))
        ready = [n for n in lengths if seen[n - 1] >= 3]
        if not ready:
            raise ValueError(f"positions: expected the {sys_.name} system's points seen in at "
                             f"least 3 frames, got {int(seen[-1])} of {t}")
        if len(ready) < len(lengths):
            notes.append(f"{name}'s first estimate is after frame {ready[0]}: the object was "
                         f"seen in fewer than 3 frames before it")
        lengths = ready
    posts = est.identify_prefixes(obs, lengths)
    p = sys_.n_params
    mean, std = np.full((t, p), np.nan), np.full((t, p), np.nan)
    check = np.full((t, 3), np.nan)
    for n, post in zip(lengths, posts):
        mean[n - 1], std[n - 1] = post.mean, post.std
        if post.check is not None:
            check[n - 1] = (float(post.check.ok), post.check.rms_m, post.check.noise_m)
    if cam is not None and cam.scale_rel_std > 0:
        std = widen_for_scale(sys_.name, sys_.params, mean, std, cam.scale_rel_std)
        notes.append(f"the scale's {100 * cam.scale_rel_std:.2g}% uncertainty is added to the "
                     "std of every parameter with a length in its unit")
    if cam is not None and cam.param_std:
        std = widen_for_placement(sys_.params, std, cam.param_std)
        notes.append("the rounding of the placement given is added to the std of "
                     + ", ".join(f"{k} (± {v:.2g})" for k, v in cam.param_std.items()))
    if cam is not None and takes and known and (cam.scale_rel_std > 0 or cam.param_std):
        # a held value is the user's, not measured through the camera
        cols = [sys_.params.index(k) for k in known]
        std[:, cols] = np.where(np.isnan(mean[:, cols]), np.nan, 0.0)
    if loose:  # searched within the scale's spread while fitting: reported as held
        notes.append(report_held(sys_.params, mean, known, loose, cam.scale_rel_std))
    notes += bound_notes(mean, known if takes else None, prior if takes else None, 0.01,
                         system=sys_, check=check)
    know = knowledge_record(known or {}, prior or {}, name, held=takes,
                            why=getattr(type(est), "knowledge_refused", ""))
    if know["note"]:
        notes.append(f"--known/--prior {know['note']}")
    elif known or prior:
        said = [f"{k} = {v:g} held" for k, v in (known or {}).items()]
        said += [f"{k} searched in {a:g} to {b:g}" for k, (a, b) in (prior or {}).items()]
        notes.append(f"--known/--prior: {name} used them ({'; '.join(said)})")
    info = {"file": str(path), "system": sys_.name, "method": name, "params": list(sys_.params),
            "model_fps": model_fps, "frames": t, "source_fps": source_fps,
            "dt_s": float(obs.dt), "method_frame_rate": rate, "resampled": bool(resampled),
            "size": list(sys_.size), "extent": list(sys_.extent), "notes": notes,
            "points_seen": int(np.isfinite(points).all(axis=(1, 2)).sum()),
            "input": "tracked positions (camera)" if cam is not None else
            ("frames (renderer framing)" if methods.spec(name).input_kind == "frames"
             else "tracked positions (renderer framing)"),
            "camera": None if cam is None else cam.as_dict(), "rotate": int(rotate),
            "scene": _scene_record(obs.scene),
            "window_s": [start, end], "capture_fps": capture_fps, "knowledge": know}
    out = {"mean": mean, "std": std, "check": check, "points": points, "info": info}
    if followed is not None:  # recorded only where given: other runs' files stay as they were
        info["object_box"] = [int(v) for v in followed["box"]]
        info["tracker"] = "appearance (ZNCC template from --object-box)"
        out["followed"] = followed
    return out


def bound_notes(mean, known: dict | None = None, prior: dict | None = None,
                tol: float = 0.005, *, system=None, check=None) -> list[str]:
    """Notes for the last estimate's parameters that sit on their search range's bound.

    A fit that ends on a bound (``g`` at -12.81 on a clip whose scale or time base is wrong,
    a 0.26 m pendulum against the prior's 0.5 m) is not a measurement: the track asked for a
    value beyond the range, whatever its interval says. Held (``known``) parameters are the
    user's and are not flagged. Where the physics allows a wider range, the note names the
    ``--prior`` that asks for it.

    Parameters
    ----------
    mean : ndarray, shape (T, P)
        Estimates frame by frame (NaN where none), the system's parameter order.
    known : dict, optional
        Held parameters.
    prior : dict, optional
        ``name -> (low, high)`` search ranges given by the user; the rest are the system's.
    tol : float
        Within this fraction of the range's width of a bound counts as on it.
    system : System, optional
        Default the ball.
    check : ndarray, shape (T, 3), optional
        (ok, RMS m, noise m) per estimate: given, a bound is flagged only where the last
        estimate's fit fails and a wider range is possible (the other systems' rule).

    Returns
    -------
    list of str
    """
    from sysid_bench.core import systems

    sys_ = systems.get("ball") if system is None else system
    m = np.asarray(mean, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != sys_.n_params:
        raise ValueError(f"mean: expected a (T, {sys_.n_params}) array, got shape {m.shape}")
    rows = np.flatnonzero(np.isfinite(m).all(axis=1))
    if rows.size == 0:
        return []
    if check is not None and not (np.isfinite(check[rows[-1], 0]) and check[rows[-1], 0] < 0.5):
        return []
    last = m[rows[-1]]
    out = []
    for i, name in enumerate(sys_.params):
        if name in (known or {}):
            continue
        lo, hi = (prior or {}).get(name, (float(sys_.prior_lo[i]), float(sys_.prior_hi[i])))
        elo, ehi = sys_.envelope[name]
        for b, side in ((lo, "lower"), (hi, "upper")):
            if side == "lower" and name in ("d", "r"):
                continue  # no drag, no spin: a physical answer at the range's edge, not a miss
            if abs(last[i] - b) > tol * (hi - lo):
                continue
            wider = (f"{elo:g}:{hi:g}" if b > elo else None) if side == "lower" else (
                f"{lo:g}:{ehi:g}" if b < ehi else None)
            if check is not None and wider is None:
                continue  # the physics' own limit: nothing beyond it to ask for
            note = (f"{name} = {last[i]:.4g} sits on its range's {side} bound {b:g}: "
                    "not measured by the clip (the track asks for a value beyond it; "
                    "a wrong scale or time base can do this)")
            if wider is not None:
                note += (f"; widen it with --prior {name}={wider} (the physics allows "
                         f"{elo:g} to {ehi:g})")
            out.append(note)
    return out


def _scene_record(scene) -> dict | None:
    """The observation's scene as JSON values (None: the system's default)."""
    if scene is None:
        return None
    from dataclasses import asdict

    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(scene).items()}


def _finite(x):
    """JSON without NaN: NaN and inf become null; arrays become lists."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _plot(res: dict, path: Path, dt: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    params = res["info"]["params"]
    t = np.arange(len(res["mean"])) * dt
    followed = res.get("followed")
    n_ax = len(params) + 1 + (followed is not None)
    fig, axes = plt.subplots(1, n_ax, figsize=(3.2 * n_ax, 3.2))
    if followed is not None:  # what was followed: the box over the first frame
        show_box(axes[-1], followed)
        axes = axes[:-1]
    pts = res["points"]
    for k in range(pts.shape[1]):
        axes[0].plot(pts[:, k, 0], pts[:, k, 1], ".", ms=3, label=f"point {k + 1}")
    axes[0].set(xlabel="x (m)", ylabel="y (m)", title="tracked")
    axes[0].legend(fontsize=7)
    z = 1.6449
    for ax, (k, p) in zip(axes[1:], enumerate(params)):
        m, s = res["mean"][:, k], res["std"][:, k]
        ok = np.isfinite(m)
        ax.errorbar(t[ok], m[ok], yerr=z * s[ok], fmt="o", ms=3, color="tab:red", lw=1)
        ax.set(xlabel="t (s)", title=f"{p} (mean, 90% interval)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def show_box(ax, followed: dict) -> None:
    """The first kept frame with the ``--object-box`` drawn over it (``track.png``).

    Parameters
    ----------
    ax : matplotlib Axes
    followed : dict
        ``box`` ``(col, row, width, height)`` px and ``frame`` (H, W) uint8
        (:attr:`~sysid_bench.core.footage.CameraClip.followed`).
    """
    from matplotlib.patches import Rectangle

    c, r, w, h = followed["box"]
    ax.imshow(followed["frame"], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    # continuous pixel coordinates: imshow puts pixel [i, j]'s centre at (j, i)
    ax.add_patch(Rectangle((c - 0.5, r - 0.5), w, h, fill=False, ec="tab:red", lw=1.2))
    ax.set(title=f"followed: box {w}x{h} px at ({c}, {r})", xticks=[], yticks=[])
    ax.title.set_fontsize(9)


def write_system_outputs(res: dict, out) -> Path:
    """``estimates.csv``, ``estimates.json`` and ``track.png`` into ``out``, all or nothing."""
    from sysid_bench.core.footage import OUT_MARKER, check_out_folder

    out = check_out_folder(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    dt = 1.0 / res["info"]["model_fps"]
    params = res["info"]["params"]
    rows = []
    for i in range(len(res["mean"])):
        r = {"frame": i, "t_s": round(i * dt, 6)}
        for k, p in enumerate(params):
            r[f"{p}_mean"], r[f"{p}_std"] = float(res["mean"][i, k]), float(res["std"][i, k])
        c = res["check"][i]
        r["check_ok"] = int(c[0]) if np.isfinite(c[0]) else None
        r["check_rms_m"], r["check_noise_m"] = float(c[1]), float(c[2])
        for k in range(res["points"].shape[1]):
            r[f"x{k + 1}_m"], r[f"y{k + 1}_m"] = (float(v) for v in res["points"][i, k])
        rows.append(r)

    def write(tmp: Path) -> None:
        with open(tmp / "estimates.csv", "w", newline="") as f:
            wr = csv.DictWriter(f, fieldnames=list(rows[0]))
            wr.writeheader()
            wr.writerows(rows)
        clean = [{k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                  for k, v in r.items()} for r in rows]
        with open(tmp / "estimates.json", "w") as f:
            json.dump({"written_by": OUT_MARKER, **_finite(res["info"]), "estimates": clean}, f,
                      indent=1)
        _plot(res, tmp / "track.png", dt)

    # files of an existing ``out`` this did not write are kept; the three are replaced together
    atomic_folder(out, write, keep_others=True)
    return out
