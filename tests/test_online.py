"""The online-cost table (sysid_bench.bench.online) on a short video: structure and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from methods.vid2param import SHIPPED_CHECKPOINT
from sysid_bench.bench.online import online_cost, online_cost_markdown


@pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")
def test_online_cost_table_short_video():
    df = online_cost(["vid2param", "lsq", "dmd"], n_videos=1, seed=3, n_frames=12,
                     options={"lsq": {"n_samples": 100}})
    rows = df.set_index("method")
    assert list(df["method"]) == ["vid2param", "vid2param+samples", "lsq", "dmd"]
    assert rows.loc["vid2param", "posteriors"] == 12 and rows.loc["vid2param", "ratio"] == 1.0
    assert rows.loc["lsq", "first_frame"] == 3 and rows.loc["lsq", "posteriors"] == 10
    assert rows.loc["lsq", "mode"] == "every prefix" and rows.loc["lsq", "status"] == "ok"
    assert np.isfinite(rows.loc["lsq", ["total_s", "cpu_s", "per_frame_s", "ratio"]]
                       .astype(float)).all()
    assert rows.loc["dmd", "status"].startswith("n/a") and np.isnan(rows.loc["dmd", "total_s"])
    md = online_cost_markdown(df)
    assert "| lsq | every prefix | 3 | 10 |" in md and "| dmd |" in md
    assert "12-frame video" in md


def test_online_cost_bad_input():
    with pytest.raises(ValueError, match="methods"):
        online_cost(["no-such-method"])
    with pytest.raises(ValueError, match="methods"):
        online_cost([])
    with pytest.raises(ValueError, match="n_videos"):
        online_cost(["lsq"], n_videos=0)


def test_online_cost_prefix_stride_interpolates(monkeypatch):
    """A stride times fewer prefixes; the estimate counts every prefix and sums interpolated
    per-prefix times (a method whose cost is linear in the prefix is estimated exactly)."""
    from sysid_bench.bench import online

    now = [0.0]
    calls = []

    class Linear:
        def identify(self, obs):  # "takes" n ms for n frames
            calls.append(len(obs.frames))
            now[0] += len(obs.frames) * 1e-3

    monkeypatch.setattr(online, "_clock", lambda: (now[0], now[0]))
    from sysid_bench.core.estimator import Observation

    obs = Observation(frames=np.zeros((50, 8, 8), np.uint8))
    n, wall, cpu = online._run_batch(Linear(), obs, 3, 10)
    assert n == 48 and calls == [3, 13, 23, 33, 43, 50]
    assert wall == pytest.approx(sum(range(3, 51)) * 1e-3) and cpu == pytest.approx(wall)
    assert online._timed_prefixes(3, 50, 1) == list(range(3, 51))
    with pytest.raises(ValueError, match="prefix_stride"):
        online_cost(["lsq"], prefix_stride=0)


def test_online_is_an_experiment_of_the_runner_on_every_system(tmp_path, monkeypatch):
    """Section 7 runs through the runner and the store like the others (issue 37): rows per
    system, the stream's cells and its samples-drawn twin; n/a where the method has no model
    (every system has one since session 23: the collision's is taken away here)."""
    from methods.vid2param._points import SYSTEM_CHECKPOINTS
    from sysid_bench.bench.online import Online

    monkeypatch.setitem(SYSTEM_CHECKPOINTS, "collision", tmp_path / "no_model.pt")
    from sysid_bench.bench.runner import run
    from sysid_bench.bench.store import Store

    out = run(scale="smoke", methods=["vid2param"], experiments=["online"],
              systems=["ball", "collision"], run_dir=tmp_path, workers=0, progress=False)
    assert out["errors"] == 0 and out["ok"] == 2 and out["na"] == 2
    with Store(tmp_path / "results.sqlite") as s:
        df = s.results("online")
    ok = df[df.status == "ok"]
    assert set(ok.system) == {"ball"} and set(ok.condition) == {"", "samples"}
    assert (ok[ok.metric == "posteriors"].value == 60).all()  # a posterior after each frame
    t = Online().tables(ok)["online_cost"]
    # rows are ordered by their measured totals: the stream and its samples-drawn twin are
    # within timing noise of each other, so the test reads them by name
    assert sorted(t.method) == ["vid2param", "vid2param+samples"]
    assert t.set_index("method").loc["vid2param", "x stream"] == 1.0
