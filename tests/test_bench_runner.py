"""The runner on the smoke scale: resume, failures, kill-and-resume, Dask = local pool."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import methods
from methods import Registration
from sysid_bench.bench import EXPERIMENTS
from sysid_bench.bench.cases import SCALES, Scale
from sysid_bench.bench.experiment import Cell, Context
from sysid_bench.bench.runner import STORE_NAME, build_grid, run
from sysid_bench.bench.store import Store, StoreConfigError
from sysid_bench.core.estimator import Estimator, Forecast, Observation, prior_posterior

ROOT = Path(__file__).resolve().parents[1]
HAVE_LSQ = "lsq" in methods.available()
try:
    methods.get_class("lsq")
except ImportError:
    HAVE_LSQ = False
SMOKE = SCALES["smoke"]
FAST = ["prior", "lsq"] if HAVE_LSQ else ["prior"]


# -- test doubles, registered only inside the tests that use them (in-process runs) --------
class Boom(Estimator):
    """Fails on every identification (a method crashing on a case)."""

    name = "boom"

    def __init__(self, *, seed: int = 0):
        self.seed = seed

    def identify(self, obs: Observation):
        raise RuntimeError("boom: this method always fails")


class NoParams(Estimator):
    """Identifies nothing (like DMD) but forecasts."""

    name = "noparams"

    def __init__(self, *, seed: int = 0):
        self.seed = seed

    def identify(self, obs: Observation):
        raise NotImplementedError("noparams identifies no physical parameters.")

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        return Forecast(mean=np.full((horizon, 2), 5.0), std=np.ones((horizon, 2)))


@pytest.fixture
def doubles(monkeypatch):
    monkeypatch.setitem(methods._REGISTRY, "boom", Registration("boom", f"{__name__}:Boom", (), True))
    monkeypatch.setitem(methods._REGISTRY, "noparams",
                        Registration("noparams", f"{__name__}:NoParams", (), True))


def _values(store_path):
    """Stored results minus timings, in a canonical order, for equality checks."""
    with Store(store_path) as s:
        df = s.results()
    df = df[df.metric != "wall_s"].drop(columns=["wall_s", "error"])
    return df.sort_values(["experiment", "method", "input", "condition", "case", "n_frames",
                           "metric"]).reset_index(drop=True)


def test_grid_is_deterministic_and_covers_inputs():
    grid = build_grid(SMOKE, ["prior"], ["identification", "forecasting"], ["ball"])
    assert grid == build_grid(SMOKE, ["prior"], ["identification", "forecasting"], ["ball"])
    assert {c.input for c in grid} == {"video", "privileged"}
    assert len(grid) == 2 * 2 * 2  # 2 experiments x 2 inputs x 2 cases
    assert len({c.id for c in grid}) == len(grid)


def test_unknown_names_list_the_known_ones(tmp_path):
    with pytest.raises(ValueError, match="unknown method 'lssq'.*Did you mean 'lsq'"):
        run(scale="smoke", systems=["ball"], methods=["lssq"], run_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="unknown experiment 'forecast'.*forecasting"):
        run(scale="smoke", systems=["ball"], methods=["prior"], experiments=["forecast"], run_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="unknown scale 'smol'"):
        run(scale="smol", run_dir=tmp_path, progress=False)


def test_run_on_the_pool_then_resume_computes_nothing(tmp_path):
    first = run(scale="smoke", systems=["ball"], methods=FAST, experiments=["identification"], run_dir=tmp_path,
                workers=2, progress=False)
    n_cells = 2 * 2 * len(FAST)
    assert first["cells"] == n_cells and first["ran"] == n_cells and first["ok"] == n_cells
    with Store(tmp_path / STORE_NAME) as s:
        df = s.results()
        inv = s.invocations()
    assert df.cell_id.nunique() == n_cells
    # every cell has all its frame counts and metrics
    per_cell = df.groupby("cell_id").size()
    assert per_cell.nunique() == 1 and per_cell.iloc[0] >= len(SMOKE.lengths) * 6
    assert set(df.n_frames) == set(SMOKE.lengths)
    # the prior scores the same on both inputs; a real method beats it on average
    se = df[df.metric == "se"].groupby(["method", "input"]).value.mean()
    assert se[("prior", "video")] == pytest.approx(se[("prior", "privileged")])
    assert inv[0]["git_commit"] and "numpy" in inv[0]["versions"] and inv[0]["scale"] == "smoke"

    again = run(scale="smoke", systems=["ball"], methods=FAST, experiments=["identification"], run_dir=tmp_path,
                workers=2, progress=False)
    assert again["ran"] == 0 and again["already"] == n_cells
    with Store(tmp_path / STORE_NAME) as s:
        assert len(s.results()) == len(df)
        assert len(s.invocations()) == 2


def test_partial_runs_add_up_to_a_full_one(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    run(scale="smoke", systems=["ball"], methods=["prior"], experiments=["identification", "forecasting"], run_dir=a,
        workers=0, progress=False)
    part = run(scale="smoke", systems=["ball"], methods=["prior"], experiments=["identification", "forecasting"],
               run_dir=b, workers=0, progress=False, max_cells=3)
    assert part["ran"] == 3
    rest = run(scale="smoke", systems=["ball"], methods=["prior"], experiments=["identification", "forecasting"],
               run_dir=b, workers=0, progress=False)
    assert rest["ran"] == 8 - 3
    va, vb = _values(a / STORE_NAME), _values(b / STORE_NAME)
    assert va.drop(columns="cell_id").equals(vb.drop(columns="cell_id"))


def test_failures_and_na_are_rows_and_the_run_goes_on(tmp_path, doubles):
    out = run(scale="smoke", systems=["ball"], methods=["boom", "noparams", "prior"],
              experiments=["identification", "forecasting"], run_dir=tmp_path, workers=0,
              progress=False)
    with Store(tmp_path / STORE_NAME) as s:
        cells = s.cells().set_index("cell_id")
        df = s.results()
    boom = cells[cells.method == "boom"]
    # boom fails on every frame count of identification -> error cells with the message
    ident = boom[boom.experiment == "identification"]
    assert (ident.status == "error").all() and ident.error.str.contains("boom: this method").all()
    # Estimator.forecast's default raises NotImplementedError -> n/a
    assert (boom[boom.experiment == "forecasting"].status == "n/a").all()
    nop = cells[cells.method == "noparams"]
    assert (nop[nop.experiment == "identification"].status == "n/a").all()
    assert nop[nop.experiment == "identification"].error.str.contains("no physical").all()
    assert (nop[nop.experiment == "forecasting"].status == "ok").all()
    assert (cells[cells.method == "prior"].status == "ok").all()
    assert out["errors"] == len(ident) and out["na"] == len(boom) - len(ident) + 2 * 2
    assert set(df[df.status == "error"].metric) == {"error"}


def test_other_scale_in_the_same_run_dir_is_refused(tmp_path):
    run(scale="smoke", systems=["ball"], methods=["prior"], experiments=["identification"], run_dir=tmp_path,
        workers=0, progress=False)
    other = Scale(**{**SMOKE.__dict__, "name": "smoke2", "seed": 8})
    with pytest.raises(StoreConfigError, match="grid_config"):
        run(scale=other, methods=["prior"], experiments=["identification"], run_dir=tmp_path,
            workers=0, progress=False)


def test_context_gives_independent_estimator_copies(tmp_path):
    ctx = Context(SMOKE, tmp_path)
    a, b = ctx.estimator("prior"), ctx.estimator("prior")
    assert a is not b and a.get_params() == b.get_params()
    a.n_samples = 3
    assert ctx.estimator("prior").n_samples != 3


_KILL_SCRIPT = """
import sys
from sysid_bench.bench.runner import run
run(scale="smoke", systems=["ball"], methods=sys.argv[2].split(","), experiments=["identification", "forecasting"],
    run_dir=sys.argv[1], workers=0, progress=False)
