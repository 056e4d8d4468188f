"""bimp.planners.core: the update against closed forms, masking, sampling, and the compiled plan's contracts (batch ==
single, a redrawn road reuses the program, non-finite plans never reach the action)."""

import math

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.planners import core
from bimp.planners.enkts import EnKTSConfig, EnKTSPlanner, make_enkts
from bimp.planners.model import model_params
from bimp.planners.problem import make_problem

ALL = jnp.ones(2, bool)


def update(X, Y, y, nu, active=None, **kw):
    """The update in float64: the oracles below use 10^4-10^5 samples, whose float32 sums would lose 1e-3 and more
    (the planner's N is 50-2000)."""
    with jax.enable_x64(True):
        active = jnp.ones(Y.shape[1], bool) if active is None else jnp.asarray(active)
        X_post, nu_post = core.student_t_update(jnp.asarray(X, jnp.float64), jnp.asarray(Y, jnp.float64),
                                                jnp.asarray(y, jnp.float64), nu, active, **kw)
        return np.asarray(X_post, float), float(nu_post)


def test_gaussian_update_matches_closed_form_kalman_on_a_linear_toy():
    rng = np.random.default_rng(0)
    mu, P = np.array([1.0, -2.0, 0.5]), np.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.5]])
    H, R = np.array([[1.0, 0.0, 1.0], [0.0, 2.0, 0.0]]), np.diag([0.4, 0.3])
    y = np.array([2.5, -3.0])
    n = 40_000
    X = rng.multivariate_normal(mu, P, size=n)
    Y = X @ H.T + rng.multivariate_normal(np.zeros(2), R, size=n)
    X_post, nu_post = update(X, Y, y, math.inf)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    np.testing.assert_allclose(X_post.mean(0), mu + K @ (y - H @ mu), atol=0.03)
    np.testing.assert_allclose(np.cov(X_post.T), (np.eye(3) - K @ H) @ P, atol=0.03)
    assert math.isinf(nu_post)


@pytest.mark.parametrize("adapt", [True, False])
def test_student_t_update_matches_the_closed_form_conditional(adapt):
    nu, n = 5.0, 1_600_000  # the regression of a nu = 5 sample converges slowly: 400k left 0.03 of spread
    mu = np.array([0.0, 1.0, -1.0, 0.5])  # [x (2), y (2)]
    Sigma = np.array([[1.0, 0.2, 0.5, 0.1], [0.2, 1.5, 0.3, 0.4], [0.5, 0.3, 1.2, 0.2], [0.1, 0.4, 0.2, 0.8]])
    draws = np.asarray(core.student_t(jax.random.key(1), jnp.ones(4), nu, (n,)), float)
    Z = mu + draws @ np.linalg.cholesky(Sigma).T
    X, Y = Z[:, :2], Z[:, 2:]
    y = np.array([2.0, -2.0])  # far in the tail: delta >> m, so the spread factor matters
    X_post, nu_post = update(X, Y, y, nu, adapt_spread=adapt)

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


def _linear_toy(n, seed=0):
    """A linear-Gaussian toy (prior, H, R, y) and its ensemble ``X``, noise-free ``h`` and noise ``v``."""
    rng = np.random.default_rng(seed)
    mu, P = np.array([1.0, -2.0, 0.5]), np.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.5]])
    H, R = np.array([[1.0, 0.0, 1.0], [0.0, 2.0, 0.0]]), np.diag([0.4, 0.3])
    X = rng.multivariate_normal(mu, P, size=n)
    v = rng.multivariate_normal(np.zeros(2), R, size=n)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    return mu, P, H, R, K, np.array([2.5, -3.0]), X, X @ H.T, v


def test_deterministic_reading_has_the_kalman_mean_and_misses_the_noise_in_the_spread():
    """Reading (b) of eq. 16 (the authors' public EnKS code): no perturbation, R added to P_y. The mean is the
    Kalman mean; the anomalies are (I - KH) A, so the spread lacks K R K^T."""
    mu, P, H, R, K, y, X, h, v = _linear_toy(40_000)
    X_post, _ = update(X, h, y, math.inf, reading="deterministic", R=jnp.asarray(np.diag(R)))
    np.testing.assert_allclose(X_post.mean(0), mu + K @ (y - H @ mu), atol=0.03)
    I_KH = np.eye(3) - K @ H
    np.testing.assert_allclose(np.cov(X_post.T), I_KH @ P @ I_KH.T, atol=0.03)
    assert np.trace(np.cov(X_post.T)) < np.trace(I_KH @ P) - 0.5 * np.trace(K @ R @ K.T)


