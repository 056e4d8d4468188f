"""The ``lane-drop`` family (issue 27 item 1): every drawn instance leaves a safe stop behind the closure (the oracle,
on 1000 draws per difficulty and every corner, checked against the env), a seeded reset is deterministic, the closure
stands in the EV's lane ahead, what the oracle does not cover is refused, and the policies drive it."""

from __future__ import annotations

import dataclasses
import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import bimp  # noqa: F401  (registers bimp/lane-drop-v0)
from bimp import make_policy
from bimp.envs import scenario_spec, wrap
from bimp.envs.oracle import stop_behind
from bimp.envs.scene import VEHICLE_LENGTH, Bounds
from bimp.envs.suite import FAMILIES
from bimp.envs.suite.lane_drop import BLOCK_SPACING, CLOSURE_BLOCKS, DIFFICULTIES, LaneDropEnv
from tests.envs.test_suite_families import BrakeAtTheBounds, drawn_params, drive_the_oracles_plan

pytestmark = pytest.mark.filterwarnings("ignore")

ID = "bimp/lane-drop-v0"
DRAWS = 1000
B = Bounds()


def draws(difficulty: str, n: int = DRAWS) -> list[dict]:
    """The drawn parameters of ``n`` seeded resets of the registered env at ``difficulty``."""
    return drawn_params(ID, {"difficulty": difficulty}, n)


@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_ev_can_stop_behind_the_closure_on_every_draw_and_corner(difficulty):
    """Braking at the planning bounds from the first step keeps at least d_min to the closure's first block: on 1000
    drawn instances of each difficulty and on every corner of its ranges."""
    params = draws(difficulty)
    ranges = DIFFICULTIES[difficulty]
    for p in params:  # the draws are the documented ranges'
        for key in ("ev_speed", "drop_distance", "density", "aggressive_share", "defensive_share"):
            lo, hi = getattr(ranges, key)
            assert lo <= p[key] <= hi, (key, p)
        assert p["ev_lane"] in (0, 2)  # an outer lane of the default 3
    gaps = stop_behind(np.array([p["ev_speed"] for p in params]), np.array([p["drop_distance"] for p in params]))
    assert gaps.min() >= B.d_min, f"{int(np.sum(gaps < B.d_min))} draws infeasible, e.g. {params[int(gaps.argmin())]}"
    corners = [float(stop_behind(v, d)) for v, d in itertools.product(ranges.ev_speed, ranges.drop_distance)]
    assert min(corners) >= B.d_min
    assert min(corners) == pytest.approx(ranges.least_gap())


def test_hard_starts_where_the_oracle_still_stops_clear():
    """hard's worst corner (30 m/s, 82 m) stops 2.35 m clear; 2 m nearer it would not stop d_min clear."""
    assert DIFFICULTIES["hard"].least_gap() == pytest.approx(2.35)
    assert stop_behind(30.0, 80.0) < B.d_min


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_oracle_is_the_env(seed):
    """Driven by the oracle's plan on hard instances, the env's least footprint gap to the closure is the oracle's,
    and no traffic enters the EV's lane between the EV and the closure while it moves (the oracle's assumption)."""
    env = gym.make(ID, config={"difficulty": "hard"})
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    p, ev, first = base.drawn_params, base.vehicle, base.closure[0]
    policy, least = BrakeAtTheBounds(env), np.inf
    for _ in range(80):  # stopped within 6 s from 30 m/s
        moving = ev.speed > 0.0
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        least = min(least, float(first.position[0] - ev.position[0]) - VEHICLE_LENGTH)
        if moving:
            assert not [v for v in base.road.vehicles if v is not ev and v.lane_index == ev.lane_index
                        and ev.position[0] < v.position[0] < first.position[0]]
        assert not info["collision"] or info["contact"]["ev_speed"] < 0.05  # only ever hit standing
        if terminated or truncated or (ev.speed == 0.0 and policy.a == B.accel[0]):
            break
    assert ev.speed == 0.0 and least >= B.d_min
    assert least == pytest.approx(float(stop_behind(p["ev_speed"], p["drop_distance"])), abs=1e-6)


def test_check_env_and_the_scenario_table():
    env = gym.make(ID)
    check_env(env, skip_render_check=True)
    spec = scenario_spec("lane-drop")
    assert spec.id == ID and spec.max_episode_steps == 200 and not spec.default
    assert FAMILIES["lane-drop"] is LaneDropEnv
    assert env.unwrapped.scene.bounds == Bounds()


