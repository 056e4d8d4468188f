"""The fast traffic core (:mod:`bimp.envs.traffic`) decides as highway-env's ``Road`` does: the same neighbours (ties,
objects, landmarks and connected lanes included) and the same collisions (flags and impacts, a vehicle class with its
own collision test included), on crafted roads; and every scenario's episodes are the same under both cores, every
vehicle at every step."""

from __future__ import annotations

import copy
import pickle

import gymnasium as gym
import numpy as np
import pytest
from highway_env.road.lane import StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.objects import Landmark, Obstacle

from bimp import envs
from bimp.envs import traffic
from bimp.envs.highway.fixed import HIGHWAY_CLASSES
from bimp.envs.traffic import FastRoad, accelerate, make_fast

LANES = 3


class Asking(IDMVehicle):
    """An IDM vehicle that, when it acts, asks the road for its neighbours on every lane, and keeps the answers."""

    answers: list

    def act(self, action=None) -> None:
        self.answers = [self.road.neighbour_vehicles(self, index) for index in lane_indices(self.road.network)]
        super().act(action)


def lane_indices(network: RoadNetwork) -> list:
    return [(a, b, k) for a, tos in network.graph.items() for b, lanes in tos.items() for k in range(len(lanes))]


def network(segments: int) -> RoadNetwork:
    """``LANES`` lanes of 4 m, in ``segments`` consecutive 60 m roads (0 -> 1 -> 2 ...)."""
    net = RoadNetwork()
    for seg in range(segments):
        for k in range(LANES):
            net.add_lane(str(seg), str(seg + 1), StraightLane([60.0 * seg, 4.0 * k], [60.0 * (seg + 1), 4.0 * k]))
    return net


def crowd(seed: int, segments: int = 1, count: int = 30, connected: bool = False) -> Road:
    """A road with ``count`` asking vehicles at random, on a coarse grid so that ties in position happen, some between
    lanes (on two lanes at once: ``on_lane`` with a margin), an obstacle and a landmark."""
    rng = np.random.default_rng(seed)
    road = Road(network=network(segments), np_random=np.random.default_rng(seed),
                neighbour_vehicles_connected_lanes=connected)
    for _ in range(count):
        x = float(rng.integers(0, 12 * segments)) * 5.0
        y = float(rng.choice([0.0, 2.0, 4.0, 8.0, 9.5]))
        road.vehicles.append(Asking(road, [x, y], heading=0.0, speed=float(rng.uniform(5, 30))))
    road.objects.append(Obstacle(road, [float(rng.integers(0, 12 * segments)) * 5.0, 4.0]))
    road.objects.append(Landmark(road, [10.0, 0.0]))
    return road


def answers(road: Road) -> list:
    """Every vehicle's answers, as indices into the road's vehicles and objects (None: no neighbour)."""
    order = {id(o): k for k, o in enumerate(road.vehicles + road.objects)}
    return [[tuple(None if n is None else order[id(n)] for n in pair) for pair in v.answers] for v in road.vehicles]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("segments, connected", [(1, False), (3, False), (3, True)])
def test_neighbours_are_highway_envs(seed, segments, connected):
    road = crowd(seed, segments, connected=connected)
    fast = make_fast(copy.deepcopy(road))
    road.act()
    fast.act()
    expected = answers(road)
    assert answers(fast) == expected
    assert any(None not in pair for rows in expected for pair in rows)  # the crowd has neighbours to find
    assert fast._acting is None  # outside act, highway-env's own search again


def test_a_tie_goes_as_highway_envs_loop_breaks_it(monkeypatch):
    """Three vehicles at one spot ahead and two at one spot behind: highway-env keeps the last tie ahead and the first
    behind; a search that took any nearest one would disagree."""
    monkeypatch.setattr(traffic, "SMALL_ROAD", 0)  # six vehicles: the arrays, not highway-env's loop, must answer
    road = Road(network=network(1), np_random=np.random.default_rng(0))
    for x in (30.0, 40.0, 40.0, 40.0, 20.0, 20.0):
        road.vehicles.append(Asking(road, [x, 0.0], speed=20.0))
    fast = make_fast(copy.deepcopy(road))
    road.act()
    fast.act()
    assert answers(road)[0][0] == (3, 4) and answers(fast) == answers(road)


def _state(road: Road) -> list:
    return [(tuple(v.position), v.heading, v.speed, v.crashed, tuple(np.atleast_1d(v.impact))) for v in road.vehicles]


class Sticky(IDMVehicle):
    """A vehicle class with its own collision test: anything within 50 m counts, where highway-env's pre-check would
    drop the pair. The fast core must test such a vehicle against every other."""

    def _is_colliding(self, other, dt):
        near = float(np.linalg.norm(other.position - self.position)) < 50.0
        return near, False, np.zeros(2)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("sticky", [False, True])
def test_collisions_are_highway_envs(seed, sticky):
    rng = np.random.default_rng(100 + seed)
    road = Road(network=network(1), np_random=np.random.default_rng(seed))
    for k in range(25):
        cls = Sticky if sticky and k == 3 else IDMVehicle
        road.vehicles.append(cls(road, [float(rng.uniform(0, 60)), float(rng.uniform(-1, 9))],
                                 heading=float(rng.normal(0, 0.3)), speed=float(rng.uniform(0, 30))))
    road.objects.append(Obstacle(road, [float(rng.uniform(0, 60)), 4.0]))
    fast = make_fast(copy.deepcopy(road))
    for _ in range(5):
        road.act(), fast.act()
        road.step(0.1), fast.step(0.1)
        assert _state(fast) == _state(road)
    assert any(v.crashed for v in road.vehicles)  # the crowd does collide: the test sees the collision code work