def test_literal_reading_moves_the_mean_but_only_widens_the_spread():
    """Reading (c), the print taken literally: every particle moves by K (y + v^j - mean(Y)). The mean is the Kalman
    mean, but no anomaly is regressed away: the spread grows to P + K R K^T instead of shrinking."""
    mu, P, H, R, K, y, X, h, v = _linear_toy(40_000, seed=1)
    X_post, _ = update(X, h + v, y, math.inf, reading="literal", V=jnp.asarray(v))
    np.testing.assert_allclose(X_post.mean(0), mu + K @ (y - H @ mu), atol=0.03)
    np.testing.assert_allclose(np.cov(X_post.T), P + K @ R @ K.T, atol=0.04)


def test_an_unknown_reading_is_refused():
    with pytest.raises(ValueError, match="reading"):
        update(np.zeros((4, 2)), np.zeros((4, 1)), np.zeros(1), math.inf, reading="printed")


@pytest.mark.parametrize("nu", [4.0, math.inf])
def test_every_reading_plans_a_finite_action_and_the_readings_differ(nu):
    env, obs = episode("bimp/Overtaking-v0", seed=1)
    actions = {}
    for r in core.READINGS:
        planner = EnKTSPlanner(env.unwrapped.scene, small(update=r, problem={"nu": nu}))
        actions[r] = np.stack([planner.act(obs) for _ in range(3)])
    for reading, a in actions.items():
        assert np.all(np.isfinite(a)) and np.all(np.abs(a) <= 1), reading
    for i, a in enumerate(core.READINGS):
        for b in core.READINGS[i + 1:]:
            assert not np.allclose(actions[a], actions[b], atol=1e-6), (a, b)


def test_huge_nu_gives_the_gaussian_result():
    rng = np.random.default_rng(2)
    X = rng.standard_normal((500, 3))
    Y = X[:, :2] * 2 + 0.3 * rng.standard_normal((500, 2))
    y = np.array([1.0, 3.0])
    gauss, _ = update(X, Y, y, math.inf)
    t_big, _ = update(X, Y, y, 1e12)
    np.testing.assert_allclose(t_big, gauss, rtol=1e-4, atol=1e-4)
    assert core.spread_factor(1e12, 100.0, 3) == pytest.approx(1.0)


def test_masking_a_row_that_reads_zero_equals_dropping_it():
    rng = np.random.default_rng(5)
    X = rng.standard_normal((50, 6))
    Y = np.column_stack([X[:, 0] + 0.3 * rng.standard_normal(50), 0.01 * rng.standard_normal(50),  # a flat row
                         X[:, 1] - X[:, 2] + 0.2 * rng.standard_normal(50)])
    y = np.array([1.0, 0.0, -0.5])
    for nu in (math.inf, 4.0):
        masked, nu_masked = update(X, Y, y, nu, active=[True, False, True])
        dropped, nu_dropped = update(X, Y[:, [0, 2]], y[[0, 2]], nu)
        np.testing.assert_allclose(masked, dropped, rtol=1e-5, atol=1e-5)
        assert nu_masked == nu_dropped
        assert not np.allclose(update(X, Y, y, nu)[0], dropped, atol=1e-3)  # the row would matter


def test_singular_measurement_covariance_stays_finite():
    rng = np.random.default_rng(3)
    X = rng.standard_normal((50, 4))
    Y = np.zeros((50, 3))  # e.g. a barrier that is 0 for every particle, and no noise
    Y[:, 0] = X[:, 0]
    for nu in (math.inf, 3.0):
        X_post, _ = update(X, Y, np.array([10.0, 0.0, 0.0]), nu, max_spread=25.0)
        assert np.all(np.isfinite(X_post)) and np.abs(X_post).max() < 1e3


