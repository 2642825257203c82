"""``sysid-bench identify VIDEO --system S`` on another system's H.264 clip."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from sysid_bench.apps.cli import main
from sysid_bench.core import systems
from sysid_bench.core.footage import write_video


@pytest.fixture(scope="module")
def pendulum_clip(tmp_path_factory):
    import av  # noqa: F401 (a dependency of [test]: missing fails, not skips)
    sys_ = systems.get("pendulum")
    theta = np.array([[-9.0, 1.2, 0.1, 0.05]])
    state0 = np.array([[1.0, 0.0]])
    frames = sys_.render(sys_.simulate(theta, state0, 80), theta)[0]
    path = tmp_path_factory.mktemp("clip") / "pendulum.mp4"
    write_video(path, frames)
    return path, theta[0]


def test_identify_reads_a_pendulum_clip(pendulum_clip, tmp_path, capsys):
    path, truth = pendulum_clip
    out = tmp_path / "out"
    rc = main(["identify", str(path), "--system", "pendulum", "--method", "lsq", "--every", "40",
               "--out", str(out), "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    rows = list(csv.DictReader(open(out / "estimates.csv")))
    assert len(rows) == 80
    assert {"g_mean", "L_std", "mu_mean", "check_ok", "x1_m", "y1_m"} <= set(rows[0])
    last = rows[-1]
    # g and L are what a swinging bob shows at once: within 2% after 4 s of H.264 video
    assert abs(float(last["g_mean"]) - truth[0]) < 0.02 * abs(truth[0])
    assert abs(float(last["L_mean"]) - truth[1]) < 0.02 * truth[1]
    info = json.load(open(out / "estimates.json"))
    assert info["system"] == "pendulum" and info["params"] == ["g", "L", "b", "mu"]
    assert (out / "track.png").stat().st_size > 0


def test_identify_unknown_system_says_did_you_mean(pendulum_clip, tmp_path, capsys):
    path, _ = pendulum_clip
    rc = main(["identify", str(path), "--system", "pendulm", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "Did you mean 'pendulum'" in err
    assert not (tmp_path / "o").exists()


def test_identify_holds_known_values_with_lsq(pendulum_clip, tmp_path, capsys):
    path, truth = pendulum_clip
    out = tmp_path / "out"
    rc = main(["identify", str(path), "--system", "pendulum", "--method", "lsq", "--every", "40",
               "--known", "g=-9.0", "--prior", "b=0.05:0.2", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0, err
    rows = [r for r in csv.DictReader(open(out / "estimates.csv")) if r["g_mean"] != "nan"]
    assert rows and all(float(r["g_mean"]) == -9.0 and float(r["g_std"]) == 0.0 for r in rows)
    assert all(0.05 <= float(r["b_mean"]) <= 0.2 for r in rows)
    know = json.load(open(out / "estimates.json"))["knowledge"]
    assert know["held"] and know["known"] == {"g": -9.0} and not know["note"]
    assert "g = -9 held" in err and "not yet held" not in err
