"""A reference method that ignores the data and answers with the prior.

It is the floor every method must beat (its normalised MSE is what guessing scores) and lets the
contract test run on a method with no dependencies.
"""

from __future__ import annotations

import time

import numpy as np

from sysid_bench._validate import check_positive_int
from sysid_bench.estimator import (
    Estimator,
    Forecast,
    Observation,
    Posterior,
    observed_positions,
    prior_posterior,
)


class PriorOnly(Estimator):
    """Posterior = uniform prior; forecast = the last seen position, spread over the box.

    Parameters
    ----------
    n_samples : int
        Prior draws returned as ``Posterior.samples``.
    seed : int
        Seed of those draws.
    """

    name = "prior"
    input_kind = "positions"
    forecasts = True
    cost = 0
    inline = True  # microseconds per cell: not worth a worker
    figure_order = 7

    def __init__(self, *, n_samples: int = 256, seed: int = 0):
        self.n_samples = n_samples
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        check_positive_int(self.n_samples, "n_samples")

    def identify(self, obs: Observation) -> Posterior:
        t0 = time.perf_counter()
        if not isinstance(obs, Observation):
            raise ValueError(f"obs: expected an Observation, got {type(obs).__name__}")
        n = check_positive_int(self.n_samples, "n_samples")
        post = prior_posterior(n_samples=n, seed=self.seed)
        post.extras["wall_s"] = time.perf_counter() - t0
        # Posterior.check stays None: the prior does not look at the observation, so there is
        # no fit to check (and its intervals are the prior's anyway)
        post.extras["check_reason"] = "the prior does not look at the observation"
        return post

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        horizon = check_positive_int(horizon, "horizon")
        pos = observed_positions(obs, min_seen=1)
        last = pos[np.isfinite(pos).all(axis=1)][-1]
        mean = np.repeat(last[None, :], horizon, axis=0)
        std = np.full((horizon, 2), 10.0 / np.sqrt(12.0))
        return Forecast(mean=mean, std=std, extras={"n_simulations": 0})
