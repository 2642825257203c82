"""Weighting and resampling of simulated draws (lsq, bo)."""

from __future__ import annotations

import numpy as np

__all__ = ["tempered_weights", "resample"]


def tempered_weights(loglik: np.ndarray, min_ess: float) -> tuple[np.ndarray, float, float]:
    """Normalised importance weights ``exp(beta * loglik)`` with the largest ``beta`` in (0, 1]
    whose effective sample size is at least ``min_ess``.

    A batch of prior draws rarely holds more than one draw inside a sharp likelihood peak; the
    untempered weights then put all mass on one draw and the spread collapses to 0. Tempering
    widens the weights to the resolution the draws actually have, so the reported spread is
    honest about the search rather than about the (unexplored) peak.

    Parameters
    ----------
    loglik : ndarray, shape (N,)
    min_ess : float

    Returns
    -------
    weights : ndarray, shape (N,)
    beta : float
    ess : float
    """
    ll = np.asarray(loglik, dtype=np.float64)
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    target = min(float(min_ess), float(np.isfinite(ll).sum()))

    def weights(beta):
        z = beta * (ll - ll.max())
        w = np.exp(z)
        w /= w.sum()
        return w, 1.0 / np.sum(w * w)

    w, ess = weights(1.0)
    if ess >= target:
        return w, 1.0, float(ess)
    lo, hi = 0.0, 1.0  # ESS(beta) falls as beta grows
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        _, e = weights(mid)
        if e >= target:
            lo = mid
        else:
            hi = mid
    w, ess = weights(lo)
    return w, lo, float(ess)


def resample(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` draws by systematic resampling of ``weights`` (N,)."""
    c = np.cumsum(weights)
    c[-1] = 1.0
    u = (rng.random() + np.arange(n)) / n
    return np.searchsorted(c, u)
