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
from sysid_bench.estimator import Estimator, Observation, Posterior
from sysid_bench.metrics import bootstrap_ci
from sysid_bench.physics import PRIOR_LO, PRIOR_SPAN

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
    """One unit of work; ``case`` is a test video index or a condition-wide label."""

    experiment: str
    method: str
    input: str
    condition: str
    case: int | str

    @property
    def id(self) -> str:
        return f"{self.experiment}|{self.method}|{self.input}|{self.condition}|{self.case}"

    def key(self) -> dict:
        return {"experiment": self.experiment, "method": self.method, "input": self.input,
                "condition": self.condition, "case": self.case}


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

    def estimator(self, method: str, warm: bool = True, **extra) -> Estimator:
        """A fresh copy of ``method`` with the scale's options (loaded once per process).

        A copy per cell keeps results independent of which cells a worker ran before (any
        state a method keeps between calls stays in the copy), so a local pool and a Dask
        cluster give the same numbers. ``warm`` loads a learned method's shipped weights
        (``fit(None)``) up front; methods about to be trained from scratch skip that.
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
        return copy.deepcopy(proto)

    def test_set(self, variant: str, n: int, **options):
        return test_set(variant, n, self.scale.seed, **options)


class Experiment:
    """Base class of the five experiments (one module each)."""

    name: str = ""
    title: str = ""
    #: what the report says the experiment measures, one paragraph
    description: str = ""

    def cells(self, scale: Scale, methods: list[str]) -> list[Cell]:
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
    """The methods among ``names`` that the paper's claims are about (they declare ``claims``),
    in registry order: the readings compare them with the baselines. A method that cannot be
    imported here counts as a baseline."""
    import methods

    names = set(names)
    out = []
    for m in methods.available(include_reference=True):
        if m not in names:
            continue
        try:
            if methods.spec(m).claims:
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
        t0 = time.perf_counter()
        try:
            p = est.identify(obs.prefix(n))
        except NotImplementedError:
            raise
        except Exception as exc:
            if out is None:
                raise
            out.fail(n, exc, case)
            continue
        res.append((n, p, time.perf_counter() - t0))
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


def ci_summary(df, by: list[str], value: str = "value", seed: int = 0):
    """Mean with a 95% bootstrap CI of ``value`` per group (cases are the resampled unit).

    Independent of the order of ``df``'s rows (each group's values are sorted, see
    :func:`~sysid_bench.metrics.bootstrap_ci`); each group's bootstrap is seeded from ``seed``
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
        recs.append({**dict(zip(by, keys)), "mean": m, "lo": lo, "hi": hi,
                     "n": int(np.isfinite(v).sum())})
    return pd.DataFrame.from_records(recs, columns=[*by, "mean", "lo", "hi", "n"])


def fmt_ci(m: float, lo: float, hi: float, digits: int = 3) -> str:
    """``"0.012 [0.010, 0.015]"``, or ``"-"`` for missing."""
    if m is None or not np.isfinite(m):
        return "-"
    f = f"{{:.{digits}g}}"
    return f"{f.format(m)} [{f.format(lo)}, {f.format(hi)}]"
