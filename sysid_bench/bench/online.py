"""Online cost: a posterior after every frame of a video, method by method.

The paper's speed claim is about online use: a robot wants the parameters after each new frame.
A method with an online stream (declared ``online``: Vid2Param) pays a constant cost per frame;
a batch method (lsq, sindy) must re-identify on every prefix of the video seen so far, from its
``min_frames`` on, and pays for all of them. This module measures both on the same videos, in
one process, methods interleaved video by video so that the machine's load falls on all of them
alike: compare the ratios, not the absolute seconds. The default rows are the methods that
declare ``online_cost``.

Every method sees video only: frame methods their frames, position methods
``Observation(frames=...)`` (they track the ball themselves, as in the report's ``video``
input), floor height given.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from sysid_bench._validate import check_positive_int

__all__ = ["online_cost", "online_cost_markdown", "online_methods"]


def online_methods() -> list[str]:
    """The default rows: registered methods that declare ``online_cost``, in registry order
    (reads every method's declarations; a method whose packages are missing is left out)."""
    import methods

    out = []
    for m in methods.available():
        try:
            if methods.spec(m).online_cost:
                out.append(m)
        except ImportError:
            continue
    return out


def _clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def _run_stream(est, frames: np.ndarray, draw_samples: bool) -> int:
    """Push every frame through one stream; returns the number of posteriors."""
    stream = est.stream()
    for f in frames:
        post = stream.push(f)
        if draw_samples:
            post.samples  # noqa: B018 -- materialise the lazily drawn samples
    return len(frames)


def _timed_prefixes(first: int, T: int, stride: int) -> list[int]:
    """The prefix lengths timed: every ``stride``-th from ``first``, and always ``T``."""
    out = list(range(first, T + 1, stride))
    if out[-1] != T:
        out.append(T)
    return out


def _run_batch(est, obs, first: int, stride: int = 1) -> tuple[int, float, float]:
    """Re-identify on every prefix ``first .. T``; returns ``(posteriors, wall_s, cpu_s)``.

    With ``stride`` > 1 only every ``stride``-th prefix (and the last) is identified and timed;
    the totals are the per-prefix times interpolated linearly in the prefix length and summed
    over every prefix (a prefix's cost grows smoothly with its length: the simulations it fits
    are that long), so the figure estimates what the full loop costs at a ``stride``-th of it.
    """
    from sysid_bench.estimator import Observation

    T = len(obs.frames)
    lengths = _timed_prefixes(first, T, stride)
    walls, cpus = [], []
    for n in lengths:
        w0, c0 = _clock()
        est.identify(Observation(frames=obs.frames[:n], dt=obs.dt, floor=obs.floor))
        w1, c1 = _clock()
        walls.append(w1 - w0)
        cpus.append(c1 - c0)
    every = np.arange(first, T + 1)
    return (T - first + 1, float(np.interp(every, lengths, walls).sum()),
            float(np.interp(every, lengths, cpus).sum()))


def online_cost(methods=None, n_videos: int = 3, seed: int = 0, *,
                n_frames: int = 200, samples: bool = True, progress: bool = False,
                options: dict | None = None, prefix_stride: int = 1) -> pd.DataFrame:
    """Cost of a posterior after every frame of ``n_videos`` test videos, per method.

    Parameters
    ----------
    methods : sequence of str, optional
        Registered method names (default :func:`online_methods`). A method that declares
        ``online`` runs its stream (one ``push`` per frame); every other method re-runs
        ``identify`` on each prefix from its ``min_frames`` on. A method that identifies no
        parameters (``NotImplementedError``, e.g. DMD) gets a row marked ``n/a``.
    n_videos : int
        Test videos (``make_dataset("test", n_videos, seed, n_frames=n_frames)``).
    seed : int
        Seed of the videos.
    n_frames : int
        Frames per video T.
    samples : bool
        Also time each online stream with every posterior's samples drawn (``<name>+samples``):
        a posterior may draw its samples only when read (Vid2Param's do).
    progress : bool
        Show a tqdm bar over videos.
    options : dict, optional
        ``{method: {option: value}}`` passed to ``methods.get``.
    prefix_stride : int >= 1
        Every-prefix methods identify every ``prefix_stride``-th prefix (and the last) and the
        total is interpolated over every prefix (:func:`_run_batch`); 1 times them all.

    Returns
    -------
    pandas.DataFrame
        One row per method: ``method``, ``mode`` (``stream`` or ``every prefix``),
        ``first_frame`` (the first frame with a posterior), ``posteriors`` (per video),
        ``total_s`` and ``cpu_s`` (median over videos of the wall-clock and process CPU seconds
        for the whole video), ``per_frame_s`` (``total_s / n_frames``), ``ratio`` and
        ``ratio_cpu`` (``total_s`` and ``cpu_s`` over the first online stream's, whose name
        is ``df.attrs["baseline"]``; NaN without one), ``status`` (``ok`` or ``n/a: <why>``).
    """
    import methods as registry
    from sysid_bench.datasets import make_dataset

    names = online_methods() if methods is None else list(methods)
    if not names:
        raise ValueError("methods: expected at least one method name, got none")
    known = registry.available(include_reference=True)
    bad = [m for m in names if m not in known]
    if bad:
        raise ValueError(f"methods: expected names from {known}, got {bad}")
    n_videos = check_positive_int(n_videos, "n_videos")
    n_frames = check_positive_int(n_frames, "n_frames")
    prefix_stride = check_positive_int(prefix_stride, "prefix_stride")
    options = options or {}
    data = make_dataset("test", n_videos, int(seed), n_frames=n_frames)

    runs: list[tuple[str, str, int]] = []  # (row label, method, first frame)
    ests = {}
    online = {m for m in names if registry.spec(m).online}
    for m in names:
        est = registry.get(m, **options.get(m, {}))
        ests[m] = est
        if m in online:
            runs.append((m, m, 1))
            if samples:
                runs.append((f"{m}+samples", m, 1))
        else:
            runs.append((m, m, max(1, int(getattr(est, "min_frames", 1)))))
    # one-time costs (loading the checkpoint, compiling the simulator) are not online costs:
    # each method identifies a short prefix once before the clock starts
    warm = data.observation(0)
    for _label, m, first in runs:
        try:
            if m in online:
                _run_stream(ests[m], warm.frames[:5], True)
            else:
                _run_batch(ests[m], type(warm)(frames=warm.frames[:first + 2], dt=warm.dt,
                                               floor=warm.floor), first + 2, 1)
        except NotImplementedError:
            pass
    wall = {r[0]: [] for r in runs}
    cpu = {r[0]: [] for r in runs}
    count = {}
    status = {r[0]: "ok" for r in runs}
    for i in tqdm(range(n_videos), desc="online cost", disable=not progress):
        obs = data.observation(i)
        for label, m, first in runs:
            if status[label] != "ok":
                continue
            w0, c0 = _clock()
            try:
                if m in online:
                    count[label] = _run_stream(ests[m], obs.frames, label.endswith("+samples"))
                    w1, c1 = _clock()
                    dw, dc = w1 - w0, c1 - c0
                else:
                    count[label], dw, dc = _run_batch(ests[m], obs, first, prefix_stride)
            except NotImplementedError as exc:
                status[label] = f"n/a: {exc}"
                continue
            wall[label].append(dw)
            cpu[label].append(dc)

    rows = []
    for label, m, first in runs:
        ok = status[label] == "ok"
        total = float(np.median(wall[label])) if ok else np.nan
        rows.append({
            "method": label,
            "mode": "stream" if m in online else "every prefix",
            "first_frame": first,
            "posteriors": count.get(label, 0) if ok else 0,
            "total_s": total,
            "cpu_s": float(np.median(cpu[label])) if ok else np.nan,
            "per_frame_s": total / n_frames,
            "status": status[label],
        })
    df = pd.DataFrame(rows)
    # the ratios are over the first online stream (without samples drawn)
    baseline = next((m for m in names if m in online), None)
    base = df.loc[df["method"] == baseline]
    ref_w = float(base["total_s"].iloc[0]) if len(base) else np.nan
    ref_c = float(base["cpu_s"].iloc[0]) if len(base) else np.nan
    df["ratio"] = df["total_s"] / ref_w
    df["ratio_cpu"] = df["cpu_s"] / ref_c
    df.attrs.update({"n_videos": n_videos, "seed": int(seed), "n_frames": n_frames,
                     "baseline": baseline, "prefix_stride": prefix_stride})
    return df


def online_cost_markdown(df: pd.DataFrame) -> str:
    """The ``online_cost`` table as Markdown, with a sentence saying what it measures."""
    T = df.attrs.get("n_frames", "T")
    n = df.attrs.get("n_videos", "?")
    base = df.attrs.get("baseline") or "stream"
    stride = int(df.attrs.get("prefix_stride", 1))
    lines = [
        f"A posterior after every frame of a {T}-frame video (median of {n} test videos, one "
        "process, methods interleaved video by video). `stream`: one push per frame; `every "
        "prefix`: identify re-run on frames 1..t for every t from the method's first frame. "
        f"`x {base}`: total time over {base}'s stream, measured in the same run."
        + (f" Every-prefix totals are estimated from one prefix in {stride} (and the last), "
           "timed, their times interpolated linearly in the prefix length and summed over every "
           "prefix." if stride > 1 else ""),
        "",
        f"| method | mode | first frame | posteriors | total s | per frame ms | x {base} |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in df.itertuples():
        if r.status != "ok":
            lines.append(f"| {r.method} | {r.mode} | {r.first_frame} | - | n/a | n/a | "
                         f"{r.status.removeprefix('n/a: ')} |")
            continue
        lines.append(f"| {r.method} | {r.mode} | {r.first_frame} | {r.posteriors} | "
                     f"{r.total_s:.3g} | {r.per_frame_s * 1e3:.3g} | {r.ratio:.3g} |")
    return "\n".join(lines) + "\n"
