"""The results store: one SQLite file per run, long-format rows, one transaction per cell.

Why SQLite (in WAL mode) rather than Parquet: a run must survive being killed at any instant
without losing or duplicating a finished cell. SQLite gives that for free: each cell's rows and
its bookkeeping record are written in **one transaction**, so after a crash a cell is either
entirely there or entirely absent, and a restarted run skips exactly the cells recorded in
``cells``. WAL mode lets ``report --from-store`` read while a run is still writing. Parquet
would need one file per cell (thousands of small files) or rewriting a growing file.

Layout
------
``meta``       key/value: ``store_format`` (see :data:`STORE_FORMAT`), ``grid_config`` (JSON: what
               decides the cases; a run with another grid config is refused), ``created``.
``invocations`` one row per ``run`` started on this store: argv/config, git commit, package
               versions, host, start time.
``cells``      one row per finished cell: id, system, experiment, method, input, condition, case,
               status (``ok`` / ``error`` / ``n/a``), error text, wall seconds, finish time,
               invocation, and the fingerprint of the method's code and weights and of the
               experiment's code: a run finding cells whose fingerprint changed computes them
               again.
``results``    the long-format table: system, experiment, method, input, condition, case, n_frames,
               metric, value, status, error, wall_s (of the cell), cell_id. A failed cell has one
               row with ``metric = "error"``; a cell whose method cannot do the task (it raised
               ``NotImplementedError``) one row with ``metric = "n/a"``; both carry the text.
``artifacts``  small arrays a figure needs (example forecasts), ``.npy`` bytes keyed by cell.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import socket
import sqlite3
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "STORE_FORMAT",
    "StoreFormatError",
    "StoreConfigError",
    "StoreCorruptError",
    "StoreDiskFullError",
    "RunDirBusyError",
    "lock_run_dir",
    "LOCK_NAME",
    "Store",
    "Row",
    "RESULT_COLUMNS",
]

#: Bump when tables or the meaning of their columns change; other versions are refused.
STORE_FORMAT = 2
RESULT_COLUMNS = (
    "system",
    "experiment",
    "method",
    "input",
    "condition",
    "case",
    "n_frames",
    "metric",
    "value",
    "status",
    "error",
    "wall_s",
    "cell_id",
)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS invocations (
    id INTEGER PRIMARY KEY AUTOINCREMENT, started REAL, info TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS cells (
    cell_id TEXT PRIMARY KEY, system TEXT NOT NULL, experiment TEXT NOT NULL,
    method TEXT NOT NULL, input TEXT NOT NULL,
    condition TEXT NOT NULL, "case" TEXT NOT NULL, status TEXT NOT NULL, error TEXT,
    wall_s REAL, finished REAL, invocation INTEGER, fingerprint TEXT);
CREATE TABLE IF NOT EXISTS results (
    system TEXT NOT NULL, experiment TEXT NOT NULL, method TEXT NOT NULL, input TEXT NOT NULL,
    condition TEXT NOT NULL,
    "case" INTEGER NOT NULL, n_frames INTEGER NOT NULL, metric TEXT NOT NULL, value REAL,
    status TEXT NOT NULL, error TEXT, wall_s REAL, cell_id TEXT NOT NULL,
    UNIQUE (system, experiment, method, input, condition, "case", n_frames, metric));
CREATE INDEX IF NOT EXISTS results_exp ON results (experiment, system, method);
CREATE TABLE IF NOT EXISTS artifacts (
    cell_id TEXT NOT NULL, name TEXT NOT NULL, data BLOB NOT NULL, PRIMARY KEY (cell_id, name));
"""


class StoreFormatError(ValueError):
    """The store was written by another store format version."""


class StoreConfigError(ValueError):
    """The store holds a run whose cases were generated differently."""


class RunDirBusyError(ValueError):
    """Another run holds the run directory's lock."""


