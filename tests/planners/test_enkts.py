import math

import gymnasium as gym
import jax.numpy as jnp
import numpy as np
import pytest

from bimp import envs
from bimp.agents import make_policy
from bimp.agents.rollout import rollout
from bimp.configs import ConfigError, load_config
from bimp.planners import core
from bimp.planners.dynamics import BicycleModel, load_model, save_model
from bimp.planners.enkts import EnKTSConfig, EnKTSPlanner, make_enks, make_enkts
from bimp.planners.model import BicycleParams


def env_at(env_id="bimp/EmergencyBrake-v0", seed=0, **config):
    env = gym.make(env_id, config=config or None)
    obs, _ = env.reset(seed=seed)
    return env, obs


@pytest.mark.parametrize("bad", [dict(n_particles=1), dict(problem={"horizon": 0}), dict(problem={"nu": 2.0}),
                                 dict(problem={"nu": 1.5}), dict(problem={"sigma_du": (0.5, 0.0)}),
                                 dict(relaxation=1.0), dict(problem={"dynamics": "magic"}), dict(update="printed")])
def test_invalid_config_raises_at_construction(bad):
    with pytest.raises(ValueError):
        EnKTSConfig(**bad)


def test_yaml_overrides_load_and_unknown_keys_raise(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("n_particles: 30\nproblem: {nu: .inf, barrier: {headway: 0.8}, sigma_du: [0.4, 0.003]}\n")
    cfg = load_config(EnKTSConfig, path)
    assert cfg.n_particles == 30 and math.isinf(cfg.problem.nu) and cfg.problem.barrier.headway == 0.8
    assert cfg.problem.sigma_du == (0.4, 0.003)
    path.write_text("n_particle: 30\n")
    with pytest.raises(ValueError, match="n_particle"):
        load_config(EnKTSConfig, path)
    with pytest.raises(ValueError, match="hedway"):
        load_config(EnKTSConfig, None, problem={"barrier": {"hedway": 1.0}})


def test_enks_is_enkts_with_infinite_nu_and_nothing_else():
    env, _ = env_at()
    a, b = make_enkts(env), make_enks(env)
    assert math.isinf(b.config.problem.nu) and not math.isinf(a.config.problem.nu)
    assert vars(a.config.problem) | {"nu": None} == vars(b.config.problem) | {"nu": None}
    assert {k: v for k, v in vars(a.config).items() if k != "problem"} == \
        {k: v for k, v in vars(b.config).items() if k != "problem"}


@pytest.mark.parametrize("name", ["enkts", "enks"])
def test_same_seed_same_actions_and_actions_in_space(name):
    runs = []
    for _ in range(2):
        env, obs = env_at("bimp/Overtaking-v0", seed=3)
        policy = make_policy(name, env)
        policy.reset(7)
        actions = []
        for _ in range(8):
            a = policy.act(obs)
            assert a.shape == (2,) and a.dtype == np.float32 and env.action_space.contains(a)
            actions.append(a)
            obs, *_ = env.step(a)
        runs.append(np.array(actions))
    np.testing.assert_array_equal(*runs)
    policy.reset(8)
    env, obs = env_at("bimp/Overtaking-v0", seed=3)
    assert not np.array_equal(policy.act(obs), runs[0][0])


def test_bad_observations_raise_value_errors_that_name_the_problem():
    env, obs = env_at()
    planner = make_enkts(env, n_particles=10, problem={"horizon": 3})
    with pytest.raises(ValueError, match="shape"):
        planner.act(obs[:-1])
    for value in (np.nan, np.inf):
        bad = obs.copy()
        bad[3] = value
        with pytest.raises(ValueError, match="non-finite.*3"):
            planner.act(bad)


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
def test_degenerate_situations_never_give_non_finite_actions():
    env, obs = env_at()  # (a model that returns NaN: tests/planners/test_core.py)
    crashed = obs.copy()
    crashed[7:9] = obs[0:2]  # OV1 on top of the EV: every barrier deep in violation for every particle
    crashed[11] = -50.0  # an absurd deceleration
    planner = make_enkts(env, n_particles=5, problem={"horizon": 20})
    for o in (crashed, obs):
        action = planner.act(o)
        assert np.all(np.isfinite(action)) and env.action_space.contains(action)


def test_plan_is_readable_for_plotting():
    env, obs = env_at()
    config = EnKTSConfig(n_particles=20, problem={"horizon": 6, "dynamics": "bicycle"})
    planner = EnKTSPlanner(env.unwrapped.scene, config)
    assert planner.plan is None
    planner.act(obs)
    plan = planner.plan
    assert plan.states.shape == (7, 4) and plan.controls.shape == (6, 2)
    assert plan.control_particles.shape == (20, 6, 2)
    np.testing.assert_allclose(plan.states[0], obs[:4], rtol=1e-6)
    np.testing.assert_allclose(plan.states[1], BicycleModel()(obs[None, :4].astype(float), plan.controls[:1])[0],
                               rtol=1e-5, atol=1e-4)  # float32 plan, float64 reference


def test_emergency_brake_plan_brakes_once_the_ovs_brake():
    """The lead OVs' deceleration, seen in the observation, must make the plan brake hard within 2 s."""
    env, obs = env_at(seed=0)
    planner = make_enkts(env)
    planner.reset(0)
    accels = []
    for _ in range(35):
        action = planner.act(obs)
        accels.append(env.unwrapped.scene.to_physical(action)[0])
        obs, *_ = env.step(action)
    assert max(accels[:8]) > -1.0  # cruising before the onset (~1 s)
    assert min(accels) < -4.0


@pytest.mark.parametrize("scenario", ["overtaking", "emergency-brake"])
def test_enkts_completes_each_scenario_on_the_default_seed_safely(scenario):
    env = gym.make(envs.env_id(scenario))
    obs, _ = env.reset(seed=0)
    planner = make_enkts(env)
    planner.reset(0)
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(planner.act(obs))
        done = terminated or truncated
    assert truncated and not info["collision"] and not info["offroad"]


def test_dynamics_may_be_a_weights_file_a_copy_acts_like_the_shipped_model(tmp_path):
    copy = save_model(load_model(), tmp_path / "copy.pt")
    (tmp_path / "p.yaml").write_text(f"n_particles: 10\nproblem: {{horizon: 5, dynamics: {copy}}}\n")
    runs = []
    for config in (load_config(EnKTSConfig, tmp_path / "p.yaml"), EnKTSConfig(n_particles=10, problem={"horizon": 5})):
        env, obs = env_at("bimp/Overtaking-v0", seed=2)
        planner = EnKTSPlanner(env.unwrapped.scene, config)
        actions = []
        for _ in range(4):
            actions.append(planner.act(obs))
            obs, *_ = env.step(actions[-1])
        runs.append(np.array(actions))
    np.testing.assert_array_equal(*runs)
    bicycle = EnKTSConfig(problem={"dynamics": "bicycle"})
    assert isinstance(EnKTSPlanner(env.unwrapped.scene, bicycle)._model, BicycleParams)


def test_jax_forward_equals_the_torch_forward():
    """The shipped weights in the compiled planner's model give the torch module's prediction."""
    import jax.numpy as jnp
    import torch

    from bimp.planners.model import model_params, step

    model, params = load_model(), model_params("mlp")
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(-50, 50, 64), rng.uniform(-5, 5, 64), rng.uniform(-1, 1, 64),
                         rng.uniform(0, 42, 64)])
    u = np.column_stack([rng.uniform(-12, 12, 64), rng.uniform(-0.35, 0.35, 64)])
    expected = model.predict_torch(torch.as_tensor(x), torch.as_tensor(u)).detach().numpy()
    got = np.asarray(step(params, jnp.asarray(x, jnp.float32), jnp.asarray(u, jnp.float32)))
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=2e-4)  # float32 state: 1e-5 of 50 m
    exact = BicycleModel()(x, u)
    bicycle = np.asarray(step(model_params("bicycle"), jnp.asarray(x, jnp.float32), jnp.asarray(u, jnp.float32)))
    np.testing.assert_allclose(bicycle, exact, rtol=1e-5, atol=2e-4)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["overtaking", "emergency-brake"])
