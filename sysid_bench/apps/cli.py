"""``sysid-bench``: one command line for everything a user runs.

Examples
--------
::

    sysid-bench list
    sysid-bench run --scale smoke --methods prior lsq --run-dir runs/try
    sysid-bench run --scale default --scheduler tcp://10.0.0.5:8786
    sysid-bench report                          # run default scale, write reports/
    sysid-bench report --from-store runs/default/results.sqlite
    sysid-bench train --help                    # a command a method ships (methods.commands())

``python -m sysid_bench`` is the same command; ``python -m sysid_bench.report`` is
``sysid-bench report``.

Adding a subcommand
-------------------
A subcommand is a module with two functions, ``add_arguments(parser)`` (its options; the shared
groups below are :data:`options`) and ``run(args) -> int`` (the exit status), and one line in
:data:`SUBCOMMANDS`::

    "identify": ("sysid_bench.apps.video", "identify a ball's physics in a video file"),

Only the chosen subcommand's module is imported, so ``sysid-bench list`` never loads torch.
A ``ValueError`` from ``run`` is printed as one ``error:`` line with exit status 2; an
``OSError`` (an output that cannot be written, a full disk, a scheduler that does not answer) as
one ``error:`` line naming the path, exit status 1. The same holds for the delegated ``train``
and ``evaluate``. Numeric options take their ranges in argparse (``_validate.arg_number``), so
an out-of-range value is refused before anything runs.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import sys
from types import SimpleNamespace

from sysid_bench.core._validate import SEED_MAX, arg_number

__all__ = ["main", "SUBCOMMANDS", "options"]


# -- the shared option groups (defined once; every subcommand picks the ones it takes) ----------
def _scale(p, default: str = "default") -> None:
    p.add_argument("--scale", default=default, help=f"smoke, default or paper (default: {default})")


def _methods(p, help: str = "default: every contender and the prior reference") -> None:
    p.add_argument("--methods", nargs="+", default=None, metavar="NAME", help=help)


def _experiments(p) -> None:
    p.add_argument("--experiments", nargs="+", default=None, metavar="NAME",
                   help="default: all five")


def _run_dir(p) -> None:
    p.add_argument("--run-dir", default=None, help="where the results store lives (default runs/<scale>)")


def _out(p, default: str | None = None, help: str | None = None) -> None:
    p.add_argument("--out", default=default,
                   help=help or f"output directory (default {default or 'chosen by the command'})")


def _seed(p, default: int = 0) -> None:
    p.add_argument("--seed", type=arg_number(0, SEED_MAX, integer=True), default=default,
                   help=f"random seed (default {default})")


def _threads(p) -> None:
    p.add_argument("--threads", type=arg_number(1, 1024, integer=True), default=1,
                   help="threads per cell (default 1: one process per core is the parallelism)")


def _scheduler(p) -> None:
    p.add_argument("--workers", type=arg_number(0, 4096, integer=True), default=None,
                   help="local processes (default: cores; 0 runs every cell in this process)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (instead of local processes)")


def _execution(p) -> None:
    """What a benchmark run takes: the run dir, workers/scheduler, threads, retries, progress."""
    _run_dir(p)
    _scheduler(p)
    _threads(p)
    p.add_argument("--retry-errors", action="store_true",
                   help="compute the stored cells that failed again (e.g. after adding a checkpoint)")
    p.add_argument("--no-progress", action="store_true")


#: the shared option groups, for subcommand modules: ``options.scale(parser)`` and so on
options = SimpleNamespace(scale=_scale, methods=_methods, experiments=_experiments,
                          run_dir=_run_dir, out=_out, seed=_seed, threads=_threads,
                          scheduler=_scheduler, execution=_execution)


# -- built-in subcommands ----------------------------------------------------------------------
def list_arguments(p) -> None:
    p.add_argument("--checkpoints", action="store_true",
                   help="the shipped checkpoints of the methods that ship some, with what each "
                        "holds (a method's describe_checkpoints()), one line each")


def _list_checkpoints() -> int:
    """Each method's shipped checkpoints, one line each (methods sharing them print once)."""
    import methods

    seen = set()
    for name in methods.available(include_reference=True):
        try:
            describe = getattr(methods.get_class(name), "describe_checkpoints", None)
        except ImportError:
            continue
        key = getattr(describe, "__func__", describe)
        if describe is None or key in seen:
            continue
        seen.add(key)
        for ckpt, line in describe().items():
            print(f"{name} {ckpt}: {line}")
    return 0


def list_run(args) -> int:
    import methods

    if getattr(args, "checkpoints", False):
        return _list_checkpoints()
    from sysid_bench.bench import EXPERIMENTS
    from sysid_bench.bench.cases import SCALES

    print("methods:")
    for name in methods.available(include_reference=True):
        try:
            spec = methods.spec(name)
            state = f"input {spec.input_kind}; {', '.join(spec.capabilities)}; cost {spec.cost}"
        except ImportError as exc:
            state = f"unavailable ({str(exc)[:100]})"
        ref = " [reference]" if name in methods.references() else ""
        print(f"  {name:10s} {state}{ref}")
    print("experiments:")
    for name, e in EXPERIMENTS.items():
        print(f"  {name:15s} {e.title}")
    print("scales:")
    for name, s in SCALES.items():
        print(f"  {name:8s} cases {s.n_cases}")
    return 0