"""


def test_killed_run_resumes_without_losses_or_duplicates(tmp_path):
    """SIGKILL a run in a subprocess mid-way, restart it, compare with an uninterrupted run."""
    meths = ",".join(FAST)
    killed, clean = tmp_path / "killed", tmp_path / "clean"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", _KILL_SCRIPT, str(killed), meths], cwd=ROOT,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    store = killed / STORE_NAME
    deadline = time.time() + 180  # imports and two cells; minutes on a loaded machine
    n_done = 0
    try:
        while time.time() < deadline and proc.poll() is None:
            if store.is_file():
                try:
                    with Store(store) as s:
                        n_done = len(s.done_cells())
                except Exception:  # the store is being created
                    n_done = 0
                if n_done >= 2:
                    break
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run finished before it could be killed"
    with Store(store) as s:
        before = s.done_cells()
    assert 2 <= len(before) < 2 * 2 * 2 * len(FAST)

    res = run(scale="smoke", systems=["ball"], methods=FAST, experiments=["identification", "forecasting"],
              run_dir=killed, workers=0, progress=False)
    assert res["already"] == len(before)
    assert res["ran"] == res["cells"] - len(before)
    run(scale="smoke", systems=["ball"], methods=FAST, experiments=["identification", "forecasting"],
        run_dir=clean, workers=0, progress=False)
    vk, vc = _values(store), _values(clean / STORE_NAME)
    assert not vk.duplicated(["experiment", "method", "input", "condition", "case", "n_frames",
                              "metric"]).any()
    assert vk.drop(columns="cell_id").equals(vc.drop(columns="cell_id"))


def test_dask_local_cluster_gives_the_same_rows_as_the_pool(tmp_path):
    import distributed
    local, dask_dir = tmp_path / "local", tmp_path / "dask"
    kw = dict(scale="smoke", systems=["ball"], methods=FAST, experiments=["identification"], progress=False)
    run(run_dir=local, workers=2, **kw)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster:
        # the address string, as `--scheduler ADDRESS` passes it
        out = run(run_dir=dask_dir, scheduler=cluster.scheduler_address, **kw)
    assert out["ok"] == out["cells"] == 2 * 2 * len(FAST)
    vl, vd = _values(local / STORE_NAME), _values(dask_dir / STORE_NAME)
    assert len(vl) and vl.equals(vd)
    with Store(dask_dir / STORE_NAME) as s:
        assert s.invocations()[0]["scheduler"]


def test_every_experiment_has_cells_for_its_methods():
    grid = build_grid(SMOKE, ["prior"], list(EXPERIMENTS))
    exps = {c.experiment for c in grid}
    # prior does not train: no sensitivity cells, and declares no online_cost: no online cells;
    # every other experiment runs it (the foreign videos' experiment only where MuJoCo imports:
    # its videos come from that engine)
    from sysid_bench.core.mujoco_scene import mujoco_available

    skipped = {"sensitivity", "online"} | ({"foreign"} if mujoco_available() is not None
                                           else set())
    assert exps == set(EXPERIMENTS) - skipped
    assert all(isinstance(c, Cell) for c in grid)


_TERM_SCRIPT = """
import sys
from sysid_bench.bench.runner import run
if __name__ == "__main__":
    run(scale="smoke", systems=["ball"], methods=sys.argv[2].split(","), experiments=["identification", "forecasting"],
        run_dir=sys.argv[1], workers=2, progress=False)
