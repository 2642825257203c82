"""What every experiment module provides, and the helpers they share.

An experiment turns a scale and a list of methods into **cells**; a cell is one method on one
input kind on one test case (or, for sensitivity, one training condition), and does all its
observed-frame counts in one go. Running a cell returns long-format :class:`~.store.Row` s and,
for figures, a few small arrays. Experiments also turn the stored rows back into tables,
figures and sentences of the report.
"""

from __future__ import annotations

import copy
import json
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sysid_bench.bench.cases import Scale, test_set
from sysid_bench.bench.store import Row
from sysid_bench.core.estimator import Estimator, Observation, Posterior
from sysid_bench.core.metrics import bootstrap_ci
from sysid_bench.core.physics import PRIOR_LO, PRIOR_SPAN

__all__ = [
    "EXPERIMENTS",
    "Cell",
    "CellOutput",
    "Context",
    "Experiment",
    "execute",
    "timed_prefixes",
    "streams",
    "paper_methods",
    "normalise",
    "ci_summary",
    "median_ci",
    "share_ci",
    "small_sample_widen",
    "fmt_ci",
    "LO",
    "SPAN",
]

LO = PRIOR_LO
SPAN = PRIOR_SPAN

#: name -> experiment, in report order. Filled by ``sysid_bench/bench/__init__.py`` (Python runs
#: a package's ``__init__`` before any of its modules, so every process that imports this module,
#: a worker unpickling :func:`execute` included, has it filled); kept here, below the experiment
#: modules, so that :func:`execute` finds an experiment without importing the package above it.
EXPERIMENTS: dict[str, Experiment] = {}


def normalise(theta: np.ndarray) -> np.ndarray:
    """Parameters (..., 4) mapped to [0, 1] by PRIOR."""
    return (np.asarray(theta, dtype=np.float64) - LO) / SPAN


@dataclass(frozen=True, order=True)
class Cell:
    """One unit of work; ``case`` is a test video index or a condition-wide label; ``system``
    the registered system whose cases the cell runs on (every experiment runs per system)."""

    experiment: str
    method: str
    input: str
    condition: str
    case: int | str
    system: str = "ball"

    @property
    def id(self) -> str:
        return (f"{self.system}/{self.experiment}|{self.method}|{self.input}|{self.condition}"
                f"|{self.case}")

    def key(self) -> dict:
        return {"system": self.system, "experiment": self.experiment, "method": self.method,
                "input": self.input, "condition": self.condition, "case": self.case}


@dataclass
class CellOutput:
    rows: list[Row] = field(default_factory=list)
    artifacts: dict[str, np.ndarray] = field(default_factory=dict)

    #: (n_frames, message) of parts of the cell that failed while the rest went on
    errors: list[tuple[int, str]] = field(default_factory=list)

    def add(self, case: int, n_frames: int, metric: str, value) -> None:
        self.rows.append(Row(int(case), int(n_frames), metric, float(value)))

    def fail(self, n_frames: int, exc: BaseException, case: int | None = None) -> None:
        """Record that the part of the cell at ``n_frames`` failed (a ``failed`` row = 1)."""
        self.errors.append((int(n_frames), _describe(exc)))
        if case is not None:
            self.add(case, n_frames, "failed", 1.0)


def _describe(exc: BaseException) -> str:
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"[:2000]


_PROTOTYPES: dict[tuple[str, str, bool], Estimator] = {}


class Context:
    """What a running cell may use: its scale, the run directory, estimators and test sets."""

    def __init__(self, scale: Scale, run_dir, threads: int = 1):
        self.scale = scale
        self.run_dir = Path(run_dir)
        self.threads = threads

    def estimator(self, method: str, warm: bool = True, share_fits: bool = False,
                  **extra) -> Estimator:
        """A fresh copy of ``method`` with the scale's options (loaded once per process).

        A copy per cell keeps results independent of which cells a worker ran before (any
        state a method keeps between calls stays in the copy), so a local pool and a Dask
        cluster give the same numbers. ``warm`` loads a learned method's shipped weights
        (``fit(None)``) up front; methods about to be trained from scratch skip that.
        ``share_fits``: a method that declares ``pure_fit`` reads the fits another cell of
        the run already computed on the same observation and stores its own
        (:mod:`sysid_bench.bench.fitcache`) after the frame counts forecasting and
        calibration ask for (the others no second cell reads).
        """
        import methods

        opts = {**self.scale.method_options(method, self.threads), **extra}
        key = (method, json.dumps(opts, sort_keys=True, default=str), warm)
        proto = _PROTOTYPES.get(key)
        if proto is None:
            proto = methods.get(method, **opts)
            if warm and proto.spec().trains:
                proto.fit(None)  # loads the shipped checkpoint once per process
            _PROTOTYPES[key] = proto
        est = copy.deepcopy(proto)
        if share_fits:
            from sysid_bench.bench.fitcache import share_fits as share

            sc = self.scale
            share(est, method, json.loads(key[1]), self.run_dir,
                  lengths=set(sc.forecast_after) | set(sc.calibration_lengths))
        return est

    def test_set(self, variant: str, n: int, **options):
        return test_set(variant, n, self.scale.seed, **options)


