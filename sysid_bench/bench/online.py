"""Experiment 7, online cost: a posterior after every frame of a video, method by method.

The paper's speed claim is about online use: a robot wants the parameters after each new frame.
A method with an online stream (declared ``online``: Vid2Param) pays a constant cost per frame;
a batch method (lsq, sindy) must re-identify on every prefix of the video seen so far, from its
``min_frames`` on, and pays for all of them. This module measures both on the same videos, in
one process, methods interleaved video by video so that the machine's load falls on all of them
alike: compare the ratios, not the absolute seconds. The default rows are the methods that
declare ``online_cost``.

Every method sees video only: frame methods their frames, position methods
``Observation(frames=...)`` (they track the object themselves, as in the report's ``video``
input), the scene's geometry given.

Two entry points: :func:`online_cost`, one table measured in one process (the benchmark's
``test_bench_online``), and :class:`Online`, the report's experiment: one cell per system,
method and test case in the runner's pool, like every other experiment, its rows in the store.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from sysid_bench.bench.cases import system_case
from sysid_bench.bench.experiment import Cell, CellOutput, Context, Experiment, fmt_ci, median_ci
from sysid_bench.core._validate import check_positive_int

__all__ = ["online_cost", "online_cost_markdown", "online_methods", "Online"]


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
    T = len(obs.frames)
    lengths = _timed_prefixes(first, T, stride)
    walls, cpus = [], []
    for n in lengths:
        w0, c0 = _clock()
        est.identify(obs.prefix(n))
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
    from sysid_bench.core.datasets import make_dataset

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
                _run_batch(ests[m], warm.prefix(first + 2), first + 2, 1)
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


class Online(Experiment):
    """The online-cost experiment: a cell per (system, method, test case)."""

    name = "online"
    title = "7. Online cost: a posterior after every frame"
    description = (
        "Seconds for a posterior after every frame of a test video (the system's own render, "
        "video input), per method: `stream` is one push per frame of a method with an online "
        "stream (`stream+samples`: each posterior's samples drawn too); `every prefix` is "
        "identify re-run on frames 1..t for every t from the method's first frame, timed on one "
        "prefix in `stride` (and the last) and interpolated linearly in the prefix length. The "
        "methods are those that declare `online_cost`. Each cell warms its method up (loads its "
        "model, compiles its simulator) before the clock starts. Cells run in the pool beside "
        "other cells: the seconds carry the run's load; `x stream` (median over the system's "
        "cases of a method's total over the stream's) compares methods of one run."
    )

    def cells(self, scale, methods, system="ball"):
        import methods as registry

        out = []
        for m in methods:
            sp = registry.spec(m)
            if not sp.online_cost:
                continue
            conds = ("", "samples") if sp.online else ("",)
            n = scale.cases(self.name, m, system)
            out += [Cell(self.name, m, "video", c, i, system) for c in conds for i in range(n)]
        return out

    def run(self, cell: Cell, ctx: Context) -> CellOutput:
        sc = ctx.scale
        i = int(cell.case)
        frames, stride = sc.online
        obs, _, _ = system_case(cell.system, i, sc.n_for(self.name, cell.system), sc.seed,
                                "video")
        obs = obs.prefix(min(int(frames), obs.n_frames))
        est = ctx.estimator(cell.method, system=cell.system)
        out = CellOutput()
        T = obs.n_frames
        if est.spec().online:
            _run_stream(est, obs.frames[:5], True)  # warm: load, first allocations
            w0, c0 = _clock()
            n = _run_stream(est, obs.frames, cell.condition == "samples")
            w1, c1 = _clock()
            wall, cpu, first = w1 - w0, c1 - c0, 1
        else:
            first = _first_answer(est, obs, max(1, int(getattr(est, "min_frames", 1))))
            _run_batch(est, obs.prefix(min(first + 2, T)), min(first + 2, T), 1)  # warm
            n, wall, cpu = _run_batch(est, obs, first, int(stride))
        for metric, v in (("total_s", wall), ("cpu_s", cpu), ("per_frame_s", wall / T),
                          ("posteriors", n), ("first_frame", first), ("stride", stride)):
            out.add(i, T, metric, v)
        return out

    # -- report -----------------------------------------------------------------------------
    @staticmethod
    def _label(method: str, condition: str) -> str:
        return f"{method}+samples" if condition == "samples" else method

    def summary(self, df) -> pd.DataFrame:
        """Per method (and samples drawn or not): mode, first frame, posteriors, median total
        and per-frame seconds with 95% CIs over cases, and the ratio to the stream's total."""
        import methods as registry

        if df.empty:
            return pd.DataFrame()
        cond = df.condition.fillna("") if "condition" in df.columns else ""
        df = df.assign(condition=cond)
        streams = [m for m in df.method.unique() if _is_online(registry, m)]
        base = streams[0] if streams else None
        tot = df[df.metric == "total_s"]
        base_tot = (tot[(tot.method == base) & (tot.condition == "")].set_index("case").value
                    if base else None)
        recs = []
        for (m, c), g in df.groupby(["method", "condition"], sort=True):
            t = g[g.metric == "total_s"]
            med, lo, hi = median_ci(t, (self.name, m, c, "total"))
            pf = g[g.metric == "per_frame_s"].assign(value=lambda x: x.value * 1e3)
            pmed, plo, phi = median_ci(pf, (self.name, m, c, "per_frame"))
            ratio = np.nan
            if base_tot is not None and len(base_tot):
                r = t.set_index("case").value / base_tot
                r = r[np.isfinite(r)]
                ratio = float(np.median(r)) if len(r) else np.nan
            first = g[g.metric == "first_frame"].value
            post = g[g.metric == "posteriors"].value
            stride = g[g.metric == "stride"].value
            recs.append({
                "method": self._label(m, c),
                "mode": "stream" if _is_online(registry, m) else "every prefix",
                "first frame": int(first.iloc[0]) if len(first) else -1,
                "posteriors": int(post.iloc[0]) if len(post) else 0,
                "cases": int(t.case.nunique()),
                "total s": fmt_ci(med, lo, hi),
                "per frame ms": fmt_ci(pmed, plo, phi),
                "stride": "-" if _is_online(registry, m) or not len(stride)
                else int(stride.iloc[0]),
                "x stream": ratio,
                "_total": med,
            })
        t = pd.DataFrame(recs)
        return t.sort_values(["mode", "_total"], ascending=[False, True]).reset_index(drop=True)

    def tables(self, df):
        t = self.summary(df)
        if t.empty:
            return {}
        return {"online_cost": t.drop(columns="_total")}

    def reading(self, df):
        t = self.summary(df)
        if t.empty:
            return []
        streams = t[t["mode"] == "stream"]
        batch = t[(t["mode"] == "every prefix") & np.isfinite(t["x stream"])]
        if streams.empty or batch.empty:
            return []
        base = streams.iloc[0]
        cheapest = batch.sort_values("x stream").iloc[0]
        return [f"A posterior after every frame costs {base.method}'s stream "
                f"{base['per frame ms']} ms a frame; re-running the cheapest other method "
                f"({cheapest.method}) on every prefix costs {cheapest['x stream']:.3g}x as much "
                "(median over cases, measured in this run)."]


def _first_answer(est, obs, first: int) -> int:
    """The first prefix length from ``first`` on where ``est`` answers: a method's declared
    ``min_frames`` is the fewest it accepts anywhere, and a system may need more (sindy's
    smoothing window on the pendulum: 17 frames); a ``ValueError`` on a prefix means "too few
    frames here". Raises the last error when no prefix up to half the video answers."""
    last = None
    for n in range(first, max(first, obs.n_frames // 2) + 1):
        try:
            est.identify(obs.prefix(n))
            return n
        except ValueError as exc:
            last = exc
    raise last


def _is_online(registry, method: str) -> bool:
    try:
        return bool(registry.spec(method).online)
    except (ValueError, ImportError):
        return False