def test_student_t_draws_are_multivariate_heavy_tailed_and_keyed():
    key = jax.random.key(4)
    a = np.asarray(core.student_t(key, jnp.array([1.0, 2.0]), 3.0, (200_000,)))
    b = np.asarray(core.student_t(key, jnp.array([1.0, 2.0]), 3.0, (200_000,)))
    g = np.asarray(core.student_t(key, jnp.array([1.0, 2.0]), math.inf, (200_000,)))
    np.testing.assert_array_equal(a, b)
    assert np.mean(np.abs(a[:, 0]) > 5) > 0.005 > np.mean(np.abs(g[:, 0]) > 5)
    np.testing.assert_allclose(g.std(0), [1.0, 2.0], rtol=0.02)
    # one mixing variable per draw: the two components' magnitudes are dependent (independent t's would not be)
    big = np.abs(a[:, 0]) > 4
    assert np.mean(np.abs(a[big, 1]) > 8) > 5 * np.mean(np.abs(a[:, 1]) > 8)


def test_chi_square_draws_have_the_distribution_for_integer_and_other_nu():
    from scipy import stats

    for nu in (4.0, 3.0, 4.5):
        draws = np.asarray(core.chi_square(jax.random.key(9), nu, (20_000,)), float)
        assert stats.kstest(draws, stats.chi2(nu).cdf).pvalue > 1e-3


# --- the compiled plan ------------------------------------------------------------------------------------------
def episode(scenario="bimp/EmergencyBrake-v0", seed=0):
    env = gym.make(scenario)
    obs, _ = env.reset(seed=seed)
    return env, obs


def small(problem: dict | None = None, **kw):
    return EnKTSConfig(n_particles=16, problem={"horizon": 6, **(problem or {})}, **kw)


def test_batched_plan_equals_single_plans_row_by_row():
    envs_, obs = zip(*(episode("bimp/Overtaking-v0", seed) for seed in (1, 2, 3)))
    scenes = [e.unwrapped.scene for e in envs_]
    assert len({s.geometry.radius for s in scenes}) == 3  # three different roads in one batch
    batch = EnKTSPlanner(lambda: scenes, small())
    batch.reset(seed=[11, 12, 13])
    singles = [EnKTSPlanner(scene, small()) for scene in scenes]
    for planner, seed in zip(singles, (11, 12, 13)):
        planner.reset(seed)
    obs = np.stack(obs)
    for _ in range(3):  # the warm start too
        actions = batch.act(obs)
        assert actions.shape == (3, 2) and actions.dtype == np.float32
        expected = np.stack([p.act(o) for p, o in zip(singles, obs)])
        np.testing.assert_allclose(actions, expected, atol=2e-5)
        obs = obs + np.array([1.0, 0, 0, 0] + [0] * (obs.shape[1] - 4), np.float32)
    plan = batch.plan
    assert plan.states.shape == (3, 7, 4) and plan.control_particles.shape == (3, 16, 6, 2)
    np.testing.assert_allclose(plan.states[1], singles[1].plan.states, atol=1e-3)
    with pytest.raises(ValueError, match="batch of 3"):
        batch.act(obs[0])


def test_a_redrawn_road_reuses_the_program_and_acts_as_a_fresh_compile():
    cfg = small()
    env, obs = episode("bimp/Overtaking-v0", seed=1)
    planner = EnKTSPlanner(lambda: env.unwrapped.scene, cfg)
    planner.act(obs)
    compiled = core.plan_step._cache_size()
    obs, _ = env.reset(seed=5)  # a new road
    planner.reset(3)
    action = planner.act(obs)
    assert core.plan_step._cache_size() == compiled
    fresh = jax.jit(core._plan, static_argnums=1)
    problem = make_problem(env.unwrapped.scene, cfg.problem, jax.device_put(model_params(cfg.problem.dynamics)))
    settings = cfg.settings(2, env.unwrapped.scene.bounds.steer)
    expected, _, _ = fresh(problem, settings, core.initial_carry(cfg.problem.horizon),
                           jnp.asarray(obs, jnp.float32), jax.random.fold_in(jax.random.key(3), 0))
    np.testing.assert_allclose(action, np.asarray(expected), atol=1e-6)


