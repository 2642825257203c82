"""Scores as pure functions of arrays: no estimator, no I/O, no hidden state.

Parameters are compared after normalising each to [0, 1] by ``PRIOR`` (so guessing the prior
mean of a uniform prior scores 1/12 = 0.083 per parameter); positions after dividing by the view
size (10 m).
"""

from __future__ import annotations

import numpy as np

from sysid_bench.core._validate import as_float_array, check_seed
from sysid_bench.core.physics import BOX_WIDTH, PRIOR_LO, PRIOR_SPAN

__all__ = [
    "normalised_param_se",
    "param_mse",
    "position_mse",
    "interval_coverage",
    "gaussian_nll",
    "bootstrap_ci",
    "GUESS_MSE",
    "central_z",
]

_SPAN = PRIOR_SPAN
_LO = PRIOR_LO
#: Normalised MSE of always answering the prior mean, for a uniform truth: 1/12.
GUESS_MSE = 1.0 / 12.0


def central_z(level):
    """z such that N(0, 1) holds ``level`` of its mass in [-z, z] (the one definition of the
    Gaussian intervals of posteriors and forecasts): 0.674 for 0.5, 1.645 for 0.9."""
    from scipy.special import ndtri

    return ndtri(1 - (1 - np.asarray(level, dtype=np.float64)) / 2)


def _pair(truth, estimate, last: int, name_t: str, name_e: str):
    t = as_float_array(truth, name_t, last=last)
    e = as_float_array(estimate, name_e, last=last, allow_nan=True)
    if t.shape != e.shape:
        raise ValueError(f"{name_e}: expected shape {t.shape} like {name_t}, got {e.shape}")
    return t, e


def normalised_param_se(theta_true, theta_est) -> np.ndarray:
    """Squared error of each parameter after normalising by ``PRIOR``.

    Parameters
    ----------
    theta_true, theta_est : array_like, shape (..., 4)

    Returns
    -------
    ndarray, shape (..., 4)
    """
    t, e = _pair(theta_true, theta_est, 4, "theta_true", "theta_est")
    return ((e - t) / _SPAN) ** 2


def param_mse(theta_true, theta_est, axis=0) -> np.ndarray:
    """Normalised parameter MSE averaged over ``axis`` (cases by default).

    Returns
    -------
    ndarray, shape (4,) for (N, 4) inputs: one value per parameter in ``PARAMS`` order.
    """
    return np.mean(normalised_param_se(theta_true, theta_est), axis=axis)


def position_mse(pos_true, pos_pred, view: float = BOX_WIDTH, axis=None) -> np.ndarray | float:
    """MSE of positions divided by ``view`` (metres), over x and y.

    Parameters
    ----------
    pos_true, pos_pred : array_like, shape (..., H, 2)
    axis : int or tuple, optional
        Axes to average; ``None`` averages everything. NaN truths (unseen frames) are skipped.
    """
    t, p = _pair(pos_true, pos_pred, 2, "pos_true", "pos_pred")
    se = ((p - t) / view) ** 2
    return np.nanmean(se, axis=axis)


def interval_coverage(truth, lo, hi, axis=0) -> np.ndarray:
    """Fraction of cases whose truth lies in ``[lo, hi]``.

    Parameters
    ----------
    truth, lo, hi : array_like, shape (N, K)

    Returns
    -------
    ndarray, shape (K,)
    """
    t = as_float_array(truth, "truth", ndim=(1, 2))
    lo = as_float_array(lo, "lo", ndim=(1, 2), allow_nan=True)
    hi = as_float_array(hi, "hi", ndim=(1, 2), allow_nan=True)
    if not (t.shape == lo.shape == hi.shape):
        raise ValueError(f"lo, hi: expected shape {t.shape} like truth, got {lo.shape} and {hi.shape}")
    return np.mean((t >= lo) & (t <= hi), axis=axis)


def gaussian_nll(truth, mean, std, normalise: bool = True) -> np.ndarray:
    """Negative log-likelihood of ``truth`` under ``N(mean, std^2)``, element-wise.

    With ``normalise`` (parameters only, last axis 4), everything is first mapped to [0, 1]
    by ``PRIOR`` so parameters of different units are comparable. A zero std gives ``inf``
    unless the mean is exact.

    Returns
    -------
    ndarray, same shape as ``truth``
    """
    t = as_float_array(truth, "truth")
    m = as_float_array(mean, "mean")
    s = np.asarray(std, dtype=np.float64)
    if not (t.shape == m.shape == s.shape):
        raise ValueError(f"mean, std: expected shape {t.shape} like truth, got {m.shape}, {s.shape}")
    if np.isnan(s).any() or (s < 0).any():
        raise ValueError("std: expected non-negative values")
    if normalise:
        if t.shape[-1] != 4:
            raise ValueError(f"truth: expected last axis 4 (parameters) to normalise, got {t.shape}")
        t, m, s = (t - _LO) / _SPAN, (m - _LO) / _SPAN, s / _SPAN
    pos = s > 0
    safe = np.where(pos, s, 1.0)
    nll = 0.5 * np.log(2 * np.pi) + np.log(safe) + 0.5 * ((t - m) / safe) ** 2
    # A point mass: certain and right is -inf, certain and wrong is +inf.
    return np.where(pos, nll, np.where(t == m, -np.inf, np.inf))


def bootstrap_ci(values, level: float = 0.95, n_boot: int = 2000, seed=0) -> tuple[float, float, float]:
    """Mean of ``values`` with a percentile-bootstrap confidence interval (``scipy.stats.bootstrap``).

    The result depends on the values, not their order: they are sorted first (a table's rows
    arrive in the order its cells finished; issue 14), so the same cases and ``seed`` give the
    same bytes.

    Parameters
    ----------
    values : array_like, shape (N,)
        NaN entries are left out.
    level : float
    n_boot : int
    seed : int, None or numpy.random.Generator

    Returns
    -------
    (mean, lo, hi)
    """
    v = as_float_array(values, "values", ndim=1, allow_nan=True)
    v = np.sort(v[np.isfinite(v)])
    if v.size == 0:
        return (np.nan, np.nan, np.nan)
    if not 0.0 < level < 1.0:
        raise ValueError(f"level: expected a probability in (0, 1), got {level!r}")
    if int(n_boot) != n_boot or n_boot < 1:
        raise ValueError(f"n_boot: expected a positive integer, got {n_boot!r}")
    rng = check_seed(seed)
    if v.size == 1:  # one value: every resample is that value (scipy refuses a sample of one)
        return float(v[0]), float(v[0]), float(v[0])
    from scipy import stats

    res = stats.bootstrap((v,), np.mean, n_resamples=int(n_boot), vectorized=True, axis=-1,
                          confidence_level=level, method="percentile", **_rng_kw(stats, rng))
    ci = res.confidence_interval
    return float(v.mean()), float(ci.low), float(ci.high)


def _rng_kw(stats, rng) -> dict:
    """The generator as scipy.stats.bootstrap takes it (``rng`` from 1.15, ``random_state`` before)."""
    import inspect

    return {"rng" if "rng" in inspect.signature(stats.bootstrap).parameters else "random_state": rng}
