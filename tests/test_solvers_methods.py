"""Every identification method on problems with a closed-form answer (calib/solvers)."""

import numpy as np
import pytest

from pmcal.calib.solvers import METHODS, Problem, box_problem, identify
from pmcal.calib.solvers.base import crlb_covariance

SIGMA = 0.1


@pytest.fixture(scope="module")
def linear():
    """y = A x + noise, sigma known: least-squares estimate and Cramer-Rao covariance in closed form."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(40, 4)) * np.array([1.0, 3.0, 0.3, 10.0])
    x_true = np.array([0.8, -1.2, 2.0, 0.3])
    y = A @ x_true + SIGMA * rng.normal(size=40)
    prob = box_problem(lambda X: X @ A.T - y, ["a", "b", "c", "d"], ["mm"] * 4, np.full(4, 5.0), sigma=SIGMA)
    x_hat = np.linalg.lstsq(A, y, rcond=None)[0]
    cov = SIGMA**2 * np.linalg.inv(A.T @ A)
    return prob, A, y, x_hat, cov


def test_problem_population_and_jacobian(linear):
    prob, A, y, _, _ = linear
    X = np.random.default_rng(0).normal(size=(7, 4))
    np.testing.assert_allclose(prob.residuals(X), X @ A.T - y)
    np.testing.assert_allclose(prob.residuals(X[2]), A @ X[2] - y)
    np.testing.assert_allclose(prob.jacobian(X[0]), A, rtol=1e-7, atol=1e-9)   # central differences
    np.testing.assert_allclose(prob.cost(X), np.sum(((X @ A.T - y) / SIGMA) ** 2, axis=1))


@pytest.mark.parametrize("method", ["hga", "lm", "tsvd"])
def test_local_optimum_and_crlb(linear, method):
    prob, _, _, x_hat, cov = linear
    res = identify(prob, method, seed=1)
    std = np.sqrt(np.diag(cov))
    assert res.method == method and res.names == ["a", "b", "c", "d"]
    np.testing.assert_array_less(np.abs(res.x - x_hat), 1e-3 * std)
    np.testing.assert_allclose(res.covariance, cov, rtol=1e-5)
    assert res.residuals.shape == (40,) and res.n_eval > 0 and res.wall_time > 0


def test_tikhonov_given_lambda_matches_closed_form(linear):
    """Regularised in box-scaled coordinates z = x / 5: (Js^T Js + lam I) z = Js^T b, Js = A * 5 / sigma."""
    prob, A, y, _, _ = linear
    lam = 3.0
    Js = A * 5.0 / SIGMA
    z = np.linalg.solve(Js.T @ Js + lam * np.eye(4), Js.T @ (y / SIGMA))
    res = identify(prob, "tikhonov", lam=lam)
    np.testing.assert_allclose(res.x, 5.0 * z, rtol=1e-8)
    assert res.info["lambda"] == lam


@pytest.mark.parametrize("method", ["ga", "pso", "sa"])
def test_global_methods_reach_the_optimum(linear, method):
    """The population methods end within a fraction of a standard deviation of the optimum."""
    prob, _, _, x_hat, cov = linear
    res = identify(prob, method, seed=3)
    std = np.sqrt(np.diag(cov))
    assert np.all(np.abs(res.x - x_hat) < 0.5 * std), (res.x - x_hat) / std
    assert res.info["chi2"] < prob.cost(x_hat) + 1.0


def test_hga_finds_global_minimum_where_lm_stalls():
    """Frequency fit y = sin(w t): many local minima in w. LM from the prior w = 1 stays in a wrong valley;
    the GA phase finds the right one and the polish nails it."""
    t = np.linspace(0, 10, 200)
    y = np.sin(3.1 * t) + 0.01 * np.random.default_rng(0).normal(size=t.size)
    prob = Problem(fun=lambda X: np.sin(X[:, :1] * t) - y, names=["w"], units=["rad/s"], x0=[1.0],
                   lower=[0.5], upper=[5.0], sigma=0.01)
    lm = identify(prob, "lm", fix_unidentifiable=False)
    hga = identify(prob, "hga", seed=0, fix_unidentifiable=False)
    assert abs(lm.x[0] - 3.1) > 0.5
    assert abs(hga.x[0] - 3.1) < 5 * hga.std[0]
    assert hga.info["chi2"] < 1.5 * t.size


def test_prior_gives_the_map_estimate(linear):
    prob, A, y, _, _ = linear
    std = np.array([0.1, 10.0, 0.05, 1.0])
    expected = np.linalg.solve(A.T @ A / SIGMA**2 + np.diag(1 / std**2), A.T @ y / SIGMA**2)
    res = identify(prob, "lm", prior_std=std)
    np.testing.assert_allclose(res.x, expected, rtol=1e-6, atol=1e-9)
    assert res.residuals.shape == (40,)          # prior pseudo-observations are not data residuals


def test_parameter_without_effect_is_fixed_and_reported():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(30, 3))
    A[:, 1] = 0.0                                 # "b" has no effect at all
    y = A @ np.array([1.0, 0.0, -2.0]) + SIGMA * rng.normal(size=30)
    prob = box_problem(lambda X: X @ A.T - y, ["a", "b", "c"], ["mm"] * 3, np.full(3, 5.0), sigma=SIGMA)
    for method in METHODS:
        res = identify(prob, method, seed=0, **({"maxfun": 3000} if method == "sa" else {}))
        assert res.fixed == ["b"] and res.info["unidentifiable"] == ["b"]
        assert res.names == ["a", "b", "c"] and res.x[1] == 0.0
        assert res.covariance[1, 1] == 0.0 and res.covariance[0, 0] > 0


def test_callback_stops_the_ga(linear):
    prob = linear[0]
    res = identify(prob, "ga", seed=0, callback=lambda gen, best: gen >= 5)
    assert res.n_iter == 5 and "callback" in res.message


def test_unknown_method_is_refused(linear):
    with pytest.raises(ValueError, match="unknown identification method"):
        identify(linear[0], "newton")


def test_crlb_covariance_is_the_inverse_fisher_matrix():
    J = np.random.default_rng(5).normal(size=(25, 4)) * np.array([1e3, 1.0, 1e-3, 5.0])
    np.testing.assert_allclose(crlb_covariance(J), np.linalg.inv(J.T @ J), rtol=1e-8)
