"""The simulator as simulation-based methods see it: counted, budgeted, and scored one way.

One place for what must be identical across methods so that their numbers are comparable:

* :class:`CountingSimulator` wraps :func:`sysid_bench.core.physics.simulate` and counts simulations
  the way sbibm's simulator wrapper does: **one trajectory = one simulation**, whatever the
  batch size, and refuses to exceed a budget when given one;
* :func:`gaussian_loglik` and :func:`mean_sq_error` score simulated positions against observed
  ones, skipping unseen (NaN) frames: the likelihood of emcee and nuts, the objective of lsq and bo.

Noise model (mirrored by ``methods.nuts`` in JAX): observed positions are the simulated ones plus
independent Gaussian noise of a **fixed** standard deviation ``sigma`` per coordinate, a
hyperparameter of every method (default :data:`DEFAULT_SIGMA` = 0.02 m). Not inferred because
clean positions (the paper's setting) have zero noise, where an inferred scale collapses to 0 and
the posterior to a spike no sampler can explore; 0.02 m is about 2.5 times the RMS error of
:func:`sysid_bench.core.tracking.track` on clean 28x28 renders (0.006-0.009 m), so tracked input is not
treated as more precise than it is. Pass a larger ``sigma`` for noisy video.
"""

from __future__ import annotations

import numpy as np

from sysid_bench.core import physics
from sysid_bench.core._validate import check_positive_float

__all__ = [
    "DEFAULT_SIGMA",
    "CountingSimulator",
    "SimulationBudgetExceeded",
    "gaussian_loglik",
    "mean_sq_error",
    "check_sigma",
]

#: Default standard deviation (m) of the Gaussian position noise in the likelihood.
DEFAULT_SIGMA = 0.02


class SimulationBudgetExceeded(RuntimeError):
    """A method asked for more simulations than its budget allows."""


class CountingSimulator:
    """:func:`sysid_bench.core.physics.simulate` that counts trajectories (sbibm-style budget).

    Parameters
    ----------
    max_simulations : int, optional
        Budget: a call that would take the count past it raises
        :class:`SimulationBudgetExceeded` before simulating. None: no budget.

    Attributes
    ----------
    n_simulations : int
        Trajectories simulated so far; a batch of B counts B.
    """

    def __init__(self, max_simulations: int | None = None) -> None:
        if max_simulations is not None and (
            isinstance(max_simulations, bool) or not isinstance(max_simulations, (int, np.integer))
            or max_simulations < 0
        ):
            raise ValueError(f"max_simulations: expected None or an int >= 0, got {max_simulations!r}")
        self.max_simulations = max_simulations
        self.n_simulations = 0

    def __call__(self, theta, state0, n_frames: int, dt: float, floor) -> np.ndarray:
        """Simulate; same arguments and result as ``physics.simulate``: (B, n_frames, 4)."""
        if self.max_simulations is not None:
            b = int(np.shape(theta)[0])
            if self.n_simulations + b > self.max_simulations:
                raise SimulationBudgetExceeded(
                    f"max_simulations: a batch of {b} would exceed the budget of "
                    f"{self.max_simulations} simulations ({self.n_simulations} used)"
                )
        out = physics.simulate(theta, state0, n_frames=n_frames, dt=dt, floor=floor)
        self.n_simulations += int(out.shape[0])
        return out

    def positions(self, theta, state0, n_frames: int, dt: float, floor) -> np.ndarray:
        """Simulated positions only, shape (B, n_frames, 2)."""
        return self(theta, state0, n_frames, dt, floor)[..., :2]


def mean_sq_error(sim_pos: np.ndarray, obs_pos: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Mean squared position error over seen frames and both coordinates.

    Parameters
    ----------
    sim_pos : ndarray, shape (..., T, 2)
    obs_pos : ndarray, shape (T, 2)
        NaN where unseen (those rows must be False in ``mask``).
    mask : ndarray of bool, shape (T,)

    Returns
    -------
    ndarray, shape (...)
        m^2.
    """
    diff = np.where(mask[:, None], sim_pos - np.where(mask[:, None], obs_pos, 0.0), 0.0)
    return np.sum(diff * diff, axis=(-2, -1)) / (2.0 * np.count_nonzero(mask))


def gaussian_loglik(sim_pos: np.ndarray, obs_pos: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Log-likelihood of observed positions: independent N(sim, sigma^2) per seen coordinate.

    The one likelihood of emcee and nuts (nuts mirrors this in JAX). Frames with
    ``mask == False`` (unseen) contribute nothing.

    Parameters
    ----------
    sim_pos : ndarray, shape (..., T, 2)
        Simulated positions (m).
    obs_pos : ndarray, shape (T, 2)
        Observed positions (m), NaN allowed where ``mask`` is False.
    mask : ndarray of bool, shape (T,)
    sigma : float
        Noise standard deviation (m).

    Returns
    -------
    ndarray, shape (...)
    """
    n = 2.0 * np.count_nonzero(mask)
    diff = np.where(mask[:, None], sim_pos - np.where(mask[:, None], obs_pos, 0.0), 0.0)
    sse = np.sum(diff * diff, axis=(-2, -1))
    return -0.5 * sse / sigma**2 - n * np.log(sigma) - 0.5 * n * np.log(2.0 * np.pi)


def check_sigma(sigma) -> float:
    """``sigma`` (position noise, metres) as a float > 0, else ``ValueError`` naming it."""
    return check_positive_float(sigma, "sigma")