class Experiment:
    """Base class of the experiments (one module each).

    An experiment runs on each registered system it declares in :attr:`systems` (``"any"``:
    every registered system, a user's too); the runner asks it for the cells of one system at
    a time (:meth:`cells`), and every cell names its system (``Cell.system``).
    """

    name: str = ""
    title: str = ""
    #: what the report says the experiment measures, one paragraph
    description: str = ""
    #: the systems it runs on: "any", or a tuple of registered names (the ball's own tasks)
    systems: str | tuple[str, ...] = "any"
    #: True for an experiment whose report compares the systems (it gets every system's rows
    #: at once, at the top of the report); others are reported system by system
    cross_system: bool = False
    #: modules besides the experiment's own whose code decides its rows (their source is part
    #: of the cells' fingerprint, so a change there computes the cells again)
    depends_on: tuple[str, ...] = ()

    def runs_on(self, system: str) -> bool:
        """Whether this experiment has cells on ``system``."""
        return self.systems == "any" or system in self.systems

    def cells(self, scale: Scale, methods: list[str], system: str = "ball") -> list[Cell]:
        """The cells of ``system`` (every one with ``Cell.system == system``)."""
        raise NotImplementedError

    def run(self, cell: Cell, ctx: Context) -> CellOutput:
        raise NotImplementedError

    # -- report ---------------------------------------------------------------------------
    def tables(self, df) -> dict:
        """Named pandas DataFrames from this experiment's rows (``status == "ok"``)."""
        return {}

    def figures(self, df, store, outdir: Path) -> dict[str, Path]:
        """Write PNG figures into ``outdir``; returns caption -> path."""
        return {}

    def reading(self, df) -> list[str]:
        """Sentences comparing the results with the paper, with numbers."""
        return []


def execute(cell: Cell, scale: Scale, run_dir: str, threads: int = 1) -> dict:
    """Run one cell, catching everything: the worker-side entry point of the runner.

    Returns
    -------
    dict
        ``cell`` (Cell), ``status`` ("ok", "error", "n/a"), ``error`` (str or None),
        ``wall_s``, ``rows`` (list of Row), ``artifacts`` (dict).
    """
    t0 = time.perf_counter()
    status, error, out = "ok", None, CellOutput()
    try:
        out = EXPERIMENTS[cell.experiment].run(cell, Context(scale, run_dir, threads))
    except NotImplementedError as exc:
        status, error = "n/a", str(exc) or f"{cell.method} does not implement this"
    except Exception as exc:  # a method failing on a case is a result, not a crash of the run
        status, error = "error", _describe(exc)
    if status == "ok" and out.errors:
        msgs = "; ".join(f"{n} frames: {m}" for n, m in out.errors)
        if all(r.metric == "failed" for r in out.rows):  # nothing worked: the cell failed
            status = "error"
        error = msgs[:4000]
    return {"cell": cell, "status": status, "error": error, "wall_s": time.perf_counter() - t0,
            "rows": out.rows if status == "ok" else [], "artifacts": out.artifacts if status == "ok" else {}}


def paper_methods(names) -> list[str]:
    """The methods among ``names`` that the paper's claims are about (they declare
    ``from_paper``),
    in registry order: the readings compare them with the baselines. A method that cannot be
    imported here counts as a baseline."""
    import methods

    names = set(names)
    out = []
    for m in methods.available(include_reference=True):
        if m not in names:
            continue
        try:
            if methods.spec(m).from_paper:
                out.append(m)
        except ImportError:
            continue
    return out


def streams(est: Estimator) -> bool:
    """True when ``est`` declares ``streams`` (its ``identify_prefixes`` is one pass)."""
    return est.spec().streams


