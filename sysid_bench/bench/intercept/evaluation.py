"""Running a policy over seeded throws and scoring it."""

from __future__ import annotations

import math
import time

import numpy as np

from sysid_bench.bench.intercept.policies import Policy
from sysid_bench.bench.intercept.registry import make_policy
from sysid_bench.bench.intercept.scene import _SCENE_FIELDS, Scene, Throw, make_throw
from sysid_bench.core._validate import (
    check_flag,
    check_int_array,
)

_DECISION_TOL = 0.01

# ---------------------------------------------------------------------------------------------
# evaluation
def wilson_interval(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``k / n`` (95% by default).

    ``scipy.stats.binomtest(k, n).proportion_ci(method="wilson")`` at the confidence level of
    the two-sided normal quantile ``z``. ``n = 0`` gives ``(nan, nan)``.
    """
    from scipy import stats

    if n <= 0:
        return (float("nan"), float("nan"))
    if not 0 <= k <= n:
        raise ValueError(f"k: expected a count in [0, n={n}], got {k}")
    if not z > 0:
        raise ValueError(f"z: expected a positive normal quantile, got {z!r}")
    level = 1.0 - 2.0 * stats.norm.sf(z)
    ci = stats.binomtest(int(k), int(n)).proportion_ci(confidence_level=level, method="wilson")
    return (float(ci.low), float(ci.high))


def _effector(p, target, span, speed):
    """Height after heading for ``target`` for ``span`` seconds at ``speed``."""
    if math.isinf(speed):
        return target
    step = speed * span
    return p + min(max(target - p, -step), step)


def _run_throw(policy: Policy, scene: Scene, throw: Throw, rng, record: bool):
    """Close the loop on one throw; returns (row dict, trace dict or None)."""
    policy.reset(scene, rng, throw if policy.privileged else None)
    policy.record = record
    lo, hi = scene.effector_range
    p = scene.effector_start
    prev_target = p
    decision = 0.0
    steps, path_t, path_y, targets = [], [0.0], [p], []
    err = ""
    n = throw.frames.shape[0]
    for k in range(n):
        t = k * scene.dt
        t0 = time.perf_counter()
        try:
            target = float(policy.act(throw.frames[k], k))
            if not math.isfinite(target):
                raise ValueError(f"target: expected a finite height, got {target!r}")
        except Exception as exc:  # noqa: BLE001 -- a failing policy fails its throw, not the run
            err = f"{type(exc).__name__}: {exc}"
            break
        steps.append(time.perf_counter() - t0)
        target = min(max(target, lo), hi)
        if abs(target - prev_target) > _DECISION_TOL:
            decision = t
        prev_target = target
        targets.append(target)
        t_next = min((k + 1) * scene.dt, throw.t_cross)
        p = _effector(p, target, t_next - t, scene.speed)
        path_t.append(t_next)
        path_y.append(p)
    miss = abs(p - throw.y_cross) if not err else float("nan")
    # the earliest frame from which every target stayed within the catch radius of the truth
    ok = np.abs(np.asarray(targets) - throw.y_cross) <= scene.catch_radius
    settled = float("nan")
    if not err and len(ok) and ok[-1]:
        settled = float(len(ok) - np.argmin(ok[::-1]) if not ok.all() else 0) * scene.dt
    pred = policy.predicted or (float("nan"), float("nan"))
    th = throw.theta
    row = {
        "throw": throw.index,
        "success": bool(not err and miss <= scene.catch_radius),
        "miss_m": miss,
        "decision_s": decision,
        "settled_s": settled,
        "step_ms": 1e3 * float(np.median(steps)) if steps else float("nan"),
        "step_mean_ms": 1e3 * float(np.mean(steps)) if steps else float("nan"),
        "skipped_steps": int(getattr(policy, "n_skipped", 0)),
        "t_cross_s": throw.t_cross,
        "y_cross_m": throw.y_cross,
        "effector_m": p if not err else float("nan"),
        "pred_t_cross_s": float(pred[0]),
        "pred_y_cross_m": float(pred[1]),
        "reachable": throw.reachable(scene),
        "n_bounces": throw.n_bounces,
        "n_frames": n,
        "floor_m": throw.floor,
        "e": th[0], "g": th[1], "d": th[2], "r": th[3],
        "error": err,
    }
    trace = None
    if record:
        end = int(np.searchsorted(throw.times, throw.t_cross)) + 1
        trace = {
            "throw": throw.index, "policy": policy.name, "success": row["success"],
            "ball_t": throw.times[:end].tolist(), "ball_x": throw.states[:end, 0].tolist(),
            "ball_y": throw.states[:end, 1].tolist(), "t_cross": throw.t_cross,
            "y_cross": throw.y_cross, "floor": throw.floor,
            "effector_t": path_t, "effector_y": path_y, "targets": targets,
            "forecasts": [{"t": f[0], "times": f[1].tolist(), "mean": f[2].tolist(),
                           "std": f[3].tolist()} for f in policy.forecasts],
        }
    return row, trace


def evaluate(policy, n_throws: int = 200, seed: int = 0, **options):
    """Success of a policy over seeded throws.

    Parameters
    ----------
    policy : str or Policy
        A name of :func:`known_policies` or a :class:`Policy` instance.
    n_throws : int
        Throws (>= 1). Throw ``i`` depends only on ``(seed, i)``.
    seed : int
    **options
        :class:`Scene` fields (``x_catch``, ``catch_radius``, ``speed``, ``t_min``, ``t_max``,
        ``effector_range``, ``effector_start``, ``dt``, ``size``, ``nuisance``); ``progress``
        (tqdm bar, default False); ``first`` (the first throw evaluated, default 0: throws
        ``first .. n_throws - 1``, each the same as in a run from 0); ``record`` (throw
        indices whose traces -- ball path, forecasts,
        effector -- go to ``df.attrs["traces"]``); the rest go to the policy's constructor.

    Returns
    -------
    pandas.DataFrame
        One row per throw: ``throw``, ``success`` (bool), ``miss_m`` (|effector - ball| at the
        crossing, m; NaN when the policy raised), ``decision_s`` (time of the last target change
        of more than 1 cm), ``step_ms`` (the policy's median control-step time over the throw),
        ``settled_s`` (the earliest frame time from which every target stayed within the catch
        radius of the true crossing height; NaN if the last one did not),
        ``step_mean_ms`` (its mean: replanning every few frames puts the cost in the mean),
        ``skipped_steps`` (replans where the model declined this prefix, e.g. too few frames
        with the ball seen; the target was kept),
        ``t_cross_s``, ``y_cross_m`` (the true crossing), ``effector_m``, ``pred_t_cross_s``,
        ``pred_y_cross_m`` (the policy's last predicted crossing, NaN if none), ``reachable``
        (an effector knowing the crossing at launch could make it), ``n_bounces``, ``n_frames``
        (frames seen), ``floor_m``, ``e``, ``g``, ``d``, ``r``, ``error`` (why the policy
        raised, empty if it did not). ``attrs``: ``policy``, ``note``, ``seed``, ``scene``,
        ``traces``.
    """
    import pandas as pd

    if isinstance(n_throws, bool) or not isinstance(n_throws, (int, np.integer)) or n_throws < 1:
        raise ValueError(f"n_throws: expected an int >= 1, got {n_throws!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected an int >= 0, got {seed!r}")
    progress = check_flag(options.pop("progress", False), "progress")
    first = options.pop("first", 0)
    if isinstance(first, bool) or not isinstance(first, (int, np.integer)) or not (
            0 <= first < n_throws):
        raise ValueError(f"first: expected an int in [0, n_throws - 1 = {n_throws - 1}], "
                         f"got {first!r}")
    record = list(options.pop("record", ()))
    # a throw index that is not thrown would keep no trace without a word
    record = (set() if not record else
              {int(i) for i in check_int_array(record, "record", lo=0, hi=int(n_throws) - 1)})
    scene = Scene(**{k: options.pop(k) for k in list(options) if k in _SCENE_FIELDS})
    if isinstance(policy, Policy):
        if options:
            raise ValueError(f"options: {sorted(options)} are neither Scene fields nor usable "
                             "with a Policy instance")
        pol = policy
    else:
        pol = make_policy(policy, **options)
    it = range(int(first), int(n_throws))
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=f"intercept {pol.name}", unit="throw")
    rows, traces = [], {}
    for i in it:
        throw = make_throw(scene, seed, i)
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(i), 1 << 20)))
        row, trace = _run_throw(pol, scene, throw, rng, i in record)
        rows.append(row)
        if trace is not None:
            traces[i] = trace
    df = pd.DataFrame(rows)
    df.attrs.update(policy=pol.name, note=pol.note, seed=int(seed), scene=scene.as_dict(),
                    traces=traces)
    return df


def summarise(df) -> dict:
    """Rates of an :func:`evaluate` table: throws, caught, rate and its 95% Wilson CI, ...."""
    n = int(len(df))
    k = int(df.success.sum())
    lo, hi = wilson_interval(k, n)
    ok = df[df.error == ""]
    return {
        "policy": df.attrs.get("policy", ""),
        "throws": n,
        "caught": k,
        "rate": k / n if n else float("nan"),
        "ci95_lo": lo,
        "ci95_hi": hi,
        "median_miss_m": float(ok.miss_m.median()) if len(ok) else float("nan"),
        "median_lead_s": float((ok.t_cross_s - ok.decision_s).median()) if len(ok) else float("nan"),
        # how long before the crossing the aim was right for good (0 where it never was)
        "median_settled_lead_s": float((ok.t_cross_s - ok.settled_s).fillna(0.0).median())
        if len(ok) else float("nan"),
        "median_step_ms": float(df.step_ms.median()),
        "mean_step_ms": float(df.step_mean_ms.mean()),
        "errors": int((df.error != "").sum()),
        "seed": df.attrs.get("seed"),
        "note": df.attrs.get("note", ""),
    }


