"""What the closed-loop score reads per step: ``info["contact"]`` and ``info["speed_limit"]``
(:func:`bimp.envs.scene.attribution_info`), on the paper's envs and on a wrapped highway-env env."""

import json
import math

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs  # noqa: F401  (registers the ids)
from bimp.agents.evaluation.metrics import at_fault_collision, episode_metrics
from bimp.agents.rollout import rollout
from bimp.envs.road import Route
from bimp.envs.scene import CONTACT_FIELDS, attribution_info


def rows(*ovs):
    """OV rows ``[present, x, y, heading, speed, acceleration]`` from ``(x, y, heading, speed)``."""
    return np.array([[1.0, *ov, 0.0] for ov in ovs])


def test_contact_is_the_touching_ov_in_the_evs_body_frame():
    # the EV at (10, 5) driving along +y (heading pi/2); the right of its travel is -x (the road's l > 0 there)
    ego = np.array([10.0, 5.0, np.pi / 2, 12.0])
    ovs = rows((10.0, 9.0, np.pi / 2, 8.0), (8.2, 6.0, np.pi / 2 + 0.1, 13.0), (30.0, 30.0, 0.0, 5.0))
    info = attribution_info(ego, ovs, [-0.1, -0.3, 20.0], ev_lateral_speed=0.4, speed_limit=15.0)
    c = info["contact"]
    assert info["speed_limit"] == 15.0 and set(c) == set(CONTACT_FIELDS)
    # the deeper overlap (-0.3) is the contact: 1 m ahead, 1.8 m to the right, turned 0.1 rad
    assert c["rel_x"] == pytest.approx(1.0) and c["rel_y"] == pytest.approx(1.8)
    assert c["rel_heading"] == pytest.approx(0.1) and (c["ev_speed"], c["ov_speed"]) == (12.0, 13.0)
    assert c["ev_lateral_speed"] == 0.4
    # rel_y has the sign of the road's l: a route along +y puts that OV at l = +1.8 too
    road = Route.from_points(np.array([[10.0, 0.0], [10.0, 50.0]]), np.array([-4.0, -4.0]), np.array([4.0, 4.0]))
    assert float(road.project(ovs[1, 1:3]).l) == pytest.approx(c["rel_y"])
    json.dumps(info, allow_nan=False)  # a trace keeps it as JSON


def test_no_contact_unless_a_gap_closes_or_the_simulator_says_so():
    ego, ovs = np.array([0.0, 0.0, 0.0, 20.0]), rows((6.0, 0.0, 0.0, 10.0), (0.0, 4.0, 0.0, 20.0))
    assert attribution_info(ego, ovs, [0.5, 2.0], 0.0, 30.0)["contact"] is None
    assert attribution_info(ego, ovs, [0.5, 2.0], 0.0, 30.0, crashed=[False, False])["contact"] is None
    # highway-env crashed the pair and pushed it apart: the flagged vehicle, though another is nearer
    c = attribution_info(ego, ovs, [0.5, 2.0], 0.0, 30.0, crashed=[False, True])["contact"]
    assert c["rel_y"] == pytest.approx(4.0)
    # a gap <= 0 decides over the flags
    c = attribution_info(ego, ovs, [0.0, 2.0], 0.0, 30.0, crashed=[False, True])["contact"]
    assert c["rel_x"] == pytest.approx(6.0)
    assert attribution_info(ego, ovs, [0.5, 2.0], 0.0, 0.0)["speed_limit"] == 0.0  # a scenario told to stand
    for bad in (-1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="speed_limit"):
            attribution_info(ego, ovs, [0.5, 2.0], 0.0, bad)


class Coast:
    """Neither accelerates nor steers: on the overtaking scenario it drives into OV1."""

    config: dict = {}
    step_info: dict = {}

    def reset(self, seed=None) -> None:
        pass

    def act(self, obs):
        return np.zeros(2, np.float32)


def test_overtaking_scripted_collision_is_recorded_and_at_fault():
    # the EV at its cruise speed closes on a slower OV1 in its lane until it hits it from behind
    env = gym.make("bimp/Overtaking-v0", config={"ev_speed": 25.0, "ov1_gap": 30.0, "ov1_speed": 15.0,
                                                 "ov2_gap": 110.0, "ov2_speed": 18.0})
    episode = rollout(env, Coast(), seed=0)
    t = episode.trace
    assert t["collision"][-1] and not any(t["collision"][:-1]) and episode.steps > 10
    assert all(c is None for c in t["contact"][:-1])
    c = t["contact"][-1]
    assert 0.0 < c["rel_x"] <= 5.0 and abs(c["rel_y"]) < 0.1 and abs(c["rel_heading"]) < 0.01
    assert c["ev_speed"] == pytest.approx(25.0) and c["ov_speed"] == pytest.approx(15.0)
    assert abs(c["ev_lateral_speed"]) < 0.01
    # no limit of its own: the cruise speed, finite and positive at every step
    assert t["speed_limit"] == [pytest.approx(25.0)] * episode.steps
    json.dumps({k: t[k] for k in ("contact", "speed_limit")}, allow_nan=False)
    m = episode_metrics(t, env.unwrapped.scene.dt, truncated=episode.truncated)
    assert m["at_fault_collision_rate"] == 1.0 and m["score"] == 0.0
    assert m["score_progress"] == pytest.approx(1.0, abs=0.01) and m["score_speed"] == pytest.approx(1.0)
    env.close()


def test_highway_env_scripted_crash_reports_the_contact_and_the_lanes_limit():
    env = gym.make("bimp/highway-fast-v0", config={"vehicles_count": 20, "vehicles_density": 2.0})
    _, info = env.reset(seed=0)
    trace = {k: [] for k in ("collision", "contact", "speed_limit")}
    for _ in range(300):  # full throttle straight on: into the vehicle ahead
        _, _, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        lane = env.unwrapped.vehicle.lane
        assert info["speed_limit"] == lane.speed_limit and 0.0 < info["speed_limit"] < math.inf
        for k in trace:
            trace[k].append(info[k])
        if terminated or truncated:
            break
    assert info["collision"] and not any(trace["collision"][:-1])
    assert all(c is None for c in trace["contact"][:-1])
    c = info["contact"]
    assert c is not None and c["rel_x"] > 0.0 and abs(c["rel_y"]) < 2.0 and c["ev_speed"] > c["ov_speed"]
    assert at_fault_collision(trace) == 1.0  # it drove into the back of a slower vehicle
    env.close()


def test_highway_env_limit_is_the_lanes_not_the_free_road_target():
    # merge-v0's lanes carry highway-env's default limit (20 m/s), below the profile's free-road target (30 m/s)
    env = gym.make("bimp/merge-v0")
    _, info = env.reset(seed=0)
    for _ in range(5):
        assert info["speed_limit"] == env.unwrapped.vehicle.lane.speed_limit == 20.0 and info["contact"] is None
        _, _, _, _, info = env.step(np.zeros(2, np.float32))
    env.close()
