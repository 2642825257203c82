"""Run the benchmark (or read a finished store) and write ``reports/``.

``python -m sysid_bench.report`` runs the default scale into ``runs/default/`` (resuming what is
already there) and writes:

* ``reports/REPORT.md``: provenance, one section per experiment (tables, figures, reading),
  the places where our numbers differ from the paper's claims, failures and "n/a" cells;
* ``reports/tables/*.csv`` and ``*.parquet``: every table of the report;
* ``reports/figures/*.png``;
* ``reports/results.parquet``: the long-format rows of the run (``reports/tables/summary.*``
  the headline numbers).

``--from-store PATH`` re-renders from an existing store without computing anything. This is
``sysid-bench report`` (:mod:`sysid_bench.apps.cli`), kept under the name users know.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys
from pathlib import Path

import numpy as np

from sysid_bench.core._io import atomic_write
from sysid_bench.core._markdown import markdown_table

__all__ = ["render", "markdown_table", "main", "add_arguments", "run", "store_label"]


def _write_table(df, base: Path, csv: bool = True) -> None:
    import io

    if csv:
        atomic_write(base.with_suffix(".csv"), df.to_csv(index=False))
    buf = io.BytesIO()
    df.astype({c: str for c in df.columns if df[c].dtype == object}).to_parquet(buf, index=False)
    atomic_write(base.with_suffix(".parquet"), buf.getvalue())


def _run_summary(store) -> tuple[list[str], dict]:
    """Provenance lines and the elapsed wall time of the run (all invocations)."""
    invs = store.invocations()
    cells = store.cells()
    lines = []
    elapsed = 0.0
    for inv in invs:
        mine = cells[cells.invocation == inv["id"]]
        if len(mine):
            elapsed += float(mine.finished.max()) - float(inv["started"])
    last = invs[-1] if invs else {}
    when = _dt.datetime.fromtimestamp(last.get("started", 0), _dt.UTC)
    lines.append(f"- scale `{last.get('scale')}`, {len(cells)} cells in the store "
                 f"({', '.join(f'{k}: {v}' for k, v in cells.status.value_counts().items())}), "
                 f"{len(invs)} invocation(s); computing time {elapsed:.0f} s wall "
                 "(sum over invocations, first start to last stored cell)")
    lines.append(f"- last invocation {when:%Y-%m-%d %H:%M} UTC on `{last.get('host')}` "
                 f"({last.get('cpus')} CPUs, {last.get('platform')}), Python {last.get('python')}, "
                 f"workers {last.get('workers') or 'cores'}"
                 + (f", Dask scheduler {last['scheduler']}" if last.get("scheduler") else ""))
    lines.append(f"- git commit `{last.get('git_commit')}`"
                 + (" (uncommitted changes)" if last.get("git_dirty") else ""))
    per_commit = {}
    for inv in invs:
        n = int((cells.invocation == inv["id"]).sum())
        if n:
            key = inv.get("git_commit", "?")[:10] + ("+dirty" if inv.get("git_dirty") else "")
            per_commit[key] = per_commit.get(key, 0) + n
    if len(per_commit) > 1:
        lines.append("- NOTE: cells were computed at several commits (resumed runs): "
                     + ", ".join(f"`{k}` {n} cells" for k, n in per_commit.items()))
    v = last.get("versions", {})
    if v:
        lines.append("- versions: " + ", ".join(f"{k} {v[k]}" for k in sorted(v)))
    if last.get("skipped_methods"):
        for m, why in last["skipped_methods"].items():
            lines.append(f"- method `{m}` was skipped: {why}")
    return lines, {"elapsed_s": elapsed, "last": last}


def _system_order(names) -> list[str]:
    """``names`` in the registry's order (a system no longer registered last, by name)."""
    from sysid_bench.core import systems as registry

    known = registry.available()
    names = set(names)
    return [s for s in known if s in names] + sorted(names - set(known))


def _headline_groups(system: str) -> tuple:
    from sysid_bench.core import systems as registry

    try:
        return registry.get(system).headline_groups
    except ValueError:  # a system no longer registered: the overall figure only
        return ()


