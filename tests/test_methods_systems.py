"""Every method on every system: ``methods.get(name, system=S)`` (issue 28, part 3; issue 37:
one class per method).

Every registered system and method must import with the ``[all]`` extras: one that does not
fails here (it is not skipped). :data:`EXPECTED` is the method x system matrix: where a method
answers today, answering n/a there fails. Cheap budgets throughout; NUTS (a JAX compile per
system) and the recovery checks are marked slow.
"""

from __future__ import annotations

import numpy as np
import pytest

import methods
from sysid_bench.core import systems
from sysid_bench.core.estimator import Forecast, Observation, Posterior

OTHER = [s for s in systems.available() if s != "ball"]

CHEAP = {
    "lsq": {"n_samples": 300, "n_starts": 2, "max_opt_evals": 20},
    "bo": {"n_calls": 6, "n_initial_points": 3, "n_surrogate": 256},
    "emcee": {"n_walkers": 18, "n_steps": 12, "n_burn": 4, "n_init": 200, "max_opt_evals": 10},
    "nuts": {"num_warmup": 20, "num_samples": 20, "n_init": 200, "search_rounds": 2,
             "n_starts": 1, "max_opt_evals": 10, "n_forecast": 10, "frame_bucket": 100},
    "sindy": {},
    "dmd": {},
    "prior": {"n_samples": 16},
}


#: What each method answers on each shipped system: "answers" (a posterior, or for dmd a
#: forecast), "n/a" (``NotAvailable`` from ``methods.get``: the method does not declare the
#: system) or "no model" (declared, but ``NotAvailable`` from ``methods.get`` until a trained
#: model is shipped or given). A method that answered and now says n/a (or the reverse) fails
#: ``test_the_method_system_matrix`` / ``_run``.
EXPECTED = {
    "lsq": dict.fromkeys(("ball", "pendulum", "spring", "collision"), "answers"),
    "bo": dict.fromkeys(("ball", "pendulum", "spring", "collision"), "answers"),
    "emcee": dict.fromkeys(("ball", "pendulum", "spring", "collision"), "answers"),
    "nuts": dict.fromkeys(("ball", "pendulum", "spring", "collision"), "answers"),
    "dmd": dict.fromkeys(("ball", "pendulum", "spring", "collision"), "answers"),
    "prior": dict.fromkeys(("ball", "pendulum", "spring", "collision"), "answers"),
    "sindy": {"ball": "answers", "pendulum": "answers", "spring": "answers", "collision": "n/a"},
    # no network is shipped for the other systems (train one: ``sysid-bench train --system``;
    # ``checkpoint=F`` loads it)
    "vid2param": {"ball": "answers", "pendulum": "answers", "spring": "answers",
                  "collision": "answers"},
    # the system's physics fitted to its network's track: wherever vid2param has a network
    "vid2param-physics": {"ball": "answers", "pendulum": "answers", "spring": "answers",
                          "collision": "answers"},
    "vid2param-changing": {"ball": "answers", "pendulum": "n/a", "spring": "n/a",
                           "collision": "n/a"},
}


def _system(name):
    return systems.get(name)  # an ImportError fails the test: the [all] extras must import it


def _case(system, n_frames=100, seed=0, noise=0.01):
    """theta (P,), noisy points (T, K, 2) of one test-split case."""
    rng = np.random.default_rng([seed, 28])
    theta = system.sample_theta(1, rng, "test")
    try:
        state0 = system.sample_state0(1, rng, theta=theta)
    except TypeError:
        state0 = system.sample_state0(1, rng)
    pts = system.observe(system.simulate(theta, state0, n_frames=n_frames), theta)[0]
    return theta[0], pts + rng.normal(0.0, noise, pts.shape)


def _check_posterior(post, system):
    assert isinstance(post, Posterior)
    assert post.system == system.name
    assert post.mean.shape == (system.n_params,) and post.std.shape == (system.n_params,)
    assert np.isfinite(post.mean).all() and np.isfinite(post.std).all() and (post.std > 0).all()
    assert (post.mean >= system.prior_lo).all() and (post.mean <= system.prior_hi).all()
    assert post.as_dict().keys() >= set(system.params)


