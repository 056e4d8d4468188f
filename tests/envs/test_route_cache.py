"""The adapter keeps the EV's route while it serves (:class:`bimp.envs.highway.lanes.RouteCache`): the kept route is
the road a fresh build gives, over the stretch a planner reads, and it is rebuilt where the lane sequence changes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import bimp  # noqa: F401  (registers bimp/ID)
from bimp import make_policy
from bimp.envs.highway.adapter import SUPPORTED
from bimp.envs.highway.lanes import AHEAD, BLEND, SLACK, RouteCache, build_route

CURVED = {"roundabout-v0", "u-turn-v0", "racetrack-v0", "intersection-v0"}


@pytest.mark.parametrize("highway_id", [*SUPPORTED, "cut-in-hard-v0", "lane-drop-hard-v0"])
def test_the_kept_route_is_the_fresh_route_where_a_planner_reads_it(highway_id):
    env = gym.make(f"bimp/{highway_id}")
    adapter = env.env.env.env
    policy = make_policy("idm", env)
    obs, _ = env.reset(seed=2)
    steps = 0
    for steps in range(1, 61):
        base = env.unwrapped
        ev = base.vehicle
        plan = getattr(ev, "route", None) or adapter.behaviour.route
        fresh, _ = build_route(base.road.network, adapter._route_lane(ev, plan), ev.position, plan)
        kept = base.scene.road
        s_ev = float(kept.project(np.array(ev.position, float)).s)
        assert kept.s[-1] - s_ev >= AHEAD - 1.0  # a planner's horizon ahead, always
        # Never lying on itself (racetrack-v0 loops in about 345 m): points 20 m apart along it are 2 m apart or more.
        gap = np.hypot(*(kept.xy[:, None, :] - kept.xy[None, :, :]).T)
        assert gap[np.abs(kept.s[:, None] - kept.s[None, :]) > 20.0].min() > 2.0
        # Every fresh point from 20 m behind the EV to 200 m ahead (the planners' windows) lies on the kept route,
        # up to the chords' sag on a curve (1 m chords on radii >= 9 m: under 2 cm) and headed the same way.
        s_fresh = fresh.project(np.array(ev.position, float)).s
        near = (fresh.s > s_fresh - 20.0) & (fresh.s < s_fresh + 200.0)
        if highway_id == "roundabout-v0":
            # A route built from a lane's start (the ring's, just past the entry) does not see the lane before it,
            # so not the blend across the gap between them that the kept route follows (lanes.smooth_bridges).
            near &= fresh.s > fresh.s[0] + BLEND
        on = kept.project(fresh.xy[near])
        tolerance = 0.02 if highway_id in CURVED else 1e-6
        assert np.abs(on.l).max() <= tolerance, highway_id
        turn = (on.heading - fresh.heading[near] + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(turn).max() <= (0.05 if highway_id in CURVED else 1e-6)
        obs, _, terminated, truncated, _ = env.step(policy.act(obs))
        if terminated or truncated:
            break
    assert adapter._routes.builds <= max(3, steps // 5), (highway_id, adapter._routes.builds, steps)


def test_the_cache_rebuilds_where_the_lane_sequence_changes():
    env = gym.make("bimp/highway-v0")
    env.reset(seed=0)
    network = env.unwrapped.road.network
    lane = network.get_lane(("0", "1", 1))
    cache = RouteCache()
    first, _ = cache.get(network, ("0", "1", 1), lane.position(100.0, 0.0))
    again, at = cache.get(network, ("0", "1", 1), lane.position(150.0, 0.3))
    assert again is first and cache.builds == 1
    assert abs(first.s[at] - first.project(lane.position(150.0, 0.0)).s) <= 0.5
    cache.get(network, ("0", "1", 2), network.get_lane(("0", "1", 2)).position(150.0, 0.0))  # a lane change
    assert cache.builds == 2
    cache.get(network, ("0", "1", 2), network.get_lane(("0", "1", 2)).position(260.0, 0.0))  # < AHEAD m left
    assert cache.builds == 3
    cache.get(network, ("0", "1", 2), network.get_lane(("0", "1", 2)).position(200.0, 0.0))  # behind the build
    assert cache.builds == 4
    env.reset(seed=1)  # a new network
    cache.get(env.unwrapped.road.network, ("0", "1", 2), network.get_lane(("0", "1", 2)).position(200.0, 0.0))
    assert cache.builds == 5


def test_the_cache_rebuilds_where_the_planned_route_changes():
    env = gym.make("bimp/roundabout-v0")
    env.reset(seed=0)
    network = env.unwrapped.road.network
    index = ("ser", "ses", 0)
    position = network.get_lane(index).position(5.0, 0.0)
    cache = RouteCache()
    one = [("ser", "ses", 0), ("ses", "se", 0), ("se", "ex", 0), ("ex", "ee", 0), ("ee", "nx", 0)]
    other = one[:3] + [("ex", "exs", 0)]
    cache.get(network, index, position, one)
    cache.get(network, index, position, list(one))
    assert cache.builds == 1
    cache.get(network, index, position, other)
    assert cache.builds == 2


def test_a_kept_route_never_comes_round_onto_itself():
    """racetrack-v0's inner lane is about 345 m round: a kept route (380 m) from it is cut where it comes back."""
    env = gym.make("bimp/racetrack-v0")
    env.reset(seed=0)
    network = env.unwrapped.road.network
    cut = 0
    for index in network.lanes_dict():
        lane = network.get_lane(index)
        position = lane.position(lane.length / 2, 0.0)
        kept, at = RouteCache().get(network, index, position)
        assert kept.s[-1] - kept.s[at] >= AHEAD
        gap = np.hypot(*(kept.xy[:, None, :] - kept.xy[None, :, :]).T)
        assert gap[np.abs(kept.s[:, None] - kept.s[None, :]) > 20.0].min() > 2.0, index
        cut += kept.s[-1] < build_route(network, index, position, ahead=AHEAD + SLACK)[0].s[-1] - 1.0
    assert cut >= 8  # the inner lane's routes, at least


