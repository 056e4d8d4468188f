"""Yielding at junctions (issue 49 item 2): the EV's path and the other vehicles' predictions follow the lane graph,
the EV yields to a ring vehicle that reaches the entry with it and not to one that is gone, it commits once inside,
and the idm baseline stays highway-env's driver unless asked to yield."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from highway_env.road.lane import StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle

import bimp  # noqa: F401  (registers bimp/ID)
from bimp.agents import make_policy
from bimp.configs import ConfigError
from bimp.envs.highway import junction
from bimp.envs.highway.behaviour import ShadowDriver

pytestmark = pytest.mark.filterwarnings("ignore")


def _roundabout(seed: int = 0):
    """bimp/roundabout-v0 at ``seed`` with the traffic removed: the EV alone at its entry."""
    env = gym.make("bimp/roundabout-v0")
    env.reset(seed=seed)
    base = env.unwrapped
    base.road.vehicles[:] = [base.vehicle]
    return env, base


def _shadow(base) -> ShadowDriver:
    ev = base.vehicle
    return ShadowDriver(base.road, np.array(ev.position, float), heading=ev.heading, speed=ev.speed,
                        target_lane_index=ev.lane_index, target_speed=16.0, route=list(ev.route))


def _ring_vehicle(base, longitudinal: float, speed: float = 14.0) -> IDMVehicle:
    """A vehicle on the outer ring lane before the south entry, bound past it to the east exit."""
    vehicle = IDMVehicle.make_on_lane(base.road, ("sx", "se", 1), longitudinal, speed)
    vehicle.plan_route_to("exr")
    return vehicle


def test_resolved_route_names_the_lane_the_entry_leads_into():
    _, base = _roundabout()
    route = junction.resolved_route(base.vehicle)
    assert route[0] == base.vehicle.lane_index and all(k is not None for _, _, k in route)
    network = base.road.network
    entry_end = network.get_lane(route[1]).position(network.get_lane(route[1]).length, 0.0)
    ring = network.graph["se"]["ex"]
    nearest = int(np.argmin([np.linalg.norm(lane.position(0.0, 0.0) - entry_end) for lane in ring]))
    assert route[2] == ("se", "ex", nearest)
    # highway-env's own prediction keeps the current lane's id on the next road: from the ring's lane 1 into an exit
    # of one lane it fails; the resolved route does not.
    vehicle = IDMVehicle.make_on_lane(base.road, ("ex", "ee", 1), 5.0, 10.0)
    vehicle.route = [("ex", "ee", 1), ("ee", "nx", None), ("nx", "nxs", None)]
    assert len(junction.predicted_positions(vehicle, np.arange(0.25, 6.0, 0.25))) == 23


def test_path_follows_the_lanes_at_the_step():
    _, base = _roundabout()
    path = junction.along_route(base.vehicle, np.arange(0.0, 80.0, 1.0))
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    assert np.allclose(path[0], base.vehicle.lane.position(base.vehicle.lane.local_coordinates(
        base.vehicle.position)[0], 0.0))
    # Along the lanes, through the entry into the ring and out of it; highway-env's sine lanes (the entry, the exit)
    # start 6.5 m from where the lane before ends, the path's two jumps.
    assert steps.min() > 0.9 and np.sum(steps > 1.1) == 2 and steps.max() < 7.0
    lanes = [base.road.network.get_lane(index) for index in junction.resolved_route(base.vehicle)]
    for point in path:  # on a lane centre of the route (a straight line would leave them at the bend)
        assert min(abs(lane.local_coordinates(point)[1]) for lane in lanes) < 0.05


def test_go_distance():
    t = np.array([0.0, 1.0, 2.0, 4.0])
    assert np.allclose(junction.go_distance(0.0, 6.0, 3.0, t), [0.0, 1.5, 6.0, 18.0])
    assert np.allclose(junction.go_distance(8.0, 6.0, 3.0, t), 8.0 * t)  # above the target: holds its speed


def test_yields_to_a_ring_vehicle_that_arrives_with_it_and_not_to_one_gone_by():
    _, base = _roundabout()
    shadow = _shadow(base)
    ring = base.road.network.get_lane(("sx", "se", 1))
    verdicts = {}
    for s in np.linspace(0.0, ring.length, 9):
        base.road.vehicles[:] = [base.vehicle, _ring_vehicle(base, float(s))]
        verdicts[float(s)] = junction.stop_distance(shadow, base.road.vehicles[1:])
    assert any(v is not None for v in verdicts.values())  # some arrival meets the EV at the entry
    gone = IDMVehicle.make_on_lane(base.road, ("ee", "nx", 1), 5.0, 14.0)  # far round the ring, driving away
    gone.plan_route_to("nxr")
    assert junction.stop_distance(shadow, [gone]) is None
    assert junction.stop_distance(shadow, []) is None
    conflict = next(v for v in verdicts.values() if v is not None)
    assert conflict > junction.MARGIN_LENGTH  # ahead of the EV, where it can still stop


def test_yield_acceleration_is_idms_behind_a_stopped_vehicle():
    network = RoadNetwork()
    network.add_lane("a", "b", StraightLane([0.0, 0.0], [500.0, 0.0]))
    road = Road(network)
    driver = IDMVehicle.make_on_lane(road, ("a", "b", 0), 10.0, 12.0)
    driver.target_speed = 16.0
    stopped = IDMVehicle.make_on_lane(road, ("a", "b", 0), 45.0, 0.0)
    road.vehicles += [driver, stopped]
    assert junction.yield_acceleration(driver, 35.0) == pytest.approx(driver.acceleration(driver, stopped))


def test_commits_once_entered_and_keeps_highway_envs_driver_for_idm():
    env, base = _roundabout()
    adapter = env
    while not hasattr(adapter, "behaviour"):
        adapter = adapter.env
    behaviour = adapter.behaviour
    assert behaviour.yielding is not None and not behaviour.yielding.entered
    policy = make_policy("idm", env, junction_yield=True)
    obs, _ = env.reset(seed=0)
    entered_at = None
    for step in range(150):
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        behaviour = adapter.behaviour
        if behaviour.yielding.entered and entered_at is None:
            entered_at = step
        if entered_at is not None:
            assert behaviour.yield_distance is None  # inside: it yields to nobody
        if terminated or truncated:
            break
    assert entered_at is not None and info["goal"]  # seed 0: in, round and out
    # On a road without yielding the command is highway-env's driver's own.
    env = gym.make("bimp/highway-v0")
    env.reset(seed=0)
    adapter = env
    while not hasattr(adapter, "behaviour"):
        adapter = adapter.env
    assert adapter.behaviour.yielding is None and adapter.behaviour.action == adapter.behaviour.own_action


def test_idm_junction_yield_option():
    env = gym.make("bimp/roundabout-v0")
    obs, _ = env.reset(seed=1)
    plain, yielding = make_policy("idm", env), make_policy("idm", env, junction_yield=True)
    adapter = env
    while not hasattr(adapter, "behaviour"):
        adapter = adapter.env
    differed = False
    for _ in range(60):
        a, b = plain.act(obs), yielding.act(obs)
        behaviour = adapter.behaviour
        if behaviour.yield_distance is not None:
            differed = differed or not np.allclose(a, b)
        else:
            assert np.allclose(a, b)
        obs, _, terminated, truncated, _ = env.step(b)
        if terminated or truncated:
            break
    assert differed  # seed 1: the EV waits at the entry, which highway-env's driver does not
    with pytest.raises(ConfigError, match="junction_yield"):
        make_policy("idm", env, junction_yield="yes")


def test_reference_lane_stays_on_the_road_until_the_next():
    env = gym.make("bimp/roundabout-v0")
    obs, info = env.reset(seed=0)
    adapter = env
    while not hasattr(adapter, "behaviour"):
        adapter = adapter.env
    policy = make_policy("idm", env, junction_yield=True)
    ahead = 0
    for _ in range(120):
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        ev = env.unwrapped.vehicle
        if tuple(adapter.behaviour.target_lane_index[:2]) != tuple(ev.lane_index[:2]):
            ahead += 1  # highway-env's driver has turned to the next road's lane before this one ends
            # The reference is the EV's own lane on its route, which the route follows (or blends across a gap
            # from): the route itself, not the next road's lane (2.3 m beside the entry).
            assert info["reference"][2] == pytest.approx(0.0, abs=1e-6)
        if terminated or truncated:
            break
    assert ahead > 0


def test_a_vehicle_turning_off_at_a_fork_is_predicted_along_its_own_branch():
    _, base = _roundabout()
    # On the ring just past the east fork, its route already on the exit: highway-env's nearest lane is the ring's.
    vehicle = IDMVehicle.make_on_lane(base.road, ("ex", "ee", 1), 1.0, 10.0)
    vehicle.route = [("ex", "exs", 0), ("exs", "exr", None)]
    assert junction.resolved_route(vehicle)[0] == ("ex", "exs", 0)
    end = junction.predicted_positions(vehicle, np.array([2.0]))[0]
    exit_lane = base.road.network.get_lane(("exs", "exr", 0))
    assert abs(exit_lane.local_coordinates(end)[1]) < 1.0 and end[0] > 40.0  # out along the exit, not round the ring


@pytest.mark.parametrize("scenario", ["bimp/roundabout-v0", "bimp/intersection-v0"])
def test_no_yield_once_at_the_stop_line(scenario):
    """A conflict first seen at the stop line would put the stop inside the junction (IDM braking far beyond its
    comfort there); the EV has entered once it reaches the line. Seeds where that happened before the rule."""
    env = gym.make(scenario)
    adapter = env
    while not hasattr(adapter, "behaviour"):
        adapter = adapter.env
    policy = make_policy("idm", env, junction_yield=True)
    yielded = 0
    for seed in (2, 7):
        obs, _ = env.reset(seed=seed)
        for _ in range(200):
            obs, _, terminated, truncated, _ = env.step(policy.act(obs))
            behaviour = adapter.behaviour
            if behaviour.yield_distance is not None:
                yielded += 1
                line = junction.stop_line(env.unwrapped.vehicle)
                assert line is not None and line > 0.0
            if terminated or truncated:
                break
    assert yielded > 0


def test_the_route_blends_across_the_roundabouts_gaps():
    """roundabout-v0's entries and exits meet the ring 5.6-6.5 m on: the route blends across each gap (no turn of
    more than the planning bound's radius over 5 m, nothing like the chord's 0.54 rad within a metre), keeps a car's
    half width and more from its edges, and leaves the lanes' centres only across the blend."""
    from bimp.envs.highway.lanes import BLEND, build_route, lane_walk

    _, base = _roundabout()
    network, ev = base.road.network, base.vehicle
    entry = network.get_lane(("ses", "se", 0))
    route, lanes = build_route(network, ("ses", "se", 0), entry.position(5.0, 0.0), ev.route)
    assert len(lane_walk(network, ("ses", "se", 0), 0.0, 120.0, list(ev.route)[1:])[3]) == 2  # entry and exit
    ahead = route.s < route.s[0] + 110.0  # through the entry, round the ring and out
    heading = np.interp(np.arange(route.s[0], route.s[0] + 110.0, 1.0), route.s, route.heading)
    assert np.abs(np.diff(heading)).max() < 0.2
    kappa = (np.abs(heading[5:] - heading[:-5]) / 5.0).max()  # over 5 m: about a radius of 8 m
    needed = np.arctan(2 * np.tan(np.arcsin(5.0 * kappa / 2)))  # highway-env's bicycle, L = 5 m (steering_needed)
    assert needed <= base.scene.bounds.steer
    assert np.minimum(route.right, -route.left)[ahead].min() > 1.3  # a car's half width and the edge margin
    off = [abs(network.get_lane(lane).local_coordinates(point)[1]) for lane, point in zip(lanes, route.xy)]
    blended = np.asarray(off)[ahead] > 0.05
    assert 0 < np.count_nonzero(blended) <= 2 * (2 * BLEND + 8)  # two blends of a gap (<= 7 m) and BLEND either side


