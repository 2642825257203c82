"""Build the grid of cells and run what the store does not hold yet.

Execution
---------
* Local (default): a ``ProcessPoolExecutor`` (spawn, one single-threaded worker per core) for
  most cells, plus one thread in this process for the methods listed in ``inline`` (by default
  those that declare ``inline``: ``prior`` and ``vid2param``; a Vid2Param cell is milliseconds
  of LSTM, so shipping it to a worker would only make every worker import torch and load the
  checkpoint).

Everything per method (cost for the order of cells, inline or not, caps, options, threads) is
read from the method's declarations (:func:`methods.spec`), never from a table here.
* ``scheduler``: the same cells as tasks on a Dask distributed cluster (an address or a
  ``distributed.Client``); workers keep their loaded estimators and test sets between tasks.

Only this process writes the store, one transaction per finished cell, so a run killed at any
moment keeps every cell it finished and a restart computes only the rest (SIGTERM and Ctrl-C
also stop the workers; a worker whose run died, even by SIGKILL, ends itself within a second:
:func:`_end_with_parent`). Local workers are spawned, so a script calling :func:`run` needs the
usual ``if __name__ == "__main__":`` guard. A worker process that
dies takes its cell with it: the cell is retried once on a fresh pool, then stored as an error.
"""

from __future__ import annotations

import contextlib
import os
import platform
import subprocess
import sys
import time
from collections import Counter
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, ThreadPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from sysid_bench.bench.cases import Scale, get_scale, unknown_name
from sysid_bench.bench.experiment import Cell, execute
from sysid_bench.bench.fingerprint import method_fingerprint
from sysid_bench.bench.store import Store, lock_run_dir
from sysid_bench.core._validate import check_flag, check_int, check_positive_int

__all__ = ["run", "build_grid", "resolve_methods", "resolve_experiments", "provenance",
           "method_fingerprint", "experiment_fingerprint", "cell_fingerprint", "default_inline", "default_run_dir", "STORE_NAME"]

STORE_NAME = "results.sqlite"
#: Paths (from the repository root) a run writes itself: left out of provenance's dirty check
REPORT_OUTPUTS = ("reports",)
#: sources (from the repository root) every simulation-based method is built on
_VERSIONED = ("numpy", "scipy", "pandas", "pyarrow", "torch", "jax", "numpyro", "emcee",
              "pysindy", "pydmd", "scikit-optimize", "scikit-learn", "dask", "distributed",
              "matplotlib")