def _check_forecast(fc, system, horizon):
    assert isinstance(fc, Forecast)
    shape = (horizon, 2) if system.n_points == 1 else (horizon, system.n_points, 2)
    assert fc.mean.shape == shape and fc.std.shape == shape
    assert np.isfinite(fc.mean).all()


def _run(method, name, forecast=True):
    system = _system(name)
    _, pts = _case(system)
    est = methods.get(method, system=name, **CHEAP[method])
    obs = Observation(positions=pts, system=name)
    if est.spec().identifies:
        post = est.identify(obs)  # n/a here fails: EXPECTED says the method answers
    else:  # dmd: forecasts only, and says why it does not identify
        with pytest.raises(NotImplementedError, match="no physical parameters"):
            est.identify(obs)
        post = None
    if post is not None:
        _check_posterior(post, system)
        if est.spec().identifies and method not in ("sindy", "prior", "dmd"):
            assert post.extras["n_simulations"] > 0
            assert post.check is not None
    if forecast:
        _check_forecast(est.forecast(obs, 7), system, 7)
    return post


# ------------------------------------------------------------------------------------------
# the registry
def test_an_unknown_system_is_refused_with_the_known_ones():
    with pytest.raises(ValueError, match="Did you mean 'spring'"):
        methods.get("lsq", system="sprung")


def test_vid2param_says_na_on_another_system():
    for name in OTHER:
        if EXPECTED["vid2param"][name] == "no model":
            with pytest.raises(ValueError, match=f"n/a on the {name} system: no model is shipped"):
                methods.get("vid2param", system=name)
        with pytest.raises(NotImplementedError):  # what the benchmarks record as n/a
            methods.get("vid2param-changing", system=name)


def test_one_class_per_method_on_every_system():
    from methods.dmd import DMD
    from methods.lsq import LSQ

    assert type(methods.get("lsq")) is LSQ
    assert type(methods.get("lsq", system="ball", n_samples=500)) is LSQ
    assert type(methods.get("dmd", system="ball")) is DMD
    assert methods.get("lsq").get_params()["system"] == "ball"
    for name in methods.available(include_reference=True):
        cls = methods.get_class(name)
        for s in OTHER:
            if EXPECTED[name][s] == "no model":  # the one class, n/a until given a model
                assert methods.get_class(name, system=s) is cls
            if EXPECTED[name][s] == "answers":
                assert methods.get_class(name, system=s) is cls
                assert methods.get(name, system=s).get_params()["system"] == s


def test_the_method_system_matrix():
    """Every registered method and system is in EXPECTED and imports; the declarations and
    ``methods.get`` agree with it (n/a exactly where expected)."""
    from methods import NotAvailable

    assert set(EXPECTED) == set(methods.available(include_reference=True))
    for name, row in EXPECTED.items():
        assert set(row) == set(systems.available()), name
        spec = methods.spec(name)  # an ImportError fails: the [all] extras must import it
        for s, want in row.items():
            _system(s)
            if want == "answers":
                est = methods.get(name, system=s)
                assert est.spec().runs_on(s), (name, s)
            else:
                with pytest.raises(NotAvailable, match=f"n/a on the {s} system"):
                    methods.get(name, system=s)
                assert spec.runs_on(s) is (want == "no model"), (name, s)


def test_a_method_refuses_a_system_it_does_not_declare():
    with pytest.raises(ValueError, match="system: expected one of ball, pendulum, spring"):
        methods.get_class("sindy")(system="collision")
    with pytest.raises(ValueError, match="unknown system"):
        methods.get_class("lsq")(system="sprung")


def test_a_generic_method_refuses_another_systems_observation():
    _system("spring")
    est = methods.get("lsq", system="spring")
    ball = Observation(positions=np.column_stack([np.linspace(1, 2, 10), np.full(10, 5.0)]))
    with pytest.raises(ValueError, match="obs: expected an observation of the spring system"):
        est.identify(ball)
    with pytest.raises(ValueError, match="obs: expected an observation of the ball system"):
        methods.get("lsq").identify(Observation(positions=np.ones((10, 2)), system="spring"))