"""


def _children(pid: int) -> set[int]:
    out = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.add(int(d.name))
    return out


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find worker processes")
def test_sigterm_stops_the_workers_and_keeps_finished_cells(tmp_path):
    script = tmp_path / "term.py"
    script.write_text(_TERM_SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path / "r"), ",".join(FAST)],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    store = tmp_path / "r" / STORE_NAME
    workers: set[int] = set()
    deadline = time.time() + 60
    try:
        while time.time() < deadline and proc.poll() is None:
            workers |= _children(proc.pid)
            if store.is_file() and workers:
                try:
                    with Store(store) as s:
                        if len(s.done_cells()) >= 1:
                            break
                except Exception:
                    pass
            time.sleep(0.05)
        assert proc.poll() is None, "the run finished before it could be stopped"
        workers |= _children(proc.pid)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM
    time.sleep(0.5)
    alive = [p for p in workers if Path(f"/proc/{p}").exists()
             and "Z" not in (Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[:1])]
    assert not alive, f"worker processes left running: {alive}"
    with Store(store) as s:
        assert len(s.done_cells()) >= 1


def test_retry_errors_recomputes_failed_cells(tmp_path, doubles, monkeypatch):
    kw = dict(scale="smoke", systems=["ball"], methods=["boom"], experiments=["identification"], run_dir=tmp_path,
              workers=0, progress=False)
    first = run(**kw)
    assert first["errors"] == 4
    assert run(**kw)["ran"] == 0  # a plain resume keeps the failures
    # the method is fixed (here: made to answer the prior) and the failures are retried
    monkeypatch.setattr(Boom, "identify", lambda self, obs: prior_posterior())
    again = run(**kw, retry_errors=True)
    assert again["retried"] == 4 and again["ok"] == 4
    with Store(tmp_path / STORE_NAME) as s:
        assert set(s.cells().status) == {"ok"}


def test_cells_of_a_changed_method_are_recomputed(tmp_path, monkeypatch):
    from sysid_bench.bench import runner

    kw = dict(scale="smoke", systems=["ball"], methods=["prior"], experiments=["identification"], run_dir=tmp_path,
              workers=0, progress=False)
    assert run(**kw)["ran"] == 4
    assert run(**kw)["ran"] == 0
    real = runner.method_fingerprint
    monkeypatch.setattr(runner, "method_fingerprint",
                        lambda m: "retrained" if m == "prior" else real(m))
    again = run(**kw)  # e.g. a new checkpoint: its old cells must not be mixed with new ones
    assert again["stale"] == 4 and again["ran"] == 4
    with Store(tmp_path / STORE_NAME) as s:
        assert len(s.cells()) == 4 and s.cells().fingerprint.str.startswith("retrained:").all()
        assert s.invocations()[-1]["fingerprints"] == {"prior": "retrained"}


def test_cells_of_a_changed_experiment_are_recomputed(tmp_path, monkeypatch):
    from sysid_bench.bench import runner

    kw = dict(scale="smoke", systems=["ball"], methods=["prior"], experiments=["identification", "forecasting"],
              run_dir=tmp_path, workers=0, progress=False)
    first = run(**kw)
    real = runner.experiment_fingerprint
    monkeypatch.setattr(runner, "experiment_fingerprint",
                        lambda e: "new metric" if e == "forecasting" else real(e))
    again = run(**kw)  # only the changed experiment's cells are computed again
    n_forecasting = first["cells"] - 4
    assert again["stale"] == n_forecasting and again["ran"] == n_forecasting
    with Store(tmp_path / STORE_NAME) as s:
        c = s.cells()
        assert c[c.experiment == "forecasting"].fingerprint.str.endswith(":new metric").all()
        assert not c[c.experiment == "identification"].fingerprint.str.contains("new").any()


def test_fingerprint_covers_checkpoints_and_shared_code():
    from sysid_bench.bench.runner import experiment_fingerprint, method_fingerprint

    fp = method_fingerprint("prior")
    assert fp == method_fingerprint("prior") and len(fp) == 16
    assert method_fingerprint("lsq") != fp
    efp = experiment_fingerprint("forecasting")
    assert efp == experiment_fingerprint("forecasting") and len(efp) == 16
    assert experiment_fingerprint("identification") != efp


def test_workers_share_a_jax_compilation_cache(tmp_path, monkeypatch):
    """Spawned workers get the run's JAX compilation cache and one thread each; the parent's
    environment comes back as it was."""
    from sysid_bench.bench.runner import _single_threaded_children

    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    with _single_threaded_children(1, tmp_path / "jax_cache"):
        assert os.environ["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "jax_cache")
        assert os.environ["NUMBA_NUM_THREADS"] == "1"
    assert "JAX_COMPILATION_CACHE_DIR" not in os.environ
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", "/elsewhere")  # the user's own is kept
    with _single_threaded_children(1, tmp_path / "jax_cache"):
        assert os.environ["JAX_COMPILATION_CACHE_DIR"] == "/elsewhere"


def test_fingerprint_covers_the_shared_sources():
    """A method's fingerprint hashes the private methods modules it may run through (the
    systems' lsq runs through methods/_points.py), the systems and the physics: a change there must
    recompute its stored cells."""
    from sysid_bench.bench.fingerprint import fingerprint_files

    names = {f.as_posix().split("/sysid_bench/core/")[-1].split("/methods/")[-1]
             for f in fingerprint_files("lsq")}
    assert {"lsq.py", "_points.py", "_simulation.py", "_tracks.py"} <= names
    assert {"systems/pendulum.py", "physics.py", "simulator.py"} <= names
    files = fingerprint_files("vid2param")
    assert any(f.suffix == ".pt" for f in files) and len(files) == len(set(files))
