"""``sysid-bench``: run the benchmark, render its report, list what there is.

Examples
--------
::

    sysid-bench list
    sysid-bench run --scale smoke --methods prior lsq --run-dir runs/try
    sysid-bench run --scale default --scheduler tcp://10.0.0.5:8786
    sysid-bench report                          # run default scale, write reports/
    sysid-bench report --from-store runs/default/results.sqlite
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["main"]


def _cmd_list(args) -> int:
    import methods
    from sysid_bench.bench import EXPERIMENTS
    from sysid_bench.bench.cases import SCALES

    print("methods:")
    for name in methods.available(include_reference=True):
        try:
            cls = methods.get_class(name)
            state = f"input {getattr(cls, 'input_kind', '?')}"
        except ImportError as exc:
            state = f"unavailable ({str(exc)[:100]})"
        ref = " [reference]" if name not in methods.available() else ""
        print(f"  {name:10s} {state}{ref}")
    print("experiments:")
    for name, e in EXPERIMENTS.items():
        print(f"  {name:15s} {e.title}")
    print("scales:")
    for name, s in SCALES.items():
        print(f"  {name:8s} cases {s.n_cases}, caps {s.method_cases or '-'}")
    return 0


def _cmd_run(args) -> int:
    from sysid_bench.bench.runner import DEFAULT_INLINE, run

    s = run(scale=args.scale, methods=args.methods, experiments=args.experiments,
            run_dir=args.run_dir, workers=args.workers, scheduler=args.scheduler,
            progress=not args.no_progress,
            inline=DEFAULT_INLINE if args.inline is None else args.inline,
            retry_errors=args.retry_errors)
    print(f"store {s['store']}: {s['cells']} cells in the grid, {s['already']} already stored, "
          f"{s['ran']} computed ({s['ok']} ok, {s['errors']} errors, {s['na']} n/a) "
          f"in {s['wall_s']:.1f} s")
    for m, why in s["skipped_methods"].items():
        print(f"skipped {m}: {why}", file=sys.stderr)
    return 0


def _cmd_report(args) -> int:
    from sysid_bench.report import report_command

    return report_command(args)


def _parser() -> argparse.ArgumentParser:
    from sysid_bench.report import _parser as report_parser

    p = argparse.ArgumentParser(prog="sysid-bench", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="methods, experiments and scales").set_defaults(fn=_cmd_list)

    r = sub.add_parser("run", help="run (or resume) a benchmark into a results store")
    r.add_argument("--scale", default="default", help="smoke, default or paper")
    r.add_argument("--run-dir", default=None, help="default runs/<scale>")
    r.add_argument("--methods", nargs="+", default=None)
    r.add_argument("--experiments", nargs="+", default=None)
    r.add_argument("--workers", type=int, default=None, help="local processes (default: cores)")
    r.add_argument("--scheduler", default=None, help="Dask scheduler address")
    r.add_argument("--inline", nargs="*", default=None,
                   help="methods run in a thread of this process (default: prior vid2param)")
    r.add_argument("--retry-errors", action="store_true",
                   help="compute the stored cells that failed again")
    r.add_argument("--no-progress", action="store_true")
    r.set_defaults(fn=_cmd_run)

    rep = sub.add_parser("report", help="run the default scale and write reports/",
                         parents=[report_parser()], add_help=False)
    rep.set_defaults(fn=_cmd_report)
    from sysid_bench.intercept import add_intercept_parser

    add_intercept_parser(sub)
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        return args.fn(args)
    except ValueError as exc:  # unknown names, store format/config mismatch
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
