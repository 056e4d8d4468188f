"""bimp.planners.mppi: the running cost is the virtual measurements' negative log-likelihood (by hand and against
``measure``), the virtual-system transition, seeding without the global RNG, the fallback, the Policy contract
on both scenarios, config validation."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch

from bimp import envs
from bimp.agents.rollout import rollout
from bimp.envs.road import RoadGeometry
from bimp.envs.scene import Bounds, Scene
from bimp.planners.dynamics import BicycleModel, load_model, save_model
from bimp.planners.mppi import MPPIConfig, MPPIPlanner, make_mppi
from bimp.planners.problem import (
    ProblemConfig,
    load_problem,
    make_problem,
    measure,
    predict_obstacles,
    reference_profile,
)


def straight_scene() -> Scene:
    straight = RoadGeometry(arc_angle=0.0)
    return Scene(road=straight.route(), geometry=straight, bounds=Bounds(), dt=0.1, vehicle_length=5.0,
                 vehicle_width=2.0,
                 actuator_accel=(-10.0, 10.0), actuator_steer=(-0.3, 0.3), n_obstacles=2)


def obs_of(scene: Scene, ego, u_prev, ovs, ref) -> np.ndarray:
    return np.concatenate([ego, u_prev, np.asarray(ovs, float).ravel(), ref])


def planner_with_context(scene: Scene, obs: np.ndarray, tuning: ProblemConfig = ProblemConfig()) -> MPPIPlanner:
    """A planner that has planned once on ``obs``, so its running cost knows the references and OVs."""
    config = MPPIConfig(n_particles=8, problem=dataclasses.replace(tuning, horizon=3))
    planner = MPPIPlanner(scene, config, dynamics=load_model())
    planner.act(obs)
    return planner


def test_running_cost_by_hand():
    """Right lane, no OVs, inside every bound: only the speed and acceleration residuals count. Then the
    steering past its bound: its input residual, two steering barriers (the step's and the first control's) and the
    first control's steering-rate barrier against the last input."""
    scene, tun = straight_scene(), ProblemConfig()
    lane = float(scene.geometry.lane_offset(1))
    obs = obs_of(scene, [50.0, lane, 0.0, 20.0], [0.8, 0.0], np.zeros((2, 6)), [25.0, 0.0, lane])
    planner = planner_with_context(scene, obs, tun)
    block = torch.tensor([[60.0, lane, 0.0, 20.0, 1.0, 0.0, 0.2, 0.0, 1.0, 0.0]], dtype=torch.float64)
    cost = planner.running_cost(block, block[:, 4:6], 0).item()
    expected = 0.5 * ((20.0 - 25.0) / tun.sigma_ref[2]) ** 2 + 0.5 * (1.0 / tun.sigma_input[0]) ** 2
    assert cost == pytest.approx(expected, rel=1e-6)

    shape, delta, keep = tun.barrier, 0.06, 1 - tun.barrier.bound_margin
    block[0, [5, 9]] = delta  # u_t and u_0 both steer 0.06 rad; the block's own du stays (0.2, 0)
    cost = planner.running_cost(block, block[:, 4:6], 0).item()
    psi = lambda phi: np.logaddexp(0.0, shape.sharpness * phi) / shape.sharpness  # noqa: E731 - the hinge
    steer = psi((delta - keep * scene.bounds.steer) / shape.widths[3])
    steer_rate = psi((delta - 0.0 - keep * scene.bounds.steer_rate) / shape.widths[5])  # u_0 against u_prev
    expected += 0.5 * (delta / tun.sigma_input[1]) ** 2 + 0.5 * (2 * steer**2 + steer_rate**2) / tun.sigma_barrier**2
    assert cost == pytest.approx(expected, rel=1e-6)


def test_running_cost_is_the_nll_of_measure_on_random_blocks():
    env = gym.make(envs.env_id("overtaking"))
    obs, _ = env.reset(seed=1)
    scene = env.unwrapped.scene
    planner = planner_with_context(scene, obs)
    ego, u_prev, ovs, ref = scene.split_obs(obs)
    rng = np.random.default_rng(0)
    n, t = 40, 2
    x = ego + rng.normal(0, 1, (n, 4)) * [30.0, 2.0, 0.05, 5.0]
    u, du, u0 = rng.normal(0, 1, (n, 2)) * [3.0, 0.05], rng.normal(0, 1, (n, 2)) * [1.0, 0.005], \
        rng.normal(0, 1, (n, 2)) * [3.0, 0.05]
    block = torch.from_numpy(np.column_stack([x, u, du, u0]))
    problem = make_problem(scene, planner.config.problem)
    s_o, l_o, v_o, a_o, present = predict_obstacles(problem, ovs, 3)
    v_ref, a_ref, lane, course = reference_profile(problem, ref, ego, 3)
    # the block after step t holds x_{t+1}: it is measured against the references and OVs of time t + 1
    h = measure(problem, x, u, du, u0, u_prev, lane[t + 1], v_ref[t + 1], a_ref[t + 1],
                (s_o[t + 1], l_o[t + 1], v_o[t + 1], a_o[t + 1], present), course[t + 1])
    tun = planner.config.problem
    sigma = np.array([*tun.sigma_ref, *tun.sigma_input] + [tun.sigma_barrier] * 11)
    np.testing.assert_allclose(planner.running_cost(block, block[:, 4:6], t).numpy(),
                               0.5 * np.sum((h / sigma) ** 2, axis=1), rtol=1e-12)


