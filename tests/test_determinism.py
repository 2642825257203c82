"""Same inputs, same bytes (issue 14): tables do not depend on the order in which cells finish,
and the stochastic baselines are functions of their seed."""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from sysid_bench.bench.experiment import ci_summary
from sysid_bench.bench.store import Row, Store
from sysid_bench.core.metrics import bootstrap_ci

ROOT = Path(__file__).resolve().parents[1]


def test_bootstrap_ci_depends_on_values_not_their_order():
    v = np.random.default_rng(0).gamma(1.0, 0.05, size=40)
    ref = bootstrap_ci(v, seed=3)
    for s in range(5):
        perm = np.random.default_rng(s).permutation(v)
        assert bootstrap_ci(perm, seed=3) == ref


def test_ci_summary_of_shuffled_rows_is_identical():
    rng = np.random.default_rng(1)
    df = pd.DataFrame({"method": np.repeat(["a", "b", "c"], 30), "n_frames": np.tile([20, 60, 100], 30),
                       "case": np.arange(90), "value": rng.gamma(1.0, 0.05, 90)})
    ref = ci_summary(df, ["method", "n_frames"])
    for s in range(3):
        got = ci_summary(df.sample(frac=1.0, random_state=s), ["method", "n_frames"])
        pd.testing.assert_frame_equal(got, ref, check_exact=True)
    # a group's interval does not change when other groups come or go
    alone = ci_summary(df[df.method == "b"], ["method", "n_frames"])
    pd.testing.assert_frame_equal(alone.reset_index(drop=True),
                                  ref[ref.method == "b"].reset_index(drop=True), check_exact=True)


def _fill(path, order):
    with Store(path, grid_config={"t": 1}) as s:
        for i in order:
            key = {"experiment": "identification", "method": "m", "input": "video",
                   "condition": "-", "case": i}
            s.add_cell(f"c{i}", key, [Row(i, n, "se", float(i * 10 + n)) for n in (20, 60)])


def test_store_results_come_in_key_order_whatever_the_finishing_order(tmp_path):
    _fill(tmp_path / "a.sqlite", range(12))
    _fill(tmp_path / "b.sqlite", np.random.default_rng(0).permutation(12))
    with Store(tmp_path / "a.sqlite") as a, Store(tmp_path / "b.sqlite") as b:
        pd.testing.assert_frame_equal(a.results(), b.results(), check_exact=True)
        pd.testing.assert_frame_equal(a.cells().drop(columns="finished"),
                                      b.cells().drop(columns="finished"), check_exact=True)


@pytest.fixture(scope="module")
def smoke_results(tmp_path_factory):
    from sysid_bench.bench.runner import STORE_NAME, run

    d = tmp_path_factory.mktemp("run")
    run(scale="smoke", systems=["ball"], methods=["prior", "sindy"], run_dir=d, workers=0, progress=False,
        experiments=["identification", "forecasting", "changing", "calibration"])
    with Store(d / STORE_NAME) as s:
        return s.results()


@pytest.mark.slow
def test_experiment_tables_of_shuffled_rows_are_identical(smoke_results):
    """Every experiment's tables from the same rows in another order (as cells finishing in
    another order give): byte-identical CSV."""
    from sysid_bench.bench import EXPERIMENTS

    ok = smoke_results[smoke_results.status == "ok"]
    # smoke has 2 cases, too few for the order to move a bootstrap: 6 scaled copies -> 12
    ok = pd.concat([ok.assign(case=ok.case + 100 * k, value=ok.value * (1.0 + 0.1 * k),
                              cell_id=ok.cell_id + f"-{k}") for k in range(6)], ignore_index=True)
    shuffled = ok.sample(frac=1.0, random_state=0)
    n = 0
    for name in ("identification", "forecasting", "changing", "calibration"):
        sub, sub_s = ok[ok.experiment == name], shuffled[shuffled.experiment == name]
        ref, got = EXPERIMENTS[name].tables(sub), EXPERIMENTS[name].tables(sub_s)
        assert ref.keys() == got.keys()
        for t in ref:
            assert ref[t].to_csv(index=False) == got[t].to_csv(index=False), f"{name}: {t}"
            n += 1
    assert n >= 4


# -- the stochastic baselines: a function of their seed ------------------------------------------
_CHEAP = {"bo": {"n_calls": 12, "n_initial_points": 6},
          "emcee": {"n_walkers": 20, "n_steps": 20, "n_burn": 10}}