def test_curve_acceleration_brakes_for_the_curve_ahead_and_not_on_a_straight():
    from bimp.envs.highway.behaviour import CURVE_REACTION, curve_acceleration
    from bimp.envs.road import Route

    radius, a_lat = 20.0, 4.0
    s = np.arange(0.0, 200.0, 1.0)
    heading = np.where(s < 100.0, 0.0, (s - 100.0) / radius)  # straight, then a circle from 100 m on
    xy = np.cumsum(np.stack([np.cos(heading), np.sin(heading)], 1), axis=0)
    route = Route(xy=xy, s=s, heading=heading, curvature=np.gradient(heading, s), left=-2 + 0 * s, right=2 + 0 * s)
    v_curve = np.sqrt(a_lat * radius)  # 8.9 m/s
    assert curve_acceleration(route, 0.0, 15.0, a_lat) == np.inf  # the curve is 100 m on: nothing to brake for yet
    brake = curve_acceleration(route, 60.0, 15.0, a_lat)
    # the curvature over 5 m is the circle's from 102.5 m on: 42.5 m ahead
    assert brake < 0 and brake == pytest.approx((v_curve ** 2 - 15.0 ** 2) / (2 * 42.5), rel=0.05)
    assert curve_acceleration(route, 120.0, 0.5 * v_curve, a_lat) > 0  # below the curve's speed: may speed up
    inside = curve_acceleration(route, 120.0, 12.0, a_lat)
    assert inside == pytest.approx((v_curve ** 2 - 144.0) / (2 * 12.0 * CURVE_REACTION), rel=1e-6)
    straight = Route(xy=xy, s=s, heading=0 * s, curvature=0 * s, left=-2 + 0 * s, right=2 + 0 * s)
    assert curve_acceleration(straight, 50.0, 30.0, a_lat) == np.inf
    with pytest.raises(ValueError, match="lateral acceleration"):
        curve_acceleration(straight, 50.0, 30.0, 0.0)