def summary_table(df):
    """One row per (system, method, input): the headline number of each experiment.

    ``param MSE @ T`` is the mean over the system's parameters; a system's declared
    ``headline_groups`` add one column each (the ball: ``e, g, d`` and ``r``).

    Returns
    -------
    pandas.DataFrame
    """
    import pandas as pd

    ok = df[df.status == "ok"]
    if "system" not in ok.columns:  # rows of a single system's experiment (older callers)
        ok = ok.assign(system="ball")
    recs = []
    for system in _system_order(ok.system.unique()):
        rows = ok[ok.system == system]
        keys = sorted({(m, i) for m, i in zip(rows.method, rows.input)
                       if not str(m).startswith("_")})
        ident = rows[rows.experiment == "identification"]
        last = int(ident.n_frames.max()) if len(ident) else None
        fc = rows[(rows.experiment == "forecasting") & (rows.metric == "pos_mse")]
        fc_at = (50 if (fc.n_frames == 50).any() else
                 (int(fc.n_frames.min()) if len(fc) else None))
        ch = rows[(rows.experiment == "changing") & rows.metric.str.startswith("followed_")]
        cal = rows[(rows.experiment == "calibration") & rows.metric.str.startswith("hit90_")]
        if "condition" in cal.columns:  # our physics: perturbed cases have their own rows
            cal = cal[cal.condition.fillna("") == ""]
        for m, i in keys:
            rec = {"system": system, "method": m, "input": i}
            sel = ident[(ident.method == m) & (ident.input == i) & (ident.n_frames == last)]
            se = sel[sel.metric == "se"].value
            rec[f"param MSE @ {last}"] = se.mean() if len(se) else np.nan
            for group in _headline_groups(system):
                # means over cases as in identification_params_at_200, averaged over the group
                v = [sel[sel.metric == f"se_{p}"].value.mean() for p in group]
                rec[f"{', '.join(group)} MSE @ {last}"] = float(np.mean(v)) if len(sel) else np.nan
            w = sel[sel.metric == "wall_s"].value
            rec[f"s / identification @ {last}"] = w.median() if len(w) else np.nan
            f = fc[(fc.method == m) & (fc.input == i) & (fc.n_frames == fc_at)].value
            rec[f"forecast MSE after {fc_at}"] = f.mean() if len(f) else np.nan
            c = ch[(ch.method == m) & (ch.input == i)].value
            rec["changes followed"] = c.mean() if len(c) else np.nan
            h = cal[(cal.method == m) & (cal.input == i)].value
            rec["90% coverage"] = h.mean() if len(h) else np.nan
            if len(sel) or len(f) or len(c) or len(h):
                recs.append(rec)
    return pd.DataFrame(recs)


def _scale_sentence(scale, names) -> str:
    """Cases, per-method caps and options and the expensive tier of ``scale``, as the methods
    in the store declare them (methods no longer importable are left out)."""
    import methods

    caps, opts, expensive = {}, {}, []
    for m in names:
        try:
            spec = methods.spec(m)
        except (ValueError, ImportError):
            continue
        key = scale.key_for(spec.scale_cases)
        if key in spec.scale_cases:
            c = spec.scale_cases[key]
            caps[m] = dict(c) if hasattr(c, "items") else c
        o = spec.options(scale.key_for(spec.scale_options))
        if o:
            opts[m] = o
        if scale.thinned(m):
            expensive.append(m)
    text = (f"Cases per experiment: {json.dumps(scale.n_cases)}; per-method caps: "
            f"{json.dumps(caps) if caps else 'none'}; method options: {json.dumps(opts)}.")
    if expensive:
        text += (f" Expensive methods ({', '.join(expensive)}) are evaluated at "
                 f"{list(scale.expensive_lengths)} frames in experiment 1, every "
                 f"{scale.expensive_stride} frames in experiment 3 and at "
                 f"{max(scale.calibration_lengths)} frames in experiment 5.")
    return text


def _page_job(store_path, system: str, exps, df, out: Path) -> tuple[list[str], list[str]]:
    """:func:`_system_page` in a worker process: its own connection to the store (artifacts)."""
    from sysid_bench.bench.store import Store

    store = Store(store_path)
    try:
        return _system_page(system, exps, df, store, out)
    finally:
        store.close()


def _pages(store_path, names, exps, df, out: Path, workers: int | None):
    """The system pages, in processes side by side (matplotlib draws one figure at a time per
    process; a page's figures are most of the report's rendering time). Yields ``(system,
    lines, readings)`` in the order of ``names``; the same bytes as one after the other."""
    import multiprocessing as mp
    import os
    from concurrent.futures import ProcessPoolExecutor

    n = min(len(names), workers if workers is not None else (os.cpu_count() or 1))
    if n <= 1:
        for system in names:
            yield (system, *_page_job(store_path, system, exps, df[df.system == system], out))
        return
    with ProcessPoolExecutor(n, mp_context=mp.get_context("spawn")) as pool:
        futs = [pool.submit(_page_job, store_path, system, exps, df[df.system == system], out)
                for system in names]
        for system, f in zip(names, futs):
            yield (system, *f.result())