def test_enkts_is_safe_on_twenty_tuning_seeds(scenario):
    """The shipped tuning on 20 tuning seeds (the safety and results seeds are never used in tests)."""
    from bimp.agents.rollout import rollout

    env = gym.make(envs.env_id(scenario))
    planner = make_enkts(env)
    unsafe = []
    for seed in range(100, 120):
        trace = rollout(env, planner, seed).trace
        if any(trace["collision"]) or any(trace["offroad"]):
            unsafe.append(seed)
    assert unsafe == []


# --- no silent failure (issue 24) ------------------------------------------------------------------------------
@pytest.mark.parametrize("nu", [2.000000000001, 2.05])
def test_nu_below_the_float32_floor_is_refused_naming_nu(nu):
    """nu = 2.000000000001 passed the old ``nu > 2`` and rounds to 2 in float32: every plan was non-finite."""
    env, _ = env_at()
    with pytest.raises(ConfigError, match="nu") as err:
        make_enkts(env, problem={"nu": nu})
    assert err.value.key == "problem.nu"
    with pytest.raises(ConfigError, match="nu"):
        make_policy("enkts", env, problem={"nu": nu})
    assert make_enkts(env, n_particles=4, problem={"nu": 2.1, "horizon": 2}).config.problem.nu == 2.1