def test_transition_is_the_virtual_system():
    model = load_model()
    config = MPPIConfig(n_particles=4, sample="inputs", problem={"horizon": 3})
    planner = MPPIPlanner(straight_scene(), config, dynamics=model)
    start = torch.tensor([[10.0, 2.0, 0.01, 20.0, -1.0, 0.01, 0.0, 0.0, -1.0, 0.01]], dtype=torch.float64)
    u0 = torch.tensor([[-1.5, 0.012]], dtype=torch.float64)
    b0 = planner._step(start, u0, 0).numpy()  # x_1 = f(x_0, u_0): the state the step's input reaches
    np.testing.assert_allclose(b0[:, :4], model.predict(start.numpy()[:, :4], u0.numpy()))
    np.testing.assert_allclose(b0[:, 4:], [[-1.5, 0.012, -0.5, 0.002, -1.5, 0.012]], atol=1e-15)
    u1 = torch.tensor([[-2.0, 0.01]], dtype=torch.float64)
    b1 = planner._step(torch.from_numpy(b0), u1, 1).numpy()  # x_2 = f(x_1, u_1); u_0 kept in the last slot
    np.testing.assert_allclose(b1[:, :4], model.predict(b0[:, :4], u1.numpy()))
    np.testing.assert_allclose(b1[:, 4:], [[-2.0, 0.01, -0.5, -0.002, -1.5, 0.012]], atol=1e-15)


def test_with_increments_the_action_is_added_to_the_input_within_the_actuator_range():
    model = load_model()
    scene = straight_scene()
    planner = MPPIPlanner(scene, MPPIConfig(n_particles=4, problem={"horizon": 3}), dynamics=model)
    start = torch.tensor([[10.0, 2.0, 0.01, 20.0, -1.0, 0.01, 0.0, 0.0, -1.0, 0.01]], dtype=torch.float64)
    b0 = planner._step(start, torch.tensor([[-0.5, 0.002]], dtype=torch.float64), 0).numpy()
    np.testing.assert_allclose(b0[:, 4:], [[-1.5, 0.012, -0.5, 0.002, -1.5, 0.012]], atol=1e-15)
    np.testing.assert_allclose(b0[:, :4], model.predict(start.numpy()[:, :4], np.array([[-1.5, 0.012]])))
    lo, hi = scene.actuator_range
    b1 = planner._step(torch.from_numpy(b0), torch.tensor([[-1e3, 1e3]], dtype=torch.float64), 1).numpy()
    np.testing.assert_allclose(b1[:, 4:6], [[lo[0], hi[1]]])  # the input stays in the actuator range


def test_with_increments_every_step_keeps_the_rate_bounds():
    env = gym.make("bimp/Overtaking-v0")
    episode = rollout(env, make_mppi(env, noise_gain=3.0), 7, max_steps=30)
    u = np.array(episode.trace["input"])
    b = env.unwrapped.scene.bounds
    assert np.all(np.abs(np.diff(u, axis=0)) <= np.array([b.accel_rate, b.steer_rate]) + 1e-6)


