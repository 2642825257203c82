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