# ------------------------------------------------------------------------------------------
# Observation and Posterior on a system
def test_observation_reads_a_systems_points():
    system = _system("pendulum")
    _, pts = _case(system)
    assert (pts[..., 0] < 0).any()  # a pendulum's x is negative half the time: not refused
    obs = Observation(positions=pts[:, 0], system="pendulum")  # (T, 2) read as K = 1
    assert obs.positions.shape == (pts.shape[0], 1, 2) and obs.points.shape == obs.positions.shape
    with pytest.raises(ValueError, match="positions: expected points within"):
        Observation(positions=pts * 1000.0, system="pendulum")  # millimetres for metres
    with pytest.raises(ValueError, match=r"positions: expected \(T, 1, 2\)"):
        Observation(positions=np.repeat(pts, 2, axis=1), system="pendulum")
    with pytest.raises(ValueError, match="state0"):
        Observation(positions=pts, state0=np.zeros(4), system="pendulum")
    with pytest.raises(ValueError, match="unknown system"):
        Observation(positions=pts, system="pendulumm")
    assert Observation(positions=pts, system="pendulum").prefix(10).system == "pendulum"


def test_the_balls_observation_takes_one_point_as_k_1():
    pos = np.column_stack([np.linspace(1, 2, 10), np.full(10, 5.0)])
    obs = Observation(positions=pos[:, None, :])
    assert obs.positions.shape == (10, 2) and obs.points.shape == (10, 1, 2)
    with pytest.raises(ValueError, match=r"positions: expected \(T, 2\) or \(T, 1, 2\)"):
        Observation(positions=np.stack([pos, pos], axis=1))


def test_posterior_is_sized_by_its_system():
    system = _system("spring")
    p = Posterior(mean=system.prior_lo, std=np.ones(system.n_params), system="spring")
    assert set(p.as_dict()) == set(system.params) | {f"{q}_std" for q in system.params}
    with pytest.raises(ValueError, match="mean"):
        Posterior(mean=np.zeros(3), std=np.ones(3), system="spring")


# ------------------------------------------------------------------------------------------
# every method on every system
@pytest.mark.parametrize("method,name", [
    (m, s) for m in ("lsq", "emcee", "sindy", "dmd", "prior") for s in OTHER
    if EXPECTED[m].get(s) == "answers"])
def test_method_runs_on_system(method, name):
    _run(method, name)


@pytest.mark.parametrize("name", OTHER)
def test_bo_runs_on_system(name):
    _run("bo", name, forecast=False)


@pytest.mark.slow
@pytest.mark.parametrize("name", OTHER)
def test_nuts_runs_on_system(name):
    post = _run("nuts", name, forecast=False)
    system = systems.get(name)
    assert set(post.extras["rhat"]) == set(system.params) == set(post.extras["ess"])


def test_unseen_points_are_skipped():
    system = _system("spring")
    theta, pts = _case(system, seed=3)
    pts[20:30] = np.nan
    post = methods.get("lsq", system="spring", **CHEAP["lsq"]).identify(
        Observation(positions=pts, system="spring"))
    _check_posterior(post, system)


def test_sindy_says_na_where_it_has_no_library():
    from methods._sindy_libraries import LIBRARIES

    for name in OTHER:
        if name in LIBRARIES:
            continue
        system = _system(name)
        _, pts = _case(system)
        with pytest.raises(NotImplementedError, match=f"sindy is n/a on the {name} system"):
            methods.get("sindy", system=name).identify(Observation(positions=pts, system=name))


# ------------------------------------------------------------------------------------------
# recovery on an easy spring: large swing, light damping, 200 frames, 1 cm noise
def _easy_spring():
    system = _system("spring")
    theta = np.array([[12.0, 10.0, 0.1, 1.5]])
    state0 = np.array([[1.5 + 0.55, 0.3]])
    rng = np.random.default_rng(7)
    pts = system.observe(system.simulate(theta, state0, n_frames=200), theta)[0]
    return system, theta[0], pts + rng.normal(0.0, 0.01, pts.shape)


def test_lsq_recovers_an_easy_spring():
    system, theta, pts = _easy_spring()
    post = methods.get("lsq", system="spring").identify(Observation(positions=pts, system="spring"))
    z = (post.mean - theta) / post.std
    assert np.all(np.abs(z) < 4), (post.mean, post.std, theta)
    assert post.check.ok
    # and it learned something: every std well below the prior's
    assert np.all(post.std < 0.3 * (system.prior_hi - system.prior_lo) / np.sqrt(12))


