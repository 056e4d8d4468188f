"""The overtaking scenario's behaviour layer (the paper's higher-level decision module): gap acceptance sets the
reference lane and speed from the traffic; ``reference: keep-lane`` keeps the discovery variant."""

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.agents.baselines import LaneKeeping
from bimp.agents.rollout import rollout

OT = "bimp/Overtaking-v0"
RIGHT, LEFT = 2.0, -2.0  # lane centre offsets


def test_a_free_left_lane_is_taken_to_pass_the_slower_ov_and_the_ev_returns_after():
    env = gym.make(OT, config={"ev_speed": 25.0, "ov1_gap": 30.0, "ov1_speed": 15.0, "ov2_gap": 120.0,
                               "ov2_speed": 20.0})
    episode = rollout(env, LaneKeeping(env), 0)  # the lane keeper follows whatever lane the reference names
    lanes = [ref[2] for ref in episode.trace["reference"]]
    assert set(lanes) <= {RIGHT, LEFT}  # never a lane outside the road
    first_left = lanes.index(LEFT)
    assert RIGHT in lanes[first_left:]  # back to the right lane after the pass
    assert episode.trace["ahead_of_ov1"][-1] and not any(episode.trace["collision"])
    back = first_left + lanes[first_left:].index(RIGHT)
    ev_s, ov1_xy = episode.trace["s"][back], episode.trace["ov_xy"][back][0]
    ov1_s, _ = env.unwrapped.scene.geometry.to_frenet(np.array(ov1_xy))
    assert ev_s - ov1_s >= 5.0  # the passed OV is behind by more than a car before the EV returns


def test_no_safe_lane_keeps_the_lane_and_follows_the_slower_ov():
    env = gym.make(OT, config={"ev_speed": 25.0, "ov1_gap": 30.0, "ov1_speed": 14.0, "ov2_gap": 40.0,
                               "ov2_speed": 15.0})  # a slow OV2 just ahead in the left lane
    obs, _ = env.reset(seed=0)
    v_ref, _, lane = env.unwrapped.scene.split_obs(obs)[3]
    assert lane == RIGHT and v_ref == pytest.approx(14.0)


def test_keep_lane_is_the_discovery_variant():
    env = gym.make(OT, config={"reference": "keep-lane", "ev_speed": 25.0})
    episode = rollout(env, LaneKeeping(env), 0, max_steps=40)
    assert all(ref[2] == RIGHT and ref[0] == 25.0 for ref in episode.trace["reference"])


def test_the_option_is_validated_and_the_emergency_brake_has_no_overtake():
    with pytest.raises(ValueError, match="reference must be one of"):
        gym.make(OT, config={"reference": "mobil"})
    env = gym.make("bimp/EmergencyBrake-v0")
    _, info = env.reset(seed=0)
    assert info["ahead_of_ov1"] is None
    with pytest.raises(ValueError, match="unknown config"):
        gym.make("bimp/EmergencyBrake-v0", config={"reference": "keep-lane"})


def test_a_pass_that_could_not_finish_before_reaching_the_ov_waits_behind_it_first():
    # 27 m/s closing at 12 m/s on OV1 25 m ahead: about 1.5 s to its tail, less than a lane change takes.
    config = {"ev_speed": 27.0, "ov1_gap": 25.0, "ov1_speed": 15.0, "ov2_gap": 120.0, "ov2_speed": 20.0}
    env = gym.make(OT, config=config)
    obs, _ = env.reset(seed=0)
    v_ref, _, lane = env.unwrapped.scene.split_obs(obs)[3]
    assert lane == RIGHT and v_ref == pytest.approx(15.0)  # brake behind OV1 first
    # The lane keeper brakes to the reference speed; the pass is asked for once the closing speed allows it.
    episode = rollout(env, LaneKeeping(env), 0, max_steps=25)
    lanes = [ref[2] for ref in episode.trace["reference"]]
    start = lanes.index(LEFT)
    assert start > 0 and episode.trace["speed"][start] < 23.0
    # The same instance 10 m further back passes at once.
    obs, _ = gym.make(OT, config={**config, "ov1_gap": 35.0}).reset(seed=0)
    assert env.unwrapped.scene.split_obs(obs)[3][2] == LEFT
