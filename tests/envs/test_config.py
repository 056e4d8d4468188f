"""Scenario configuration: validation with names, per-reset overrides, render rate."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers import RecordVideo

from bimp import envs
from bimp.envs.scenarios import MIN_CENTRE_GAP, N_OBSTACLES, EmergencyBrakeEnv, OvertakingEnv
from bimp.envs.scene import split_obs

EB, OT = "bimp/EmergencyBrake-v0", "bimp/Overtaking-v0"

BAD = [  # (env id, config, words the message must contain)
    (EB, {"brake_decel": -6}, ["brake_decel", "> 0", "deceleration magnitude", "-6"]),
    (EB, {"brake_decel": 0.0}, ["brake_decel", "0"]),
    (EB, {"brake_decel": (-1.0, 7.0)}, ["brake_decel", "(-1, 7)"]),
    (EB, {"ov1_gap": 0}, ["ov1_gap", "in [6, 1000]", "got 0"]),
    (OT, {"ov2_gap": 1e9}, ["ov2_gap", "in [6, 1000]", "got 1e+09"]),
    (EB, {"ov2_gap": (5.9, 50.0)}, ["ov2_gap", "5.9"]),
    (OT, {"ov1_gap": 0}, ["ov1_gap", "got 0"]),
    (EB, {"ev_speed": (5, 3)}, ["ev_speed", "lo <= hi", "(5, 3)"]),
    (EB, {"ov_speed": float("nan")}, ["ov_speed", "finite", "nan"]),
    (EB, {"ev_speed": (20.0, float("inf"))}, ["ev_speed", "finite", "inf"]),
    (EB, {"brake_onset": "1.0"}, ["brake_onset", "'1.0'"]),
    (EB, {"brake_onset": True}, ["brake_onset", "True"]),
    (EB, {"brake_onset": (True, 2.0)}, ["brake_onset", "True"]),
    (EB, {"brake_onset": (1.0, 2.0, 3.0)}, ["brake_onset", "(1.0, 2.0, 3.0)"]),
    (EB, {"brake_onset": -0.5}, ["brake_onset", ">= 0", "-0.5"]),
    (EB, {"ev_speed": -1.0}, ["ev_speed", "-1"]),
    (EB, {"ev_speed": 50.0}, ["ev_speed", "40", "50"]),
    (EB, {"ref_zero_step": 20}, ["ref_zero_step", "ref_hold", "20", "3"]),
    (EB, {"ref_zero_step": 30}, ["ref_zero_step", "ref_hold"]),  # 3 s: must come *after* the hold
    (EB, {"ref_zero_step": (20, 90)}, ["ref_zero_step", "(20, 90)"]),  # the worst case of the range
    (EB, {"ref_hold": (1.0, 9.0)}, ["ref_hold", "(1, 9)"]),
    (EB, {"ref_zero_step": 80.5}, ["ref_zero_step", "integer", "80.5"]),
    (OT, {"radius": 0.0}, ["radius", "got 0"]),
    (OT, {"radius": (3.0, 200.0)}, ["radius", "(3, 200)"]),
    (OT, {"arc_angle_deg": (50.0, 120.0)}, ["arc_angle_deg", "(50, 120)"]),
    (OT, {"arc_angle_deg": -100.0}, ["arc_angle_deg", "-100"]),
    (OT, {"ov2_gap": (30.0, 130.0)}, ["ov2_gap", "ov1_gap", "(30, 130)"]),  # OV2 may start on OV1
    (OT, {"ov1_gap": (25.0, 96.0)}, ["ov2_gap", "ov1_gap", "(25, 96)"]),
    (EB, {"policy_frequency": 3}, ["policy_frequency", "3"]),
    (EB, {"policy_frequency": 0}, ["policy_frequency", "0"]),
    # The planners plan with a 0.1 s model: any other policy frequency (dt 0.2 s, 0.05 s) is refused, saying so.
    (EB, {"policy_frequency": 5}, ["policy_frequency=5", "dt = 0.1 s", "policy_frequency 10"]),
    (OT, {"policy_frequency": 20, "simulation_frequency": 20}, ["policy_frequency=20", "dt = 0.1 s"]),
    (OT, {"policy_frequency": 10.5}, ["policy_frequency", "10.5"]),
    (EB, {"simulation_frequency": 15}, ["simulation_frequency", "multiple", "15"]),
    # highway-env's action config would be ignored: the env drives the EV by its own continuous action.
    (OT, {"action": {"type": "DiscreteMetaAction"}}, ["action", "DiscreteMetaAction", "own continuous"]),
    (EB, {"action": {"type": "ContinuousAction"}}, ["action", "ContinuousAction", "own continuous"]),
    # highway-env's rendering keys, checked as the adapter checks them.
    (OT, {"screen_width": "800"}, ["screen_width", "'800'", "an int"]),
    (EB, {"show_trajectories": "yes"}, ["show_trajectories", "'yes'", "bool"]),
    (OT, {"scaling": float("nan")}, ["scaling", "nan"]),
]


@pytest.mark.parametrize("env_id, config, words", BAD, ids=[str(c) for _, c, _ in BAD])
def test_bad_parameters_raise_value_errors_naming_key_and_value_at_make_and_at_reset(env_id, config, words):
    with pytest.raises(ValueError) as err:
        gym.make(env_id, config=config)
    for word in words:
        assert word in str(err.value), (word, str(err.value))
    env = gym.make(env_id)
    env.reset(seed=0)
    with pytest.raises(ValueError) as err:
        env.reset(seed=0, options={"config": config})
    assert words[0] in str(err.value)


def test_bad_reset_config_raises_before_anything_changes():
    env = gym.make(EB)
    obs, _ = env.reset(seed=5)
    base = env.unwrapped
    config_before, road_before = dict(base.config), base.road
    with pytest.raises(ValueError, match="brake_decel"):
        env.reset(seed=6, options={"config": {"brake_decel": -6}})
    assert base.config == config_before and base.road is road_before  # nothing was reset or simulated
    np.testing.assert_array_equal(env.reset(seed=5)[0], obs)


def test_documented_defaults_and_edges_of_the_accepted_ranges_pass():
    for cls in (OvertakingEnv, EmergencyBrakeEnv):
        env = cls()
        assert {k: env.config[k] for k in cls.PARAMS} == {k: p.default for k, p in cls.PARAMS.items()}
        for key, param in cls.PARAMS.items():
            assert key in cls.__doc__ and param.rule in cls.__doc__  # the docstring lists the checked table
    edges = {"ev_speed": 0.0, "ov1_gap": MIN_CENTRE_GAP, "ov2_gap": [MIN_CENTRE_GAP, 60], "brake_onset": 0,
             "brake_decel": 1e-3, "ov_speed": (40, 40), "ref_hold": 0.0, "ref_zero_step": np.int64(1)}
    env = gym.make(EB, config=edges)
    _, info = env.reset(seed=0)
    assert min(info["ov_distance"]) == pytest.approx(1.0) and not info["collision"]  # d_min apart at the start
    assert env.unwrapped.config["ov2_gap"] == (MIN_CENTRE_GAP, 60.0)
    gym.make(EB, config={"ref_zero_step": 40})
    gym.make(EB, config={"ref_zero_step": 31, "policy_frequency": 10, "simulation_frequency": 20})  # 3.1 s
    env = gym.make(OT, config={"arc_angle_deg": (-90, 90), "radius": 4.5, "ov1_gap": 10.0, "ov2_gap": 16.0})
    env.reset(seed=0)


def test_highway_env_keys_still_pass_through():
    env = gym.make(OT, render_mode="rgb_array",
                   config={"screen_width": 400, "screen_height": 120, "scaling": 3.0, "show_trajectories": True})
    env.reset(seed=0)
    env.step(np.zeros(2))
    assert env.render().shape == (120, 400, 3)


def test_integer_ranges_draw_integer_steps():
    env = gym.make(EB, config={"ref_zero_step": (60, 62)})
    drawn = set()
    for seed in range(12):
        env.reset(seed=seed)
        drawn.add(round(env.unwrapped.ref_zero / 0.1, 9))
    assert drawn == {60.0, 61.0, 62.0}


# --- per-reset configuration ---------------------------------------------------------------------------------------
def ov1_speed(obs):
    return float(split_obs(obs, N_OBSTACLES)[2][0, 4])


def test_reset_config_applies_to_that_reset_only():
    env = gym.make(OT, config={"ov1_speed": 16.0})
    assert ov1_speed(env.reset(seed=0)[0]) == pytest.approx(16.0)
    assert ov1_speed(env.reset(seed=0, options={"config": {"ov1_speed": 17.0}})[0]) == pytest.approx(17.0)
    assert env.unwrapped.config["ov1_speed"] == 17.0  # in force for this episode
    assert ov1_speed(env.step(np.zeros(2))[0]) == pytest.approx(17.0)
    assert ov1_speed(env.reset(seed=0)[0]) == pytest.approx(16.0)  # back on the gym.make config
    assert env.unwrapped.config["ov1_speed"] == 16.0
    assert ov1_speed(env.reset(seed=1, options={"foo": 1})[0]) == pytest.approx(16.0)  # other options: no effect


def test_reset_config_changing_the_simulation_frequency_is_undone_too():
    env = gym.make(EB)
    env.reset(seed=0, options={"config": {"simulation_frequency": 20}})
    assert env.unwrapped.config["simulation_frequency"] == 20 and env.unwrapped.scene.dt == pytest.approx(0.1)
    env.step(np.zeros(2))
    assert env.unwrapped.time == pytest.approx(0.1) and env.unwrapped.steps == 2  # two simulation steps per step
    env.reset(seed=0)
    assert env.unwrapped.config["simulation_frequency"] == 10 and env.unwrapped.metadata["render_fps"] == 10


# --- render rate ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", list(envs.ENV_IDS.values()))
def test_render_fps_is_the_policy_frequency_per_instance(env_id, tmp_path):
    # One frame per policy step (10 Hz) however many simulation steps it takes; highway-env's default would double
    # the rate, in the class-level dict every instance shares.
    fine = gym.make(env_id, render_mode="rgb_array", config={"simulation_frequency": 20})
    plain = gym.make(env_id, render_mode="rgb_array")
    assert fine.metadata["render_fps"] == 10 and plain.metadata["render_fps"] == 10
    fine.reset(seed=0)
    assert fine.metadata["render_fps"] == 10 and plain.metadata["render_fps"] == 10
    assert type(fine.unwrapped).metadata["render_fps"] == 10 and fine.unwrapped.metadata is not plain.unwrapped.metadata
    video = RecordVideo(fine, str(tmp_path / "videos"), episode_trigger=lambda _: False, disable_logger=True)
    assert video.frames_per_sec == 10
    video.close()


def test_drawn_parameters_are_recorded_per_episode():
    env = gym.make(EB, config={"ev_speed": 24.0, "ov_speed": (20.0, 24.0)})
    env.reset(seed=0)
    drawn = dict(env.unwrapped.drawn_params)
    assert set(drawn) == set(EmergencyBrakeEnv.PARAMS)
    assert drawn["ev_speed"] == 24.0 and drawn["ref_zero_step"] == 80 and isinstance(drawn["ref_zero_step"], int)
    assert len(drawn["ov_speed"]) == 2 and drawn["ov_speed"][0] != drawn["ov_speed"][1]  # one per OV
    assert 50.0 <= drawn["ov1_gap"] <= 60.0 and env.unwrapped.obstacles[0].speed == drawn["ov_speed"][0]
    env.reset(seed=1)
    assert env.unwrapped.drawn_params["ov1_gap"] != drawn["ov1_gap"]
