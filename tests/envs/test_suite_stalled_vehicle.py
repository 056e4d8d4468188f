"""The ``stalled-vehicle`` family (issue 27 item 1): every drawn instance leaves a safe stop (the oracle, on 1000
draws per difficulty and every corner, checked against the env), a seeded reset is deterministic, the stalled vehicle
stands in the EV's lane ahead, what the oracle does not cover is refused, and the policies drive it."""

from __future__ import annotations

import dataclasses
import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import bimp  # noqa: F401  (registers bimp/stalled-vehicle-v0)
from bimp import make_policy
from bimp.envs import scenario_spec, wrap
from bimp.envs.oracle import stop_behind
from bimp.envs.scene import VEHICLE_LENGTH, Bounds
from bimp.envs.suite import FAMILIES
from bimp.envs.suite.stalled_vehicle import DIFFICULTIES, StalledVehicleEnv
from tests.envs.test_suite_families import BrakeAtTheBounds, drawn_params, drive_the_oracles_plan

pytestmark = pytest.mark.filterwarnings("ignore")

ID = "bimp/stalled-vehicle-v0"
DRAWS = 1000
B = Bounds()


def draws(difficulty: str, n: int = DRAWS) -> list[dict]:
    """The drawn parameters of ``n`` seeded resets of the registered env at ``difficulty`` (highway-env's reset of
    the env under the adapter: the draws, without the adapter's scene)."""
    return drawn_params(ID, {"difficulty": difficulty}, n)


@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_ev_can_stop_behind_the_stalled_vehicle_on_every_draw_and_corner(difficulty):
    """Braking at the planning bounds from the first step keeps at least d_min to the stalled vehicle: on 1000 drawn
    instances of each difficulty and on every corner of its ranges."""
    params = draws(difficulty)
    ranges = DIFFICULTIES[difficulty]
    for p in params:  # the draws are the documented ranges'
        for key in ("ev_speed", "stall_distance", "density", "aggressive_share", "defensive_share"):
            lo, hi = getattr(ranges, key)
            assert lo <= p[key] <= hi, (key, p)
    gaps = stop_behind(np.array([p["ev_speed"] for p in params]), np.array([p["stall_distance"] for p in params]))
    assert gaps.min() >= B.d_min, f"{int(np.sum(gaps < B.d_min))} draws infeasible, e.g. {params[int(gaps.argmin())]}"
    corners = [float(stop_behind(v, d)) for v, d in itertools.product(ranges.ev_speed, ranges.stall_distance)]
    assert min(corners) >= B.d_min
    assert min(corners) == pytest.approx(ranges.least_gap())  # the worst corner is the one the ranges are refused on


def test_hard_starts_where_the_oracle_still_stops_clear():
    """hard's worst corner (30 m/s, 85 m) stops more than 5 m clear; 5 m nearer it would not stop d_min clear."""
    assert DIFFICULTIES["hard"].least_gap() > 5.0
    assert stop_behind(30.0, 80.0) < B.d_min  # 5 m nearer and the fastest EV cannot stop clear: why hard starts at 85


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_oracle_is_the_env(seed):
    """Driven by the oracle's plan on hard instances, the env's least footprint gap to the stalled vehicle is the
    oracle's, and no traffic enters the EV's lane between the EV and the stalled vehicle (the oracle's assumption)."""
    env = gym.make(ID, config={"difficulty": "hard"})
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    p, ev, stalled = base.drawn_params, base.vehicle, base.stalled_vehicle
    policy, least = BrakeAtTheBounds(env), np.inf
    for _ in range(80):  # stopped within 6 s from 30 m/s
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        least = min(least, float(stalled.position[0] - ev.position[0]) - VEHICLE_LENGTH)
        between = [v for v in base.road.vehicles if v not in (ev, stalled) and v.lane_index == ev.lane_index
                   and ev.position[0] < v.position[0] < stalled.position[0]]
        assert not between
        assert not info["collision"] or info["contact"]["ev_speed"] < 0.05  # only ever hit standing
        if terminated or truncated or (ev.speed == 0.0 and policy.a == B.accel[0]):
            break
    assert ev.speed == 0.0 and least >= B.d_min
    assert least == pytest.approx(float(stop_behind(p["ev_speed"], p["stall_distance"])), abs=1e-6)


def test_check_env_and_the_scenario_table():
    env = gym.make(ID)
    check_env(env, skip_render_check=True)
    spec = scenario_spec("stalled-vehicle")
    assert spec.id == ID and spec.max_episode_steps == 200 and not spec.default
    assert FAMILIES["stalled-vehicle"] is StalledVehicleEnv
    assert env.unwrapped.scene.bounds == Bounds()  # the paper's planning bounds: a straight road