def test_same_key_same_actions_other_key_other_actions():
    env, obs = episode()
    runs = []
    for seed in (7, 7, 8):
        planner = make_enkts(env, n_particles=16)
        planner.reset(seed)
        runs.append(np.stack([planner.act(obs) for _ in range(3)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


def test_a_non_finite_plan_never_reaches_the_action():
    env, obs = episode()
    planner = EnKTSPlanner(env.unwrapped.scene, small())
    planner._model = planner._model._replace(w1=planner._model.w1.at[0, 0].set(jnp.nan))  # a broken model
    action = planner.act(obs)
    scene = env.unwrapped.scene
    assert np.all(np.isfinite(action)) and planner.fallbacks == 1
    np.testing.assert_allclose(scene.to_physical(action), scene.split_obs(obs)[1], atol=1e-5)  # holds the input
    assert np.all(np.isfinite(planner.plan.controls))


def test_float32_plan_agrees_with_float64():
    """The precision choice: the float64 program (x64 on) moves the applied action by far less than the spread."""
    env, obs = episode("bimp/Overtaking-v0", seed=2)
    cfg = small()
    problem = make_problem(env.unwrapped.scene, cfg.problem, model_params(cfg.problem.dynamics))
    settings = cfg.settings(2, env.unwrapped.scene.bounds.steer)
    args = (settings, core.initial_carry(cfg.problem.horizon), obs, jax.random.key(0))
    a32, _, plan32 = core.plan_step(jax.tree.map(lambda a: np.asarray(a, np.float32), problem), *args)
    with jax.enable_x64(True):
        p64 = jax.tree.map(lambda a: np.asarray(a, np.float64), problem)
        a64, _, _ = jax.jit(core._plan, static_argnums=1)(p64, *args)
    spread = np.asarray(plan32.control_particles[:, 0]).std(0)
    u32 = env.unwrapped.scene.to_physical(np.asarray(a32))
    u64 = env.unwrapped.scene.to_physical(np.asarray(a64))
    assert np.all(np.abs(u32 - u64) < 0.1 * spread + 1e-6)


# --- each measure beyond the paper's equations, on a constructed ensemble -------------------------------------
def test_innovation_clipping_asks_only_for_what_the_ensemble_can_reach():
    rng = np.random.default_rng(6)
    Y = np.column_stack([10.0 + rng.standard_normal(1000), 0.5 + rng.standard_normal(1000)])
    Y = (Y - Y.mean(0)) / Y.std(0) * [1.0, 1.0] + [10.0, 0.5]  # exact mean and spread
    target = np.asarray(core._target(jnp.asarray(Y), 2.0))
    np.testing.assert_allclose(target, [8.0, 0.0], atol=1e-5)  # 2 std short of 10; 0 is within reach of 0.5


def test_relaxation_gives_back_a_share_of_the_lost_spread_and_never_shrinks():
    rng = np.random.default_rng(7)
    Z = rng.standard_normal((500, 3)) * [0.2, 1.0, 0.5] + [1.0, -2.0, 0.0]
    prior = np.array([1.0, 1.0, 0.25])  # the first column lost spread, the second kept it, the third gained
    out = np.asarray(core._relax(jnp.asarray(Z), jnp.asarray(prior), 0.5))
    np.testing.assert_allclose(out.mean(0), Z.mean(0), atol=1e-5)  # float32
    np.testing.assert_allclose(out.std(0), [0.2 + 0.5 * (1.0 - 0.2), 1.0, 0.5], rtol=0.05)


def test_barrier_gating_keeps_tracking_rows_and_touched_barriers():
    h = np.zeros((50, 8))
    h[:, :5] = 0.0  # tracking rows read 0 here but always take part
    h[3, 5] = 0.01  # one particle touches barrier 5
    h[:, 6] = 1e-4  # barrier 6 flat below the threshold for every particle
    h[:, 7] = 2.0   # barrier 7 violated by all
    np.testing.assert_array_equal(np.asarray(core._active(jnp.asarray(h))), [1, 1, 1, 1, 1, 1, 0, 1])


def test_gating_and_first_control_barriers_can_be_switched_off():
    h = np.zeros((50, 5 + 2 + 9))  # tracking (5), two OVs, the nine bound barriers
    h[3, 5] = 0.01  # one particle touches OV 1's barrier; every other barrier is flat
    gated = np.asarray(core._active(jnp.asarray(h)))
    np.testing.assert_array_equal(gated, [1] * 6 + [0] * 10)
    assert np.asarray(core._active(jnp.asarray(h), gate=False)).all()
    h[:, -4:] = 1.0  # the first control breaks its bounds in every particle
    assert np.asarray(core._active(jnp.asarray(h)))[-4:].all()
    np.testing.assert_array_equal(np.asarray(core._active(jnp.asarray(h), first_control=False)),
                                  [1] * 6 + [0] * 10)


def test_the_spread_cap_bounds_the_widening():
    rng = np.random.default_rng(8)
    X = rng.standard_normal((2000, 2))
    Y = X[:, :1] + 0.5 * rng.standard_normal((2000, 1))
    y = np.array([30.0])  # a huge surprise: the Student's-t factor would widen the ensemble many times
    wide, _ = update(X, Y, y, 4.0, adapt_spread=True)
    capped, _ = update(X, Y, y, 4.0, adapt_spread=True, max_spread=1.5)
    plain, _ = update(X, Y, y, 4.0, adapt_spread=False)
    assert wide.std(0)[1] > 3 * plain.std(0)[1]
    np.testing.assert_allclose(capped.std(0), np.sqrt(1.5) * plain.std(0), rtol=1e-6)


def test_a_batch_on_a_junction_road_plans_each_row_on_its_own_paths():
    """roundabout-v0 publishes the OVs' paths (Scene.ov_paths): a batch takes each row's, as single plans do."""
    envs_, obs = zip(*(episode("bimp/roundabout-v0", seed) for seed in (1, 2)))
    scenes = [e.unwrapped.scene for e in envs_]
    assert all(s.ov_paths is not None for s in scenes) and not np.allclose(*(s.ov_paths for s in scenes))
    batch = EnKTSPlanner(lambda: scenes, small())
    batch.reset(seed=[11, 12])
    singles = [EnKTSPlanner(scene, small()) for scene in scenes]
    for planner, seed in zip(singles, (11, 12)):
        planner.reset(seed)
    actions = batch.act(np.stack(obs))
    np.testing.assert_allclose(actions, np.stack([p.act(o) for p, o in zip(singles, obs)]), atol=2e-5)
    # Far OVs leave these first actions alike whatever the paths: check the problem carries each row's own.
    problem = batch._problem_of(scenes, np.stack(obs).astype(np.float32))
    assert problem.paths.shape == (2, *scenes[0].ov_paths.shape)
    for row, scene in enumerate(scenes):
        np.testing.assert_allclose(problem.paths[row], scene.ov_paths, atol=1e-4)


def test_a_batch_of_scenes_with_and_without_paths_is_refused():
    """One batch is one program: rows on a junction road (the OVs' paths) and rows on another road (none) are
    refused, whichever comes first, rather than planning some rows without their paths."""
    (junction, obs_j), (straight, obs_s) = episode("bimp/roundabout-v0", 1), episode("bimp/highway-fast-v0", 1)
    for envs_, obs in (((junction, straight), (obs_j, obs_s)), ((straight, junction), (obs_s, obs_j))):
        scenes = [e.unwrapped.scene for e in envs_]
        batch = EnKTSPlanner(lambda: scenes, small())
        batch.reset(seed=[11, 12])
        with pytest.raises(ValueError, match="mixes scenes"):
            batch._problem_of(scenes, np.stack([o[:len(obs[0])] for o in obs]).astype(np.float32))
    (exit_, obs_e), (fast, obs_f) = episode("bimp/exit-v0", 1), episode("bimp/highway-fast-v0", 1)
    scenes = [exit_.unwrapped.scene, fast.unwrapped.scene]  # a leading lane (exit-v0's) in one row only
    batch = EnKTSPlanner(lambda: scenes, small())
    batch.reset(seed=[11, 12])
    with pytest.raises(ValueError, match="leading lane"):
        batch._problem_of(scenes, np.stack([obs_e, obs_f]).astype(np.float32))


def test_a_planner_reads_its_scene_source_once_at_build_and_takes_a_scene_or_a_batch_alike():
    from bimp.envs.scene import scene_batch
    from bimp.planners.dynamics import steer_bound
    from bimp.planners.mppi import MPPIConfig, MPPIPlanner

    env, _ = episode("bimp/Overtaking-v0", 1)
    scene = env.unwrapped.scene
    calls = []

    def source():
        calls.append(1)
        return scene

    EnKTSPlanner(source, small())
    MPPIPlanner(source, MPPIConfig(n_particles=4, problem={"horizon": 3}))
    assert len(calls) == 2  # once each
    pair = np.empty(2, dtype=object)
    pair[:] = [scene, scene]
    for batch in ((scene, scene), [scene, scene], pair, (s for s in (scene, scene))):
        assert scene_batch(batch) == [scene, scene]
    assert scene_batch(scene) == [scene]
    assert steer_bound(scene) == steer_bound([scene, scene]) == steer_bound(pair) == scene.bounds.steer