class StoreCorruptError(ValueError):
    """The file is damaged (truncated, overwritten): SQLite cannot read it, or its integrity
    check fails. The message names the file and what to do."""


class StoreDiskFullError(OSError):
    """The disk filled while writing the store (``errno`` ENOSPC). The cells stored before it are
    kept (each cell is one transaction); the run resumes once there is room."""


def _corrupt(path: Path, why: str) -> StoreCorruptError:
    why = " ".join(why.replace("*", " ").split())[:200]  # SQLite's report spans lines
    return StoreCorruptError(
        f"path: the results store {str(path)!r} is corrupt ({why}); its results cannot be "
        "trusted. Move it aside (or delete it) and re-run into an empty --run-dir, which "
        "computes every cell again"
    )


def _disk_full(path: Path) -> StoreDiskFullError:
    err = StoreDiskFullError(
        f"disk full writing the results store {str(path)!r}: the cells stored so far are kept; "
        "free space (or move the run dir to a disk with room) and run the same command again"
    )
    err.errno = errno.ENOSPC
    return err


@contextlib.contextmanager
def _sqlite_errors(path: Path):
    """Turn SQLite's errors about the file into errors naming it: a damaged file
    (:class:`StoreCorruptError`), a full disk (:class:`StoreDiskFullError`)."""
    try:
        yield
    except sqlite3.OperationalError as exc:
        if getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL or "disk is full" in str(exc):
            raise _disk_full(path) from exc
        raise
    except sqlite3.DatabaseError as exc:  # "file is not a database", "disk image is malformed"
        code = getattr(exc, "sqlite_errorcode", None)
        if type(exc) is sqlite3.DatabaseError or code in (sqlite3.SQLITE_CORRUPT,
                                                          sqlite3.SQLITE_NOTADB):
            raise _corrupt(path, str(exc)) from exc
        raise


def _transaction(con: sqlite3.Connection):
    """``BEGIN IMMEDIATE`` ... ``COMMIT`` as a context manager that rolls back on any error,
    without masking it: after a full disk SQLite may already have rolled the transaction back,
    and a second ROLLBACK ("cannot rollback - no transaction is active") would hide why."""

    @contextlib.contextmanager
    def tx():
        con.execute("BEGIN IMMEDIATE")
        try:
            yield
            con.execute("COMMIT")
        except BaseException:
            if con.in_transaction:
                try:
                    con.execute("ROLLBACK")
                except sqlite3.Error:
                    pass  # the error that brought us here is the one to report
            raise

    return tx()


#: The lock file a run holds in its run directory (``fcntl.flock``, exclusive) while it runs.
LOCK_NAME = "run.lock"


