"""Changes followed and mean normalised SE of vid2param-changing with a given checkpoint, on the
default scale's changing-experiment videos (what the report's section 3 computes).

    python scripts/eval_changing.py shipped | CHECKPOINT
"""
import sys

import numpy as np

from sysid_bench.bench import EXPERIMENTS
from sysid_bench.bench.cases import SCALES
from sysid_bench.bench.experiment import Cell, Context

ck = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1] != "shipped" else None
exp = EXPERIMENTS["changing"]
sc = SCALES["default"]
ctx = Context(sc, "runs/eval_changing", threads=1)
orig = ctx.estimator
ctx.estimator = lambda m, **kw: orig(m, **({"checkpoint": ck} if ck else {}), **kw)
fol, se = [], []
for i in range(sc.n_for("changing", "ball")):
    out = exp.run(Cell("changing", "vid2param-changing", "video", "", i), ctx)
    fol += [r.value for r in out.rows if r.metric.startswith("followed_")]
    se += [r.value for r in out.rows if r.metric == "se"]
print(f"{ck or 'shipped'}: changes followed {np.mean(fol):.3f} ({int(sum(fol))} of {len(fol)}), "
      f"mean se {np.mean(se):.4f}", flush=True)
