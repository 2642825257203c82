"""``sysid-bench intercept``: the command line."""

from __future__ import annotations

import json

from sysid_bench.apps.intercept.results import write_results
from sysid_bench.bench.intercept.evaluation import evaluate, summarise
from sysid_bench.bench.intercept.scene import CATCH_RADIUS_MAX
from sysid_bench.core import physics
from sysid_bench.core._validate import (
    SEED_MAX,
    arg_number,
)


def _option_value(text: str):
    try:
        return json.loads(text)
    except ValueError:
        return text


def add_arguments(p):
    """The ``intercept`` options on a ``sysid-bench`` subcommand parser
    (``sysid_bench.apps.cli.SUBCOMMANDS``)."""
    p.add_argument("--policy", required=True,
                   help="oracle, random-1hz, random-2hz, react, kalman, a policy an online "
                        "method declares, or a registered method that forecasts (lsq, ...)")
    p.add_argument("--throws", type=arg_number(1, 10**6, integer=True), default=200,
                   help="number of throws (default 200)")
    p.add_argument("--seed", type=arg_number(0, SEED_MAX, integer=True), default=0,
                   help="seed of the throws (default 0)")
    p.add_argument("--out", default="runs/intercept",
                   help="output directory (default runs/intercept/; the report's interception "
                        "tables are measured by the run itself)")
    p.add_argument("--speed", type=arg_number(0, physics.V_MAX, lo_open=True, unit="m/s"),
                   default=None, help=f"effector speed limit, m/s (0 < speed <= {physics.V_MAX:g})")
    p.add_argument("--catch-radius", type=arg_number(0, CATCH_RADIUS_MAX, lo_open=True, unit="m"),
                   default=None, help=f"catch radius, m (0 < r <= {CATCH_RADIUS_MAX:g})")
    p.add_argument("--draw", type=arg_number(0, None, integer=True), default=0,
                   help="throw whose trace is kept for the figure (0 to --throws - 1)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a scene field or policy option (JSON value), e.g. every=3; repeatable")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(fn=run)
    return p


def run(args) -> int:
    """``sysid-bench intercept``: evaluate, print the rates, write the table. Returns 0."""
    import shlex
    import sys

    opts = {}
    for kv in args.option:
        if "=" not in kv:
            raise ValueError(f"--option: expected KEY=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        opts[k.strip().replace("-", "_")] = _option_value(v)
    if args.draw >= args.throws:
        raise ValueError(f"draw: expected a throw in [0, {args.throws - 1}] (--throws "
                         f"{args.throws}), got {args.draw}")
    if args.speed is not None:
        opts["speed"] = args.speed
    if args.catch_radius is not None:
        opts["catch_radius"] = args.catch_radius
    df = evaluate(args.policy, n_throws=args.throws, seed=args.seed, record=[args.draw],
                  progress=not args.no_progress, **opts)
    cmd = (f"sysid-bench intercept --policy {shlex.quote(args.policy)} --throws {args.throws} "
           f"--seed {args.seed} --draw {args.draw}"
           + (f" --speed {args.speed:g}" if args.speed is not None else "")
           + (f" --catch-radius {args.catch_radius:g}" if args.catch_radius is not None else "")
           + "".join(f" --option {shlex.quote(o)}" for o in args.option))
    csv, js = write_results(df, args.out, command=cmd)
    s = summarise(df)
    print(f"{s['policy']}: caught {s['caught']}/{s['throws']} = {100 * s['rate']:.1f}% "
          f"(95% CI {100 * s['ci95_lo']:.1f}-{100 * s['ci95_hi']:.1f}%), median miss "
          f"{s['median_miss_m']:.3f} m, control step median {s['median_step_ms']:.2f} ms "
          f"(mean {s['mean_step_ms']:.2f} ms), {s['errors']} errors")
    if s["note"]:
        print(f"note: {s['note']}")
    print(f"table: {csv}")
    if s["errors"]:
        first = df[df.error != ""].iloc[0]
        print(f"first error (throw {first.throw}): {first.error}", file=sys.stderr)
    return 0