def timed_prefixes(est: Estimator, obs: Observation, lengths, out: CellOutput | None = None,
                   case: int | None = None) -> list[tuple[int, Posterior, float]]:
    """Posteriors after each of ``lengths`` frames, with the seconds each identification took.

    Methods with their own ``identify_prefixes`` (streaming) do one pass; the time of a prefix
    is then what the method reports in ``extras["wall_s"]`` (else the pass pro rata). Other
    methods are timed call by call around ``identify``; a prefix on which such a method fails
    (too short for it, say) is skipped and noted in ``out`` instead of failing the whole cell.

    Returns
    -------
    list of (n_frames, Posterior, seconds)
    """
    from sysid_bench.bench.fitcache import clock

    lengths = [int(n) for n in lengths]
    if streams(est):
        t0 = time.perf_counter()
        posts = est.identify_prefixes(obs, lengths)
        total = time.perf_counter() - t0
        res = []
        for n, p in zip(lengths, posts):
            w = p.extras.get("wall_s")
            res.append((n, p, float(w) if w is not None else total * n / max(lengths)))
        return res
    res = []
    for n in lengths:
        t0 = clock()  # a fit another cell computed counts its own seconds (fitcache)
        try:
            p = est.identify(obs.prefix(n))
        except NotImplementedError:
            raise
        except Exception as exc:
            if out is None:
                raise
            out.fail(n, exc, case)
            continue
        res.append((n, p, clock() - t0))
    return res


# -- report helpers ---------------------------------------------------------------------------
def _group_seed(seed: int, value: str, by, keys) -> int:
    """A bootstrap seed from a table group's identity (its columns and keys), not from a shared
    stream: a group's interval is the same whatever else the table holds or in which order."""
    import hashlib
    import json

    ident = [int(seed), value, list(by), [k.item() if hasattr(k, "item") else k for k in keys]]
    digest = hashlib.sha256(json.dumps(ident, default=str).encode()).digest()
    return int.from_bytes(digest[:8], "little")


#: below this many cases a percentile bootstrap is too narrow (its resamples are few and its
#: spread is the sample's, not the mean's); :func:`small_sample_widen`
SMALL_N = 10


def small_sample_widen(values, lo: float, hi: float) -> tuple[float, float]:
    """``(lo, hi)`` widened to hold the Student-t 95% interval of the mean when fewer than
    :data:`SMALL_N` values are finite.

    A percentile bootstrap of 3 or 4 cases under-covers badly (of 3 values it has 10 distinct
    resamples); a fresh run on another machine, whose samplers draw other chains, then lands
    outside a CI that only looked precise (issue 29). The t interval is clipped to what the
    values can be: at 0 below when none is negative, at 1 above when all lie in [0, 1] (shares,
    normalised errors). Ten cases and more keep the bootstrap's interval unchanged.
    """
    from scipy import stats

    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    n = v.size
    if n < 2 or n >= SMALL_N:
        return lo, hi
    mean, sem = float(v.mean()), float(stats.sem(v))
    # (equal values: no spread, and scipy answers NaN for a zero scale)
    t_lo, t_hi = ((mean, mean) if sem == 0.0 else
                  (float(x) for x in stats.t.interval(0.95, n - 1, loc=mean, scale=sem)))
    if (v >= 0).all():
        t_lo = max(t_lo, 0.0)
        if (v <= 1).all():
            t_hi = min(t_hi, 1.0)
    return min(lo, t_lo), max(hi, t_hi)


def ci_summary(df, by: list[str], value: str = "value", seed: int = 0):
    """Mean with a 95% bootstrap CI of ``value`` per group (cases are the resampled unit).

    Independent of the order of ``df``'s rows (each group's values are sorted, see
    :func:`~sysid_bench.core.metrics.bootstrap_ci`); each group's bootstrap is seeded from ``seed``
    and the group's identity.

    Returns
    -------
    pandas.DataFrame
        ``by`` columns plus ``mean``, ``lo``, ``hi``, ``n``.
    """
    import pandas as pd

    recs = []
    for keys, g in df.groupby(by, sort=True, dropna=False):
        keys = keys if isinstance(keys, tuple) else (keys,)
        v = g[value].to_numpy(dtype=float)
        m, lo, hi = (bootstrap_ci(v, seed=_group_seed(seed, value, by, keys), n_boot=1000)
                     if len(v) else (np.nan,) * 3)
        lo, hi = small_sample_widen(v, lo, hi)
        recs.append({**dict(zip(by, keys)), "mean": m, "lo": lo, "hi": hi,
                     "n": int(np.isfinite(v).sum())})
    return pd.DataFrame.from_records(recs, columns=[*by, "mean", "lo", "hi", "n"])


