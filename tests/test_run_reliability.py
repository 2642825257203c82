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
    cmd = [sys.executable, "-m", "sysid_bench.cli", "run", "--scale", "smoke", "--methods", "nuts",
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