def render(store_path, out_dir="reports", experiments=None, title: str | None = None,
           workers: int | None = None) -> Path:
    """Write the report of the store at ``store_path`` into ``out_dir``.

    ``workers``: processes drawing the system pages side by side (None: one per core; 1: in
    this process).

    Returns
    -------
    Path
        ``out_dir / "REPORT.md"``.
    """
    from sysid_bench.bench import EXPERIMENTS
    from sysid_bench.bench.cases import SCALES
    from sysid_bench.bench.runner import resolve_experiments
    from sysid_bench.bench.store import Store

    exps = resolve_experiments(experiments)
    out = Path(out_dir)
    figdir, tabdir = out / "figures", out / "tables"
    store = Store(store_path)
    try:
        df = store.results()
        prov, info = _run_summary(store)
        scale = SCALES.get(info["last"].get("scale", ""))
        md = [f"# {title or 'sysid-bench report'}", ""]
        md += ["Generated by `python -m sysid_bench.report` from the results store "
               f"`{store_label(store_path)}`; every number below is computed from that store "
               "(`--from-store` re-renders it). Methods see the same seeded test cases. "
               "Intervals are 95% bootstrap CIs over cases.", ""]
        md += ["## Run", "", *prov, ""]
        sc_name = info["last"].get("scale", "default")
        md += ["Reproduce: `python -m sysid_bench.report" + ("" if sc_name == "default" else
               f" --scale {sc_name}") + "` (or `sysid-bench report`, `tox -e bench`); a killed "
               "run resumes where it stopped; `python -m sysid_bench.report --from-store "
               f"{store_label(store_path)}` re-renders this file without computing.", ""]
        if scale is not None:
            md += [_scale_sentence(scale, sorted(df.method.unique()) if len(df) else []), ""]
        # the whole long-format run, for anyone's analysis (Parquet only: compressed)
        _write_table(df, out / "results", csv=False)
        head = summary_table(df)
        if len(head):
            _write_table(head, tabdir / "summary")
            md += ["## Summary", "",
                   "Means over the cases of each experiment (details, case counts and confidence "
                   "intervals in the sections below); `-`: not run or not applicable.", "",
                   markdown_table(head, floatfmt=".3g"), ""]
        from sysid_bench.core import systems as registry

        readings = []
        cross = [n for n in exps if EXPERIMENTS[n].cross_system]
        per_system = [n for n in exps if not EXPERIMENTS[n].cross_system]
        for name in cross:  # the comparison across systems, at the top
            md += _section(EXPERIMENTS[name], df[df.experiment == name], store, out, tabdir,
                           figdir, readings)
        names = _system_order(df[df.experiment.isin(per_system)].system.unique()
                              if len(df) else [])
        if names:
            md += ["## Systems", "",
                   "One page per system, with every experiment that ran on it:", ""]
        for system, page, mine in _pages(store_path, names, per_system, df, out, workers):
            atomic_write(out / f"{system}.md", "\n".join(page))
            try:
                paper = registry.get(system).paper
            except ValueError:
                paper = ""
            if paper:  # this system's readings are the comparisons with its paper
                readings += mine
            n_ok = int((df[(df.system == system) & df.experiment.isin(per_system)]
                        .drop_duplicates("cell_id").status == "ok").sum())
            md += [f"- [{system}]({system}.md): {n_ok} cells"
                   + (f"; the system of {paper}, whose claims the readings check" if paper
                      else "")]
        if names:
            md.append("")
        md += ["## Where our figures differ from the paper (and where they agree)", ""]
        md += [f"- {s}" for s in readings] or ["_Nothing to compare yet._"]
        md.append("")
        path = out / "REPORT.md"
        atomic_write(path, "\n".join(md))
        return path
    finally:
        store.close()


