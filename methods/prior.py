"""A reference method that ignores the data and answers with the prior.

It is the floor every method must beat (its normalised MSE is what guessing scores) and lets the
contract test run on a method with no dependencies. It runs on any registered system: the
system's uniform prior, and a forecast that holds the last seen points. What the user knows
(``known`` values, ``prior`` ranges) is the prior it answers: a held parameter's value with std 0,
a user's range uniform (issue 38 §4).
"""

from __future__ import annotations

import time

import numpy as np

from methods._points import check_system_param, prepare_points, system_of
from methods._simulation import make_rng
from sysid_bench.core._validate import check_positive_int
from sysid_bench.core.estimator import (
    Estimator,
    Forecast,
    Observation,
    Posterior,
    observed_positions,
    prior_posterior,
)
from sysid_bench.core.footage import check_knowledge


class PriorOnly(Estimator):
    """Posterior = uniform prior; forecast = the last seen position, spread over the box (the
    ball) or the view (another system).

    Parameters
    ----------
    system : str
        A registered system (:func:`sysid_bench.core.systems.available`); the class runs on any.
    n_samples : int
        Prior draws returned as ``Posterior.samples``.
    seed : int
        Seed of those draws.
    known : dict of str -> float, optional
        Parameters held fixed: mean and every sample the value, std 0 (``extras["known"]``);
        checked as ``--known`` is (:func:`sysid_bench.core.footage.check_knowledge`).
    prior : dict of str -> (float, float), optional
        Ranges replacing the system's prior for these parameters (``extras["prior"]``).
    """

    name = "prior"
    input_kind = "positions"
    forecasts = True
    cost = 0
    inline = True  # microseconds per cell: not worth a worker
    systems = "any"
    #: Systems answered by the ball's own path (:func:`prior_posterior`, the box-wide forecast
    #: from :func:`observed_positions`, which knows its floor); any other, a user's included,
    #: gets the generic one (the system's prior box, its view).
    own_path = ("ball",)

    def __init__(self, *, system: str = "ball", n_samples: int = 256, seed: int = 0,
                 known: dict | None = None, prior: dict | None = None):
        self.system = system
        self.n_samples = n_samples
        self.seed = seed
        self.known = known
        self.prior = prior

    def _validate(self) -> None:
        super()._validate()
        check_system_param(self)
        check_positive_int(self.n_samples, "n_samples")
        check_knowledge(self.system, self.known, self.prior)

    def identify(self, obs: Observation) -> Posterior:
        t0 = time.perf_counter()
        if self.known or self.prior:
            return self._user_prior(t0)
        if self.system not in self.own_path:
            system = system_of(self.system)
            samples = system.sample_theta(check_positive_int(self.n_samples, "n_samples"),
                                          make_rng(self.seed, 0))
            mean = 0.5 * (system.prior_lo + system.prior_hi)
            std = (system.prior_hi - system.prior_lo) / np.sqrt(12.0)
            return Posterior(mean=mean, std=std, samples=samples,
                             extras={"n_simulations": 0, "wall_s": time.perf_counter() - t0,
                                     "check_reason": "the prior does not look at the observation"},
                             system=system.name)
        if not isinstance(obs, Observation):
            raise ValueError(f"obs: expected an Observation, got {type(obs).__name__}")
        n = check_positive_int(self.n_samples, "n_samples")
        post = prior_posterior(n_samples=n, seed=self.seed)
        post.extras["wall_s"] = time.perf_counter() - t0
        # Posterior.check stays None: the prior does not look at the observation, so there is
        # no fit to check (and its intervals are the prior's anyway)
        post.extras["check_reason"] = "the prior does not look at the observation"
        return post

    def _user_prior(self, t0: float) -> Posterior:
        """The system's uniform prior with the user's ranges and held values (any system)."""
        system = system_of(self.system)
        known, prior = check_knowledge(system, self.known, self.prior)
        lo, hi = system.prior_lo.copy(), system.prior_hi.copy()
        for name, (a, b) in {**prior, **{k: (v, v) for k, v in known.items()}}.items():
            i = system.params.index(name)
            lo[i], hi[i] = a, b
        n = check_positive_int(self.n_samples, "n_samples")
        samples = lo + (hi - lo) * make_rng(self.seed, 0).random((n, lo.size))
        held = [system.params.index(k) for k in known]
        samples[:, held] = [known[k] for k in known]  # exactly the value, not lo + 0 * u
        mean, std = 0.5 * (lo + hi), (hi - lo) / np.sqrt(12.0)
        mean[held] = [known[k] for k in known]
        return Posterior(mean=mean, std=std, samples=samples, system=system.name,
                         extras={"n_simulations": 0, "wall_s": time.perf_counter() - t0,
                                 "check_reason": "the prior does not look at the observation",
                                 "known": dict(known),
                                 "prior": {k: [float(a), float(b)] for k, (a, b) in prior.items()}})

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        if self.system not in self.own_path:
            return self._forecast_points(obs, horizon)
        horizon = check_positive_int(horizon, "horizon")
        pos = observed_positions(obs, min_seen=1)
        last = pos[np.isfinite(pos).all(axis=1)][-1]
        mean = np.repeat(last[None, :], horizon, axis=0)
        std = np.full((horizon, 2), 10.0 / np.sqrt(12.0))
        return Forecast(mean=mean, std=std, extras={"n_simulations": 0})

    def _forecast_points(self, obs: Observation, horizon: int) -> Forecast:
        """Another system: its last seen points held, spread over the view; (H, 2) or (H, K, 2)."""
        system = system_of(self.system)
        track = prepare_points(obs, system, 1)
        K = system.n_points
        last = np.empty((K, 2))
        for k in range(K):
            seen = np.flatnonzero(track.mask[:, k])
            last[k] = track.positions[seen[-1], k] if seen.size else np.nan
        x0, x1, y0, y1 = system.extent
        last = np.where(np.isfinite(last), last, [[0.5 * (x0 + x1), 0.5 * (y0 + y1)]])
        spread = np.array([x1 - x0, y1 - y0]) / np.sqrt(12.0)
        mean = np.repeat(last[None], horizon, axis=0)
        std = np.broadcast_to(spread, mean.shape).copy()
        if K == 1:
            mean, std = mean[:, 0], std[:, 0]
        return Forecast(mean=mean, std=std, extras={"n_simulations": 0})
