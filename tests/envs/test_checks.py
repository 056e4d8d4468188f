"""The shared checks (:mod:`bimp.envs.checks`): highway-env's own config keys through the adapter (every refusal a
one-line ValueError naming the key and the value, before anything is simulated), and the action every bimp env's
``step`` takes (real numbers only)."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import pytest

import bimp  # noqa: F401  (registers bimp/ID)
from bimp.envs import PlanningWrapper
from bimp.envs.checks import KEY_RULES, MAX_VEHICLES, check_highway_config, checked_action
from bimp.envs.highway.adapter import ENV_CLASSES, PROFILES, SUPPORTED

pytestmark = pytest.mark.filterwarnings("ignore")
NAN, INF = float("nan"), float("inf")


def one_line_error(call, *words: str) -> str:
    with pytest.raises(ValueError) as err:
        call()
    message = str(err.value)
    assert "\n" not in message, message
    for word in words:
        assert word in message, (word, message)
    return message


# --- highway-env's keys through the adapter ----------------------------------------------------------------------
BAD_KEYS = [  # (id, config, words the message must contain: the key and the value first)
    ("highway-v0", {"vehicles_count": "x"}, ["vehicles_count", "'x'", "an int"]),
    ("highway-v0", {"vehicles_count": 5.0}, ["vehicles_count", "5.0", "an int"]),
    ("highway-v0", {"vehicles_count": -1}, ["vehicles_count", "-1"]),
    ("highway-v0", {"lanes_count": 2.5}, ["lanes_count", "2.5", "an int"]),
    ("highway-v0", {"lanes_count": 0}, ["lanes_count", "0"]),
    ("highway-v0", {"lanes_count": True}, ["lanes_count", "True"]),
    ("highway-v0", {"initial_lane_id": 99}, ["initial_lane_id", "99", "lanes_count=4"]),
    ("highway-v0", {"lanes_count": 2, "initial_lane_id": 2}, ["initial_lane_id", "2", "lanes_count=2"]),
    ("highway-v0", {"initial_lane_id": -1}, ["initial_lane_id", "-1"]),
    ("highway-v0", {"initial_lane_id": "0"}, ["initial_lane_id", "'0'"]),
    ("highway-v0", {"controlled_vehicles": 0}, ["controlled_vehicles", "0", "one EV"]),
    ("highway-fast-v0", {"controlled_vehicles": 2}, ["controlled_vehicles", "2", "one EV"]),
    ("highway-v0", {"vehicles_count": 10000}, ["vehicles_count", "10000", f"[0, {MAX_VEHICLES}]"]),
    ("exit-v0", {"vehicles_count": MAX_VEHICLES + 1}, ["vehicles_count", str(MAX_VEHICLES + 1), str(MAX_VEHICLES)]),
    ("intersection-v0", {"initial_vehicle_count": 10000}, ["initial_vehicle_count", "10000", str(MAX_VEHICLES)]),
    ("racetrack-v0", {"other_vehicles": 10000}, ["other_vehicles", "10000", str(MAX_VEHICLES)]),
    ("highway-v0", {"lanes_count": 10000}, ["lanes_count", "10000"]),
    ("highway-v0", {"vehicles_cont": 5}, ["vehicles_cont", "unknown", "'vehicles_count'"]),  # the valid keys listed
    ("merge-v0", {"lanes_count": 3}, ["lanes_count", "unknown"]),  # highway-v0's key, not merge-v0's
    ("highway-v0", {"collision_reward": NAN}, ["collision_reward", "nan", "finite"]),
    ("roundabout-v0", {"high_speed_reward": INF}, ["high_speed_reward", "inf", "finite"]),
    ("two-way-v0", {"left_lane_reward": "0.2"}, ["left_lane_reward", "'0.2'"]),
    # The reward's normalization interval empty: highway-env divides by its width.
    ("highway-v0", {"collision_reward": 0.5}, ["collision_reward", "0.5", "below", "high_speed_reward"]),
    ("merge-v0", {"merging_speed_reward": 2.0}, ["collision_reward + merging_speed_reward", "below"]),
    ("racetrack-v0", {"collision_reward": 1}, ["collision_reward", "1", "below"]),
    ("highway-v0", {"high_speed_reward": 1e308, "right_lane_reward": 1e308}, ["high_speed_reward", "finite"]),
    ("highway-v0", {"reward_speed_range": [30, 20]}, ["reward_speed_range", "[30, 20]", "lo < hi"]),
    ("u-turn-v0", {"reward_speed_range": [8, NAN]}, ["reward_speed_range", "nan"]),
    ("highway-v0", {"duration": 0}, ["duration", "0", "> 0"]),
    ("highway-v0", {"vehicles_density": 0}, ["vehicles_density", "0", "[0.1, 10]"]),
    ("exit-v0", {"vehicles_density": 1e-320}, ["vehicles_density", "1e-320"]),  # 1 / it overflows
    ("highway-v0", {"ego_spacing": 1000}, ["ego_spacing", "1000", "(0, 10]"]),  # the EV past the end of the road
    ("highway-v0", {"ego_spacing": "2"}, ["ego_spacing", "'2'"]),
    ("highway-v0", {"normalize_reward": 1}, ["normalize_reward", "1", "bool"]),
    ("exit-v0", {"offroad_terminal": "False"}, ["offroad_terminal", "'False'", "bool"]),
    ("exit-v0", {"lanes_count": 1}, ["lanes_count", "1", "[2, "]),
    ("roundabout-v0", {"incoming_vehicle_destination": 3}, ["incoming_vehicle_destination", "3", "[0, 2]"]),
    ("intersection-v0", {"destination": "zz"}, ["destination", "'zz'", "'o1'"]),
    ("intersection-v0", {"spawn_probability": 1.5}, ["spawn_probability", "1.5", "[0, 1]"]),
    ("racetrack-v0", {"speed_limit": -1}, ["speed_limit", "-1"]),
    ("racetrack-v0", {"lane_centering_cost": -4}, ["lane_centering_cost", "-4"]),
    ("highway-v0", {"other_vehicles_type": "no.such.Vehicle"}, ["other_vehicles_type", "'no.such.Vehicle'"]),
    ("highway-v0", {"other_vehicles_type": "highway_env.vehicle.kinematics.Vehicle"}, ["other_vehicles_type"]),
    ("highway-v0", {"screen_width": 10**6}, ["screen_width", "1000000"]),
    ("u-turn-v0", {"centering_position": [0.5]}, ["centering_position", "[0.5]"]),
    ("highway-v0", {"scaling": 0}, ["scaling", "0"]),
    # The families pass highway-env's keys through the same checks.
    ("cut-in-v0", {"collision_reward": NAN}, ["collision_reward", "nan"]),
    ("two-way-overtake-v0", {"high_speed_reward": "x"}, ["high_speed_reward", "'x'"]),
    ("stalled-vehicle-v0", {"lanes_count": 2.5}, ["lanes_count", "2.5", "[2, 5]"]),  # the family's own check
    ("lane-drop-v0", {"lanes_count": None}, ["lanes_count", "None", "[2, 5]"]),
]


@pytest.mark.parametrize("highway_id, config, words", BAD_KEYS, ids=[f"{i}-{c}" for i, c, _ in BAD_KEYS])
def test_highway_env_keys_are_checked_at_make_and_at_reset(highway_id, config, words):
    start = time.perf_counter()
    one_line_error(lambda: gym.make(f"bimp/{highway_id}", config=config), *words)
    assert time.perf_counter() - start < 2.0  # refused before anything is built: no hang on 10000 vehicles
    env = gym.make(f"bimp/{highway_id}")
    env.reset(seed=0)
    one_line_error(lambda: env.reset(seed=0, options={"config": config}), words[0])


def test_a_reset_config_is_checked_against_the_envs_own_config():
    # initial_lane_id 2 is a lane of highway-v0's default 4, not of the 2 this env was made with.
    env = gym.make("bimp/highway-v0", config={"lanes_count": 2})
    env.reset(seed=0)
    one_line_error(lambda: env.reset(seed=0, options={"config": {"initial_lane_id": 2}}), "initial_lane_id",
                   "lanes_count=2")
    env.reset(seed=0, options={"config": {"initial_lane_id": 1}})
    assert env.unwrapped.vehicle.lane_index[2] == 1


def test_wrap_checks_the_keys_it_carries_over():
    from bimp.envs import wrap

    # highway-env takes any key; the adapter refuses one that highway-v0 does not have.
    one_line_error(lambda: wrap(gym.make("highway-v0", config={"vehicles_cont": 5})), "vehicles_cont", "unknown")


GOOD_KEYS = [  # valid configs: built, reset and stepped
    ("highway-v0", {"vehicles_count": MAX_VEHICLES, "lanes_count": 2, "initial_lane_id": 1}),
    ("highway-v0", {"vehicles_count": np.int64(5), "lanes_count": 1, "initial_lane_id": 0, "duration": 5.5,
                    "collision_reward": -2, "reward_speed_range": (15.0, 25.0), "normalize_reward": np.bool_(True),
                    "other_vehicles_type": "highway_env.vehicle.behavior.AggressiveVehicle"}),
    ("highway-fast-v0", {"collision_reward": 0.5, "normalize_reward": False, "vehicles_density": 2.0}),
    ("exit-v0", {"lanes_count": 2, "vehicles_count": 0, "initial_lane_id": None}),
    ("merge-v0", {"merging_speed_reward": -1.0, "screen_width": 300, "centering_position": np.array([0.4, 0.5])}),
    ("roundabout-v0", {"incoming_vehicle_destination": 2, "offscreen_rendering": True}),
    ("two-way-v0", {"left_lane_reward": 0, "high_speed_reward": 1}),
    ("u-turn-v0", {"show_trajectories": True, "scaling": 4}),
    ("racetrack-v0", {"other_vehicles": 0, "speed_limit": 12.0, "lane_centering_cost": 0}),
    ("intersection-v0", {"destination": "o3", "initial_vehicle_count": 4, "spawn_probability": 0.0}),
    ("cut-in-v0", {"lanes_count": 4, "collision_reward": -2.0}),
    # highway-env snapshots every vehicle for the trajectories it draws: the families' own vehicles too.
    ("cut-in-v0", {"show_trajectories": True}),
    ("erratic-traffic-v0", {"show_trajectories": True}),
    ("two-way-overtake-v0", {"high_speed_reward": 0.5}),
]


@pytest.mark.parametrize("highway_id, config", GOOD_KEYS, ids=[f"{i}-{c}" for i, c in GOOD_KEYS])
def test_valid_configs_still_build_and_step(highway_id, config):
    env = gym.make(f"bimp/{highway_id}", config=config)
    obs, _ = env.reset(seed=0)
    obs, reward, *_ = env.step(np.zeros(2, np.float32))
    assert np.all(np.isfinite(obs)) and np.isfinite(reward)
    for key, value in config.items():
        assert np.all(env.unwrapped.config[key] == value) or value is None, key


@pytest.mark.parametrize("highway_id", list(PROFILES))
def test_every_key_highway_env_has_is_checked_or_owned_and_its_defaults_pass(highway_id):
    """A key highway-env adds in a later version, with no rule here, fails this test rather than passing unchecked."""
    cls = ENV_CLASSES[highway_id]
    owned = {"observation", "action", "policy_frequency", "simulation_frequency"}  # the adapter's own handling
    if highway_id not in SUPPORTED:
        owned |= {"difficulty", *cls.range_keys(), *cls.CHECKED_KEYS}  # a family's
    assert sorted(set(cls.default_config()) - set(KEY_RULES) - owned) == []
    check_highway_config(highway_id, cls, cls.default_config())


# --- actions -----------------------------------------------------------------------------------------------------
ENV_IDS = ["bimp/Overtaking-v0", "bimp/EmergencyBrake-v0", "bimp/overtaking-noisy-v0", "bimp/highway-fast-v0",
           "bimp/cut-in-v0", "planning-wrapper"]
BAD_ACTIONS = [  # (action, words the message must contain: what was given)
    ("1.0", ["'1.0'", "str"]),
    (["1.0", "0.0"], ["['1.0', '0.0']", "list"]),
    (1 + 2j, ["(1+2j)", "complex"]),
    (np.array([1 + 2j, 0.0]), ["dtype complex128"]),
    (True, ["True", "bool"]),
    (np.array([True, False]), ["dtype bool", "True"]),
    ([True, 0.0], ["[True, 0.0]", "list"]),  # numpy would make it [1.0, 0.0]
    ([0.0, np.True_], ["True", "list"]),
    (np.array(["0.5", "0.5"]), ["dtype <U3", "'0.5'"]),
    (np.array([0.5, None], dtype=object), ["dtype object", "None"]),
    (None, ["None", "NoneType"]),
    ([0.1, [0.2, 0.3]], ["[0.1, [0.2, 0.3]]"]),  # ragged
]
GOOD_ACTIONS = [np.zeros(2, np.float32), [0.1, -0.002], [0, 0], np.array([1, 0], np.int64), (0.5, 0.0),
                np.array([[0.1, 0.0]]), [np.float32(0.1), 0.0], [2.0, 0.0]]  # the last clipped to [-1, 1]


def make_env(env_id: str) -> gym.Env:
    if env_id == "planning-wrapper":  # the RL baseline's view: checked before its map to the env's action
        return PlanningWrapper(gym.make("bimp/Overtaking-v0"))
    return gym.make(env_id)


@pytest.fixture(scope="module")
def envs() -> dict[str, gym.Env]:
    return {env_id: make_env(env_id) for env_id in ENV_IDS}


@pytest.mark.parametrize("action, words", BAD_ACTIONS, ids=[repr(a) for a, _ in BAD_ACTIONS])
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_step_refuses_what_is_not_real_numbers_before_simulating(envs, env_id, action, words):
    env = envs[env_id]
    env.reset(seed=0)
    clock = env.unwrapped.time
    one_line_error(lambda: env.step(action), "action", *words)
    assert env.unwrapped.time == clock  # nothing simulated


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_step_takes_float_arrays_and_lists_of_numbers_and_refuses_nan(envs, env_id):
    env = envs[env_id]
    env.reset(seed=0)
    for action in GOOD_ACTIONS:
        env.reset(seed=0)
        obs, *_ = env.step(action)
        assert np.all(np.isfinite(obs)) and env.unwrapped.time > 0
    one_line_error(lambda: env.step(np.array([np.nan, 0.0])), "finite")
    one_line_error(lambda: env.step(np.zeros(3)), "shape")


def test_checked_action_is_a_float_array():
    out = checked_action([0, np.int32(1)])
    assert out.dtype == float and out.tolist() == [0.0, 1.0]