@pytest.mark.parametrize("scenario", ["overtaking", "emergency-brake"])
def test_actions_are_finite_in_the_space_and_seeded(scenario):
    env = gym.make(envs.env_id(scenario))
    planner = make_mppi(env)
    from bimp.planners.enkts import EnKTSConfig

    assert planner.n_particles == EnKTSConfig().n_particles and planner.horizon == load_problem().horizon
    runs = []
    global_state = torch.get_rng_state()
    for seed in (0, 0, 1):
        obs, _ = env.reset(seed=0)
        planner.reset(seed)
        actions = []
        for _ in range(4):
            action = planner.act(obs)
            assert action.dtype == np.float32 and action.shape == (2,) and env.action_space.contains(action)
            actions.append(action)
            obs, *_ = env.step(action)
        runs.append(np.array(actions))
    np.testing.assert_array_equal(runs[0], runs[1])  # same seed, same actions
    assert not np.array_equal(runs[0], runs[2])
    assert torch.equal(torch.get_rng_state(), global_state)  # the global RNG is never drawn from
    assert planner.fallbacks == 0


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
def test_non_finite_plan_falls_back_to_the_last_input():
    scene = straight_scene()
    lane = float(scene.geometry.lane_offset(1))
    broken = lambda x, u: np.full_like(x, np.nan)  # noqa: E731 - a model that has gone wrong
    planner = MPPIPlanner(scene, MPPIConfig(n_particles=8, problem={"horizon": 3}), dynamics=broken)
    u_prev = np.array([-2.0, 0.01])
    action = planner.act(obs_of(scene, [0.0, lane, 0.0, 20.0], u_prev, np.zeros((2, 6)), [20.0, 0.0, lane]))
    assert planner.fallbacks == 1 and np.all(np.isfinite(action))
    np.testing.assert_allclose(scene.to_physical(action), u_prev, atol=1e-6)


def test_config_validation_and_unknown_overrides():
    for bad in ({"n_particles": 1}, {"problem": {"horizon": 0}}, {"temperature": 0.0}, {"noise_gain": -1.0},
                {"control_cost": float("nan")}):
        with pytest.raises(ValueError):
            MPPIConfig(**bad)
    env = gym.make(envs.env_id("overtaking"))
    with pytest.raises(ValueError, match="lambda_"):
        make_mppi(env, lambda_=2.0)
    planner = make_mppi(env, n_particles=20, problem={"horizon": 5})
    assert (planner.n_particles, planner.horizon, planner.config.problem.horizon) == (20, 5, 5)
    with pytest.raises(ValueError, match="horizon is now problem.horizon"):  # one name, no alias
        make_mppi(env, horizon=5)


def test_default_dynamics_follow_the_problem_key(tmp_path):
    copy = save_model(load_model(), tmp_path / "copy.pt")
    x = np.column_stack([np.zeros(5), np.zeros(5), np.linspace(-1, 1, 5), np.linspace(0, 35, 5)])
    u = np.column_stack([np.linspace(-8, 3, 5), np.linspace(-0.2, 0.2, 5)])
    planner = MPPIPlanner(straight_scene(), MPPIConfig(n_particles=4, problem={"horizon": 3, "dynamics": str(copy)}))
    np.testing.assert_array_equal(planner.dynamics(x, u), load_model()(x, u))
    planner = MPPIPlanner(straight_scene(), MPPIConfig(n_particles=4, problem={"horizon": 3, "dynamics": "bicycle"}))
    assert isinstance(planner.dynamics, BicycleModel)


def small_mppi(**config) -> tuple[MPPIPlanner, np.ndarray]:
    scene = straight_scene()
    lane = float(scene.geometry.lane_offset(1))
    obs = obs_of(scene, [0.0, lane, 0.0, 20.0], [0.0, 0.0], np.zeros((2, 6)), [25.0, 0.0, lane])
    return MPPIPlanner(scene, MPPIConfig(n_particles=8, problem={"horizon": 3}, **config), dynamics=load_model()), obs


def test_the_generator_is_seeded_from_the_whole_seed():
    """torch's manual_seed keeps the low 32 bits: seeds 12345 and 2**40 + 12345 drew the same noise."""
    planner, obs = small_mppi()
    actions = []
    for seed in (12345, 2**40 + 12345, 12345):
        planner.reset(seed)
        actions.append(planner.act(obs))
    assert not np.array_equal(actions[0], actions[1])
    np.testing.assert_array_equal(actions[0], actions[2])


@pytest.mark.parametrize("seed", [-1, 1.5, True, "3"])
def test_seeds_enkts_refuses_are_refused(seed):
    planner, _ = small_mppi()
    with pytest.raises(ValueError, match="seed"):
        planner.reset(seed)


def test_a_negative_config_seed_is_refused_naming_it():
    with pytest.raises(ValueError, match="seed") as err:
        MPPIConfig(seed=-1)
    assert err.value.key == "seed"


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
def test_a_fallback_is_reported_per_step_and_recorded_in_the_trace():
    env = gym.make(envs.env_id("emergency-brake"))
    planner = make_mppi(env, n_particles=8, problem={"horizon": 3})
    episode = rollout(env, planner, 3, max_steps=2)
    assert episode.trace["policy_info"] == [{"fallback": False}] * 2
    planner.dynamics = lambda x, u: np.full_like(x, np.nan)  # a model that has gone wrong
    episode = rollout(env, planner, 3, max_steps=2)
    assert episode.trace["policy_info"] == [{"fallback": True}] * 2 and planner.step_info["fallback"] is True
