"""Train the sensitivity experiment's condition models: ``python -m methods.vid2param.conditions``.

One recipe and one budget for every condition: ``V2PConfig()`` trained from scratch with
``TrainConfig()``'s defaults (4000 steps of 32 videos x 200 frames, the first 600 on the NLL
alone: what ``python -m methods.vid2param.train --out DIR`` runs), only the training data
differ (as the benchmark's sensitivity experiment trains them; a test checks the two agree):

``noise:<level>``      the interleaved train split, labels with Gaussian noise of ``level`` x
                       the range (``noise:0`` is the control)
``extrapolation:<p>``  ``p`` drawn from the lower half of its range only
``simplified``         drag and rolling fixed at one value in training

Each condition trains in ``<out>/<name>/`` (resumable: a killed run continues where it
stopped, same batches) and is exported to ``methods/vid2param/checkpoints/sensitivity/<name>.pt``
with its card. Conditions already exported are skipped. A GPU is used when present
(``--device auto``); the checkpoints are the same format either way.

Example::

    python -m methods.vid2param.conditions --out runs/conditions            # all nine
    python -m methods.vid2param.conditions --out runs/conditions --only noise:0 simplified
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from methods.vid2param.checkpoint import (
    CONDITION_CHECKPOINTS,
    SENSITIVITY_CONDITIONS,
    condition_checkpoint,
)

__all__ = ["train_condition", "condition_data", "main", "CONDITION_STAGES"]

#: The stages fitted after each condition's network (those of the shipped condition models).
CONDITION_STAGES = (("prior_noise", {"steps": 150}),)


def condition_data(condition: str) -> tuple[str, dict]:
    """``(variant, variant_options)`` of the training data of ``condition`` (a
    ``sysid_bench.core.datasets`` variant)."""
    if condition not in SENSITIVITY_CONDITIONS:
        raise ValueError(f"condition: expected one of {SENSITIVITY_CONDITIONS}, got {condition!r}")
    kind, _, arg = condition.partition(":")
    if kind == "extrapolation":
        return "extrapolation", {"param": arg}
    if kind == "noise":
        return "noisy", {"label_noise": float(arg)}
    return "simplified", {}


def train_condition(condition: str, out, threads: int = 1, device: str = "auto",
                    progress: bool = True, max_minutes: float | None = None,
                    steps: int | None = None) -> Path | None:
    """Train (or resume) the model of ``condition`` and export it; returns the checkpoint path,
    or None when stopped early by ``max_minutes`` (resumable). ``steps``: the recipe's length
    (``TrainConfig.recipe``; default ``TrainConfig().steps``), the same for every condition."""
    from methods.vid2param.model import V2PConfig
    from methods.vid2param.train import TrainConfig, export, train

    variant, opts = condition_data(condition)
    run = Path(out) / condition_checkpoint(condition).split("/", 1)[1]
    tc = TrainConfig.recipe(steps, threads=int(threads), variant=variant, variant_options=opts)
    _, info = train(V2PConfig(), tc, out=run, device=device, progress=progress,
                    max_minutes=max_minutes)
    if not info["done"]:
        return None
    dest = CONDITION_CHECKPOINTS[condition_checkpoint(condition)]
    dest.parent.mkdir(parents=True, exist_ok=True)
    # the recipe's last phase, as the shipped condition models: the physics prior's noise
    return export(run / "state.pt", dest, stages=CONDITION_STAGES)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m methods.vid2param.conditions",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="folder of the resumable training runs")
    p.add_argument("--only", nargs="+", default=None, metavar="CONDITION",
                   help=f"conditions to train (default: all of {', '.join(SENSITIVITY_CONDITIONS)})")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="auto")
    p.add_argument("--steps", type=int, default=None,
                   help="the recipe's length for every condition (default: TrainConfig's, 4000); "
                        "its warm-up phases keep their share")
    p.add_argument("--retrain", action="store_true", help="train conditions already exported too")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop each run after this long (resumable)")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    todo = a.only or list(SENSITIVITY_CONDITIONS)
    for c in todo:
        condition_data(c)  # validate every name before any work
    for c in todo:
        dest = CONDITION_CHECKPOINTS[condition_checkpoint(c)]
        if dest.exists() and not a.retrain:
            print(f"{c}: {dest} exists, skipped")
            continue
        got = train_condition(c, a.out, a.threads, a.device, not a.no_progress, a.max_minutes,
                              a.steps)
        print(f"{c}: {got if got else 'stopped early (resumable)'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
