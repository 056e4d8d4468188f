import math

import numpy as np
import pytest

from planners.smoother import spread_factor, student_t, student_t_update


def test_gaussian_update_matches_closed_form_kalman_on_a_linear_toy():
    rng = np.random.default_rng(0)
    mu, P = np.array([1.0, -2.0, 0.5]), np.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.5]])
    H, R = np.array([[1.0, 0.0, 1.0], [0.0, 2.0, 0.0]]), np.diag([0.4, 0.3])
    y = np.array([2.5, -3.0])
    n = 40_000
    X = rng.multivariate_normal(mu, P, size=n)
    Y = X @ H.T + rng.multivariate_normal(np.zeros(2), R, size=n)
    X_post, nu_post = student_t_update(X, Y, y, math.inf)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    np.testing.assert_allclose(X_post.mean(0), mu + K @ (y - H @ mu), atol=0.03)
    np.testing.assert_allclose(np.cov(X_post.T), (np.eye(3) - K @ H) @ P, atol=0.03)
    assert math.isinf(nu_post)


@pytest.mark.parametrize("adapt", [True, False])
def test_student_t_update_matches_the_closed_form_conditional(adapt):
    rng = np.random.default_rng(1)
    nu, n = 5.0, 400_000
    mu = np.array([0.0, 1.0, -1.0, 0.5])  # [x (2), y (2)]
    Sigma = np.array([[1.0, 0.2, 0.5, 0.1], [0.2, 1.5, 0.3, 0.4], [0.5, 0.3, 1.2, 0.2], [0.1, 0.4, 0.2, 0.8]])
    Z = mu + student_t(rng, np.ones(4), nu, n) @ np.linalg.cholesky(Sigma).T
    X, Y = Z[:, :2], Z[:, 2:]
    y = np.array([2.0, -2.0])  # far in the tail: delta >> m, so the spread factor matters
    X_post, nu_post = student_t_update(X, Y, y, nu, adapt_spread=adapt)

    Sxx, Sxy, Syy = Sigma[:2, :2], Sigma[:2, 2:], Sigma[2:, 2:]
    innov = y - mu[2:]
    delta = innov @ np.linalg.solve(Syy, innov)
    cond_mean = mu[:2] + Sxy @ np.linalg.solve(Syy, innov)
    cond_scale = (nu + delta) / (nu + 2) * (Sxx - Sxy @ np.linalg.solve(Syy, Sxy.T))
    assert nu_post == nu + 2
    np.testing.assert_allclose(X_post.mean(0), cond_mean, atol=0.02)
    scale_of_ensemble = np.cov(X_post.T) * (nu_post - 2) / nu_post
    if adapt:
        np.testing.assert_allclose(scale_of_ensemble, cond_scale, rtol=0.06, atol=0.02)
    else:  # without the rescaling the spread ignores the surprise: visibly too narrow here
        assert np.trace(scale_of_ensemble) < 0.6 * np.trace(cond_scale)


def test_huge_nu_gives_the_gaussian_result():
    rng = np.random.default_rng(2)
    X = rng.standard_normal((500, 3))
    Y = X[:, :2] * 2 + 0.3 * rng.standard_normal((500, 2))
    y = np.array([1.0, 3.0])
    gauss, _ = student_t_update(X, Y, y, math.inf)
    t_big, _ = student_t_update(X, Y, y, 1e12)
    np.testing.assert_allclose(t_big, gauss, rtol=1e-6, atol=1e-8)
    assert spread_factor(math.inf, 100.0, 3) == 1.0


def test_nu_at_most_two_and_bad_shapes_raise():
    X, Y, y = np.zeros((4, 2)), np.ones((4, 1)), np.zeros(1)
    for nu in (2.0, 1.0, -3.0):
        with pytest.raises(ValueError, match="nu"):
            student_t_update(X, Y, y, nu)
    with pytest.raises(ValueError, match="shapes"):
        student_t_update(X, Y, np.zeros(2), 5.0)


def test_singular_measurement_covariance_stays_finite():
    rng = np.random.default_rng(3)
    X = rng.standard_normal((50, 4))
    Y = np.zeros((50, 3))  # e.g. a barrier that is 0 for every particle, and no noise
    Y[:, 0] = X[:, 0]
    for nu in (math.inf, 3.0):
        X_post, _ = student_t_update(X, Y, np.array([10.0, 0.0, 0.0]), nu, max_spread=25.0)
        assert np.all(np.isfinite(X_post)) and np.abs(X_post).max() < 1e3


def test_student_t_draws_are_heavy_tailed_and_seeded():
    a = student_t(np.random.default_rng(4), np.array([1.0, 2.0]), 3.0, 200_000)
    b = student_t(np.random.default_rng(4), np.array([1.0, 2.0]), 3.0, 200_000)
    g = student_t(np.random.default_rng(4), np.array([1.0, 2.0]), math.inf, 200_000)
    np.testing.assert_array_equal(a, b)
    assert np.mean(np.abs(a[:, 0]) > 5) > 0.005 > np.mean(np.abs(g[:, 0]) > 5)
    np.testing.assert_allclose(g.std(0), [1.0, 2.0], rtol=0.02)