def small_planner(env, **config):
    return EnKTSPlanner(lambda: env.unwrapped.scene, EnKTSConfig(n_particles=8, problem={"horizon": 4}, **config))


def test_a_fallback_is_reported_per_step_and_recorded_in_the_trace():
    env, obs = env_at()
    healthy = small_planner(env)
    healthy.act(obs)
    assert healthy.step_info == {"fallback": False}
    broken = small_planner(env)
    broken._model = broken._model._replace(w1=broken._model.w1.at[0, 0].set(np.nan))  # every plan non-finite
    broken.act(obs)
    assert broken.step_info["fallback"] is True and broken.fallbacks == 1
    episode = rollout(env, broken, 3, max_steps=3)
    assert episode.trace["policy_info"] == [{"fallback": True}] * 3


def test_a_batch_reports_the_fallback_of_each_row(monkeypatch):
    envs_ = [env_at(seed=s)[0] for s in (0, 1)]
    config = EnKTSConfig(n_particles=8, problem={"horizon": 4})
    planner = EnKTSPlanner(lambda: [e.unwrapped.scene for e in envs_], config)
    plan_batch = core.plan_batch

    def second_row_fails(*args):  # the core reports row 1's plan as non-finite
        action, carry, plan = plan_batch(*args)
        return action, carry, plan._replace(ok=jnp.array([True, False]))

    monkeypatch.setattr(core, "plan_batch", second_row_fails)
    planner.reset([3, 4])
    planner.act(np.stack([e.unwrapped.observation_type.observe() for e in envs_]))
    assert planner.step_info == {"fallback": (False, True)} and planner.fallbacks == 1


def test_config_file_goes_on_top_of_the_shipped_settings(tmp_path):
    """A YAML of ``horizon: 20`` alone replaced configs/planner.yaml: N fell from the shipped 100 to 50."""
    env, _ = env_at()
    shipped = make_enkts(env).config
    path = tmp_path / "mine.yaml"
    path.write_text("problem: {horizon: 20}\n")
    for name in ("enkts", "enks"):
        assert make_policy(name, env, config=path).config.n_particles == shipped.n_particles == 100
    path.write_text("problem: {horizon: 12}\n")
    mine = make_enkts(env, config=path, max_innovation=3.0).config
    assert (mine.problem.horizon, mine.n_particles, mine.max_innovation) == (12, 100, 3.0)
    assert mine.problem.sigma_du == shipped.problem.sigma_du  # configs/problem.yaml still under it, key by key
    assert math.isinf(make_enks(env, config=path).config.problem.nu)  # EnKS's nu over the file


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("highway_id", ["highway-v0", "highway-fast-v0", "merge-v0", "exit-v0", "roundabout-v0",
                                        "two-way-v0", "u-turn-v0", "racetrack-v0", "intersection-v0"])
def test_enkts_drives_every_wrapped_highway_env_id(highway_id):
    """A short seeded episode on each supported highway-env road (issue 26): the scene changes every step (a new
    road window), actions stay finite and in the space, no plan falls back; and the same seed and observations give
    the same actions on a second env of the id."""
    runs = []
    for _ in range(2):
        env = gym.make(f"bimp/{highway_id}")
        policy = make_policy("enkts", env, n_particles=20, problem={"horizon": 8})
        obs, _ = env.reset(seed=7)
        policy.reset(7)
        actions = []
        for _ in range(12):
            action = policy.act(obs)
            assert action.shape == (2,) and np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
            assert not policy.step_info["fallback"]
            actions.append(action)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
        runs.append(np.array(actions))
    np.testing.assert_array_equal(runs[0], runs[1])