def test_the_closure_stands_in_the_evs_lane_ahead():
    env = gym.make(ID, config={"difficulty": "hard"})
    for seed in range(5):
        obs, info = env.reset(seed=seed)
        base = env.unwrapped
        p, ev, closure = base.drawn_params, base.vehicle, base.closure
        assert len(closure) == CLOSURE_BLOCKS and ev.lane_index[2] == p["ev_lane"]
        assert list(base.road.objects) == closure
        for k, block in enumerate(closure):
            assert block.speed == 0.0 and block.lane_index == ev.lane_index
            assert block.position[0] - ev.position[0] == pytest.approx(p["drop_distance"] + k * BLOCK_SPACING)
            assert block.position[1] == pytest.approx(ev.position[1])
        assert ev.speed == pytest.approx(p["ev_speed"])
        others = [v for v in base.road.vehicles if v is not ev]
        assert others and all(v.lane_index != ev.lane_index for v in others)  # traffic beside, none in the lane
        assert sum(p[f"traffic_{k}"] for k in ("idm", "aggressive", "defensive")) == len(others)
        start = closure[0].position.copy()
        for _ in range(10):
            obs, *_ = env.step(np.zeros(2, np.float32))
        assert np.array_equal(closure[0].position, start)  # it never moves
        # The first block is an OV of the observation once among the 8 nearest (dense traffic beside can crowd it
        # out while it is far): its row reads speed 0.
        rows = env.unwrapped.scene.split_obs(obs)[2]
        near = rows[np.hypot(*(rows[:, 1:3] - start).T) < 1e-3]
        assert len(near) <= 1 and (not len(near) or near[0, 4] == 0.0)


def test_difficulty_sets_the_ranges_and_a_range_overrides_one():
    base = gym.make(ID, config={"difficulty": "easy"}).unwrapped
    assert {k: base.config[k] for k in LaneDropEnv.range_keys()} == dataclasses.asdict(DIFFICULTIES["easy"])
    env = gym.make(ID, config={"difficulty": "hard", "density": 0, "ev_speed": [26, 27]})
    env.reset(seed=0)
    p = env.unwrapped.drawn_params
    assert p["density"] == 0.0 and 26 <= p["ev_speed"] <= 27 and sum(p[f"traffic_{k}"] for k in
                                                                      ("idm", "aggressive", "defensive")) == 0
    assert env.unwrapped.config["drop_distance"] == DIFFICULTIES["hard"].drop_distance
    easy, medium, hard = (DIFFICULTIES[k] for k in ("easy", "medium", "hard"))
    for key, sign in (("drop_distance", -1), ("density", 1), ("aggressive_share", 1), ("ev_speed", 1)):
        assert sign * getattr(easy, key)[0] < sign * getattr(medium, key)[0] < sign * getattr(hard, key)[0] or \
            sign * getattr(easy, key)[1] < sign * getattr(medium, key)[1] < sign * getattr(hard, key)[1], key


@pytest.mark.parametrize(("config", "match"), [
    ({"ev_speed": [20, 35]}, "ev_speed"),
    ({"ev_speed": [25, 20]}, "ev_speed"),
    ({"density": "dense"}, "density"),
    ({"density": [1.0, np.nan]}, "density"),
    ({"aggressive_share": [0.5, 0.6], "defensive_share": [0.3, 0.5]}, "defensive_share"),
    ({"difficulty": "hard", "drop_distance": [60, 100]}, "drop_distance must be .*oracle"),
    ({"drop_distance": [100, 300]}, "drop_distance"),
])
def test_what_the_oracle_does_not_cover_is_refused(config, match):
    with pytest.raises(ValueError, match=match):
        gym.make(ID, config=config)


def test_the_ranges_refuse_themselves_where_the_oracle_fails():
    with pytest.raises(ValueError, match="drop_distance"):
        dataclasses.replace(DIFFICULTIES["medium"], ev_speed=(22.0, 30.0), drop_distance=(70.0, 150.0))


def test_wrap_takes_the_family_env_and_keeps_its_config():
    env = wrap(LaneDropEnv(config={"difficulty": "easy", "lanes_count": 4}))
    assert env.highway_id == "lane-drop-v0"
    assert env.unwrapped.config["difficulty"] == "easy" and env.unwrapped.config["lanes_count"] == 4
    env.reset(seed=0)
    assert env.unwrapped.drawn_params["drop_distance"] >= DIFFICULTIES["easy"].drop_distance[0]
    assert env.unwrapped.drawn_params["ev_lane"] in (0, 3)


def test_mobil_merges_out_of_the_closed_lane_where_the_road_is_free():
    """The behaviour layer (highway-env's MOBIL) sees the closure as a standing obstacle and merges: IDM/MOBIL
    passes the whole closure on an empty road."""
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
    assert base.vehicle.position[0] > base.closure[-1].position[0]


@pytest.mark.slow
@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_oracles_plan_in_the_env_on_100_seeds(difficulty):
    """The oracle's plan driven for whole episodes, seeds 0-99: never a collision at the EV's fault. Traffic that
    enters the closed lane ahead of the braking EV (the oracle's assumption broken, on a few seeds of each difficulty)
    stands against the closure, and aggressive drivers rear-end the standing EV on hard (not its fault; success
    counts them: docs/suite.md)."""
    rear_ended, entered = drive_the_oracles_plan(ID, {"difficulty": difficulty}, lambda env: env.closure)
    # When written: rear-ended 0 / 1 / 27 and entered 1 / 8 / 3 of 100 (easy / medium / hard).
    assert len(rear_ended) <= {"easy": 0, "medium": 3, "hard": 32}[difficulty], rear_ended
    assert len(entered) <= {"easy": 3, "medium": 12, "hard": 6}[difficulty], entered