def test_lsq_answers_the_prior_for_a_parameter_the_track_does_not_inform():
    """The collision's wall restitution ew before a cart meets a wall: its Laplace variance is
    the uniform prior's, and the answer is the prior's centre and spread (the optimiser's point
    there moved with the frame rate: a camera clip read at 120 and at 20 frames/s answered eb
    0.51 and 0.998), its draws the prior's; the informed parameters keep the fit."""
    sys_ = systems.get("collision")
    theta, s0 = sys_.sample_cases(6, np.random.default_rng(3), "test")
    pts = sys_.observe(sys_.simulate(theta[4:5], s0[4:5], n_frames=40), theta[4:5])[0]
    pts = pts + np.random.default_rng(4).normal(0.0, 0.005, pts.shape)
    # the default budget: the cheap one leaves eb and mu 6-7 stds off (unconverged) here
    post = methods.get("lsq", system="collision").identify(
        Observation(positions=pts, system="collision"))
    assert post.extras["uninformed"] == ["ew"]
    j = sys_.params.index("ew")
    lo, hi = sys_.prior_lo[j], sys_.prior_hi[j]
    assert post.mean[j] == lo + 0.5 * (hi - lo)
    assert np.isclose(post.std[j], (hi - lo) / np.sqrt(12.0))
    col = post.samples[:, j]
    assert col.min() < lo + 0.2 * (hi - lo) and col.max() > hi - 0.2 * (hi - lo)
    informed = [k for k in range(len(sys_.params)) if k != j]
    z = (post.mean[informed] - theta[4, informed]) / post.std[informed]
    assert np.all(np.abs(z) < 4), z
    assert np.all(post.std[informed] < 0.5 * (sys_.prior_hi - sys_.prior_lo)[informed] / np.sqrt(12))
    assert post.check.ok


@pytest.mark.slow
def test_nuts_recovers_an_easy_spring():
    system, theta, pts = _easy_spring()
    post = methods.get("nuts", system="spring", num_warmup=100, num_samples=100).identify(
        Observation(positions=pts, system="spring"))
    z = (post.mean - theta) / post.std
    assert np.all(np.abs(z) < 4), (post.mean, post.std, theta)
    assert post.extras["converged"], post.extras["warning"]


def test_a_known_initial_state_is_used_as_given():
    system, theta, pts = _easy_spring()
    state0 = np.array([1.5 + 0.55, 0.3])
    post = methods.get("lsq", system="spring", **CHEAP["lsq"]).identify(
        Observation(positions=pts, state0=state0, system="spring"))
    assert post.extras["state0_known"] and np.allclose(post.extras["state0"], state0)
    assert np.all(np.abs(post.mean - theta) < 4 * post.std + 1e-9)


# ------------------------------------------------------------------------------------------
# a system a user registers: the methods that declare "any" run on it with no other change
@pytest.fixture
def decay(tmp_path, monkeypatch):
    import re
    import sys
    from pathlib import Path

    doc = Path(__file__).resolve().parents[1] / "docs" / "adding-a-system.md"
    module = re.findall(r"```python\n(.*?)```", doc.read_text(), flags=re.S)[0]
    (tmp_path / "toy_decay_methods.py").write_text(module)
    monkeypatch.syspath_prepend(str(tmp_path))
    systems.register("decay", "toy_decay_methods:Decay")
    yield "decay"
    systems.unregister("decay")
    sys.modules.pop("toy_decay_methods", None)


def test_a_registered_system_gets_every_method_that_declares_any(decay):
    from methods import NotAvailable
    from sysid_bench.core.testing import check_estimator, estimator_checks

    system = systems.get(decay)
    rng = np.random.default_rng(5)
    theta = system.sample_theta(1, rng, "test")
    state0 = system.sample_state0(1, rng)
    pts = system.observe(system.simulate(theta, state0, n_frames=60), theta)[0]
    obs = Observation(positions=pts, state0=state0[0], system=decay)  # it tracks no start
    est = methods.get("lsq", system=decay, **CHEAP["lsq"])
    post = est.identify(obs)
    _check_posterior(post, system)
    assert post.check is not None
    _check_forecast(est.forecast(obs, 7), system, 7)
    check_estimator(methods.get("prior"))  # its checks include the new system's
    assert "check_on_system_decay" in dict(estimator_checks(methods.get("prior")))
    with pytest.raises(NotAvailable, match="sindy is n/a on the decay system"):
        methods.get("sindy", system=decay)
