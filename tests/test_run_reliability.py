"""A run's processes and its run dir under abuse (issue 14): SIGKILL, two runs at once."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
        "PYTHONPATH": str(ROOT)}


def _workers(ppid: int) -> list[int]:
    """Spawned multiprocessing workers whose parent is ``ppid`` (from /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes()
        except OSError:
            continue
        parent = int(stat.rsplit(")", 1)[1].split()[1])
        if parent == ppid and b"spawn_main" in cmd:
            out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigkilled_run_takes_its_workers_with_it(tmp_path):
    """Workers of a run killed with SIGKILL used to live on, orphaned and computing."""
    cmd = [sys.executable, "-m", "sysid_bench.apps.cli", "run", "--scale", "smoke", "--methods", "nuts",
           "emcee", "--experiments", "calibration", "--workers", "2", "--run-dir",
           str(tmp_path / "r"), "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    seen: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            seen = _workers(proc.pid)
            if len(seen) >= 2:
                break
            time.sleep(0.2)
        assert seen, "the run started no workers"
        time.sleep(3.0)  # let them import and start computing their cells
        seen = sorted(set(seen) | set(_workers(proc.pid)))
        assert proc.poll() is None, "the run ended before it could be killed"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and any(_alive(p) for p in seen):
            time.sleep(0.1)
        left = [p for p in seen if _alive(p)]
        assert not left, f"workers {left} outlived their killed parent"
    finally:
        if proc.poll() is None:
            proc.kill()
        for p in seen:  # never leave orphans behind, even when the test fails
            if _alive(p):
                os.kill(p, signal.SIGKILL)


_HOLD_LOCK = """
import sys, time
from sysid_bench.bench.store import lock_run_dir
with lock_run_dir(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(600)
"""


def _hold_lock(run_dir) -> subprocess.Popen:
    """A process holding ``run_dir``'s lock (as a running ``sysid-bench run`` does)."""
    proc = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(run_dir)], cwd=ROOT, env=_ENV,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_second_run_on_a_busy_run_dir_is_refused_and_writes_nothing(tmp_path, capsys):
    from sysid_bench.apps.cli import main
    from sysid_bench.bench.runner import STORE_NAME, run
    from sysid_bench.bench.store import RunDirBusyError, Store

    args = dict(scale="smoke", methods=["prior"], experiments=["identification"],
                run_dir=tmp_path, workers=0, progress=False)
    run(**args)
    with Store(tmp_path / STORE_NAME) as s:
        before = (len(s.results()), len(s.invocations()))
    holder = _hold_lock(tmp_path)
    try:
        with pytest.raises(RunDirBusyError, match=f"run_dir: .*in use by another run \\(pid {holder.pid}"):
            run(**args)
        rc = main(["run", "--scale", "smoke", "--methods", "prior", "--experiments",
                   "identification", "--run-dir", str(tmp_path), "--workers", "0", "--no-progress"])
        assert rc == 2
        err = capsys.readouterr().err
        assert "in use by another run" in err and str(holder.pid) in err
    finally:
        holder.kill()
        holder.wait()
    with Store(tmp_path / STORE_NAME) as s:  # the refused runs recorded nothing
        assert (len(s.results()), len(s.invocations())) == before


def test_lock_of_a_killed_run_does_not_block_the_next(tmp_path):
    from sysid_bench.bench.runner import run

    holder = _hold_lock(tmp_path)
    holder.send_signal(signal.SIGKILL)  # dies holding it: the kernel drops an flock with its fds
    holder.wait()
    assert (tmp_path / "run.lock").exists()
    out = run(scale="smoke", systems=["ball"], methods=["prior"], experiments=["identification"], run_dir=tmp_path,
              workers=0, progress=False)
    assert out["ok"] == out["cells"] > 0


def test_lock_is_released_when_a_run_ends_and_taken_by_a_run(tmp_path):
    from sysid_bench.bench.store import RunDirBusyError, lock_run_dir

    with lock_run_dir(tmp_path):
        with pytest.raises(RunDirBusyError, match="run_dir"):  # a second open file conflicts
            with lock_run_dir(tmp_path):
                pass
    with lock_run_dir(tmp_path):  # released on exit
        pass


# -- Ctrl-C (issue 37, bad-input-turn4: a traceback per process, "leaked semaphore" warnings) --
def test_processes_a_run_starts_ignore_ctrl_c():
    """Ctrl-C reaches every process of the terminal's group; the workers must leave it to the
    run, which stops them and says in one line what is stored."""
    from sysid_bench.bench.runner import _children_ignore_sigint

    probe = [sys.executable, "-c", "import signal; print(signal.getsignal(signal.SIGINT) == signal.SIG_IGN)"]
    # a known start: a shell that runs the tests in the background (CI, nohup ... &) hands them
    # SIGINT already ignored, which every child would inherit
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with _children_ignore_sigint():
            inside = subprocess.run(probe, capture_output=True, text=True, timeout=60).stdout
        outside = subprocess.run(probe, capture_output=True, text=True, timeout=60).stdout
        assert (inside.strip(), outside.strip()) == ("True", "False")
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, before)


def test_an_interrupted_run_is_one_line_saying_how_to_resume(tmp_path, monkeypatch, capsys):
    from sysid_bench.apps.cli import main
    from sysid_bench.bench import runner

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "_run_local", interrupted)
    rc = main(["run", "--scale", "smoke", "--methods", "prior", "--experiments", "identification",
               "--run-dir", str(tmp_path / "r"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 130
    assert len(err) == 1 and err[0].startswith("interrupted:") and "resume" in err[0], err


@pytest.mark.slow
def test_ctrl_c_of_a_run_is_one_line_and_the_same_command_resumes(tmp_path):
    """SIGINT to the whole process group (as a terminal's Ctrl-C) while workers compute."""
    cmd = [sys.executable, "-m", "sysid_bench", "run", "--scale", "smoke", "--methods", "prior",
           "lsq", "--experiments", "identification", "forecasting", "--run-dir",
           str(tmp_path / "r"), "--workers", "2", "--no-progress"]
    p = subprocess.Popen(cmd, cwd=ROOT, env=_ENV, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    store = tmp_path / "r" / "results.sqlite"
    t0 = time.time()
    while time.time() - t0 < 120 and not (store.is_file() and _workers(p.pid)):
        time.sleep(0.5)
    time.sleep(3)
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=60)
    if p.returncode == 0:
        pytest.skip("the run finished before the interrupt")
    assert p.returncode == 130, err
    assert err.strip().splitlines() == [ln for ln in err.strip().splitlines()
                                        if ln.startswith("interrupted:")], err
    again = subprocess.run(cmd, cwd=ROOT, env=_ENV, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
