"""The road-edge guard (bimp.planners.guard): a plan that leaves the road is replaced by braking in lane."""

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.agents import make_policy
from bimp.agents.evaluation.provenance import config_hash, resolved_config
from bimp.planners.guard import brake_in_lane, guarded, leaves_road


@pytest.fixture(scope="module")
def scene():
    env = gym.make("bimp/Overtaking-v0")  # a straight start, edges at l = -4 and +4 m (y down: > 0 right)
    env.reset(seed=0)
    return env.unwrapped.scene


def path(y_end: float, steps: int = 20) -> np.ndarray:
    """States along the road from x = 10 m, drifting laterally from y = 0 to ``y_end``."""
    return np.column_stack([np.linspace(12, 50, steps), np.linspace(0, y_end, steps), np.zeros(steps),
                            np.full(steps, 20.0)])


def test_a_plan_leaves_the_road_when_a_corner_crosses_the_edge(scene):
    x0 = np.array([10.0, 0.0, 0.0, 20.0])
    assert not leaves_road(scene, x0, path(2.0))  # the corners reach 3 m: inside the 4 m edge
    assert leaves_road(scene, x0, path(3.5))  # 4.5 m: over it
    assert leaves_road(scene, x0, path(-3.5))  # and on the other side


def test_an_ev_already_over_the_edge_may_come_back_but_not_go_further(scene):
    x0 = np.array([10.0, 3.5, 0.0, 20.0])  # a corner 0.5 m over
    assert not leaves_road(scene, x0, path(3.2)[::-1])  # back towards the lane
    assert leaves_road(scene, x0, np.column_stack([np.full(5, 20.0), np.full(5, 3.8), np.zeros(5), np.full(5, 20.0)]))


def test_braking_in_lane_brakes_fully_and_steers_the_heading_back_to_the_roads(scene):
    for error in (0.04, -0.04):
        a, steer = brake_in_lane(scene, np.array([10.0, 0.0, error, 20.0]))
        assert a == scene.bounds.accel[0]
        assert np.sign(steer) == -np.sign(error) and abs(steer) <= scene.bounds.steer
    assert brake_in_lane(scene, np.array([10.0, 0.0, 0.0, 20.0]))[1] == pytest.approx(0.0, abs=1e-9)
    assert np.isfinite(brake_in_lane(scene, np.array([10.0, 0.0, 0.3, 0.0]))).all()  # at rest: no division by 0


def test_braking_in_lane_turns_with_a_curve():
    env = gym.make("bimp/racetrack-v0")
    env.reset(seed=0)
    scene = env.unwrapped.scene
    p = scene.road.project(scene.road.xy[np.argmax(np.abs(scene.road.curvature))])
    x0 = np.array([*scene.road.xy[np.argmax(np.abs(scene.road.curvature))], float(p.heading), 8.0])
    steer = brake_in_lane(scene, x0)[1]
    assert np.sign(steer) == np.sign(p.curvature) and abs(steer) == pytest.approx(
        min(np.arctan(scene.vehicle_length * abs(float(p.curvature))), scene.bounds.steer), rel=0.05)


def test_guarded_keeps_a_plan_on_the_road_and_replaces_one_that_leaves(scene):
    x0, planned = np.array([10.0, 0.0, 0.02, 20.0]), np.array([0.5, 0.5], np.float32)
    action, acted = guarded(scene, x0, path(1.0), planned)
    assert not acted and np.array_equal(action, planned)
    action, acted = guarded(scene, x0, path(3.8), planned)
    assert acted and action.dtype == np.float32 and np.all(np.abs(action) <= 1)
    assert np.allclose(scene.to_physical(action), brake_in_lane(scene, x0))


def test_the_guard_is_where_the_road_asks_for_it_and_said_per_step_when_on():
    env = gym.make("bimp/Overtaking-v0")  # the paper's scenario: the planner as printed
    obs, _ = env.reset(seed=1)
    plain, on = make_policy("enkts", env), make_policy("enkts", env, road_guard=True)
    assert plain.config.road_guard is None and not plain.guard and on.guard
    assert resolved_config(plain)["config"]["road_guard"] is None and "road" not in resolved_config(plain)
    assert config_hash("enkts", resolved_config(plain)) == config_hash(
        "enkts", resolved_config(make_policy("enkts", env, road_guard=False)))  # the records from before it
    plain.reset(seed=1)
    on.reset(seed=1)
    action = plain.act(obs)
    assert "guard" not in plain.step_info  # a config without it records as before
    assert np.array_equal(on.act(obs), action) and on.step_info["guard"] is False  # on the road: the plan's own
    batch = make_policy("enks", [gym.make("bimp/Overtaking-v0") for _ in range(2)], road_guard=True)
    batch.reset(seed=[1, 2])
    assert batch.act(np.stack([obs, obs])).shape == (2, 2) and len(batch.step_info["guard"]) == 2
    road = gym.make("bimp/highway-v0")  # a highway-env road asks for it, and the record says so
    road.reset(seed=1)
    asked, off = make_policy("enkts", road), make_policy("enkts", road, road_guard=False)
    assert asked.guard and resolved_config(asked)["road"] == {"road_guard": True} and not off.guard
    assert config_hash("enkts", resolved_config(asked)) != config_hash("enkts", resolved_config(off))
    with pytest.raises(ValueError, match="mixes roads that ask for the road-edge guard"):
        make_policy("enkts", [road, gym.make("bimp/Overtaking-v0")])


def test_where_the_scene_knows_its_lanes_a_corner_on_a_lane_beside_the_route_is_road(scene):
    """At a roundabout's entry the route's edges are the entry lane's, and a plan turning into the ring crosses them
    over the ring's lanes: there the guard braked the EV to a halt on 20 of 20 development seeds."""
    x0 = np.array([10.0, 0.0, 0.0, 20.0])
    assert not leaves_road(dataclasses.replace(scene, on_lanes=lambda points: True), x0, path(3.5))
    assert leaves_road(dataclasses.replace(scene, on_lanes=lambda points: False), x0, path(3.5))
    env = gym.make("bimp/roundabout-v0")
    env.reset(seed=0)
    entry = env.unwrapped.scene  # the EV's route into the ring; seed 0's plan at the entry, traced
    x0, state = np.array([3.65, 30.9, -1.38, 3.35]), np.array([[6.79, 23.04, -1.01, 5.36]])
    assert entry.edge_distance(state)[0] < 0 < entry.edge_distance(x0)  # past the route's edge: else vacuous
    assert not leaves_road(entry, x0, state)
    assert leaves_road(dataclasses.replace(entry, on_lanes=None), x0, state)
    assert leaves_road(entry, x0, np.array([[10.0, 35.0, -1.01, 5.36]]))  # beside the entry, on no lane