def _section(e, sub, store, out: Path, tabdir: Path, figdir: Path, readings: list,
             level: str = "##", label: str = "") -> list[str]:
    """One experiment's section (tables, figures, reading, failures) from its rows ``sub``."""
    md = [f"{level} {e.title}", "", e.description, ""]
    ok = sub[sub.status == "ok"]
    if ok.empty:
        bad_only = sub.drop_duplicates("cell_id") if len(sub) else sub
        if len(bad_only):
            md += ["_No results: every cell failed or does not apply (below)._", ""]
        else:
            return md + ["_No results in the store for this experiment._", ""]
    else:
        for tname, t in e.tables(ok).items():
            _write_table(t, tabdir / tname)
            rel = (tabdir / tname).relative_to(out).as_posix()
            md += [f"**{tname}** (`{rel}.csv`)", "", markdown_table(t), ""]
        for caption, path in e.figures(ok, store, figdir).items():
            md += [f"![{caption}]({Path(path).relative_to(out).as_posix()})", "",
                   f"*{caption}*", ""]
        r = e.reading(ok)
        if r:
            md += ["Reading:", "", *[f"- {s}" for s in r], ""]
            where = f"{label}, " if label else ""
            readings += [f"({where}{e.title.split('.')[0]}) {s}" for s in r]
    bad = sub[(sub.status != "ok") | (sub.metric == "failed")]
    if len(bad):
        bad = bad.assign(status=np.where(bad.status == "ok", "partly failed", bad.status))
        g = (bad.groupby(["method", "input", "status"])
             .agg(cells=("cell_id", "nunique"), first_message=("error", "first"))
             .reset_index())
        g["first_message"] = g.first_message.str.slice(0, 160)
        md += ["Cells that failed, failed at some frame counts (`partly failed`: the "
               "other frame counts are in the tables) or do not apply (`n/a`: the method "
               "raised NotImplementedError):", "", markdown_table(g), ""]
    return md


def _system_page(system: str, exps, df, store, out: Path) -> tuple[list[str], list[str]]:
    """The page of ``system``: every experiment that ran on it, its own tables and figures
    (``tables/<system>/``, ``figures/<system>/``). Returns the page's lines and its readings."""
    from sysid_bench.bench import EXPERIMENTS

    md = [f"# {system}: every experiment", "",
          f"Part of the [report](REPORT.md): the rows of the `{system}` system, every figure with "
          "its 95% CI over cases.", ""]
    readings: list[str] = []
    for name in exps:
        e = EXPERIMENTS[name]
        if not e.runs_on(system) and not (df.experiment == name).any():
            continue
        md += _section(e, df[df.experiment == name], store, out, out / "tables" / system,
                       out / "figures" / system, readings, label=system)
    return md, readings


def store_label(store_path) -> str:
    """How the report names its store: relative to the current folder when it lies inside it
    (``runs/default/results.sqlite``), otherwise its run directory's name and file name; never
    a machine's absolute path."""
    p = Path(store_path)
    try:
        return p.resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return f"{p.resolve().parent.name}/{p.name}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``sysid-bench report`` (the shared groups of :mod:`sysid_bench.apps.cli`)."""
    from sysid_bench.apps.cli import options

    options.scale(p)
    p.add_argument("--from-store", default=None, metavar="PATH",
                   help="re-render the report of this results store; computes nothing")
    options.out(p, "reports")
    options.methods(p)
    options.experiments(p)
    options.execution(p)


def report_command(args) -> int:
    from sysid_bench.bench.runner import STORE_NAME, resolve_experiments
    from sysid_bench.bench.runner import run as run_grid

    if args.from_store:
        store = Path(args.from_store)
        if store.is_dir():
            store = store / STORE_NAME
        if not store.is_file():
            raise SystemExit(f"--from-store: no results store at {str(args.from_store)!r}")
        resolve_experiments(args.experiments)
    else:
        summary = run_grid(scale=args.scale, methods=args.methods, experiments=args.experiments,
                           run_dir=args.run_dir, workers=args.workers, scheduler=args.scheduler,
                           progress=not args.no_progress, retry_errors=args.retry_errors,
                           threads=getattr(args, "threads", 1))
        print(f"{summary['ran']} cells computed ({summary['errors']} errors, {summary['na']} n/a), "
              f"{summary['already']} already stored, {summary['wall_s']:.0f} s", file=sys.stderr)
        store = summary["store"]
    workers = getattr(args, "workers", None)
    path = render(store, args.out, experiments=args.experiments,
                  workers=1 if workers == 0 else workers)
    print(path)
    return 0


#: ``sysid-bench report`` runs this
run = report_command


def main(argv=None) -> int:
    """``python -m sysid_bench.report ARGS``: the same as ``sysid-bench report ARGS``."""
    from sysid_bench.apps.cli import main as cli_main

    return cli_main(["report", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
