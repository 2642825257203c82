"""The interception results on disk (``sysid-bench intercept --out``)."""

from __future__ import annotations

import json
from pathlib import Path

from sysid_bench.bench.intercept.evaluation import summarise
from sysid_bench.bench.intercept.figure import slug as _slug
from sysid_bench.bench.intercept.figure import thin_trace
from sysid_bench.core._io import atomic_write


def write_results(df, out_dir, command: str = "", extra: dict | None = None) -> tuple[Path, Path]:
    """Write an :func:`evaluate` table and its summary (with the scene and traces).

    Files: ``out_dir/tables/intercept_<policy>.csv`` (one row per throw) and
    ``out_dir/tables/intercept_<policy>.json`` (summary, scene, seed, command, traces and the
    keys of ``extra``), both written atomically. Returns their paths.
    """
    tab = Path(out_dir) / "tables"
    base = tab / f"intercept_{_slug(df.attrs.get('policy', 'policy'))}"
    csv, js = base.with_suffix(".csv"), base.with_suffix(".json")
    atomic_write(csv, df.to_csv(index=False))
    meta = {"summary": summarise(df), "scene": df.attrs.get("scene"), "command": command,
            "traces": {str(k): thin_trace(v) for k, v in df.attrs.get("traces", {}).items()},
            **(extra or {})}
    atomic_write(js, json.dumps(meta, default=float))
    return csv, js