def test_a_fast_road_pickles_and_copies_as_a_fast_road():
    env = gym.make(envs.env_id("intersection-v0"))  # highway-env's RegulatedRoad, made fast
    env.reset(seed=0)
    road = env.unwrapped.road
    for copied in (pickle.loads(pickle.dumps(road)), copy.deepcopy(road)):
        assert type(copied) is type(road) and copied.vehicles[0].road is copied
        assert [tuple(v.position) for v in copied.vehicles] == [tuple(v.position) for v in road.vehicles]


def test_make_fast_keeps_a_road_subclass_own_step():
    class Counting(Road):
        stepped = 0

        def step(self, dt: float) -> None:
            self.stepped += 1
            super().step(dt)

    road = make_fast(Counting(network=network(1)))
    road.step(0.1)
    assert isinstance(road, FastRoad) and isinstance(road, Counting) and road.stepped == 1
    with pytest.raises(TypeError, match="expects a highway-env Road"):
        make_fast(object())


# --- every scenario, both cores --------------------------------------------------------------------------------
def drive(scenario: str, seed: int, steps: int, fast: bool) -> tuple[list, list]:
    """Every vehicle's position, heading, speed and crashed flag at every step, and each step's outcome, of an episode
    driven by actions drawn from ``seed`` (so the EV moves about and meets its traffic)."""
    env = gym.make(envs.env_id(scenario), fast_traffic=fast)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    states, outcomes = [], []
    for _ in range(steps):
        # Throttle and brake at random, the wheels nearly straight: the EV stays on the road among its traffic.
        action = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-0.03, 0.03)], dtype=np.float32)
        _, reward, terminated, truncated, info = env.step(action)
        road = env.unwrapped.road if hasattr(env.unwrapped, "road") else env.unwrapped.env.unwrapped.road
        assert isinstance(road, FastRoad) == fast
        states.append(np.array([[*v.position, v.heading, v.speed, v.crashed] for v in road.vehicles]))
        outcomes.append((reward, terminated, truncated, info.get("collision"), info.get("offroad")))
        if terminated or truncated:
            break
    env.close()
    return states, outcomes


def same(scenario: str, seed: int, steps: int) -> int:
    """Both cores' episodes compared step by step (to 1e-9 m); the steps driven."""
    slow_states, slow_outcomes = drive(scenario, seed, steps, fast=False)
    fast_states, fast_outcomes = drive(scenario, seed, steps, fast=True)
    assert fast_outcomes == slow_outcomes, scenario
    for step, (a, b) in enumerate(zip(slow_states, fast_states)):
        assert a.shape == b.shape and np.array_equal(a, b), (scenario, seed, step)  # bit for bit
    return len(slow_states)


@pytest.mark.parametrize("scenario", list(envs.SCENARIOS))
def test_every_scenario_drives_the_same_under_both_cores(scenario, monkeypatch):
    monkeypatch.setattr(traffic, "SMALL_ROAD", 0)  # the paper's three vehicles through the arrays too
    steps = same(scenario, seed=7, steps=40)
    assert steps >= 10, f"{scenario}: the episode ended after {steps} steps: too short to compare"


@pytest.mark.slow
@pytest.mark.parametrize("scenario", list(envs.SCENARIOS))
def test_every_scenario_drives_the_same_under_both_cores_on_100_seeds(scenario):
    for seed in range(100):
        same(scenario, seed, steps=10_000)


# --- highway-env's own envs, accelerated -----------------------------------------------------------------------
def plain_run(highway_id: str, fast: bool, steps: int = 4) -> list:
    """A plain highway-env env (its default config, its own actions and observation) driven by actions its own
    action space samples from a fixed seed: every vehicle at every step, the observation and the reward."""
    env = gym.make(highway_id)
    if fast:
        env = accelerate(env)
    obs, _ = env.reset(seed=3)
    env.action_space.seed(3)
    out = []
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        road = env.unwrapped.road
        assert isinstance(road, FastRoad) == fast
        out.append((np.array([[*v.position, v.heading, v.speed, v.crashed] for v in road.vehicles]),
                    np.asarray(obs, float), reward, terminated, truncated))
        if terminated or truncated:
            break
    return out


@pytest.mark.parametrize("highway_id", sorted(HIGHWAY_CLASSES))
def test_accelerate_keeps_a_plain_highway_env_envs_trajectories(highway_id):
    slow, fast = plain_run(highway_id, False), plain_run(highway_id, True)
    assert len(slow) == len(fast)
    for (a, oa, *ra), (b, ob, *rb) in zip(slow, fast):
        assert a.shape == b.shape and np.allclose(a, b, rtol=0.0, atol=1e-9)
        assert np.array_equal(oa, ob) and ra == rb


def test_accelerate_refuses_what_it_cannot_speed_up_exactly_and_leaves_it_as_it_was():
    with pytest.raises(ValueError, match="accelerate takes a highway-env env of one of .*CartPoleEnv"):
        accelerate(gym.make("CartPole-v1"))
    env = gym.make("highway-fast-v0")
    env.reset(seed=0)

    class Mine(IDMVehicle):
        pass

    env.unwrapped.road.vehicles.append(Mine(env.unwrapped.road, [0.0, 0.0]))
    with pytest.raises(ValueError, match="test_traffic.*Mine"):
        accelerate(env)
    assert type(env.unwrapped.road) is Road
