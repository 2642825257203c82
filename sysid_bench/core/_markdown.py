"""Markdown tables, shared by the report and the sections other commands add to it.

It sits below both (the report imports the interception section, which writes tables too), so
neither has to import the other for it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["markdown_table"]


def markdown_table(df, index: bool = False, floatfmt: str = ".4g") -> str:
    """A GitHub-flavoured markdown table of ``df`` (no tabulate dependency).

    Parameters
    ----------
    df : pandas.DataFrame
    index : bool
        Include the index as the first column(s).
    floatfmt : str
        Format spec of float cells.
    """
    if index:
        df = df.reset_index()
    cols = [str(c) for c in df.columns]

    def cell(v) -> str:
        if isinstance(v, (float, np.floating)):
            return "-" if not np.isfinite(v) else format(float(v), floatfmt)
        s = "" if v is None else str(v)
        return s.replace("|", "\\|").replace("\n", " ")

    rows = [[cell(v) for v in r] for r in df.itertuples(index=False, name=None)]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)
