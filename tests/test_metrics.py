"""Metrics on hand-computed cases."""

import numpy as np
import pytest

from sysid_bench.core import metrics as M
from sysid_bench.core.physics import PRIOR


def test_param_mse_hand_computed():
    lo = np.array([PRIOR[p][0] for p in "egdr"])
    hi = np.array([PRIOR[p][1] for p in "egdr"])
    truth = np.vstack([lo, hi])
    est = np.vstack([lo + 0.5 * (hi - lo), hi])  # first case off by half a range, second exact
    np.testing.assert_allclose(M.param_mse(truth, est), [0.125] * 4)
    np.testing.assert_allclose(M.normalised_param_se(truth, est)[0], [0.25] * 4)


def test_guessing_the_mean_scores_one_twelfth():
    rng = np.random.default_rng(0)
    u = rng.random((200_000, 4))
    lo = np.array([PRIOR[p][0] for p in "egdr"])
    hi = np.array([PRIOR[p][1] for p in "egdr"])
    truth = lo + u * (hi - lo)
    mse = M.param_mse(truth, np.broadcast_to((lo + hi) / 2, truth.shape))
    np.testing.assert_allclose(mse, M.GUESS_MSE, rtol=0.01)


def test_position_mse():
    t = np.zeros((3, 2))
    p = np.array([[1.0, 0.0], [0.0, 2.0], [np.nan, np.nan]])
    # squares of (0.1, 0, 0, 0.2) over 4 seen values; the NaN frame is skipped
    assert M.position_mse(t, p) == pytest.approx((0.01 + 0.04) / 4)


def test_interval_coverage():
    truth = np.array([[0.0], [1.0], [2.0], [3.0]])
    lo, hi = np.full((4, 1), 0.5), np.full((4, 1), 2.0)
    np.testing.assert_allclose(M.interval_coverage(truth, lo, hi), [0.5])


def test_gaussian_nll_hand_computed():
    nll = M.gaussian_nll(np.array([1.0]), np.array([0.0]), np.array([2.0]), normalise=False)
    assert nll[0] == pytest.approx(0.5 * np.log(2 * np.pi) + np.log(2.0) + 0.5 * 0.25)
    sure = M.gaussian_nll(np.array([1.0, 1.0]), np.array([1.0, 0.0]), np.zeros(2), normalise=False)
    assert sure[0] == -np.inf and sure[1] == np.inf


def test_gaussian_nll_normalised_matches_manual():
    lo = np.array([PRIOR[p][0] for p in "egdr"])
    span = np.array([PRIOR[p][1] - PRIOR[p][0] for p in "egdr"])
    truth = lo + 0.5 * span
    mean = lo + 0.6 * span
    std = 0.1 * span
    expected = 0.5 * np.log(2 * np.pi) + np.log(0.1) + 0.5
    np.testing.assert_allclose(M.gaussian_nll(truth, mean, std), expected)


def test_bootstrap_ci_brackets_mean():
    m, lo, hi = M.bootstrap_ci(np.arange(100.0), seed=1)
    assert m == pytest.approx(49.5) and lo < m < hi
    assert M.bootstrap_ci(np.arange(100.0), seed=1) == (m, lo, hi)


def test_bootstrap_ci_is_the_percentile_bootstrap():
    # the plain percentile bootstrap written out with the same generator: scipy.stats.bootstrap
    # draws the same resamples, so the interval (and every table built on it) is unchanged
    v = np.random.default_rng(5).gamma(2.0, size=40)
    ref_v = np.sort(v)
    idx = np.random.default_rng(11).integers(0, v.size, size=(500, v.size))
    ref = np.quantile(ref_v[idx].mean(axis=1), [0.05, 0.95])
    m, lo, hi = M.bootstrap_ci(v, level=0.9, n_boot=500, seed=11)
    assert m == pytest.approx(v.mean(), rel=1e-12)
    np.testing.assert_allclose((lo, hi), ref, rtol=1e-12)
    # known value: for many values the interval approaches mean +- 1.96 standard errors
    w = np.random.default_rng(0).normal(3.0, 2.0, size=4000)
    m, lo, hi = M.bootstrap_ci(w, seed=0)
    se = w.std() / np.sqrt(w.size)
    np.testing.assert_allclose((lo, hi), (m - 1.96 * se, m + 1.96 * se), atol=0.15 * se)
    # one value; NaN left out
    assert M.bootstrap_ci([2.0, np.nan]) == (2.0, 2.0, 2.0)
    with pytest.raises(ValueError, match="level: expected a probability"):
        M.bootstrap_ci(v, level=95)
    with pytest.raises(ValueError, match="n_boot: expected a positive integer"):
        M.bootstrap_ci(v, n_boot=0)


def test_metric_bad_input():
    with pytest.raises(ValueError, match="theta_est"):
        M.param_mse(np.zeros((2, 4)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="theta_true"):
        M.param_mse(np.full((2, 4), np.nan), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="std"):
        M.gaussian_nll(np.zeros(4), np.zeros(4), -np.ones(4), normalise=False)
