"""Section 0's figure draws when no method forecasts (a toy method alone in a smoke run failed
to render: matplotlib cannot log-scale an axis with no positive value)."""

import numpy as np
import pandas as pd

from sysid_bench.bench import systems as section0


def test_the_figure_of_methods_that_do_not_forecast(tmp_path, monkeypatch):
    last = max(section0.SYSTEM_LENGTHS)
    table = pd.DataFrame({"system": ["ball", "pendulum"], "method": ["toy", "toy"],
                          f"param_mse@{last}": [0.02, 0.05],
                          "forecast_mse@50": [np.nan, np.nan]})
    exp = section0.Systems()
    monkeypatch.setattr(exp, "summary", lambda df: table)
    figs = exp.figures(pd.DataFrame({"x": [1]}), None, tmp_path)
    (path,) = figs.values()
    assert path.is_file() and path.stat().st_size > 0
