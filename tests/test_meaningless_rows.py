"""Issue 29's set (a) in the report: the calibration experiment's `meaningless` cells feed the
model-check table, and no answer claims precision with a passing check."""
from __future__ import annotations

import numpy as np
import pytest

from sysid_bench.bench import EXPERIMENTS
from sysid_bench.bench.calibration import (
    MEANINGLESS,
    MEANINGLESS_KINDS,
    Calibration,
    meaningless_observation,
)
from sysid_bench.bench.cases import SCALES
from sysid_bench.bench.cases import test_set as make_test_set
from sysid_bench.bench.experiment import Cell, Context


def test_cells_at_the_report_scales_only():
    exp = EXPERIMENTS["calibration"]
    default = [c for c in exp.cells(SCALES["default"], ["lsq", "prior"]) if c.condition == MEANINGLESS]
    assert sorted(c.case for c in default if c.method == "lsq") == list(range(len(MEANINGLESS_KINDS)))
    assert not [c for c in exp.cells(SCALES["smoke"], ["lsq"]) if c.condition == MEANINGLESS]


def test_observations_are_seeded_videos_of_each_kind():
    ds = make_test_set("interleaved", 2, SCALES["default"].seed)
    shape = np.asarray(ds.frames).shape[-2:]
    for k, kind in enumerate(MEANINGLESS_KINDS):
        a, truth = meaningless_observation(ds, k)
        b, _ = meaningless_observation(ds, k)
        assert a.frames.shape == (200, *shape) and np.array_equal(a.frames, b.frames), kind
        assert (truth is not None) == (kind == "outlier frame")
    white = meaningless_observation(ds, MEANINGLESS_KINDS.index("white video"))[0]
    assert (white.frames == 255).all()
    with pytest.raises(ValueError, match="k: expected"):
        meaningless_observation(ds, len(MEANINGLESS_KINDS))


def test_lsq_claims_no_precision_on_meaningless_clips_and_the_table_counts_them(tmp_path):
    import pandas as pd

    exp = EXPERIMENTS["calibration"]
    ctx = Context(SCALES["default"], tmp_path, 1)
    rows = []
    for k in range(len(MEANINGLESS_KINDS)):
        out = exp.run(Cell("calibration", "lsq", "video", MEANINGLESS, k), ctx)
        rows += [("lsq", "video", MEANINGLESS, r.case, r.n_frames, r.metric, r.value)
                 for r in out.rows]
    df = pd.DataFrame(rows, columns=["method", "input", "condition", "case", "n_frames",
                                     "metric", "value"])
    honest = df[df.metric.str.startswith("honest_")]
    assert len(honest) == 3 * len(MEANINGLESS_KINDS) and (honest.value == 1).all()
    # white and noise videos: the tracker finds no ball, lsq refuses by name
    assert set(df[df.metric == "refused"].case) == {2, 3}
    tables = Calibration().tables(df)
    tab = tables["model_check"].set_index("physics")
    assert tab.loc["meaningless", "cases"] == len(MEANINGLESS_KINDS)
    assert tab.loc["meaningless", "honest (e, g, d)"].startswith("1 ")
    # the coverage tables have no truth to hold: meaningless rows stay out of them
    assert tables["calibration"].empty


@pytest.mark.parametrize("z, honest", [(1.8, 1.0), (4.0, 0.0)])
def test_the_outlier_clip_counts_an_answer_the_outlier_moved_not_an_ordinary_miss(
        tmp_path, monkeypatch, z, honest):
    """A precise, passing answer on the outlier clip: e off by 1.8 std (a 90% interval misses
    it, as it misses one truth in ten without an outlier) is honest; off by 4 std (moved by the
    outlier) is not."""
    from sysid_bench.core.estimator import Check, Posterior

    k = MEANINGLESS_KINDS.index("outlier frame")
    ctx = Context(SCALES["default"], tmp_path, 1)
    truth = meaningless_observation(ctx.test_set("interleaved", 2), k)[1]
    std = np.array([0.01, 0.1, 0.002, 0.05])

    class Fixed:
        def identify(self, obs):
            mean = truth.copy()
            mean[0] += z * std[0]
            return Posterior(mean=mean, std=std, check=Check(0.01, 0.02, True, 400))

    monkeypatch.setattr(Context, "estimator", lambda self, method, **kw: Fixed())
    out = Calibration().run(Cell("calibration", "lsq", "video", MEANINGLESS, k), ctx)
    got = {r.metric: r.value for r in out.rows}
    assert got["honest_e"] == honest
    assert got["honest_g"] == got["honest_d"] == 1.0
