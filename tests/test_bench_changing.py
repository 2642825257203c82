"""Experiment 3 (changing parameters): the reading states the paper's claim per Vid2Param model."""

import pandas as pd


def test_changing_reading_states_the_claim_per_vid2param_model():
    from sysid_bench.bench.changing import Changing

    def rows(method, followed):
        return [dict(method=method, condition="all", case=i, n_frames=50 * (i + 1),
                     metric="followed_e", value=float(f)) for i, f in enumerate(followed)]

    df = pd.DataFrame(rows("vid2param", [0, 0, 1, 0]) + rows("vid2param-changing", [1, 1, 1, 0])
                      + rows("lsq", [1, 0, 0, 0]))
    lines = Changing().reading(df)
    const = [ln for ln in lines if "`vid2param` " in ln][0]
    moving = [ln for ln in lines if "`vid2param-changing`" in ln][0]
    assert "25%" in const and "does not hold" in const
    assert "75%" in moving and "claim holds" in moving
    assert lines[-1].startswith("Other methods") and "lsq 25%" in lines[-1]