_DIGEST = """
import hashlib, sys, warnings
import numpy as np
warnings.filterwarnings("ignore")
import methods
from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.estimator import Observation
name, opts = sys.argv[1], eval(sys.argv[2])
ds = make_dataset("test", n=1, seed=11)
obs = Observation(positions=ds.states[0, :, :2])  # floor and state0 unknown: the harder path
p = methods.get(name, seed=5, **opts).identify(obs)
print(hashlib.sha256(p.mean.tobytes() + p.std.tobytes() + p.samples.tobytes()).hexdigest())
"""


def _digest_here(name):
    import methods
    from sysid_bench.core.datasets import make_dataset
    from sysid_bench.core.estimator import Observation

    ds = make_dataset("test", n=1, seed=11)
    p = methods.get(name, seed=5, **_CHEAP[name]).identify(Observation(positions=ds.states[0, :, :2]))
    return hashlib.sha256(p.mean.tobytes() + p.std.tobytes() + p.samples.tobytes()).hexdigest()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bo", "emcee"])
def test_same_seed_same_posterior_in_this_and_another_process(name):
    here = _digest_here(name)
    assert _digest_here(name) == here  # twice in one process (caches warm, state carried over)
    # another process, other hash seed and BLAS/OpenMP thread counts
    env = {**os.environ, "PYTHONHASHSEED": "12345", "OMP_NUM_THREADS": "2",
           "OPENBLAS_NUM_THREADS": "2", "MKL_NUM_THREADS": "2", "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", _DIGEST, name, repr(_CHEAP[name])], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == here


# -- issue 37: the across-systems table (section 0) ------------------------------------------
def test_an_uninformed_parameter_is_scored_at_the_prior_centre_not_where_the_search_stopped():
    """lsq's r after 200 frames without rolling: moving it across its whole range changes the
    track by less than the noise, so the last bits of a BLAS kernel sent the search to either
    end (se_r 0.97 or 1.6e-05 on the same case, the table's MSE 0.027 vs 0.080 between runs).
    Scored at the prior's centre (its interval is the prior's), both ends give the same figure."""
    from sysid_bench.bench.systems import _scored_point
    from sysid_bench.core import systems
    from sysid_bench.core.estimator import Posterior

    ball = systems.get("ball")
    lo, hi = np.asarray(ball.prior_lo, float), np.asarray(ball.prior_hi, float)
    k = list(ball.params).index("r")
    u_true = np.array([0.7, 0.3, 0.4, 0.99])
    scores = []
    for end in (0.005, 0.995):
        u = u_true.copy()
        u[k] = end
        post = Posterior(mean=lo + u * (hi - lo), std=(hi - lo) / np.sqrt(12.0),
                         extras={"uninformed": ["r"]})
        scores.append(((_scored_point(post, ball) - u_true) ** 2).tobytes())
        informed = Posterior(mean=lo + u * (hi - lo), std=0.01 * (hi - lo))
        np.testing.assert_allclose(_scored_point(informed, ball), u)  # a claimed point is scored
    assert scores[0] == scores[1]


def test_cached_cases_cannot_be_changed_by_a_cell():
    """The cases are cached per worker process and handed out as views: a method writing into
    its observation would change the cases of every later cell in that worker (results then
    depend on which cells a worker ran before). Read-only, such a write fails in its own cell."""
    from sysid_bench.bench.systems import system_case

    obs, truth, points = system_case("ball", 0, 2, 7, "positions")
    for a in (obs.positions, truth, points):
        with pytest.raises(ValueError, match="read-only"):
            a[0] = 0.0
    again = system_case("ball", 0, 2, 7, "positions")
    assert again[0].positions.tobytes() == obs.positions.tobytes()
    from sysid_bench.bench.cases import test_set

    ds = test_set("interleaved", 2, 7)
    for a in (ds.frames, ds.states, ds.theta, ds.labels, ds.floor):
        assert not a.flags.writeable


def _systems_rows(better: str):
    rng = np.random.default_rng(5)
    recs = []
    for m in ("a", "b", "c"):
        for i in range(4):
            se = rng.uniform(0.01, 0.02) if m == better else rng.uniform(0.03, 0.05)
            for metric, v in (("se", se), ("cov90", 1.0)):
                recs.append({"experiment": "systems", "method": m, "input": "positions",
                             "system": "ball", "condition": "", "case": i, "n_frames": 200, "metric": metric,
                             "value": v, "status": "ok"})
    return pd.DataFrame(recs)


def test_the_systems_table_keeps_its_row_order_when_the_figures_move():
    """Rows were sorted by rank and parameter MSE, so a rerun whose figures moved within their
    CIs reordered the table; now by system, method, input."""
    from sysid_bench.bench.systems import Systems

    orders = [Systems().summary(_systems_rows(b))[["system", "method", "input"]]
              for b in ("a", "c")]
    pd.testing.assert_frame_equal(orders[0], orders[1])
    assert list(orders[0].method) == ["a", "b", "c"]
