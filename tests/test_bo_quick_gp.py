"""bo's quick GP (methods/bo.py: QuickGPR) gives skopt's bits: likelihood, gradient, predictions."""

import numpy as np
import pytest

pytest.importorskip("skopt")
pytestmark = pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")

import methods  # noqa: E402
import methods.bo as bo  # noqa: E402
from sysid_bench.core.datasets import make_dataset  # noqa: E402


def _pair(n=12, d=4, seed=3):
    """The library's default GP and the quick one, fitted to the same random data."""
    from skopt.utils import cook_estimator, normalize_dimensions

    rng = np.random.default_rng(seed)
    X, y = rng.random((n, d)), rng.normal(size=n)
    lib = cook_estimator("GP", space=normalize_dimensions([(0.0, 1.0)] * d), random_state=7,
                         noise="gaussian")
    lib.set_params(optimizer=None)  # one likelihood at the start theta: a fast fit
    quick = bo._quick_gpr_class()(**lib.get_params(deep=False))
    return lib.fit(X, y), quick.fit(X, y), rng


def test_likelihood_and_gradient_bits_equal_on_random_thetas():
    lib, quick, rng = _pair()
    assert quick._quick() is not None  # the fast path is the one tested
    assert lib.log_marginal_likelihood_value_ == quick.log_marginal_likelihood_value_
    bounds = lib.kernel_.bounds
    for _ in range(5):
        theta = rng.uniform(bounds[:, 0], bounds[:, 1])
        a, ga = lib.log_marginal_likelihood(theta, eval_gradient=True, clone_kernel=False)
        b, gb = quick.log_marginal_likelihood(theta, eval_gradient=True, clone_kernel=False)
        assert a == b and ga.tobytes() == gb.tobytes()
        assert lib.log_marginal_likelihood(theta, clone_kernel=False) == \
            quick.log_marginal_likelihood(theta, clone_kernel=False)
        for k, a in lib.kernel_.get_params().items():  # the same kernel values left behind
            if isinstance(a, (float, np.ndarray)):
                assert np.asarray(a).tobytes() == np.asarray(quick.kernel_.get_params()[k]).tobytes()


def test_predictions_bits_equal():
    lib, quick, rng = _pair()
    X = rng.random((50, 4))
    for a, b in zip(lib.predict(X, return_std=True), quick.predict(X, return_std=True)):
        assert a.tobytes() == b.tobytes()
    assert lib.predict(X).tobytes() == quick.predict(X).tobytes()
    x = X[:1]
    for a, b in zip(lib.predict(x, True, False, True, True), quick.predict(x, True, False, True, True)):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
    with pytest.raises(ValueError, match="n_samples > 1"):
        quick.predict(X, return_std=True, return_mean_grad=True)


def test_posterior_bytes_equal_to_library_search(monkeypatch):
    obs = make_dataset("test", 1, seed=5, n_frames=40).observation(0, positions=True)
    opts = dict(bo.BayesOpt.contract_options, n_calls=4)  # one GP fit and one acquisition
    quick = methods.get("bo", **opts).identify(obs)

    def library(func, n_dims, *, random_state, **options):
        from skopt import gp_minimize

        return gp_minimize(func, [(0.0, 1.0)] * n_dims, random_state=random_state, **options)

    monkeypatch.setattr(bo, "_gp_minimize", library)
    lib = methods.get("bo", **opts).identify(obs)
    for field in ("mean", "std", "samples"):
        assert getattr(lib, field).tobytes() == getattr(quick, field).tobytes()
    assert {k: v for k, v in lib.extras.items() if k != "wall_s"} == \
        {k: v for k, v in quick.extras.items() if k != "wall_s"}


def test_skopt_helpers_give_the_library_values():
    import skopt.acquisition as acquisition
    import skopt.space.space as space
    from scipy.stats import norm

    sp = space.Space([(0.0, 1.0), (-2.0, 3.0), (1e-3, 10.0, "log-uniform")])
    lib_rows, lib_t = None, None
    for quick in (False, True):
        rng = np.random.RandomState(4)
        with bo._quick_skopt_helpers() if quick else np.errstate():
            rows = sp.rvs(n_samples=300, random_state=rng)
            t = sp.transform(rows)
            assert (acquisition.norm is not norm) == quick
        if quick:
            assert rows == lib_rows and [type(v) for v in rows[0]] == [type(v) for v in lib_rows[0]]
            assert t.tobytes() == lib_t.tobytes()
        lib_rows, lib_t = rows, t
    assert acquisition.norm is norm and space._transpose_list_array is not bo._transpose_rows
    x = np.concatenate([np.random.default_rng(1).normal(0, 10, 500), [0.0, -0.0, 40.0, -40.0, np.inf, -np.inf]])
    q = bo._QuickNorm(norm)
    assert q.cdf(x).tobytes() == norm.cdf(x).tobytes() and q.pdf(x).tobytes() == norm.pdf(x).tobytes()
    assert q.logcdf(1.0) == norm.logcdf(1.0)


def test_quick_cholesky_and_cho_solve_bits_equal():
    from numpy.linalg import LinAlgError
    from scipy.linalg import cho_solve, cholesky

    rng = np.random.default_rng(2)
    A = rng.normal(size=(15, 15))
    K = A @ A.T + 1e-3 * np.eye(15)
    chol, solve = bo._quick_cholesky(cholesky), bo._quick_cho_solve(cho_solve)
    for lower in (True, False):
        L = cholesky(K, lower=lower, check_finite=False)
        assert chol(K, lower=lower, check_finite=False).tobytes() == L.tobytes()
        for b in (rng.normal(size=(15, 1)), rng.normal(size=15), np.eye(15)):
            assert solve((L, lower), b, check_finite=False).tobytes() == \
                cho_solve((L, lower), b, check_finite=False).tobytes()
    with pytest.raises(LinAlgError, match="not positive definite"):
        chol(-K, lower=True, check_finite=False)
