"""The online-cost table (sysid_bench.bench.online) on a short video: structure and bad input."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from methods.vid2param import SHIPPED_CHECKPOINT  # noqa: E402
from sysid_bench.bench.online import online_cost, online_cost_markdown  # noqa: E402


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
