"""The interception task: scene, policies, evaluation, failures, CLI and report section."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from sysid_bench.apps import intercept as ic


def _cmp(a: pd.DataFrame, b: pd.DataFrame) -> None:
    # everything but the wall-clock column must be identical
    wall = ["step_ms", "step_mean_ms"]
    pd.testing.assert_frame_equal(a.drop(columns=wall), b.drop(columns=wall))


# -- the scene ------------------------------------------------------------------------------------
def test_throw_is_seeded_and_independent_of_other_throws():
    sc = ic.Scene()
    a, b = ic.make_throw(sc, 3, 2), ic.make_throw(sc, 3, 2)
    assert a.frames.tobytes() == b.frames.tobytes()
    assert a.states.tobytes() == b.states.tobytes()
    c = ic.make_throw(sc, 4, 2)
    assert c.frames.tobytes() != a.frames.tobytes()
    # the rules of the scene hold for the drawn throw
    assert sc.t_min <= a.t_cross <= sc.t_max
    assert a.n_bounces >= 1
    assert a.frames.shape == (int(a.t_cross / sc.dt) + 1, *sc.size)
    assert a.frames.dtype == np.uint8


def test_scored_crossing_is_first_after_t_min_and_after_a_bounce():
    sc = ic.Scene()
    for i in range(5):
        th = ic.make_throw(sc, 0, i)
        x = th.states[:, 0] - sc.x_catch
        late = th.times >= sc.t_min
        j = int(np.searchsorted(th.times, th.t_cross))
        # no sign change of x - x_catch between t_min and the scored crossing
        seg = x[late & (th.times < th.times[j - 1])]
        if len(seg):
            assert np.all(np.sign(seg) == np.sign(seg[0]))
        assert abs(np.interp(th.t_cross, th.times, th.states[:, 0]) - sc.x_catch) < 0.05
        assert th.n_bounces >= 1


def test_same_seed_same_throws_same_outcomes():
    a = ic.evaluate("random-2hz", n_throws=3, seed=11)
    b = ic.evaluate("random-2hz", n_throws=3, seed=11)
    _cmp(a, b)
    c = ic.evaluate("random-2hz", n_throws=3, seed=12)
    assert not np.allclose(a.y_cross_m, c.y_cross_m)
    # a prefix of the throws is the same throws
    d = ic.evaluate("random-2hz", n_throws=2, seed=11)
    _cmp(a.iloc[:2].reset_index(drop=True), d)
    k1, k2 = ic.evaluate("kalman", 2, 5), ic.evaluate("kalman", 2, 5)
    _cmp(k1, k2)


def test_rows_have_the_documented_columns():
    df = ic.evaluate("oracle", n_throws=2, seed=0)
    for col in ("throw", "success", "miss_m", "decision_s", "step_ms", "t_cross_s",
                "y_cross_m", "pred_t_cross_s", "pred_y_cross_m", "error"):
        assert col in df.columns
    assert df.success.dtype == bool
    assert list(df.throw) == [0, 1]
    assert df.attrs["policy"] == "oracle"


# -- the limit bites ------------------------------------------------------------------------------
def test_oracle_succeeds_where_feasible():
    df = ic.evaluate("oracle", n_throws=8, seed=0)
    assert df.reachable.all()
    assert df.success.all()
    assert (df.miss_m < 1e-9).all()
    # with an effector too slow to get there, the oracle fails exactly where it cannot reach
    slow = ic.evaluate("oracle", n_throws=8, seed=0, speed=0.2)
    assert (~slow.reachable).any()
    assert not slow.success[~slow.reachable].any()
    assert slow.success[slow.reachable].all()


def test_wait_and_react_fails_because_of_the_speed_limit():
    limited = ic.evaluate("react", n_throws=12, seed=0)
    free = ic.evaluate("react", n_throws=12, seed=0, speed=math.inf)
    assert free.success.mean() >= 0.9
    assert limited.success.mean() <= free.success.mean() - 0.25
    # the decisive move is late: react keeps changing its target till the end
    assert (limited.t_cross_s - limited.decision_s).median() < 0.2


def test_random_targets_change_at_their_rate():
    class Spy(ic.RandomTargets):
        def act(self, frame, k):
            out = super().act(frame, k)
            self.seen.append(out)
            return out

        def reset(self, scene, rng, throw=None):
            super().reset(scene, rng, throw)
            self.seen = []

    pol = Spy(2.0)
    ic.evaluate(pol, n_throws=1, seed=0)
    changes = np.flatnonzero(np.diff(pol.seen) != 0) + 1
    assert np.all(changes % 10 == 0)  # 2 Hz at 20 frames per second


def test_kalman_catches_most_throws():
    df = ic.evaluate("kalman", n_throws=6, seed=0)
    assert df.success.sum() >= 4
    assert (df.error == "").all()


def test_crossing_from_forecast():
    times = 1.0 + 0.1 * np.arange(1, 11)
    mean = np.stack([np.linspace(4.2, 6.0, 10), np.linspace(2.0, 3.0, 10)], axis=1)
    t, y, j = ic.crossing_from_forecast(1.0, (4.0, 2.0), times, mean, 5.0, 0.0)
    assert 1.0 < t < 2.0 and 2.0 < y < 3.0
    assert times[j] >= t
    # the crossing happens before t_min: none counts
    assert ic.crossing_from_forecast(1.0, (4.0, 2.0), times, mean, 5.0, 5.0) is None


# -- bad input ------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [0, -1, 1.5, True, "3"])
def test_bad_n_throws(n):
    with pytest.raises(ValueError, match="n_throws"):
        ic.evaluate("oracle", n_throws=n)


@pytest.mark.parametrize("name, value", [("catch_radius", 0.0), ("catch_radius", -0.1),
                                         ("speed", 0.0), ("speed", -1.0), ("speed", float("nan"))])
def test_bad_scene_numbers(name, value):
    with pytest.raises(ValueError, match=name):
        ic.evaluate("oracle", n_throws=1, **{name: value})


def test_unknown_policy_lists_known_ones():
    with pytest.raises(ValueError) as exc:
        ic.evaluate("catapult", n_throws=1)
    msg = str(exc.value)
    for name in ("oracle", "random-1hz", "random-2hz", "kalman", "vid2param",
                 "vid2param-physics", "lsq"):
        assert name in msg


def test_unknown_policy_option():
    with pytest.raises(ValueError, match="options"):
        ic.evaluate("kalman", n_throws=1, warp_drive=True)


def test_a_raising_policy_fails_its_throw_and_the_evaluation_goes_on():
    class Flaky(ic.Policy):
        name = "flaky"

        def reset(self, scene, rng, throw=None):
            super().reset(scene, rng, throw)
            self.throw_no = getattr(self, "throw_no", -1) + 1

        def act(self, frame, k):
            if self.throw_no == 1 and k == 3:
                raise RuntimeError("lost the ball")
            return 3.0

    df = ic.evaluate(Flaky(), n_throws=3, seed=0)
    assert len(df) == 3
    assert df.error[1] == "RuntimeError: lost the ball"
    assert not df.success[1] and np.isnan(df.miss_m[1])
    assert df.error[0] == "" and df.error[2] == ""
    assert np.isfinite(df.miss_m[[0, 2]]).all()


def test_a_non_finite_target_is_a_failure():
    class Nan(ic.Policy):
        name = "nan"

        def act(self, frame, k):
            return float("nan")

    df = ic.evaluate(Nan(), n_throws=1)
    assert "target" in df.error[0] and not df.success[0]


# -- identifying methods as policies -------------------------------------------------------------
def test_registered_method_as_policy():
    df = ic.evaluate("lsq", n_throws=1, seed=0, n_samples=300, every=15)
    assert (df.error == "").all(), df.error[0]
    assert np.isfinite(df.pred_t_cross_s[0])
    assert df.skipped_steps[0] >= 0 and df.step_mean_ms[0] >= df.step_ms[0]


def test_a_method_declining_a_prefix_keeps_the_target():
    class Picky(ic.Identify):
        def __init__(self):
            super().__init__("lsq", n_samples=200, every=10)
            real = self.est.forecast

            def forecast(obs, horizon):
                if obs.n_frames < 30:
                    raise ValueError("positions: too few frames")
                return real(obs, horizon)

            self.est.forecast = forecast

    df = ic.evaluate(Picky(), n_throws=1, seed=0)
    assert df.error[0] == "" and df.skipped_steps[0] == 3  # prefixes 4, 14, 24
    assert np.isfinite(df.pred_y_cross_m[0])


@pytest.mark.slow
def test_vid2param_policy_runs_and_says_how_it_forecast():
    df = ic.evaluate("vid2param-physics", n_throws=1, seed=0, every=20, record=[0])
    assert (df.error == "").all(), df.error[0]
    tr = df.attrs["traces"][0]
    assert tr["forecasts"] and len(tr["effector_t"]) == df.n_frames[0] + 1


# -- CLI and report -------------------------------------------------------------------------------
def test_cli_prints_rates_and_writes_the_table(tmp_path, capsys):
    from sysid_bench.apps.cli import main

    rc = main(["intercept", "--policy", "random-1hz", "--throws", "3", "--seed", "2",
               "--out", str(tmp_path), "--no-progress"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "random-1hz: caught" in out and "95% CI" in out
    df = pd.read_csv(tmp_path / "tables" / "intercept_random-1hz.csv")
    assert len(df) == 3 and set(df.throw) == {0, 1, 2}
    meta = json.loads((tmp_path / "tables" / "intercept_random-1hz.json").read_text())
    assert meta["summary"]["throws"] == 3
    assert "--seed 2" in meta["command"]
    assert main(["intercept", "--policy", "catapult", "--throws", "1", "--out",
                 str(tmp_path)]) == 2
    assert "known policies" in capsys.readouterr().err


def test_wilson_interval():
    lo, hi = ic.wilson_interval(27, 35)
    assert 0.6 < lo < 0.77 < hi < 0.9
    assert ic.wilson_interval(0, 10)[0] == 0.0 and ic.wilson_interval(10, 10)[1] == 1.0


@pytest.mark.parametrize("k, n, lo, hi", [
    # Newcombe (1998), Statistics in Medicine 17:857, Table I, method 3 (score, no correction)
    (81, 263, 0.2553, 0.3662), (15, 148, 0.0624, 0.1605), (0, 20, 0.0, 0.1611),
    (1, 29, 0.0061, 0.1718),
    # docs/intercept.md: 186 catches of 200 throws, 88.6-95.8%
    (186, 200, 0.8859, 0.9578),
])
def test_wilson_interval_known_values(k, n, lo, hi):
    got = ic.wilson_interval(k, n)
    np.testing.assert_allclose(got, (lo, hi), atol=6e-5)


def test_wilson_interval_bad_input():
    assert all(np.isnan(ic.wilson_interval(0, 0)))
    with pytest.raises(ValueError, match=r"k: expected a count in \[0, n=10\], got 11"):
        ic.wilson_interval(11, 10)
    with pytest.raises(ValueError, match="z: expected a positive"):
        ic.wilson_interval(1, 10, z=0.0)


def test_vid2param_policy_starts_its_path_at_the_fitted_position_now():
    # a crossing due before the forecast's first step must be visible to the last replan, so
    # the policy hands the forecast's fitted position now (camera frame) to the crossing search
    from sysid_bench.core.tracking import track

    pol = ic.make_policy("vid2param", every=10)
    sc = ic.Scene()
    th = ic.make_throw(sc, 0, 0)
    pol.reset(sc, np.random.default_rng(0), th)
    seen = []
    real = pol._aim
    pol._aim = lambda t, pos, mean, std=None: (seen.append((t, pos, mean)),
                                               real(t, pos, mean, std))[1]
    for k in range(40):
        pol.act(th.frames[k], k)
    assert len(seen) == 4  # frames 4, 14, 24, 34
    fine = round(sc.dt / (th.times[1] - th.times[0]))
    for t, pos, mean in seen:
        k = round(t / sc.dt)
        assert np.all(np.isfinite(pos))
        # the path is continuous: one frame from now to the forecast's first step is about the
        # ball's own step (10 m/s, 0.48 m a frame, just after the bounce before frame 34)
        step = np.abs(th.states[(k + 1) * fine, :2] - th.states[k * fine, :2]).max()
        assert np.abs(mean[0] - pos).max() < step + 0.2
        if np.isfinite(track(th.frames[k][None])[0]).all():  # frame 33 is dropped
            assert np.abs(pos - th.states[k * fine, :2]).max() < 0.3, (t, pos)
