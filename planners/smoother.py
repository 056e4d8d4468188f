"""The Student's-t ensemble update at the heart of EnKTS (paper eq. 16-19) and Student's-t sampling.

``nu = math.inf`` is the Gaussian case (EnKS): the same code, not a copy.
"""

from __future__ import annotations

import math

import numpy as np

# Relative Tikhonov regularization of P_y: a barrier that reads 0 for every particle leaves only the
# (sampled) noise in its row, and a near-singular P_y would turn into huge gains.
_RIDGE = 1e-6


def student_t(rng: np.random.Generator, scale: np.ndarray, nu: float, size: int) -> np.ndarray:
    """``size`` draws ``(size, d)`` from St(0, diag(scale**2), nu); Gaussian for ``nu = inf``.

    Drawn as a Gaussian over sqrt(chi2_nu / nu), one mixing variable per draw (a multivariate t, not d
    independent ones), so a surprising draw is surprising in every component together.
    """
    scale = np.asarray(scale, dtype=float)
    z = rng.standard_normal((size, scale.size)) * scale
    if math.isinf(nu):
        return z
    return z * np.sqrt(nu / rng.chisquare(nu, size=(size, 1)))


def spread_factor(nu: float, delta: float, m: int) -> float:
    """Covariance factor that turns the ensemble's perturbed-observation spread into the Student's-t posterior.

    The conditional of a joint St(mu, Sigma, nu) given m observed entries has scale
    ``(nu + delta)/(nu + m) * S`` (S the Schur complement of the scale) and dof ``nu + m`` (eq. 17, 19).
    The perturbed-observation update leaves samples whose *covariance* is ``nu/(nu-2) * S``; a Student's-t
    with scale ``c S`` and dof ``nu'`` has covariance ``c S nu'/(nu'-2)``. Equating gives the factor below.
    It is 1 for nu = inf, > 1 when the innovation is surprising (delta > m(nu-2)/nu + ...): heavy surprise
    widens the search, the mechanism the paper relies on.
    """
    if math.isinf(nu):
        return 1.0
    return (nu + delta) * (nu - 2.0) / (nu * (nu + m - 2.0))


def student_t_update(
    X: np.ndarray, Y: np.ndarray, y: np.ndarray, nu: float, adapt_spread: bool = True,
    max_spread: float = math.inf,
) -> tuple[np.ndarray, float]:
    """One Student's-t ensemble Kalman update (paper eq. 16-19, as read in docs/design.md).

    X: ensemble ``(N, D)``; Y: predicted measurement samples ``(N, m)``, noise included (eq. 14);
    y: the observation ``(m,)``; nu: degrees of freedom (> 2; ``math.inf`` = Gaussian / EnKS).

    - gain ``K = P_xy P_y^-1`` from ensemble (co)variances (eq. 18; the (nu-2)/nu factors cancel);
    - perturbed-observation update ``X^j + K (y - Y^j)`` (eq. 16; the printed eq. subtracts the predicted
      mean, which ignores the observation: a typo);
    - ``delta``: Mahalanobis distance of the mean innovation under the scale ``P_y (nu-2)/nu`` (eq. 17);
    - if ``adapt_spread``: anomalies rescaled by ``sqrt(spread_factor)``, capped at ``max_spread``;
    - returns ``(X_post (N, D), nu + m)`` (eq. 19).
    """
    X, Y, y = np.asarray(X, float), np.asarray(Y, float), np.asarray(y, float)
    if not nu > 2.0:
        raise ValueError(f"nu must be > 2 (finite variance), got {nu}")
    n, m = Y.shape
    if X.shape[0] != n or y.shape != (m,) or n < 2:
        raise ValueError(f"shapes X {X.shape}, Y {Y.shape}, y {y.shape} do not fit (N >= 2 rows each)")
    # Sums over rows rather than np.mean/np.cov: this runs H times per plan and numpy's wrappers cost more
    # than the arithmetic at N = 50.
    A = X - X.sum(axis=0) / n
    y_mean = Y.sum(axis=0) / n
    B = Y - y_mean
    P_xy = A.T @ B / (n - 1)
    P_y = B.T @ B / (n - 1)
    P_y.flat[:: m + 1] += _RIDGE * np.trace(P_y) / m + 1e-12
    # One solve gives both the gain and the whitened mean innovation (P_y is SPD after the ridge).
    innov = y - y_mean
    sol = np.linalg.solve(P_y, np.column_stack([P_xy.T, innov]))
    K = sol[:, :-1].T
    X_post = X + (y - Y) @ K.T
    nu_post = nu + m
    if adapt_spread and not math.isinf(nu):
        delta = float(innov @ sol[:, -1]) * nu / (nu - 2.0)
        factor = min(spread_factor(nu, delta, m), max_spread)
        mean = X_post.sum(axis=0) / n
        X_post = mean + math.sqrt(factor) * (X_post - mean)
    return X_post, nu_post
