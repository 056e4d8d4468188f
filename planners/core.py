"""The pure planner core of EnKTS and EnKS (paper Algorithm 1), in JAX.

    action, carry, plan = plan_step(problem, settings, carry, obs, key)

One compiled function per :class:`Settings` (the static shapes and switches): ``jax.jit`` with ``lax.scan`` over the
horizon, fixed shapes (inactive barrier rows are masked, not dropped; the control history has its full width from
the start), no Python branches on data, nothing that raises once compiled (the one check, of the static ``update``
reading, runs while tracing), explicit PRNG keys, the road's shape traced (a redrawn road is new data, not a new
program). ``jax.vmap`` of it plans a batch of episodes at once; the same code runs on a GPU when JAX sees one.
:class:`bimp.planners.enkts.EnKTSPlanner` is the thin stateful adapter around it.

Per control step, smoothing over the horizon ``t = 0 .. H-1`` (particles ``j = 1 .. N``):

    du_t^j = du_nominal_t + w^j,   w ~ St(0, diag(sigma_du^2), nu)               (eq. 7, prediction)
    u_t^j  = u_{t-1}^j + du_t^j;   x_{t+1}^j = f(x_t^j, u_t^j)                   (eq. 1, the learned model)
    Y^j    = h(x_{t+1}^j, u_t^j, du_t^j) + v^j,  v ~ St(0, R, nu)               (eq. 8, 14)
    [x_{t+1}, du_t, u_0 .. u_{H-1}]^j <- student_t_update(..., Y, y, nu)         (eq. 16-19)

The update reaches back over the stored controls (smoothing); past positions are not stored, they are not needed to
predict the future. The applied action is the smoothed mean of ``u_0``; the next plan starts from this plan's mean
controls shifted by one step. EnKS is the same code with ``nu = inf``.

Precision: float32. Measured against float64 on the same keys (``tests/planners/test_core.py``), the applied
action differs by far less than the ensemble's own spread, and float32 is what the MLP was trained and evaluated in.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from bimp.envs.scene import split_obs
from bimp.planners import model as vehicle
from bimp.planners.problem import (
    ACTIVE,
    N_FIRST_CONTROL,
    N_TRACK,
    Problem,
    measure,
    predict_obstacles,
    reference_profile,
)

# Relative Tikhonov regularization of P_y: a barrier that reads 0 for every particle leaves only the (sampled)
# noise in its row, and a near-singular P_y would turn into huge gains.
RIDGE = 1e-6
UNROLL = 1


class Settings(NamedTuple):
    """The static part of a planner's config: shapes and switches (one compiled program per value).

    n_particles N, horizon H, iterations (smoothing passes; 1 = the paper's single pass), n_obstacles K,
    adapt_spread, grow_nu, gate_barriers, first_control_barriers, update (the reading of eq. 16: one of
    ``READINGS``); nu, max_spread, max_innovation, relaxation and sigma_du are numbers the program is specialized on
    too (they are few and fixed per config)."""

    n_particles: int
    horizon: int
    n_obstacles: int
    nu: float
    adapt_spread: bool
    grow_nu: bool
    max_spread: float
    max_innovation: float
    relaxation: float
    iterations: int
    sigma_du: tuple[float, float]
    gate_barriers: bool = True
    first_control_barriers: bool = True
    update: str = "perturbed"


# The readings of the printed update (eq. 16), ``X^j + K (ybar^j - yhat)``: see :func:`student_t_update`.
READINGS = ("perturbed", "deterministic", "literal")


class Carry(NamedTuple):
    """What one plan hands the next: the mean controls ``(H, 2)`` and whether there are any yet."""

    previous: jnp.ndarray
    has_previous: jnp.ndarray


class PlanOut(NamedTuple):
    """The plan: mean ``controls (H, 2)``, the smoothed ``control_particles (N, H, 2)``, and ``ok``: False when the
    plan came out non-finite and the action fell back to holding the last input (states: :func:`roll_out`)."""

    controls: jnp.ndarray
    control_particles: jnp.ndarray
    ok: jnp.ndarray


def initial_carry(horizon: int) -> Carry:
    return Carry(jnp.zeros((horizon, 2), jnp.float32), jnp.zeros((), bool))


# --- sampling and the update ------------------------------------------------------------------------------------
def student_t(key: jax.Array, scale: jnp.ndarray, nu: float, shape: tuple[int, ...]) -> jnp.ndarray:
    """Draws ``(*shape, d)`` from St(0, diag(scale^2), nu), ``scale (d,)``; Gaussian for ``nu = inf``.

    A Gaussian over sqrt(chi2_nu / nu), one mixing variable per draw: the multivariate t of the paper, in which a
    surprising draw is surprising in every component together (``jax.random.t`` component-wise is not, and is
    slower). The planner draws a whole plan's noise at once, in one call per kind.
    """
    k_z, k_w = jax.random.split(key)
    scale = jnp.asarray(scale)
    # Drawn in float32 whatever the precision of the arithmetic: float32 and float64 plans then see the same noise.
    z = jax.random.normal(k_z, (*shape, scale.shape[0]), jnp.float32).astype(scale.dtype) * scale
    if math.isinf(nu):
        return z
    return z * jnp.sqrt(nu / chi_square(k_w, nu, (*shape, 1)).astype(scale.dtype))


def chi_square(key: jax.Array, nu: float, shape: tuple[int, ...]) -> jnp.ndarray:
    """Chi-square draws of ``nu`` degrees of freedom, float32. An integer ``nu`` (up to 64) is the sum of ``nu``
    squared standard normals, exactly the distribution and 10-20x faster here than ``jax.random.chisquare``, whose
    gamma sampler is a rejection loop (165 ms against 8 ms for 200k draws at nu = 4 on this machine's CPU)."""
    if float(nu).is_integer() and nu <= 64:
        return jnp.sum(jax.random.normal(key, (*shape, int(nu)), jnp.float32) ** 2, axis=-1)
    return jax.random.chisquare(key, nu, shape, jnp.float32)


def spread_factor(nu, delta, m):
    """Covariance factor that turns the perturbed-observation ensemble's spread into the Student's-t posterior.

    The conditional of a joint St(mu, Sigma, nu) given m observed entries has scale ``(nu + delta)/(nu + m) S`` and
    dof ``nu + m`` (eq. 17, 19). The perturbed-observation update leaves samples of *covariance* ``nu/(nu-2) S``;
    a Student's-t of scale ``c S`` and dof ``nu'`` has covariance ``c S nu'/(nu'-2)``. Equating gives this factor.
    It exceeds 1 when the innovation is surprising: heavy surprise widens the search.
    """
    return (nu + delta) * (nu - 2.0) / (nu * (nu + m - 2.0))


def student_t_update(X, Y, y, nu, active, adapt_spread: bool = True, max_spread: float = math.inf, *,
                     reading: str = "perturbed", V=None, R=None):
    """One Student's-t ensemble Kalman update (paper eq. 16-19, read as in ``docs/design.md``).

    X: ensemble ``(N, D)``; Y: predicted measurement samples ``(N, m)``; y: the observation ``(m,)``; nu: degrees
    of freedom (> 2; ``inf`` = Gaussian); active: bool ``(m,)``, the rows that take part (an inactive row is masked
    out exactly as if dropped: zero anomalies, unit variance, no innovation).

    - gain ``K = P_xy P_y^-1`` from ensemble (co)variances (eq. 18; the (nu-2)/nu factors cancel);
    - the shift of particle j, by ``reading`` of the printed eq. 16 (``X^j + K (ybar^j - yhat)``):
      ``"perturbed"`` (ours, the default): ``Y = h + v`` noise included (eq. 14), ``X^j + K (y - Y^j)``, the
      perturbed-observation ensemble update; ``"deterministic"`` (the form of the authors' public EnKS code):
      ``Y = h`` without noise, the noise covariance ``R (m,)`` added to ``P_y``, ``X^j + K (y - Y^j)``, whose
      posterior spread is too narrow by the missing ``K R K^T``; ``"literal"`` (the print): ``Y = h + v``, every
      particle moved by ``K (y + v^j - mean(Y))`` with ``V = v (N, m)``, so the regression never removes the
      anomalies it explains and the spread only grows;
    - ``delta``: Mahalanobis distance of the mean innovation under the scale ``P_y (nu-2)/nu`` (eq. 17);
    - if ``adapt_spread``: anomalies rescaled by ``sqrt(spread_factor)``, capped at ``max_spread``;
    - returns ``(X_post (N, D), nu + m_active)`` (eq. 19).
    """
    if reading not in READINGS:
        raise ValueError(f"reading must be one of {READINGS}, got {reading!r}")
    n, m = Y.shape
    mask = active.astype(Y.dtype)
    A = X - X.mean(axis=0)
    y_mean = Y.mean(axis=0)
    B = (Y - y_mean) * mask
    P_xy = A.T @ B / (n - 1)
    P_y = B.T @ B / (n - 1)
    if reading == "deterministic":
        P_y = P_y + jnp.diag(R * mask)
    m_active = mask.sum()
    ridge = RIDGE * jnp.trace(P_y) / jnp.maximum(m_active, 1.0) + 1e-12
    P_y = P_y + jnp.diag(jnp.where(active, ridge, 1.0))
    innov = (y - y_mean) * mask
    # One solve gives both the gain and the whitened mean innovation (P_y is SPD after the ridge).
    sol = jnp.linalg.solve(P_y, jnp.concatenate([P_xy.T, innov[:, None]], axis=1))
    shifts = (innov + V * mask) if reading == "literal" else (y - Y) * mask
    X_post = X + shifts @ sol[:, :-1]
    nu_post = nu + m_active
    gaussian = isinstance(nu, (int, float)) and math.isinf(nu)  # traced nu: the caller decides (Settings)
    if adapt_spread and not gaussian:
        delta = innov @ sol[:, -1] * nu / (nu - 2.0)
        factor = jnp.minimum(spread_factor(nu, delta, m_active), max_spread)
        mean = X_post.mean(axis=0)
        X_post = mean + jnp.sqrt(factor) * (X_post - mean)
    return X_post, nu_post


def _mean_std(A):
    mean = A.mean(axis=0)
    return mean, jnp.sqrt(((A - mean) ** 2).mean(axis=0))


def _active(h, gate: bool = True, first_control: bool = True):
    """Rows ``(m,)`` of the measurement ``h (N, m)`` that take part in the update: the tracking rows, and the barriers
    some particle touches. A barrier that reads ~0 for every particle is flat there and carries no information, yet
    with N = 50 its noise regresses spuriously on the plan and collapses the ensemble within a few steps.
    ``gate=False`` keeps every row (the ablation's "no gating"); ``first_control=False`` drops the last four rows,
    the first control's bounds (:data:`bimp.planners.problem.BARRIERS`)."""
    rows = jnp.arange(h.shape[1])
    active = (rows < N_TRACK) | (h.max(axis=0) > ACTIVE) if gate else jnp.ones(h.shape[1], bool)
    return active if first_control else active & (rows < h.shape[1] - N_FIRST_CONTROL)


def _target(Y, max_innovation):
    """The virtual observation ``(m,)``: zeros, moved to within ``max_innovation`` standard deviations of the
    predicted mean ``Y (N, m)``.

    A barrier deep in violation that the ensemble can barely move (a gap no braking closes in one step) would
    otherwise be an innovation of tens of sigmas, and the linear update would extrapolate the regression far outside
    the ensemble: controls of -12 m/s^2 from a spread of 0.5. Asking per step only for what the ensemble can reach
    bounds every shift, and the surprise still widens the spread (delta).
    """
    mean, std = _mean_std(Y)
    reach = max_innovation * std
    return jnp.clip(0.0, mean - reach, mean + reach)


def _relax(Z, prior_std, relaxation):
    """Relaxation to the prior spread (Whitaker & Hamill 2012): each column's posterior spread moves back by
    ``relaxation`` towards its prior spread.

    With N = 50 and about ten measurement rows, each update also removes ~m/N of every column's variance through
    spurious sample correlations; over 20 steps the first control (the one applied) would keep a few percent of its
    spread, and a danger that only shows late in the horizon could no longer move it.
    """
    mean, post_std = _mean_std(Z)
    scale = jnp.where(post_std > 0, 1.0 + relaxation * (prior_std / jnp.maximum(post_std, 1e-12) - 1.0), 1.0)
    return mean + (Z - mean) * jnp.maximum(scale, 1.0)


# --- one smoothing pass -----------------------------------------------------------------------------------------
def _smooth(problem: Problem, cfg: Settings, key, ego, u_prev, nominal, obstacles, references):
    """One smoothing pass over the horizon; returns the smoothed control particles ``(N, H, 2)``."""
    n, horizon = cfg.n_particles, cfg.horizon
    dtype = problem.noise.dtype
    sigma_du = jnp.asarray(cfg.sigma_du, dtype)
    du_nominal = jnp.diff(jnp.concatenate([u_prev[None], nominal]), axis=0)  # (H, 2)
    s_o, l_o, v_o, a_o, present = obstacles
    # [x (4), du (2), u_0 .. u_{H-1}]: future controls are constant columns until their step writes them, and a
    # column without spread is left alone by the update (zero covariance, zero gain).
    Z0 = jnp.zeros((n, 6 + 2 * horizon), dtype)

    def step(state, inputs):
        x, u_last, Z, nu = state
        t, w_du, v_y, du_nom, obs_t, (vr, ar, lane, course) = inputs
        du = du_nom + w_du
        u = u_last + du
        x_next = vehicle.step(problem.model, x, u)
        Z = Z.at[:, :4].set(x_next).at[:, 4:6].set(du)
        Z = jax.lax.dynamic_update_slice(Z, u, (0, 6 + 2 * t))
        h = measure(problem, x_next, u, du, Z[:, 6:8], u_prev, lane, vr, ar, (*obs_t, present), course)
        Y = h + v_y
        active = _active(h, cfg.gate_barriers, cfg.first_control_barriers)
        prior_std = _mean_std(Z)[1]
        R = None
        if cfg.update == "deterministic":  # regresses on h and adds the noise covariance: St(0, R, nu) has R nu/(nu-2)
            R = problem.noise**2 * (1.0 if math.isinf(cfg.nu) else nu / (nu - 2.0))
        Z, nu_post = student_t_update(Z, Y if R is None else h, _target(Y, cfg.max_innovation), nu, active,
                                      cfg.adapt_spread, cfg.max_spread, reading=cfg.update, V=v_y, R=R)
        if cfg.relaxation > 0:
            Z = _relax(Z, prior_std, cfg.relaxation)
        if cfg.grow_nu:
            nu = nu_post
        return (Z[:, :4], jax.lax.dynamic_slice(Z, (0, 6 + 2 * t), (n, 2)), Z, nu), None

    # The state measured at step t is x_{t+1}: its references and obstacles are those of time t + 1.
    k_du, k_y = jax.random.split(key)
    inputs = (jnp.arange(horizon), student_t(k_du, sigma_du, cfg.nu, (horizon, n)),
              student_t(k_y, problem.noise, cfg.nu, (horizon, n)), du_nominal,
              (s_o[1:], l_o[1:], v_o[1:], a_o[1:]), tuple(r[1:] for r in references))
    start = (jnp.broadcast_to(ego, (n, 4)), jnp.broadcast_to(u_prev, (n, 2)), Z0, jnp.asarray(cfg.nu, dtype))
    (_, _, Z, _), _ = jax.lax.scan(step, start, inputs, unroll=UNROLL)
    return Z[:, 6:].reshape(n, horizon, 2)


def _plan(problem: Problem, cfg: Settings, carry: Carry, obs: jnp.ndarray, key: jax.Array):
    """One receding-horizon step: ``(action (2,) in [-1, 1], carry, PlanOut)`` for the observation ``obs`` (flat,
    the env's layout, read by :func:`bimp.envs.scene.split_obs`). Pure: the same arguments give the same result."""
    obs = obs.astype(problem.noise.dtype)  # float32 unless the problem is built in float64
    ego, u_prev, ovs, ref = split_obs(obs, cfg.n_obstacles)
    previous = carry.previous.astype(obs.dtype)
    shifted = jnp.concatenate([previous[1:], previous[-1:]])
    nominal = jnp.where(carry.has_previous, shifted, jnp.broadcast_to(u_prev, (cfg.horizon, 2)))
    obstacles = predict_obstacles(problem, ovs, cfg.horizon)
    references = reference_profile(problem, ref, ego, cfg.horizon)
    keys = jax.random.split(key, cfg.iterations)
    for i in range(cfg.iterations):  # static: the iterated variant is a longer program, not a data branch
        U = _smooth(problem, cfg, keys[i], ego, u_prev, nominal, obstacles, references)
        nominal = U.mean(axis=0)
    ok = jnp.all(jnp.isfinite(nominal)) & jnp.all(jnp.isfinite(U))
    hold = jnp.broadcast_to(u_prev, (cfg.horizon, 2))
    lim = problem.limits
    controls = jnp.clip(jnp.where(ok, nominal, hold), lim.actuator_lo, lim.actuator_hi)
    U = jnp.where(ok, U, hold[None])

    action = jnp.clip(2.0 * (controls[0] - lim.actuator_lo) / (lim.actuator_hi - lim.actuator_lo) - 1.0, -1.0, 1.0)
    return action, Carry(controls, jnp.ones((), bool)), PlanOut(controls, U, ok)


@jax.jit
def roll_out(model, x0: jnp.ndarray, controls: jnp.ndarray) -> jnp.ndarray:
    """States ``(H + 1, 4)`` from ``x0 (4,)`` under ``controls (H, 2)`` (the plan's states, for figures: computed
    when asked for, not in every plan)."""
    def step(x, u):
        nxt = vehicle.step(model, x[None], u[None])[0]
        return nxt, nxt

    return jnp.concatenate([x0[None], jax.lax.scan(step, x0, controls)[1]])


plan_step = jax.jit(_plan, static_argnums=1)

# One compiled program for a batch of episodes: the problem's road and the OVs' paths differ per row.
_BATCH_AXES = Problem(road=0, limits=None, barrier=None, noise=None, model=None, lane_rate=None, course=None, paths=0,
                      lane_heading=None)


@partial(jax.jit, static_argnums=1)
def plan_batch(problem: Problem, cfg: Settings, carry: Carry, obs: jnp.ndarray, keys: jax.Array):
    """:func:`plan_step` for ``B`` episodes at once: ``problem.road`` leaves ``(B, P)``, ``carry`` and ``obs`` with a
    leading ``B``, ``keys (B,)``. Row ``i`` equals ``plan_step`` on row ``i``'s arguments."""
    return jax.vmap(_plan, in_axes=(_BATCH_AXES, None, 0, 0, 0))(problem, cfg, carry, obs, keys)


__all__ = ["Carry", "PlanOut", "READINGS", "Settings", "chi_square", "initial_carry", "plan_batch", "plan_step",
           "roll_out", "spread_factor", "student_t", "student_t_update"]