def test_the_stalled_vehicle_stands_in_the_evs_lane_ahead():
    env = gym.make(ID, config={"difficulty": "hard"})
    for seed in range(5):
        obs, info = env.reset(seed=seed)
        base = env.unwrapped
        p, ev, stalled = base.drawn_params, base.vehicle, base.stalled_vehicle
        assert stalled.speed == 0.0 and stalled.lane_index == ev.lane_index and ev.lane_index[2] == p["ev_lane"]
        assert stalled.position[0] - ev.position[0] == pytest.approx(p["stall_distance"])
        assert ev.speed == pytest.approx(p["ev_speed"])
        others = [v for v in base.road.vehicles if v not in (ev, stalled)]
        assert others and all(v.lane_index != ev.lane_index for v in others)  # traffic beside, none in the lane
        assert sum(p[f"traffic_{k}"] for k in ("idm", "aggressive", "defensive")) == len(others)
        start = stalled.position.copy()
        for _ in range(10):
            obs, *_ = env.step(np.zeros(2, np.float32))
        assert stalled.speed == 0.0 and np.array_equal(stalled.position, start)  # it never moves
        # The stalled vehicle is an OV of the observation once among the nearest: its row reads speed 0.
        rows = env.unwrapped.scene.split_obs(obs)[2]
        near = rows[np.hypot(*(rows[:, 1:3] - stalled.position).T) < 1e-3]
        assert len(near) <= 1 and (not len(near) or near[0, 4] == 0.0)


def test_difficulty_sets_the_ranges_and_a_range_overrides_one():
    base = gym.make(ID, config={"difficulty": "easy"}).unwrapped
    assert {k: base.config[k] for k in StalledVehicleEnv.range_keys()} == dataclasses.asdict(DIFFICULTIES["easy"])
    env = gym.make(ID, config={"difficulty": "hard", "density": 0, "ev_speed": [26, 27]})
    env.reset(seed=0)
    p = env.unwrapped.drawn_params
    assert p["density"] == 0.0 and 26 <= p["ev_speed"] <= 27 and sum(p[f"traffic_{k}"] for k in
                                                                      ("idm", "aggressive", "defensive")) == 0
    assert env.unwrapped.config["stall_distance"] == DIFFICULTIES["hard"].stall_distance
    # Harder: nearer stalls, denser traffic, more aggressive drivers, a faster EV.
    easy, medium, hard = (DIFFICULTIES[k] for k in ("easy", "medium", "hard"))
    for key, sign in (("stall_distance", -1), ("density", 1), ("aggressive_share", 1), ("ev_speed", 1)):
        assert sign * getattr(easy, key)[0] < sign * getattr(medium, key)[0] < sign * getattr(hard, key)[0] or \
            sign * getattr(easy, key)[1] < sign * getattr(medium, key)[1] < sign * getattr(hard, key)[1], key


@pytest.mark.parametrize(("config", "match"), [
    ({"ev_speed": [20, 35]}, "ev_speed"),
    ({"ev_speed": [25, 20]}, "ev_speed"),
    ({"density": "dense"}, "density"),
    ({"density": [1.0, np.nan]}, "density"),
    ({"aggressive_share": [0.5, 0.6], "defensive_share": [0.3, 0.5]}, "defensive_share"),
    ({"difficulty": "hard", "stall_distance": [60, 100]}, "stall_distance must be .*oracle"),
])
def test_what_the_oracle_does_not_cover_is_refused(config, match):
    with pytest.raises(ValueError, match=match):
        gym.make(ID, config=config)


def test_the_ranges_refuse_themselves_where_the_oracle_fails():
    with pytest.raises(ValueError, match="stall_distance"):
        dataclasses.replace(DIFFICULTIES["medium"], ev_speed=(22.0, 30.0), stall_distance=(70.0, 150.0))


def test_wrap_takes_the_family_env_and_keeps_its_config():
    env = wrap(StalledVehicleEnv(config={"difficulty": "easy", "lanes_count": 4}))
    assert env.highway_id == "stalled-vehicle-v0"
    assert env.unwrapped.config["difficulty"] == "easy" and env.unwrapped.config["lanes_count"] == 4
    env.reset(seed=0)
    assert env.unwrapped.drawn_params["stall_distance"] >= DIFFICULTIES["easy"].stall_distance[0]


def test_mobil_changes_lanes_around_the_stall_where_the_road_is_free():
    """The behaviour layer (highway-env's MOBIL) takes the free lane beside the stall: IDM/MOBIL passes it."""
    env = gym.make(ID, config={"difficulty": "easy", "density": 0})
    agent = make_policy("idm", env)
    obs, _ = env.reset(seed=0)
    base = env.unwrapped
    done, lanes = False, set()
    while not done:
        obs, _, terminated, truncated, info = env.step(agent.act(obs))
        lanes.add(base.vehicle.lane_index[2])
        done = terminated or truncated
    assert truncated and not info["collision"] and len(lanes) > 1
    assert base.vehicle.position[0] > base.stalled_vehicle.position[0] + 50.0


@pytest.mark.slow
@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_oracles_plan_in_the_env_on_100_seeds(difficulty):
    """The oracle's plan driven for whole episodes, seeds 0-99: never a collision at the EV's fault, and on easy and
    medium nothing enters the EV's lane ahead of it while it moves (the oracle's assumption) and no collision at all.
    On hard, traffic enters there while the EV brakes on a few seeds (3 of 100 when written; the braking EV keeps
    clear of it) and highway-env's aggressive drivers rear-end the standing EV (26 of 100): not the EV's fault, but
    success counts every collision (docs/suite.md)."""
    rear_ended, entered = drive_the_oracles_plan(ID, {"difficulty": difficulty}, lambda env: [env.stalled_vehicle])
    assert not (rear_ended or entered) or difficulty == "hard", (rear_ended, entered)
    assert len(rear_ended) <= 32 and len(entered) <= 6, (rear_ended, entered)