@pytest.mark.parametrize("bad", [{"behind": -1.0}, {"ahead": 0.0}, {"slack": -5.0}, {"spacing": 0.0},
                                 {"ahead": float("nan")}])
def test_a_bad_cache_is_refused_naming_its_numbers(bad):
    with pytest.raises(ValueError, match="route cache needs"):
        RouteCache(**bad)


def test_a_road_whose_tightest_curve_the_actuator_cannot_reach_is_refused_at_make(monkeypatch):
    import dataclasses

    import gymnasium as gym

    from bimp.envs.highway import profiles
    from bimp.envs.highway.lanes import steering_needed
    from bimp.envs.scene import Bounds

    env = gym.make("bimp/racetrack-v0")
    radii = {lane.radius for ends in env.unwrapped.road.network.graph.values() for lanes in ends.values()
             for lane in lanes if hasattr(lane, "radius")}
    assert min(radii) == 15  # the hairpin: 0.326 rad, inside the racetrack's ±0.6 rad actuator
    needed = steering_needed(env.unwrapped.road.network.get_lane(("d", "e", 0)), 5.0)
    assert 0.32 < needed < 0.33
    narrow = dataclasses.replace(profiles.PROFILES["racetrack-v0"], bounds=Bounds(steer=0.3, steer_rate=0.03),
                                 actuator_steer=(-0.3, 0.3))
    monkeypatch.setitem(profiles.PROFILES, "racetrack-v0", narrow)
    with pytest.raises(ValueError, match=r"racetrack-v0: the route's curve on lane .* \(radius 15 m\) needs 0\.32\d "
                                         r"rad of steering, past the actuator's steering range ±0\.3 rad"):
        gym.make("bimp/racetrack-v0")
