"""The ball's own fits hold what the user knows (issue 38 §4): a known value exact with std 0,
the others fitted given it, a user's range kept, and the model check judging the held value."""

import numpy as np
import pytest

import methods
from sysid_bench.core import physics
from sysid_bench.core.estimator import Observation

TRUTH = np.array([0.8, -9.81, 0.01, 0.3])
#: small budgets (the same code paths as the defaults)
BUDGETS = {
    "lsq": {"n_samples": 400, "max_refine": 300},
    "emcee": {"n_walkers": 16, "n_steps": 150, "n_burn": 50},
    "bo": {"n_calls": 12, "n_initial_points": 6, "n_surrogate": 256},
    "nuts": {"num_warmup": 100, "num_samples": 100, "num_chains": 2},
}
SLOW = {"bo": "~6 s under load (the GP)", "nuts": "~100 s under load (compilation)"}
#: how near the truth e and d come given g (bo's 12 evaluations are a coarse search)
NEAR = {"lsq": (0.05, 0.005), "emcee": (0.05, 0.005), "nuts": (0.05, 0.005), "bo": (0.1, 0.01)}


def _methods():
    return [pytest.param(m, marks=pytest.mark.slow) if m in SLOW else m for m in BUDGETS]


@pytest.fixture(scope="module")
def ball_obs():
    """60 frames of our physics with 1 cm noise, the floor known (as identify's camera gives)."""
    rng = np.random.default_rng([38, 4])
    st = physics.simulate(TRUTH[None], np.array([[2.0, 7.0, 5.0, 3.5]]), n_frames=60)
    pos = st[0, :, :2] + 0.01 * rng.standard_normal((60, 2))
    return Observation(positions=pos, dt=0.05, floor=0.0)


@pytest.mark.parametrize("name", _methods())
def test_a_known_g_is_held_and_the_rest_fitted(name, ball_obs):
    post = methods.get(name, known={"g": -9.81}, **BUDGETS[name]).identify(ball_obs)
    assert post.mean[1] == -9.81 and post.std[1] == 0.0 and np.all(post.samples[:, 1] == -9.81)
    assert post.check.ok, post.check
    tol_e, tol_d = NEAR[name]
    assert abs(post.mean[0] - TRUTH[0]) < tol_e and abs(post.mean[2] - TRUTH[2]) < tol_d
    assert post.extras["known"] == {"g": -9.81} and post.extras["prior"] == {}


@pytest.mark.parametrize("name", _methods())
def test_a_users_range_is_kept(name, ball_obs):
    post = methods.get(name, known={"g": -9.81}, prior={"e": (0.75, 0.79)},
                       **BUDGETS[name]).identify(ball_obs)
    e = post.samples[:, 0]
    assert 0.75 <= e.min() and e.max() <= 0.79 and 0.75 <= post.mean[0] <= 0.79
    assert post.extras["prior"] == {"e": [0.75, 0.79]}


@pytest.mark.parametrize("name", _methods())
def test_a_wrong_known_g_fails_the_check(name, ball_obs):
    post = methods.get(name, known={"g": -7.0}, **BUDGETS[name]).identify(ball_obs)
    assert not post.check.ok and post.check.rms_m > 5 * post.check.noise_m
    assert post.mean[1] == -7.0 and post.std[1] == 0.0  # held even where the check failed


def test_observation_known_is_held_as_the_option(ball_obs):
    import dataclasses

    a = methods.get("lsq", known={"g": -9.81}, **BUDGETS["lsq"]).identify(ball_obs)
    b = methods.get("lsq", **BUDGETS["lsq"]).identify(
        dataclasses.replace(ball_obs, known={"g": -9.81}))
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.std, b.std)


def test_no_knowledge_is_the_default_fit(ball_obs):
    a = methods.get("lsq", **BUDGETS["lsq"]).identify(ball_obs)
    b = methods.get("lsq", known={}, prior=None, **BUDGETS["lsq"]).identify(ball_obs)
    assert a.mean.tobytes() == b.mean.tobytes() and a.std.tobytes() == b.std.tobytes()
    assert "known" not in a.extras


@pytest.mark.parametrize("kw, match", [
    ({"known": {"L": 1.0}}, "known: 'L' is no parameter"),
    ({"prior": {"e": (0.9, 1.5)}}, "prior: e = 0.9:1.5 reaches outside"),
])
def test_bad_knowledge_on_the_ball_names_the_option(kw, match):
    with pytest.raises(ValueError, match=match):
        methods.get("lsq", system="ball", **kw)


@pytest.fixture(scope="module")
def ball_clip(tmp_path_factory):
    """40 frames of the ball as the renderer draws them, H.264 at 20 fps."""
    from sysid_bench.core.footage import write_video
    from sysid_bench.core.render import render

    st = physics.simulate(TRUTH[None], np.array([[2.0, 7.0, 5.0, 3.5]]), n_frames=40)
    path = tmp_path_factory.mktemp("clip") / "ball.mp4"
    write_video(path, render(st, size=(128, 128))[0], fps=20)
    return path


@pytest.mark.parametrize("g, ok", [(-9.81, True), (-7.0, False)])
def test_identify_holds_known_g_on_a_ball_clip(ball_clip, tmp_path, capsys, g, ok):
    import json

    from sysid_bench.apps.cli import main

    out = tmp_path / "out"
    rc = main(["identify", str(ball_clip), "--method", "lsq", "--every", "40", "--known",
               f"g={g}", "--prior", "e=0.7:0.9", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0, err
    res = json.load(open(out / "estimates.json"))
    know, last = res["knowledge"], res["estimates"][-1]
    assert know == {"known": {"g": g}, "prior": {"e": [0.7, 0.9]}, "held": True, "note": ""}
    assert "not yet held" not in err and f"g = {g:g} held; e searched in 0.7 to 0.9" in err
    assert last["g_mean"] == g and last["g_std"] == 0.0 and 0.7 <= last["e_mean"] <= 0.9
    assert bool(last["check_ok"]) is ok and res["check"]["check_ok"] is ok
    if ok:
        assert abs(last["e_mean"] - TRUTH[0]) < 0.05