def median_ci(df, key, value: str = "value", case: str = "case", n_boot: int = 1000,
              level: float = 0.95) -> tuple[float, float, float]:
    """Median of ``df[value]`` pooled over rows, with a percentile-bootstrap CI that resamples
    cases (``df[case]``: a case's rows go in or out together, as they are not independent).

    A median shown without an interval cannot say whether another run's differs (issue 29: a
    fresh run on another machine must land inside the committed figure's CI). Independent of
    row order; seeded from ``key`` (the group's identity). Fewer than :data:`SMALL_N` cases:
    the interval is widened to the range of the values (one case: that range).

    Returns
    -------
    (median, lo, hi) : tuple of float
        NaN thrice when no value is finite.
    """
    v = df[value].to_numpy(dtype=float)
    c = df[case].to_numpy()
    ok = np.isfinite(v)
    v, c = v[ok], c[ok]
    if not v.size:
        return (np.nan,) * 3
    med = float(np.median(v))
    ids, gid = np.unique(c, return_inverse=True)
    k = len(ids)
    if k == 1:
        return med, float(v.min()), float(v.max())
    order = np.lexsort((gid, v))  # by value, ties by case: the same for any row order
    v, gid = v[order], gid[order]
    rng = np.random.default_rng(_group_seed(0, value, ["median", case], list(key)))
    counts = np.zeros((n_boot, k), dtype=np.int64)
    np.add.at(counts, (np.arange(n_boot)[:, None], rng.integers(0, k, (n_boot, k))), 1)
    cw = np.cumsum(counts[:, gid], axis=1)  # (n_boot, n): how many resampled values <= each
    total = cw[:, -1]
    # np.median's two middle values: ranks floor((t-1)/2) and ceil((t-1)/2) of each resample
    lo_r, hi_r = (total - 1) // 2, total // 2
    at_lo = (cw <= lo_r[:, None]).sum(axis=1)
    at_hi = (cw <= hi_r[:, None]).sum(axis=1)
    meds = 0.5 * (v[at_lo] + v[at_hi])
    a = (1.0 - level) / 2
    lo, hi = np.quantile(meds, [a, 1.0 - a])
    if k < SMALL_N:
        # a few cases' resamples are few and alike (a rerun elsewhere missed 3 cases' CI):
        # no distribution-free 95% interval of a median exists below 6 cases, so the range of
        # the values is shown instead
        lo, hi = min(lo, float(v[0])), max(hi, float(v[-1]))
    return med, float(lo), float(hi)


def share_ci(rows):
    """Mean with its 95% CI over cases of ``rows``' 0/1 values (each case's values averaged
    first; a bootstrap over cases).

    A bootstrap of cases that all score 1 (or all 0) has no width, and would let a reading call
    a share of 1.00 [1.00, 1.00] from four cases above 97%. There the open side is the exact
    binomial bound over cases instead: with all ``n`` cases holding, a share of holding cases
    below ``0.025 ** (1 / n)`` would give that outcome less than 2.5% of the time (0.40 for 4
    cases, 0.69 for 10, 0.96 for 100).

    Returns
    -------
    pandas.Series
        ``mean``, ``lo``, ``hi``, ``n``.
    """
    from scipy import stats

    per_case = rows.groupby("case").value.mean().reset_index().assign(k=0)
    s = ci_summary(per_case, ["k"]).iloc[0].copy()
    n = len(per_case)
    if n:
        if (per_case.value >= 1.0).all():
            s["lo"] = min(s["lo"], stats.binomtest(n, n).proportion_ci(0.95, "exact").low)
        elif (per_case.value <= 0.0).all():
            s["hi"] = max(s["hi"], stats.binomtest(0, n).proportion_ci(0.95, "exact").high)
    return s


def fmt_ci(m: float, lo: float, hi: float, digits: int = 3) -> str:
    """``"0.012 [0.010, 0.015]"``, or ``"-"`` for missing."""
    if m is None or not np.isfinite(m):
        return "-"
    f = f"{{:.{digits}g}}"
    return f"{f.format(m)} [{f.format(lo)}, {f.format(hi)}]"