def run_arguments(p) -> None:
    _scale(p)
    _methods(p)
    _experiments(p)
    _execution(p)
    p.add_argument("--inline", nargs="*", default=None, metavar="NAME",
                   help="methods run in a thread of this process (default: those declaring inline)")
    p.add_argument("--system", nargs="+", default=None, metavar="NAME", dest="systems",
                   help="only these systems' cells (default every registered system: "
                        "sysid_bench.core.systems.available())")


def run_run(args) -> int:
    from sysid_bench.bench.runner import run

    s = run(scale=args.scale, methods=args.methods, experiments=args.experiments,
            run_dir=args.run_dir, workers=args.workers, scheduler=args.scheduler,
            progress=not args.no_progress, inline=args.inline, threads=args.threads,
            retry_errors=args.retry_errors, systems=args.systems)
    print(f"store {s['store']}: {s['cells']} cells in the grid, {s['already']} already stored, "
          f"{s['ran']} computed ({s['ok']} ok, {s['errors']} errors, {s['na']} n/a) "
          f"in {s['wall_s']:.1f} s")
    for m, why in s["skipped_methods"].items():
        print(f"skipped {m}: {why}", file=sys.stderr)
    return 0


def _delegate_arguments(p) -> None:
    p.add_argument("argv", nargs=argparse.REMAINDER, help="the delegated command's own options")


def _delegated(entry: str):
    """``run`` of a delegated command: its ``main(argv)`` (``"module:function"``) gets the rest
    of the command line."""
    def run(args) -> int:
        module, func = entry.split(":")
        return int(getattr(importlib.import_module(module), func)(args.argv) or 0)

    return run


#: name -> (module, help). The module's ``<name>_arguments``/``<name>_run`` (built-ins, here)
#: or ``add_arguments``/``run`` (a module of its own) define the subcommand. The commands the
#: methods ship (``methods.commands()``: training, evaluation) are added to these, delegated.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "list": ("sysid_bench.apps.cli", "methods (with their declarations), experiments and scales"),
    "run": ("sysid_bench.apps.cli", "run (or resume) a benchmark into a results store"),
    "report": ("sysid_bench.apps.report", "run a scale (resuming its store) and write reports/"),
    "identify": ("sysid_bench.apps.video", "identify a ball's e, g, d, r frame by frame from a video file"),
    "intercept": ("sysid_bench.apps.intercept", "the interception task: a policy's success rate over seeded throws"),
}


def _delegated_commands() -> dict[str, tuple[str, str]]:
    """The methods' commands, ``name -> ("module:function", help)``, that no built-in shadows
    (reading them imports no method's module)."""
    import methods

    return {k: v for k, v in methods.commands().items() if k not in SUBCOMMANDS}


def _functions(name: str):
    delegated = _delegated_commands()
    if name in delegated:
        return _delegate_arguments, _delegated(delegated[name][0])
    module = importlib.import_module(SUBCOMMANDS[name][0])
    if hasattr(module, f"{name}_arguments"):  # defined here (also as ``python -m``'s __main__)
        return getattr(module, f"{name}_arguments"), getattr(module, f"{name}_run")
    return module.add_arguments, module.run


def _parser(chosen: str | None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sysid-bench",
                                description="One command line for everything a user runs.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, help) in {**SUBCOMMANDS, **_delegated_commands()}.items():
        sp = sub.add_parser(name, help=help, description=help)
        if name == chosen:  # only the chosen one's module is imported
            add, run = _functions(name)
            add(sp)
            sp.set_defaults(fn=run)
    return p


def os_error_line(exc: OSError) -> str:
    """One line for an ``OSError``: the path and the reason (``disk full`` for ENOSPC), not the
    traceback that only repeats them."""
    msg = str(exc)
    if exc.filename is not None and exc.strerror:
        target = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
        msg = f"{target}: {exc.strerror}"
    if exc.errno == errno.ENOSPC and "disk full" not in msg:
        msg = f"disk full: {msg}"
    return msg


def main(argv=None) -> int:
    """Run ``sysid-bench`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    try:
        delegated = _delegated_commands()
        if chosen in delegated:  # its own parser handles the rest, --help included
            rest = argv[argv.index(chosen) + 1:]
            return _functions(chosen)[1](SimpleNamespace(argv=rest))
        known = chosen in SUBCOMMANDS or chosen in delegated
        args = _parser(chosen if known else None).parse_args(argv)
        return args.fn(args)
    except ValueError as exc:  # unknown names, store format/config mismatch: one clear line
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unwritable --out / --run-dir, a full disk, no scheduler
        print(f"error: {os_error_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:  # Ctrl-C: one line (a run says what is stored), no traceback
        print(str(exc) or "interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
