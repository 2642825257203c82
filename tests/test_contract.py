"""The contract, over the registry: ``sysid_bench.core.testing.check_estimator`` on every method.

Each method runs with its class's ``contract_options`` (cheap budgets, same code path), on the
ball and on every other system it declares (``check_on_system_<name>``). Measured
on the loaded 2-core box: nuts 133 s (it compiles its sampler), bo 23 s, emcee 3.6 s, the others
under 2 s each; nuts and bo are marked slow (``--runslow``).
"""

import pytest

import methods
from sysid_bench.core.testing import EstimatorCheckError, check_estimator, estimator_checks

#: methods whose checks take more than a few seconds on a loaded 2-core machine
SLOW = {"nuts", "bo"}


def _params():
    for name in methods.available(include_reference=True):
        marks = [pytest.mark.slow] if name in SLOW else []
        yield pytest.param(name, id=name, marks=marks)


@pytest.mark.parametrize("name", _params())
def test_check_estimator(name):
    spec = methods.spec(name)  # an ImportError fails: the [all] extras must import every method
    check_estimator(methods.get(name, **spec.contract_options))


def test_the_contract_runs_on_every_declared_system():
    from sysid_bench.core import systems

    every = [s for s in systems.available() if s != "ball"]
    names = [n for n, _ in estimator_checks(methods.get("lsq"))]
    assert [f"check_on_system_{s}" for s in every] == [n for n in names if "on_system" in n]
    sindy = [n for n, _ in estimator_checks(methods.get("sindy"))]
    assert "check_on_system_pendulum" in sindy and "check_on_system_collision" not in sindy


def test_a_method_broken_on_a_system_fails_there():

    from methods.prior import PriorOnly

    class Unsized(PriorOnly):
        """Answers in normalised units (not the system's physical ones) off the ball."""

        name = "unsized"

        def identify(self, obs):
            post = super().identify(obs)
            if self.system != "ball":
                post.mean = post.mean * 1e3
            return post

    checks = dict(estimator_checks(Unsized()))
    checks["check_identify"]()  # the ball is fine
    with pytest.raises(EstimatorCheckError, match="check_on_system_spring .*far outside"):
        checks["check_on_system_spring"]()


def test_checks_are_named_and_chosen_by_capability():
    names = [n for n, _ in estimator_checks(methods.get("dmd"))]
    assert "check_not_implemented_has_reason" in names and "check_forecast" in names
    assert "check_identify" not in names  # dmd declares identifies = False
    assert "check_identify" in [n for n, _ in estimator_checks(methods.get("prior"))]


def test_a_broken_method_fails_with_the_check_name():
    from sysid_bench.core.estimator import Estimator, prior_posterior

    class Shy(Estimator):
        name = "shy"

        def __init__(self, *, seed: int = 0):
            self.seed = seed

        def identify(self, obs):
            return prior_posterior()

        def forecast(self, obs, horizon):
            raise NotImplementedError("no")  # declared not to forecast, but gives no reason

    with pytest.raises(EstimatorCheckError, match="check_not_implemented_has_reason"):
        check_estimator(Shy())

    class Sloppy(Shy):
        name = "sloppy"

        def __init__(self, *, seed: int = 0, n: int = 5):
            self.seed = seed
            self.n = int(n) + 1  # does work in the constructor

    with pytest.raises(EstimatorCheckError, match="check_constructor_stores_arguments"):
        check_estimator(Sloppy())


def test_check_estimator_wants_an_instance():
    with pytest.raises(ValueError, match="estimator"):
        check_estimator(methods.get_class("prior"))


@pytest.mark.parametrize("name", ["prior", "lsq", "dmd"])
def test_checks_do_not_depend_on_their_order(name):
    # each check builds what it needs: reversed, shuffled, or one alone, they all pass
    import random

    est = methods.get(name, **methods.spec(name).contract_options)
    # the per-system checks build their own estimator and observation by construction (and run
    # in test_check_estimator): the ball's checks only, to keep this test quick
    checks = [c for c in estimator_checks(est) if not c[0].startswith("check_on_system_")]
    for order in (checks[::-1], random.Random(3).sample(checks, len(checks))):
        for _, run in order:
            run()
    for check_name, _ in checks:  # each alone, on a fresh estimator
        fresh = methods.get(name, **methods.spec(name).contract_options)
        dict(estimator_checks(fresh))[check_name]()


def test_the_stream_contract_is_checked():
    from sysid_bench.core.estimator import Estimator, LoopStream, prior_posterior

    class Claims(Estimator):
        """Declares an online stream but has the default one."""

        name = "claims"
        online = True

        def __init__(self, *, seed: int = 0):
            self.seed = seed

        def identify(self, obs):
            return prior_posterior()

    # (local classes do not pickle: run the one check)
    with pytest.raises(EstimatorCheckError, match="check_stream .*declares online = True"):
        dict(estimator_checks(Claims()))["check_stream"]()

    class Miscounts(LoopStream):
        @property
        def n_frames(self):
            return 0

    class Counts(Claims):
        name = "counts"
        online = False

        def stream(self):
            return Miscounts(self)

    with pytest.raises(EstimatorCheckError, match="check_stream .*n_frames after 1 pushes"):
        dict(estimator_checks(Counts()))["check_stream"]()


def test_a_batched_pass_must_answer_as_one_video_does():
    import numpy as np

    from sysid_bench.core.estimator import Estimator, prior_posterior
    from sysid_bench.core.testing import contract_observation

    class Drifts(Estimator):
        """Its own batched pass answers differently from identify_prefixes."""

        name = "drifts"

        def __init__(self, *, seed: int = 0):
            self.seed = seed

        def identify(self, obs):
            return prior_posterior()

        def identify_prefixes_batch(self, observations, lengths, check=True):
            out = super().identify_prefixes_batch(observations, lengths, check)
            for posts in out:
                for p in posts:
                    p.mean = np.asarray(p.mean) + 0.1
            return out

    with pytest.raises(EstimatorCheckError, match="check_prefixes .*identify_prefixes_batch"):
        dict(estimator_checks(Drifts()))["check_prefixes"]()
    with pytest.raises(ValueError, match=r"observations\[1\]"):
        Drifts().identify_prefixes_batch([contract_observation("both"), "x"], [5])


def test_a_stream_must_check_what_identify_checks():
    import dataclasses

    from sysid_bench.core.estimator import Check, Estimator, LoopStream, prior_posterior

    class Checks(Estimator):
        """identify checks its answers; its stream's check() drops the verdict."""

        name = "checks"

        def __init__(self, *, seed: int = 0):
            self.seed = seed

        def identify(self, obs):
            return dataclasses.replace(prior_posterior(), check=Check(0.01, 0.01, True, 10))

        def stream(self):
            class Drops(LoopStream):
                def check(self):
                    return dataclasses.replace(super().check(), check=None)

            return Drops(self)

    with pytest.raises(EstimatorCheckError, match=r"check_stream .*stream.check\(\)"):
        dict(estimator_checks(Checks()))["check_stream"]()