@contextlib.contextmanager
def lock_run_dir(run_dir):
    """Hold ``run_dir``'s run lock for the ``with`` block: one writing run per run directory.

    Two runs on one store would both compute the missing cells and interleave their
    invocations (issue 14). The lock is ``fcntl.flock`` on ``run_dir/run.lock``: the kernel drops
    it with the process's files however the process ends, so a run killed with SIGKILL leaves
    a file but no lock, and the next run goes ahead. The file says who holds it (pid, host,
    start time) for the error message; it is informational, rewritten in place by each holder
    (it must stay the same file to be locked). Where ``fcntl`` is missing (Windows) nothing is
    locked. Readers (``report --from-store``) take no lock.

    Raises
    ------
    RunDirBusyError
        Another process (or another open of the file in this one) holds the lock.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = run_dir / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
            except (ValueError, OSError):
                holder = {}
            who = (f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}, started "
                   f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(holder['started']))}"
                   if "started" in holder else "pid unknown")
            raise RunDirBusyError(
                f"run_dir: {str(run_dir)!r} is in use by another run ({who}); wait for it to "
                "finish or use another --run-dir. Two runs on one store would mix their cells"
            ) from None
        info = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                           "started": time.time()}).encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, info, 0)
        yield
    finally:
        os.close(fd)  # releases the lock


@dataclass(frozen=True)
class Row:
    """One long-format result of a cell.

    ``case`` is the test video index (a cell may cover several, e.g. a sensitivity condition);
    ``n_frames`` the observed frames the value refers to (0 when it does not apply).
    """

    case: int
    n_frames: int
    metric: str
    value: float


def _connect(path: Path) -> sqlite3.Connection:
    con = sqlite3.connect(str(path), timeout=60.0, isolation_level=None)
    con.execute("PRAGMA journal_mode=WAL")
    # NORMAL in WAL mode: a committed transaction survives a killed process (only an OS crash /
    # power loss may roll back the last commits, never corrupt the file).
    con.execute("PRAGMA synchronous=NORMAL")
    return con


class Store:
    """A run's results on disk.

    Parameters
    ----------
    path : str or Path
        The SQLite file (created with its directory when missing).
    grid_config : dict, optional
        JSON-able description of everything that decides the cases (scale sizes, seed). Given
        when writing: a new store records it, an existing one must match it. ``None`` opens an
        existing store read-only in spirit (no check, nothing recorded).

    Raises
    ------
    StoreFormatError
        The file was written by another store format version.
    StoreConfigError
        ``grid_config`` differs from the one the store was created with.
    FileNotFoundError
        ``grid_config`` is None and there is no store at ``path``.
    """

    def __init__(self, path, grid_config: Mapping | None = None):
        self.path = Path(path)
        if grid_config is None and not self.path.is_file():
            raise FileNotFoundError(f"path: expected an existing results store, got {str(path)!r}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        existed = self.path.is_file() and self.path.stat().st_size > 0
        self._con = None
        try:
            with _sqlite_errors(self.path):
                self._con = _connect(self.path)
                if existed:
                    self._check_integrity()
                self._check_or_init(grid_config)
        except BaseException:
            if self._con is not None:
                self._con.close()
            raise

    def _check_integrity(self) -> None:
        """SQLite's own check of every page and index of the file (``PRAGMA integrity_check``,
        first problem only), before anything is read or written: a store with garbage in its
        middle otherwise opens, reads its ``cells`` table, and a run reports every cell "already
        stored" from a damaged file. Milliseconds per MB."""
        row = self._con.execute("PRAGMA integrity_check(1)").fetchone()
        if row is None or row[0] != "ok":
            raise _corrupt(self.path, f"integrity check: {row[0] if row else 'no answer'}")

    # -- setup ------------------------------------------------------------------------------
    def _check_or_init(self, grid_config: Mapping | None) -> None:
        con = self._con
        has_meta = con.execute(
            "SELECT name FROM sqlite_master WHERE type='table' AND name='meta'"
        ).fetchone()
        if has_meta:
            fmt = con.execute("SELECT value FROM meta WHERE key='store_format'").fetchone()
            if fmt is None or int(fmt[0]) != STORE_FORMAT:
                got = "none" if fmt is None else fmt[0]
                raise StoreFormatError(
                    f"path: the results store {str(self.path)!r} has store format {got}, this "
                    f"version of sysid-bench reads format {STORE_FORMAT}; re-run into a new "
                    "store (another --run-dir) or use the sysid-bench version that wrote it"
                )
            self._stored_grid_config()  # a damaged one is refused here, reading or writing
        elif grid_config is None:
            raise StoreFormatError(f"path: {str(self.path)!r} is not a sysid-bench results store")
        con.executescript(_SCHEMA)
        if grid_config is None:
            return
        want = json.dumps(grid_config, sort_keys=True)
        with _transaction(con):
            have = con.execute("SELECT value FROM meta WHERE key='grid_config'").fetchone()
            if have is None:
                con.executemany(
                    "INSERT INTO meta VALUES (?, ?)",
                    [
                        ("store_format", str(STORE_FORMAT)),
                        ("grid_config", want),
                        ("created", str(time.time())),
                    ],
                )
            elif self._stored_grid_config() != json.loads(want):
                raise StoreConfigError(
                    f"grid_config: the store {str(self.path)!r} was made with {have[0]}, this run "
                    f"asks for {want}; its cases would differ, so results would mix. Use another "
                    "--run-dir (or delete that store)"
                )

    def close(self) -> None:
        self._con.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- metadata ---------------------------------------------------------------------------
    @property
    def grid_config(self) -> dict | None:
        """What the store's cells were made with (:meth:`Scale.grid_config`)."""
        return self._stored_grid_config()

    def _stored_grid_config(self) -> dict:
        """The stored grid_config; a missing or unreadable one is :class:`StoreCorruptError`
        (it says which cases the cells are of: without it they cannot be trusted, issue 37)."""
        r = self._con.execute("SELECT value FROM meta WHERE key='grid_config'").fetchone()
        if r is None:
            raise _corrupt(self.path, "its meta table has no grid_config")
        try:
            cfg = json.loads(r[0])
        except (TypeError, ValueError):
            cfg = None
        if not isinstance(cfg, dict):
            raise _corrupt(self.path, f"its grid_config is not a JSON object: {str(r[0])[:60]!r}")
        return cfg

    def record_invocation(self, info: Mapping) -> int:
        """Append what this run was started with (config, commit, versions); returns its id."""
        info = {"host": socket.gethostname(), "pid": os.getpid(), **info}
        with _sqlite_errors(self.path):
            cur = self._con.execute(
                "INSERT INTO invocations (started, info) VALUES (?, ?)",
                (time.time(), json.dumps(info, sort_keys=True, default=str)),
            )
        return int(cur.lastrowid)

    def invocations(self) -> list[dict]:
        rows = self._con.execute("SELECT id, started, info FROM invocations ORDER BY id").fetchall()
        return [{"id": i, "started": s, **json.loads(info)} for i, s, info in rows]

    # -- cells ------------------------------------------------------------------------------
    def done_cells(self) -> set[str]:
        """Ids of the cells already stored (whatever their status)."""
        return {r[0] for r in self._con.execute("SELECT cell_id FROM cells")}

    def add_cell(
        self,
        cell_id: str,
        key: Mapping,
        rows: Iterable[Row],
        *,
        status: str = "ok",
        error: str | None = None,
        wall_s: float = float("nan"),
        artifacts: Mapping[str, np.ndarray] | None = None,
        invocation: int | None = None,
        fingerprint: str | None = None,
    ) -> bool:
        """Store one finished cell atomically; returns False when it was already stored.

        Parameters
        ----------
        cell_id : str
        key : mapping
            ``system`` (default "ball"), ``experiment``, ``method``, ``input``, ``condition``,
            ``case`` of the cell.
        rows : iterable of Row
            Ignored for ``status`` ``error`` / ``n/a``: one row with that metric is written.
        status : {"ok", "error", "n/a"}
        error : str, optional
        wall_s : float
            Seconds the whole cell took.
        artifacts : dict of str to ndarray, optional
        invocation : int, optional
            Id from :meth:`record_invocation`.
        fingerprint : str, optional
            Hash of the method's code and weights and the experiment's code the cell was
            computed with (see :meth:`stale_cells`).
        """
        if status not in ("ok", "error", "n/a"):
            raise ValueError(f"status: expected 'ok', 'error' or 'n/a', got {status!r}")
        k = (str(key.get("system", "ball")), key["experiment"], key["method"], key["input"],
             str(key.get("condition", "")))
        if status != "ok":
            case = key["case"]
            rows = [Row(int(case) if str(case).isdigit() else -1, 0, status, float("nan"))]
        payload = [
            (*k, int(r.case), int(r.n_frames), r.metric, _num(r.value), status, error, wall_s, cell_id)
            for r in rows
        ]
        con = self._con
        with _sqlite_errors(self.path), _transaction(con):
            if con.execute("SELECT 1 FROM cells WHERE cell_id=?", (cell_id,)).fetchone():
                return False  # (an empty transaction, committed)
            con.executemany(
                f"INSERT INTO results VALUES ({', '.join('?' * len(RESULT_COLUMNS))})", payload
            )
            for name, arr in (artifacts or {}).items():
                buf = io.BytesIO()
                np.save(buf, np.asarray(arr), allow_pickle=False)
                con.execute("INSERT INTO artifacts VALUES (?, ?, ?)", (cell_id, name, buf.getvalue()))
            con.execute(
                "INSERT INTO cells VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (cell_id, *k, str(key["case"]), status, error, wall_s, time.time(), invocation,
                 fingerprint),
            )
        return True

    def stale_cells(self, fingerprints: Mapping[tuple[str, str], str]) -> list[str]:
        """Ids of the cells of each ``(experiment, method)`` in ``fingerprints`` computed with
        another fingerprint (other code or weights)."""
        rows = self._con.execute(
            "SELECT cell_id, experiment, method, fingerprint FROM cells").fetchall()
        return [c for c, e, m, fp in rows
                if (e, m) in fingerprints and fp != fingerprints[(e, m)]]

    def drop_cells(self, status: str | None = "error", ids: Iterable[str] | None = None) -> int:
        """Forget cells (rows, artifacts, record) so a run computes them again.

        Parameters
        ----------
        status : str, optional
            Drop every cell with this status ...
        ids : iterable of str, optional
            ... or exactly these cells (then ``status`` is ignored).

        Returns
        -------
        int
            Cells dropped.
        """
        con = self._con
        with _sqlite_errors(self.path), _transaction(con):
            if ids is None:
                ids = [r[0] for r in
                       con.execute("SELECT cell_id FROM cells WHERE status=?", (status,))]
            ids = list(ids)
            for table in ("results", "artifacts", "cells"):
                con.executemany(f"DELETE FROM {table} WHERE cell_id=?", [(i,) for i in ids])
        return len(ids)

    # -- reading ----------------------------------------------------------------------------
    def results(self, experiment: str | None = None):
        """The long-format results as a pandas DataFrame (columns :data:`RESULT_COLUMNS`), sorted
        by their key (experiment, system, method, input, condition, case, n_frames, metric)."""
        import pandas as pd

        q = "SELECT * FROM results"
        args: tuple = ()
        if experiment is not None:
            q += " WHERE experiment=?"
            args = (experiment,)
        # the table's unique key: rows in the same order however the cells finished (issue 14)
        q += (' ORDER BY experiment, system, method, input, condition, "case", n_frames, '
              'metric')
        df = pd.read_sql_query(q, self._con, params=args)
        return df

    def cells(self):
        """One row per stored cell (pandas DataFrame)."""
        import pandas as pd

        return pd.read_sql_query("SELECT * FROM cells ORDER BY cell_id", self._con)

    def artifact(self, cell_id: str, name: str) -> np.ndarray | None:
        r = self._con.execute(
            "SELECT data FROM artifacts WHERE cell_id=? AND name=?", (cell_id, name)
        ).fetchone()
        return None if r is None else np.load(io.BytesIO(r[0]), allow_pickle=False)

    def artifacts(self, like: str = "%") -> dict[tuple[str, str], np.ndarray]:
        """All artifacts whose cell id matches the SQL LIKE pattern ``like``."""
        rows = self._con.execute(
            "SELECT cell_id, name, data FROM artifacts WHERE cell_id LIKE ? ORDER BY cell_id, name",
            (like,)
        ).fetchall()
        return {(c, n): np.load(io.BytesIO(d), allow_pickle=False) for c, n, d in rows}


def _num(v) -> float | None:
    v = float(v)
    # SQLite stores NaN as NULL; keep inf as is (REAL supports it).
    return None if np.isnan(v) else v
