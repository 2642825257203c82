"""NUTS on the systems (``methods.nuts``): extending an unconverged chain.

The budgets here are far too small for R-hat and ESS to pass, so the chain must extend as many
times as allowed and report it; the sampling runs through one JAX compile (marked slow).
"""

from __future__ import annotations

import numpy as np
import pytest

import methods
from sysid_bench.core import systems
from sysid_bench.core.estimator import Observation

_CHEAP = {"num_warmup": 20, "num_samples": 20, "n_init": 200, "search_rounds": 2,
          "n_starts": 1, "max_opt_evals": 10, "n_forecast": 10, "frame_bucket": 100}


def _spring_case():
    system = systems.get("spring")
    theta = np.array([[12.0, 10.0, 0.1, 1.5]])
    state0 = np.array([[1.5 + 0.55, 0.3]])
    pts = system.observe(system.simulate(theta, state0, n_frames=100), theta)[0]
    return pts + np.random.default_rng(7).normal(0.0, 0.01, pts.shape)


@pytest.mark.parametrize("bad", [-1, 1.5, "2", None])
def test_max_extensions_is_validated(bad):
    with pytest.raises(ValueError, match="max_extensions"):
        methods.get("nuts", system="spring", max_extensions=bad).identify(
            Observation(positions=_spring_case(), system="spring"))


@pytest.mark.slow
def test_an_unconverged_chain_extends_as_allowed():
    obs = Observation(positions=_spring_case(), system="spring")
    once = methods.get("nuts", system="spring", max_extensions=1, **_CHEAP).identify(obs)
    never = methods.get("nuts", system="spring", max_extensions=0, **_CHEAP).identify(obs)
    # 20 draws cannot give ESS >= 50 (an antithetic chain aside): the chain extends
    assert once.extras["extensions"] == 1 and once.extras["num_samples_kept"] == 40
    assert once.samples.shape == (40, 4)
    assert never.extras["extensions"] == 0 and never.extras["num_samples_kept"] == 20
    assert never.samples.shape == (20, 4)
    # the extension continues the same chain: its first 20 draws are the unextended run's
    np.testing.assert_allclose(once.samples[:20], never.samples, rtol=0, atol=1e-12)
    # the verdict is over all kept draws, and still honest about them
    if not once.extras["converged"]:
        assert once.extras["warning"]
