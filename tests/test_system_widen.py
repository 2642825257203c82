"""A system posterior whose model check fails claims no interval narrower than the prior's."""

import numpy as np
import pytest

import methods
from sysid_bench.bench.systems import system_case
from sysid_bench.core import systems
from sysid_bench.core.estimator import Observation

pytestmark = pytest.mark.skipif("lsq" not in methods.available(), reason="lsq not installed")


def test_failed_check_widens_to_the_prior():
    sys_ = systems.get("pendulum")
    rng = np.random.default_rng(0)
    # points scattered over the view: no pendulum trajectory explains them
    junk = Observation(positions=rng.uniform(-2.0, 2.0, (120, 1, 2)), system="pendulum")
    post = methods.get("lsq", system="pendulum").identify(junk)
    assert not post.check.ok and "widened to the prior" in post.check.note
    prior_std = (sys_.prior_hi - sys_.prior_lo) / np.sqrt(12.0)
    assert (post.std >= prior_std - 1e-12).all() and post.extras["widened"] == "prior"
    lo, hi = np.quantile(post.samples, [0.05, 0.95], axis=0)
    assert ((hi - lo) > 0.8 * (sys_.prior_hi - sys_.prior_lo)).all()


def test_passing_check_keeps_the_intervals():
    obs, truth, _ = system_case("pendulum", 0, 2, 7, "positions")
    post = methods.get("lsq", system="pendulum").identify(obs.prefix(120))
    assert post.check.ok and "widened" not in post.extras
    prior_std = (systems.get("pendulum").prior_hi - systems.get("pendulum").prior_lo) / np.sqrt(12)
    assert (post.std < 0.5 * prior_std).any()
