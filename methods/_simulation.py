"""The skeleton every simulation-based method (lsq, bo, emcee, nuts) is built on.

A :class:`SimulationMethod` implements one thing, ``_fit(obs) -> Fit``: its search or sampler,
returning a named :class:`Fit` (the posterior, the draws a forecast resamples with their initial
states and floors, the prepared track, the counting simulator and the clock) instead of a 3- to
7-tuple. ``identify`` and ``forecast`` are written once, here: ``identify`` is the fit's
posterior; ``forecast`` resamples ``n_forecast`` draws (by the fit's weights when it has them,
uniformly otherwise, from the seed's stream 1 so the forecast does not reuse the fit's draws)
and continues each draw's own trajectory past the last observed frame.

The counting simulator and the likelihood are the harness's (:mod:`sysid_bench.simulator`),
track preparation is :mod:`methods._tracks`, weighting and resampling :mod:`methods._weights`.
"""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass

import numpy as np

from methods._tracks import Track, clip_state
from methods._weights import resample
from sysid_bench._validate import check_positive_int
from sysid_bench.estimator import Estimator, Forecast, Observation, Posterior
from sysid_bench.simulator import CountingSimulator

__all__ = ["SimulationMethod", "Fit", "forecast_by_simulation", "make_rng", "Stopwatch",
           "one_blas_thread"]


def one_blas_thread():
    """Context limiting BLAS to one thread (``threadpoolctl``).

    The baselines' matrices are tiny (GP kernels of 20 points, a 120 x 140 Hankel matrix, 4-8
    column Jacobians); on the shared 2-core machine OpenBLAS threads contending for the cores
    made them 6-20x slower (bo 19 s -> 3 s, dmd 1.3 s -> 0.06 s per call).
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


class Stopwatch:
    """Wall-clock seconds since construction (``perf_counter``)."""

    def __init__(self) -> None:
        self._t0 = time.perf_counter()

    def __call__(self) -> float:
        return time.perf_counter() - self._t0


def make_rng(seed, stream: int = 0) -> np.random.Generator:
    """Generator for one purpose (``stream``) of a method, fixed by its ``seed``.

    An int (or None) seed gives ``default_rng([seed, stream])`` so that, e.g., a forecast's
    resampling does not reuse the identification's draws; a Generator is used as it is.
    """
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, bool) or not (seed is None or isinstance(seed, (int, np.integer))):
        raise ValueError(f"seed: expected an int, None or numpy.random.Generator, got {seed!r}")
    return np.random.default_rng(None if seed is None else [int(seed), stream])


def forecast_by_simulation(
    sim: CountingSimulator,
    theta: np.ndarray,
    state: np.ndarray,
    floor: float,
    dt: float,
    horizon: int,
    skip: int = 0,
    clock: Stopwatch | None = None,
    extras: dict | None = None,
) -> Forecast:
    """Forecast positions by simulating posterior samples.

    Simulates ``skip + horizon + 1`` frames from ``state`` and returns the last ``horizon``:
    with ``state`` the initial states and ``skip = T - 1`` this continues each sample's own
    trajectory past the last observed frame; with ``state`` the estimated state at the last
    observed frame and ``skip = 0`` it continues from there.

    Parameters
    ----------
    sim : CountingSimulator
    theta : ndarray, shape (S, 4)
    state : ndarray, shape (S, 4)
    floor : float or ndarray, shape (S,)
    dt : float
    horizon : int
    skip : int
    clock : Stopwatch, optional
        Started when the forecast's work began; ``extras["wall_s"]`` reads it at the end.
    extras : dict, optional
        More entries for ``Forecast.extras``.

    Returns
    -------
    Forecast
        mean/std (horizon, 2), samples (S, horizon, 2); ``extras`` holds ``n_simulations`` (all
        of ``sim``'s, the identification's included) and ``wall_s``.
    """
    traj = sim.positions(theta, clip_state(state, floor), skip + horizon + 1, dt, floor)
    samples = traj[:, skip + 1 :]
    ex = dict(extras or {})
    ex["n_simulations"] = sim.n_simulations
    if clock is not None:
        ex["wall_s"] = clock()
    return Forecast(mean=samples.mean(axis=0), std=samples.std(axis=0), samples=samples, extras=ex)


@dataclass
class Fit:
    """What a simulation-based method's fit found.

    Attributes
    ----------
    posterior : Posterior
    theta : ndarray, shape (N, 4)
        Draws a forecast resamples from (physical units).
    state0 : ndarray, shape (N, 4)
        Their initial states.
    floor : float or ndarray, shape (N,)
        The floor (one for all, or per draw when the method samples it).
    track : Track
    sim : CountingSimulator
        The simulator the fit used (a forecast's simulations add to its count).
    clock : Stopwatch
        Started when the fit began (a forecast's ``wall_s`` includes the fit).
    weights : ndarray, shape (N,), optional
        Normalised weights of the draws; None when they are equally weighted samples.
    """

    posterior: Posterior
    theta: np.ndarray
    state0: np.ndarray
    floor: float | np.ndarray
    track: Track
    sim: CountingSimulator
    clock: Stopwatch
    weights: np.ndarray | None = None


class SimulationMethod(Estimator):
    """Base of the simulation-based methods: implement ``_fit``; ``identify``/``forecast`` follow.

    Subclasses take an ``n_forecast`` hyperparameter (draws simulated by ``forecast``) and a
    ``seed``.
    """

    input_kind = "positions"
    min_frames = 3  # fewer seen frames cannot fix a state and parameters (``_tracks.prepare``)
    forecasts = True

    @abc.abstractmethod
    def _fit(self, obs: Observation) -> Fit:
        """Search or sample; everything ``identify`` and ``forecast`` need."""

    def identify(self, obs: Observation) -> Posterior:
        """Posterior over ``(e, g, d, r)`` given all frames of ``obs`` (see the class)."""
        return self._fit(obs).posterior

    def _forecast_state0(self, fit: Fit, idx: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Initial states of the forecast's draws ``idx``: by default the draws' own."""
        return fit.state0[idx]

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Positions of the ``horizon`` frames after ``obs``: ``n_forecast`` draws of the fit
        (with their initial states and floors) continued past the last frame.

        Returns
        -------
        Forecast
            mean/std (horizon, 2); samples (n_forecast, horizon, 2); ``extras`` holds
            ``n_simulations`` (the fit's included), ``wall_s`` and ``posterior_extras``.
        """
        m = check_positive_int(self.n_forecast, "n_forecast")
        fit = self._fit(obs)
        # a stream independent of the fit's draws, still fixed by the seed
        rng = make_rng(self.seed, 1)
        if fit.weights is not None:
            idx = resample(fit.weights, m, rng)
        else:
            idx = rng.choice(len(fit.theta), size=m, replace=len(fit.theta) < m)
        state0 = self._forecast_state0(fit, idx, rng)
        floor = fit.floor[idx] if np.ndim(fit.floor) else fit.floor
        return forecast_by_simulation(
            fit.sim, fit.theta[idx], state0, floor, fit.track.dt, horizon,
            skip=fit.track.n_frames - 1, clock=fit.clock,
            extras={"posterior_extras": fit.posterior.extras},
        )
