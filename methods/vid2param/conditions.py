"""Train the sensitivity experiment's condition models: ``python -m methods.vid2param.conditions``.

One recipe and one budget for every condition of a system; only the training data differ (as
the benchmark's sensitivity experiment trains them; a test checks the two agree):

``noise:<level>``      the interleaved train split, labels with Gaussian noise of ``level`` x
                       the range (``noise:0`` is the control)
``extrapolation:<p>``  ``p`` drawn from the lower half of its range only
``simplified``         the system's ``simplified_params`` (the ball's drag and rolling) fixed at
                       one value in training

The ball (``--system ball``, the default): ``V2PConfig()`` trained from scratch with
``TrainConfig()``'s defaults (4000 steps of 32 videos x 200 frames, the first 600 on the NLL
alone: what ``python -m methods.vid2param.train --out DIR`` runs). Another system: its preset's
network and its points curriculum (``presets``: the recurrence learns from the tracked points'
noisy true positions, no frame) for :data:`SYSTEM_CONDITION_TRAIN`'s budget, then its preset's
stages.

Each condition trains in ``<out>/[<system>/]<name>/`` (resumable: a killed run continues where
it stopped, same batches) and is exported to
``methods/vid2param/checkpoints/sensitivity/[<system>/]<name>.pt`` with its card. Conditions
already exported are skipped. A GPU is used when present (``--device auto``); the checkpoints
are the same format either way.

Example::

    python -m methods.vid2param.conditions --out runs/conditions            # the ball's nine
    python -m methods.vid2param.conditions --out runs/conditions --only noise:0 simplified
    python -m methods.vid2param.conditions --system pendulum --out runs/conditions
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from methods.vid2param.checkpoint import (
    SENSITIVITY_CONDITIONS,
    condition_checkpoint,
    condition_path,
    system_conditions,
)

__all__ = ["train_condition", "condition_data", "main", "CONDITION_STAGES",
           "SYSTEM_CONDITION_TRAIN", "conditions_of"]

#: The stages fitted after each of the ball's condition networks (those of its shipped
#: condition models).
CONDITION_STAGES = (("prior_noise", {"steps": 150}),)

#: Every other system's condition recipe (``TrainConfig`` fields over its preset's): the points
#: curriculum alone, 800 steps of 64 trajectories of 100 frames (51,200 trajectories; the
#: shipped system models saw 32,000-64,000 of 200 frames), ~0.2 s a step on one core, ~3 min a
#: condition. 100 frames: the experiment tests at up to 50. Validated once, at the end.
SYSTEM_CONDITION_TRAIN = {"steps": 800, "points_steps": 800, "nll_only_steps": 800,
                          "batch": 64, "n_frames": 100, "val_every": 800, "val_n": 100}


def conditions_of(system: str = "ball") -> tuple[str, ...]:
    """The conditions of ``system`` (``system_conditions``; the ball's are
    :data:`SENSITIVITY_CONDITIONS`, a test checks the two agree)."""
    return system_conditions(system)


def condition_data(condition: str, system: str = "ball") -> tuple[str, dict]:
    """``(variant, variant_options)`` of the training data of ``condition`` (a
    ``sysid_bench.core.datasets`` variant for the ball, ``System.sample_variant``'s otherwise)."""
    known = conditions_of(system)
    if condition not in known:
        raise ValueError(f"condition: expected one of {known} ({system}), got {condition!r}")
    kind, _, arg = condition.partition(":")
    if kind == "extrapolation":
        return "extrapolation", {"param": arg}
    if kind == "noise":
        return "noisy", {"label_noise": float(arg)}
    return "simplified", {}


def train_condition(condition: str, out, threads: int = 1, device: str = "auto",
                    progress: bool = True, max_minutes: float | None = None,
                    steps: int | None = None, system: str = "ball") -> Path | None:
    """Train (or resume) the model of ``condition`` of ``system`` and export it; returns the
    checkpoint path, or None when stopped early by ``max_minutes`` (resumable). ``steps``: the
    recipe's length (the ball's ``TrainConfig.recipe``, default ``TrainConfig().steps``; another
    system's :data:`SYSTEM_CONDITION_TRAIN`), the same for every condition."""
    import copy

    from methods.vid2param import presets
    from methods.vid2param.model import V2PConfig
    from methods.vid2param.train import TrainConfig, export, train

    variant, opts = condition_data(condition, system)
    run = Path(out) / condition_checkpoint(condition, system).split("/", 1)[1]
    if system == "ball":
        mc = V2PConfig()
        tc = TrainConfig.recipe(steps, threads=int(threads), variant=variant,
                                variant_options=opts)
        stages = CONDITION_STAGES
    else:
        p = presets.get(system)
        mc = V2PConfig.preset(system)
        rec = {**copy.deepcopy(dict(p.train)), **SYSTEM_CONDITION_TRAIN}
        if steps is not None:
            rec.update(steps=int(steps), points_steps=int(steps), nll_only_steps=int(steps),
                       val_every=int(steps))
        rec.update(size=tuple(mc.frame_size), threads=int(threads), variant=variant,
                   variant_options=opts)
        tc = TrainConfig(**rec)
        stages = p.stages
    _, info = train(mc, tc, out=run, device=device, progress=progress, max_minutes=max_minutes)
    if not info["done"]:
        return None
    dest = condition_path(condition, system)
    dest.parent.mkdir(parents=True, exist_ok=True)
    # the recipe's last phase, as the shipped models of the system
    return export(run / "state.pt", dest, stages=stages)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m methods.vid2param.conditions",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="folder of the resumable training runs")
    p.add_argument("--system", default="ball",
                   help="the system whose condition models to train (default: the ball)")
    p.add_argument("--only", nargs="+", default=None, metavar="CONDITION",
                   help="conditions to train (default: all of the system's; the ball's are "
                        f"{', '.join(SENSITIVITY_CONDITIONS)})")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="auto")
    p.add_argument("--steps", type=int, default=None,
                   help="the recipe's length for every condition (default: the ball's "
                        "TrainConfig's, 4000; another system's 800); the ball's warm-up phases "
                        "keep their share")
    p.add_argument("--retrain", action="store_true", help="train conditions already exported too")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop each run after this long (resumable)")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    try:
        todo = a.only or list(conditions_of(a.system))
        for c in todo:
            condition_data(c, a.system)  # validate every name before any work
    except ValueError as e:
        p.error(str(e))
    for c in todo:
        dest = condition_path(c, a.system)
        if dest.exists() and not a.retrain:
            print(f"{c}: {dest} exists, skipped")
            continue
        got = train_condition(c, a.out, a.threads, a.device, not a.no_progress, a.max_minutes,
                              a.steps, a.system)
        print(f"{c}: {got if got else 'stopped early (resumable)'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
