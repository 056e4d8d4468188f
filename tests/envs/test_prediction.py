"""The OVs' paths along their lanes (bimp.envs.highway.prediction): what the planners predict on a junction road."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import bimp  # noqa: F401  (registers bimp/ID)
from bimp.envs.highway.prediction import PATH_STEPS, lane_path
from bimp.envs.scene import travel

pytestmark = pytest.mark.filterwarnings("ignore")
T = 0.1 * np.arange(PATH_STEPS + 1)


def _base(highway_id, seed=0):
    env = gym.make(f"bimp/{highway_id}")
    env.reset(seed=seed)
    return env, env.unwrapped


def test_travel_stops_rather_than_reverses():
    d = travel(10.0, -5.0, T)
    np.testing.assert_allclose(d[T >= 2.0], 10.0)  # 10 m/s at -5 m/s^2: 10 m, stopped after 2 s
    np.testing.assert_allclose(travel(8.0, 0.5, T), 8.0 * T + 0.25 * T**2)


def test_a_vehicle_on_the_ring_is_predicted_round_it():
    """On roundabout-v0's ring, a vehicle along its lane stays on the lane: where the planners' straight-heading
    rule puts it metres outside the ring after 2 s."""
    env, base = _base("roundabout-v0")
    network = base.road.network
    lane = network.get_lane(("se", "ex", 0))
    vehicle = base.road.vehicles[1]
    vehicle.position, vehicle.heading, vehicle.speed = lane.position(2.0, 0.5), lane.heading_at(2.0), 8.0
    vehicle.lane_index, vehicle.lane = ("se", "ex", 0), lane
    path = lane_path(network, vehicle, 0.0, T)
    assert path.shape == (len(T), 3)
    inside = T * 8.0 + 2.0 < lane.length
    expected = np.array([lane.position(2.0 + 8.0 * t, 0.5) for t in T[inside]])
    np.testing.assert_allclose(path[inside, :2], expected, atol=0.05)
    np.testing.assert_allclose(path[inside, 2], [lane.heading_at(2.0 + 8.0 * t) for t in T[inside]], atol=0.02)
    straight = vehicle.position + 16.0 * np.array([np.cos(vehicle.heading), np.sin(vehicle.heading)])
    assert np.hypot(*(straight - path[20, :2])) > 4.0  # the rule this replaces, 2 s on


def test_a_path_goes_on_along_the_route_into_the_next_road():
    env, base = _base("intersection-v0", seed=3)
    network = base.road.network
    vehicle = next(v for v in base.road.vehicles[1:] if getattr(v, "route", None) and len(v.route) > 1)
    path = lane_path(network, vehicle, 0.0, 0.1 * np.arange(201))  # 20 s: well past its first lane
    end = tuple(network.get_closest_lane_index(path[-1, :2], path[-1, 2])[:2])
    assert end != tuple(vehicle.lane_index[:2]) and end in [tuple(r[:2]) for r in vehicle.route]


def test_a_lane_change_drifts_on_as_before():
    """A vehicle heading off its lane (changing lanes) keeps its heading relative to the lane: on a straight lane
    that is the straight-heading rule, so the straight roads' prediction is unchanged."""
    env, base = _base("roundabout-v0")
    network = base.road.network
    lane = network.get_lane(("ser", "ses", 0))  # the straight approach
    vehicle = base.road.vehicles[1]
    vehicle.position, vehicle.heading, vehicle.speed = lane.position(5.0, 0.0), lane.heading_at(5.0) + 0.1, 5.0
    vehicle.lane_index, vehicle.lane = ("ser", "ses", 0), lane
    t = T[:11]
    path = lane_path(network, vehicle, 0.0, t)
    expected = vehicle.position + (5.0 * t)[:, None] * np.array([np.cos(vehicle.heading), np.sin(vehicle.heading)])
    np.testing.assert_allclose(path[:, :2], expected, atol=1e-6)


@pytest.mark.parametrize("highway_id, published", [("roundabout-v0", True), ("intersection-v0", True),
                                                    ("highway-fast-v0", False), ("racetrack-v0", False)])
def test_the_adapter_publishes_paths_on_the_junction_roads_in_the_slots_order(highway_id, published):
    env = gym.make(f"bimp/{highway_id}")
    obs, _ = env.reset(seed=1)
    obs, *_ = env.step(np.zeros(2, np.float32))
    scene = env.unwrapped.scene
    if not published:
        assert scene.ov_paths is None
        return
    _, _, ovs, _ = scene.split_obs(obs)
    assert scene.ov_paths.shape == (scene.n_obstacles, PATH_STEPS + 1, 3)
    present = ovs[:, 0] > 0
    assert present.any()
    np.testing.assert_allclose(scene.ov_paths[present, 0, :2], ovs[present, 1:3], atol=1e-3)  # now: where it is
    assert np.all(scene.ov_paths[~present] == 0.0)


def test_a_path_starts_where_a_vehicle_off_a_sine_lanes_centre_is():
    """roundabout-v0's entries are sine lanes, whose own lateral coordinate is across their straight base: the
    path starts at the vehicle's position all the same, and keeps its offset from the lane's centre."""
    env, base = _base("roundabout-v0")
    network = base.road.network
    index = ("ses", "se", 0)
    lane = network.get_lane(index)
    assert type(lane).__name__ == "SineLane"
    vehicle = base.road.vehicles[1]
    s = lane.length / 2  # where the sine slopes most
    h = lane.heading_at(s)
    normal = np.array([-np.sin(h), np.cos(h)])
    vehicle.position, vehicle.heading, vehicle.speed = lane.position(s, 0.0) + 1.5 * normal, h, 0.0
    vehicle.lane_index, vehicle.lane = index, lane
    path = lane_path(network, vehicle, 0.0, T[:3])
    np.testing.assert_allclose(path[:, :2], np.tile(vehicle.position, (3, 1)), atol=1e-6)


@pytest.mark.parametrize("branch", ["il1", "il2", "il3"])
def test_a_route_popped_before_the_lanes_end_is_followed(branch):
    """highway-env pops the road a vehicle is on from its route half a car before the lane's end: the path goes on
    along the rest of the route (the branch the vehicle takes), not the lane graph's own choice."""
    env, base = _base("intersection-v0")
    network = base.road.network
    index = ("o0", "ir0", 0)
    lane = network.get_lane(index)
    vehicle = base.road.vehicles[1]
    vehicle.position, vehicle.heading, vehicle.speed = lane.position(lane.length - 1.0, 0.0), lane.heading_at(
        lane.length), 8.0
    vehicle.lane_index, vehicle.lane = index, lane
    vehicle.route = [("ir0", branch, 0), (branch, "o" + branch[-1], 0)]
    path = lane_path(network, vehicle, 0.0, 0.1 * np.arange(51))  # 5 s: 40 m, into the branch's exit road
    roads = [tuple(network.get_closest_lane_index(p[:2], p[2])[:2]) for p in path[-5:]]
    assert all(road in [(branch, "o" + branch[-1]), ("ir0", branch)] for road in roads), roads