def _cpu_flags() -> set[str]:
    """The CPU's feature flags (Linux ``/proc/cpuinfo``; empty elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def portable_float_env() -> dict[str, str]:
    """Variables that make the workers' floating point the same on every x86-64 CPU that has
    AVX2 and FMA (``docs/reliability.md``, "Same report on any machine").

    OpenBLAS (NumPy's and SciPy's) picks its kernels by CPU: on a fixed case ``Prescott``
    kernels moved bo's e in the 5th digit and every emcee and nuts draw, and the chains
    amplify that. ``OPENBLAS_CORETYPE=Haswell`` runs the same kernels on every such CPU,
    AVX-512 ones included. NumPy's own AVX-512 loops (``exp``, ``log``, ``sin``: results 1 ulp
    from the baseline's) are turned off; XLA compiles for at most AVX2. Empty on other CPUs
    (ARM, x86 without AVX2): there the figures move within their CIs.
    """
    import platform

    if platform.machine().lower() not in ("x86_64", "amd64") or not {"avx2", "fma"} <= _cpu_flags():
        return {}
    return {"OPENBLAS_CORETYPE": "Haswell", "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"}


def _thread_env(threads: int) -> dict[str, str]:
    n = str(int(threads))
    port = portable_float_env()
    isa = " --xla_cpu_max_isa=AVX2" if port else ""
    xla = ("--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" if n == "1"
           else f"intra_op_parallelism_threads={n}") + isa
    return {"OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n,
            "NUMBA_NUM_THREADS": n, "XLA_FLAGS": xla, **port}


def default_run_dir(scale: str) -> Path:
    return Path("runs") / scale


def resolve_experiments(names=None) -> list[str]:
    """Validated experiment names (all, in report order, when ``names`` is None)."""
    from sysid_bench.bench import EXPERIMENTS

    if names is None:
        return list(EXPERIMENTS)
    out = []
    for n in names:
        if n not in EXPERIMENTS:
            raise unknown_name("experiment", n, EXPERIMENTS)
        out.append(n)
    return out


def resolve_methods(names=None) -> tuple[list[str], dict[str, str]]:
    """Validated method names and the ones skipped because they cannot be imported.

    Unknown names raise ``ValueError`` listing the known ones. Without ``names``, every
    registered contender plus the reference helpers (``prior``: the score of guessing).

    Returns
    -------
    usable : list of str
    skipped : dict of name to reason
    """
    import methods

    known = methods.available(include_reference=True)
    wanted = [*methods.available(), *methods.references()] if names is None else list(names)
    usable, skipped = [], {}
    for n in wanted:
        if n not in known:
            raise unknown_name("method", n, known)
        try:
            methods.get_class(n)
        except ImportError as exc:
            skipped[n] = str(exc)
            continue
        usable.append(n)
    return usable, skipped


def build_grid(scale: Scale, methods: list[str], experiments: list[str],
               systems: list[str] | None = None) -> list[Cell]:
    """Every cell of the run, in a deterministic order: experiment by experiment, and within
    one, system by system (``systems``: default every registered system) among those the
    experiment runs on."""
    from sysid_bench.bench import EXPERIMENTS
    from sysid_bench.core import systems as registry

    names = registry.available() if systems is None else list(systems)
    cells: list[Cell] = []
    for e in experiments:
        exp = EXPERIMENTS[e]
        for s in names:
            if exp.runs_on(s):
                cells += exp.cells(scale, methods, s)
    return cells


def experiment_fingerprint(name: str) -> str:
    """Hash (16 hex digits) of the source of experiment ``name``'s module.

    A cell's fingerprint is its method's and its experiment's (:func:`cell_fingerprint`), so
    an experiment whose measurement changed (a new metric, another horizon) is computed again
    instead of mixing rows of two definitions in one table.
    """
    import hashlib
    import importlib
    import inspect

    from sysid_bench.bench import EXPERIMENTS

    exp = EXPERIMENTS[name]
    src = inspect.getsource(inspect.getmodule(type(exp)))
    for mod in exp.depends_on:
        src += inspect.getsource(importlib.import_module(mod))
    return hashlib.sha256(src.encode()).hexdigest()[:16]


def cell_fingerprint(method_fp: str, experiment_fp: str) -> str:
    """The fingerprint stored with a cell: its method's code and weights, its experiment's code."""
    return f"{method_fp}:{experiment_fp}"


def default_inline(meths) -> list[str]:
    """The methods among ``meths`` that declare ``inline`` (run in a thread of this process)."""
    import methods

    return [m for m in meths if methods.spec(m).inline]


def provenance() -> dict:
    """Git commit (and whether the tree is dirty), package versions, Python and machine."""
    from importlib import metadata

    root = Path(__file__).resolve().parents[2]
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, timeout=10).stdout.strip() or "unknown"
        # the report's own outputs (``reports/``, rewritten by every run) do not make the
        # code the run measured "uncommitted"
        dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no",
                                     "--", ".", *(f":(exclude){p}" for p in REPORT_OUTPUTS)],
                                    cwd=root, capture_output=True, text=True,
                                    timeout=10).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        commit, dirty = "unknown", None
    versions = {}
    for pkg in _VERSIONED:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    from sysid_bench import __version__

    return {"git_commit": commit, "git_dirty": dirty, "sysid_bench": __version__,
            "versions": versions, "python": sys.version.split()[0],
            "platform": platform.platform(), "cpus": os.cpu_count()}


@contextlib.contextmanager
def _single_threaded_children(threads: int = 1, jax_cache=None):
    """Spawned workers inherit these: ``threads`` BLAS/OpenMP/XLA threads each (default one:
    workers = cores), and ``jax_cache`` as JAX's persistent compilation cache (NUTS compiles
    its sampler per frame bucket, ~10-50 s each: every worker after the first, and a resumed
    run, loads it instead; the compiled code is the same). Variables the user set already are
    kept."""
    env = _thread_env(threads)
    if jax_cache is not None:
        env["JAX_COMPILATION_CACHE_DIR"] = str(jax_cache)
    old = {k: os.environ.get(k) for k in env}
    for k, v in env.items():
        os.environ.setdefault(k, v)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _order(cells: list[Cell]) -> list[Cell]:
    from sysid_bench.bench import EXPERIMENTS

    def cost(c: Cell):
        heavy = getattr(EXPERIMENTS[c.experiment], "heavy", False)
        return (-(1000 if heavy else costs[c.method]), c.experiment, c.system, c.method,
                c.input, c.condition, str(c.case))

    import methods

    known = set(methods.available(include_reference=True))
    # a cell of no registered method (an experiment's built-in baseline) costs little
    costs = {m: methods.spec(m).cost if m in known else 1 for m in {c.method for c in cells}}

    return sorted(cells, key=cost)


def run(
    *,
    scale: str | Scale = "default",
    methods=None,
    experiments=None,
    run_dir=None,
    workers: int | None = None,
    scheduler=None,
    inline=None,
    progress: bool = True,
    threads: int = 1,
    argv=None,
    max_cells: int | None = None,
    retry_errors: bool = False,
    systems=None,
) -> dict:
    """Run (or resume) a benchmark into ``run_dir/results.sqlite``.

    Parameters
    ----------
    scale : str or Scale
        "smoke", "default" or "paper".
    methods, experiments : list of str, optional
        Default: every contender (that imports), the ``prior`` reference, every experiment.
    run_dir : path, optional
        Default ``runs/<scale>``. Holds the store and cached trained models.
    workers : int, optional
        Local worker processes; default the number of cores. 0 runs every cell in this process.
    scheduler : str or distributed.Client, optional
        Run on a Dask cluster instead of the local pool.
    inline : iterable of str, optional
        Methods whose (non-heavy) cells run in a thread of this process; default those that
        declare ``inline``.
    progress : bool
        tqdm progress bar over the cells.
    max_cells : int, optional
        Stop after this many new cells (for tests; the rest stays for a resume).
    threads : int
        Threads per cell: worker processes get this many BLAS/OpenMP/XLA threads, and a method
        that declares ``threads_param`` gets it as that hyperparameter (default 1: workers =
        cores, so more only oversubscribes the machine and distorts the timings).
    retry_errors : bool
        First drop the stored cells whose status is "error" (a missing checkpoint, a bug since
        fixed), so they are computed again; otherwise a resumed run keeps them as they are.
    systems : list of str, optional
        Only these registered systems' cells (default every registered system, a user's too).

    Raises
    ------
    RunDirBusyError
        Another run is writing to ``run_dir`` (its lock file ``run.lock`` is held).

    Returns
    -------
    dict
        ``store`` (Path), ``cells`` (grid size), ``already`` (stored before), ``ran``, ``ok``,
        ``errors``, ``na``, ``skipped_methods``, ``retried`` (error cells dropped), ``stale``
        (cells dropped because their method's fingerprint changed), ``wall_s``.
    """
    sc = get_scale(scale)
    systems = _resolve_systems(systems)
    exps = resolve_experiments(experiments)
    meths, skipped = resolve_methods(methods)
    threads = check_positive_int(threads, "threads")
    progress = check_flag(progress, "progress")
    retry_errors = check_flag(retry_errors, "retry_errors")
    if workers is not None:
        check_int(workers, "workers", lo=0)
    inline = default_inline(meths) if inline is None else _check_inline(inline, meths, skipped)
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir(sc.name)
    with lock_run_dir(run_dir):  # one writing run per run dir; RunDirBusyError otherwise
        return _run_locked(sc, exps, meths, skipped, run_dir, workers, scheduler, inline,
                           progress, argv, max_cells, retry_errors, threads, systems)


def _resolve_systems(systems) -> list[str] | None:
    """Registered system names (``ValueError`` with "did you mean" for an unknown one)."""
    if systems is None:
        return None
    from sysid_bench.core import systems as registry

    if isinstance(systems, str):
        systems = [systems]
    return [registry.get(s).name for s in systems]


def _check_inline(inline, meths, skipped) -> list[str]:
    """``inline`` as a list of names among the methods of this run (or skipped from it); a name
    that is not one (``--inline bogus``) would otherwise be ignored without a word."""
    if isinstance(inline, str):
        inline = [inline]
    inline = list(inline)
    bad = [m for m in inline if m not in meths and m not in skipped]
    if bad:
        raise ValueError(f"inline: expected names among the methods of this run "
                         f"({', '.join(meths)}), got {', '.join(map(repr, bad))}")
    return inline


def _run_locked(sc, exps, meths, skipped, run_dir, workers, scheduler, inline, progress, argv,
                max_cells, retry_errors, threads, systems=None) -> dict:
    """:func:`run`'s body, under the run dir's lock."""
    from tqdm.auto import tqdm

    store = Store(run_dir / STORE_NAME, grid_config=sc.grid_config())
    t0 = time.perf_counter()
    try:
        fps = {m: method_fingerprint(m) for m in meths}
        efps = {e: experiment_fingerprint(e) for e in exps}
        cell_fps = {(e, m): cell_fingerprint(fps[m], efps[e]) for e in exps for m in meths}
        grid = build_grid(sc, meths, exps, systems)
        for c in grid:  # a cell of no registered method (a built-in policy): the experiment's
            cell_fps.setdefault((c.experiment, c.method), cell_fingerprint("-", efps[c.experiment]))
        inv = store.record_invocation({
            "argv": list(sys.argv if argv is None else argv), "scale": sc.name,
            "methods": meths, "skipped_methods": skipped, "experiments": exps,
            "workers": workers, "scheduler": None if scheduler is None else str(scheduler),
            "inline": list(inline), "retry_errors": bool(retry_errors),
            "fingerprints": fps, "experiment_fingerprints": efps, **provenance(),
        })
        stale = store.stale_cells(cell_fps)
        if stale:  # code or weights changed since: recompute, never mix
            store.drop_cells(ids=stale)
        retried = store.drop_cells("error") if retry_errors else 0
        done = store.done_cells()
        todo = _order([c for c in grid if c.id not in done])
        if max_cells is not None:
            todo = todo[: int(max_cells)]
        counts: Counter = Counter()
        bar = tqdm(total=len(grid), initial=len(grid) - len(todo) if max_cells is None else
                   sum(c.id in done for c in grid), desc=f"sysid-bench {sc.name}", unit="cell",
                   disable=not progress, dynamic_ncols=True)

        def write(res: dict) -> None:
            c: Cell = res["cell"]
            store.add_cell(c.id, c.key(), res["rows"], status=res["status"], error=res["error"],
                           wall_s=res["wall_s"], artifacts=res["artifacts"], invocation=inv,
                           fingerprint=cell_fps.get((c.experiment, c.method)))
            counts[res["status"]] += 1
            bar.update(1)
            bar.set_postfix(err=counts["error"], na=counts["n/a"], refresh=False)

        try:
            if scheduler is not None:
                _run_dask(todo, sc, run_dir, scheduler, write, threads)
            else:
                with _sigterm_as_exit():
                    _run_local(todo, sc, run_dir, workers, set(inline), write, threads)
        except KeyboardInterrupt:
            # one line for the command line (cli prints it), not a traceback per process
            n = sum(counts.values())
            raise KeyboardInterrupt(
                f"interrupted: {n} cells computed and stored this time, {len(todo) - n} not; "
                f"run the same command again to resume from the store {store.path}") from None
        finally:
            bar.close()
        return {"store": store.path, "cells": len(grid), "already": len(grid) - len(todo),
                "ran": sum(counts.values()), "ok": counts["ok"], "errors": counts["error"],
                "na": counts["n/a"], "skipped_methods": skipped, "retried": retried,
                "stale": len(stale),
                "wall_s": time.perf_counter() - t0}
    finally:
        store.close()


def _run_local(todo, sc, run_dir, workers, inline, write, threads=1) -> None:
    import multiprocessing as mp

    from sysid_bench.bench import EXPERIMENTS

    n_workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if n_workers < 0:
        raise ValueError(f"workers: expected a number >= 0, got {workers!r}")
    if n_workers == 0:
        for c in todo:
            write(execute(c, sc, str(run_dir), threads))
        return
    here = [c for c in todo
            if c.method in inline and not getattr(EXPERIMENTS[c.experiment], "heavy", False)]
    ids = {c.id for c in here}
    pooled = [c for c in todo if c.id not in ids]
    attempts: Counter = Counter()
    pool, broken = None, False
    futs: dict = {}
    th = ThreadPoolExecutor(1, thread_name_prefix="inline")
    try:
        futs = {th.submit(execute, c, sc, str(run_dir), threads): (c, None) for c in here}
        while pooled or futs:
            if pooled:
                if pool is None or broken:
                    if pool is not None:
                        pool.shutdown(wait=False, cancel_futures=True)
                    with _single_threaded_children(threads, Path(run_dir) / "jax_cache"):
                        pool = ProcessPoolExecutor(min(n_workers, len(pooled)),
                                                   mp_context=mp.get_context("spawn"),
                                                   initializer=_end_with_parent,
                                                   initargs=(os.getpid(),))
                    broken = False
                with _children_ignore_sigint():  # (the workers start at the first submit)
                    futs.update({pool.submit(execute, c, sc, str(run_dir), threads): (c, pool)
                                 for c in pooled})
                pooled = []
            finished, _ = wait(futs, return_when=FIRST_COMPLETED)
            for f in finished:
                c, owner = futs.pop(f)
                try:
                    res = f.result()
                except BrokenProcessPool:
                    # a worker died (killed, out of memory); every cell pending on that pool
                    # fails with it, so each is retried on a fresh pool, up to 3 times
                    broken = broken or owner is pool
                    attempts[c.id] += 1
                    if attempts[c.id] < 3:
                        pooled.append(c)
                        continue
                    res = {"cell": c, "status": "error", "wall_s": float("nan"), "rows": [],
                           "artifacts": {}, "error": "the worker process running this cell died "
                           "(killed or out of memory) on 3 attempts"}
                write(res)
    except BaseException:
        for f in futs:
            f.cancel()
        if pool is not None:
            _terminate(pool)
        th.shutdown(wait=False, cancel_futures=True)
        raise
    if pool is not None:
        pool.shutdown(wait=True)
    th.shutdown(wait=True)


#: Seconds between a worker's checks that the run that started it is still alive.
_PARENT_POLL_S = 0.5


@contextlib.contextmanager
def _children_ignore_sigint():
    """Processes started in this block ignore SIGINT (the disposition survives their exec).

    Ctrl-C reaches every process of the terminal's group: each spawned worker printed its own
    KeyboardInterrupt traceback (bad-input-turn4). The run alone handles it: it stops the
    workers (:func:`_terminate`) and says in one line what is stored.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _end_with_parent(parent_pid: int) -> None:
    """Pool initializer: end this worker when the run that spawned it dies.

    A run killed with SIGKILL cannot stop its workers, and a worker busy in a cell never reads
    the queue that would tell it, so it computed on, orphaned (issue 14). Two guards: on Linux
    the kernel sends SIGKILL when the parent dies (``PR_SET_PDEATHSIG``; instant, even inside C
    code holding the GIL); everywhere a daemon thread sees the parent pid change (the orphan is
    re-parented) and exits the process.
    """
    import threading

    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):  # no prctl (musl builds, sandboxes): the thread stays
            pass
    if os.getppid() != parent_pid:  # the parent died before the guards were set
        os._exit(1)
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's to handle

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(_PARENT_POLL_S)
        os._exit(1)  # no cleanup to wait for: the store is written only by the parent

    threading.Thread(target=watch, name="end-with-parent", daemon=True).start()


def _terminate(pool: ProcessPoolExecutor) -> None:
    """Stop a pool now: cancel what waits, end the workers (their cells are not stored)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=5)


@contextlib.contextmanager
def _sigterm_as_exit():
    """SIGTERM (``timeout``, a scheduler's kill) unwinds like Ctrl-C: workers are stopped and
    every finished cell is already in the store."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _run_dask(todo, sc, run_dir, scheduler, write, threads=1) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError as exc:  # pragma: no cover - dask is an optional extra
        raise ImportError("--scheduler needs dask[distributed]: pip install -e .[dask]") from exc
    own = not isinstance(scheduler, Client)
    client = Client(scheduler) if own else scheduler
    try:
        futs = {client.submit(execute, c, sc, str(run_dir), threads, pure=False): c for c in todo}
        for f in as_completed(list(futs)):
            c = futs[f]
            try:
                res = f.result()
            except Exception as exc:  # KilledWorker and friends: the cluster gave up on it
                res = {"cell": c, "status": "error", "wall_s": float("nan"), "rows": [],
                       "artifacts": {}, "error": f"{type(exc).__name__}: {exc}"[:2000]}
            write(res)
    finally:
        if own:
            client.close()
