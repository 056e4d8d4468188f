"""The ``dense-highway`` family (issue 27 item 1): every drawn instance leaves a safe stop behind the leader braking
as hard as highway-env lets its traffic brake (the oracle, on 1000 draws per difficulty and every corner, checked
against the env), a seeded reset puts the leader and the traffic where the draws say, what the oracle does not cover
is refused, and the policies drive it."""

from __future__ import annotations

import dataclasses
import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from highway_env.vehicle.behavior import AggressiveVehicle, DefensiveVehicle, IDMVehicle

import bimp  # noqa: F401  (registers bimp/dense-highway-v0)
from bimp.agents.evaluation.metrics import contact_at_fault
from bimp.envs import scenario_spec, wrap
from bimp.envs.scene import VEHICLE_LENGTH, Bounds
from bimp.envs.suite import FAMILIES
from bimp.envs.suite.dense_highway import (
    DIFFICULTIES,
    LEADER_DECEL,
    REAR_CLEAR,
    DenseHighwayEnv,
    least_gap,
)
from bimp.envs.suite.family import MIN_TRAFFIC_GAP
from tests.envs.test_suite_families import BrakeAtTheBounds, drawn_params

pytestmark = pytest.mark.filterwarnings("ignore")

ID = "bimp/dense-highway-v0"
DRAWS = 1000
B = Bounds()
KINDS = ("idm", "aggressive", "defensive")


def draws(difficulty: str, n: int = DRAWS) -> list[dict]:
    """The drawn parameters of ``n`` seeded resets of the registered env at ``difficulty``."""
    return drawn_params(ID, {"difficulty": difficulty}, n)


def test_the_hardest_braking_is_highway_envs_clip():
    """The leader's braking in the oracle is the clip of IDMVehicle.act, which the Linear kinds act through."""
    assert LEADER_DECEL == IDMVehicle.ACC_MAX == 6.0
    for kind in (AggressiveVehicle, DefensiveVehicle):  # LinearVehicle.act ends in IDMVehicle.act's clip
        assert issubclass(kind, IDMVehicle) and kind.ACC_MAX == IDMVehicle.ACC_MAX


@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_ev_can_stop_behind_its_braking_leader_on_every_draw_and_corner(difficulty):
    """Braking at the planning bounds from the first step keeps at least d_min to a leader braking at 6 m/s^2 to a
    stop from the first step: on 1000 drawn instances of each difficulty and on every corner of its ranges."""
    params = draws(difficulty)
    ranges = DIFFICULTIES[difficulty]
    for p in params:  # the draws are the documented ranges'
        for key in ("ev_speed", "leader_gap", "density", "aggressive_share", "defensive_share"):
            lo, hi = getattr(ranges, key)
            assert lo <= p[key] <= hi, (key, p)
        assert ranges.traffic_speed[0] <= p["leader_speed"] <= ranges.traffic_speed[1]
        assert p["leader_kind"] in KINDS
    gaps = least_gap(*(np.array([p[k] for p in params]) for k in ("ev_speed", "leader_gap", "leader_speed")))
    assert gaps.min() >= B.d_min, f"{int(np.sum(gaps < B.d_min))} draws infeasible, e.g. {params[int(gaps.argmin())]}"
    corners = [float(least_gap(*c)) for c in itertools.product(ranges.ev_speed, ranges.leader_gap,
                                                                ranges.traffic_speed)]
    assert min(corners) >= B.d_min
    assert min(corners) == pytest.approx(ranges.least_gap())  # the worst corner is the one the ranges are refused on


def test_hard_starts_where_the_oracle_still_stops_clear():
    """hard's worst corner stops clear; 5 m nearer it would not (why hard's leader_gap starts where it does)."""
    hard = DIFFICULTIES["hard"]
    assert hard.least_gap() >= B.d_min
    assert float(least_gap(hard.ev_speed[1], hard.leader_gap[0] - 5.0, hard.traffic_speed[0])) < B.d_min


class BrakingLeader:
    """The oracle's leader, as the env's leader's ``act``: it brakes at LEADER_DECEL to a stop (and not below 0,
    as the oracle's; highway-env's own IDM would reverse), straight along its lane."""

    def __init__(self, leader, dt: float):
        self.leader, self.dt = leader, dt

    def __call__(self, action=None):
        self.leader.action = {"steering": 0.0, "acceleration": -min(LEADER_DECEL, self.leader.speed / self.dt)}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_oracle_is_the_env(seed):
    """On hard instances whose leader brakes as the oracle's does (at 6 m/s^2 to a stop from the first step), the
    env's least footprint gap to it, driven by the oracle's plan, is the oracle's, and no collision is the EV's."""
    env = gym.make(ID, config={"difficulty": "hard"})
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    p, ev, leader = base.drawn_params, base.vehicle, base.leader
    leader.act = BrakingLeader(leader, 1.0 / base.config["simulation_frequency"])
    policy, least = BrakeAtTheBounds(env), np.inf
    for _ in range(80):  # stopped within 6 s from 30 m/s
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        least = min(least, float(leader.position[0] - ev.position[0]) - VEHICLE_LENGTH)
        assert leader.lane_index == ev.lane_index
        assert not info["collision"] or not contact_at_fault(info["contact"])
        if terminated or truncated or (ev.speed == 0.0 and policy.a == B.accel[0]):
            break
    assert ev.speed == 0.0 and leader.speed == 0.0 and least >= B.d_min
    assert least == pytest.approx(float(least_gap(p["ev_speed"], p["leader_gap"], p["leader_speed"])), abs=1e-6)


def test_check_env_and_the_scenario_table():
    env = gym.make(ID)
    check_env(env, skip_render_check=True)
    spec = scenario_spec("dense-highway")
    assert spec.id == ID and spec.max_episode_steps == 150 and not spec.default
    assert FAMILIES["dense-highway"] is DenseHighwayEnv
    assert env.unwrapped.scene.bounds == Bounds()  # the paper's planning bounds: a straight road
    assert env.unwrapped.scene is not None and DenseHighwayEnv.TARGET_SPEED == 30.0


def test_the_leader_and_the_traffic_start_where_the_draws_say():
    env = gym.make(ID, config={"difficulty": "hard"})
    for seed in range(5):
        env.reset(seed=seed)
        base = env.unwrapped
        p, ev, leader = base.drawn_params, base.vehicle, base.leader
        assert leader.lane_index == ev.lane_index and ev.lane_index[2] == p["ev_lane"]
        assert leader.position[0] - ev.position[0] == pytest.approx(p["leader_gap"])
        assert leader.speed == pytest.approx(p["leader_speed"]) and ev.speed == pytest.approx(p["ev_speed"])
        others = [v for v in base.road.vehicles if v not in (ev, leader)]
        assert sum(p[f"traffic_{k}"] for k in KINDS) == len(others)
        assert p["traffic_aggressive"] > 0  # hard's drivers are 50-70% aggressive
        # Traffic in the EV's lane too, but none between the EV and the leader, nor within 15 m past the leader
        # nor within REAR_CLEAR behind the EV.
        own = [v.position[0] - ev.position[0] for v in others if v.lane_index == ev.lane_index]
        assert own and all(x < -REAR_CLEAR or x >= p["leader_gap"] + MIN_TRAFFIC_GAP for x in own)
        assert {v.lane_index[2] for v in others} == set(range(base.config["lanes_count"]))


def test_difficulty_sets_the_ranges_and_a_range_overrides_one():
    base = gym.make(ID, config={"difficulty": "easy"}).unwrapped
    assert {k: base.config[k] for k in DenseHighwayEnv.range_keys()} == dataclasses.asdict(DIFFICULTIES["easy"])
    env = gym.make(ID, config={"difficulty": "hard", "density": 0, "ev_speed": [25, 26]})
    env.reset(seed=0)
    p = env.unwrapped.drawn_params
    assert p["density"] == 0.0 and 25 <= p["ev_speed"] <= 26 and sum(p[f"traffic_{k}"] for k in KINDS) == 0
    assert len(env.unwrapped.road.vehicles) == 2  # the EV and its leader
    assert env.unwrapped.config["leader_gap"] == DIFFICULTIES["hard"].leader_gap
    # Harder: denser traffic, more aggressive drivers, a faster EV, slower traffic.
    easy, medium, hard = (DIFFICULTIES[k] for k in ("easy", "medium", "hard"))
    for key, sign in (("density", 1), ("aggressive_share", 1), ("ev_speed", 1), ("traffic_speed", -1)):
        assert sign * getattr(easy, key)[0] < sign * getattr(medium, key)[0] < sign * getattr(hard, key)[0] or \
            sign * getattr(easy, key)[1] < sign * getattr(medium, key)[1] < sign * getattr(hard, key)[1], key


def test_denser_than_the_other_families_at_each_difficulty():
    for name in ("stalled-vehicle", "cut-in", "lane-drop"):
        for difficulty, ranges in DIFFICULTIES.items():
            other = FAMILIES[name].DIFFICULTIES[difficulty].density
            # lane-drop's hard tops out at the envelope's 50 vehicles/km/lane too, in the one lane beside its closure
            assert ranges.density[0] > other[0] and ranges.density[1] >= other[1], (name, difficulty)


@pytest.mark.parametrize(("config", "match"), [
    ({"ev_speed": [20, 35]}, "ev_speed"),
    ({"ev_speed": [25, 20]}, "ev_speed"),
    ({"density": "dense"}, "density"),
    ({"density": [1.0, np.nan]}, "density"),
    ({"density": [40, 60]}, "density"),
    ({"aggressive_share": [0.5, 0.6], "defensive_share": [0.3, 0.5]}, "defensive_share"),
    ({"difficulty": "hard", "leader_gap": [30, 60]}, "leader_gap must be .*oracle"),
    ({"difficulty": "hard", "leader_gap": [50, 70]}, "leader_gap must be .*traffic_speed from 15"),
    ({"difficulty": "medium", "ev_speed": [22, 30]}, "leader_gap must be .*ev_speed up to 30"),
])
def test_what_the_oracle_does_not_cover_is_refused(config, match):
    with pytest.raises(ValueError, match=match):
        gym.make(ID, config=config)


def test_the_ranges_refuse_themselves_where_the_oracle_fails():
    with pytest.raises(ValueError, match="leader_gap"):
        dataclasses.replace(DIFFICULTIES["medium"], leader_gap=(20.0, 70.0))


def test_wrap_takes_the_family_env_and_keeps_its_config():
    env = wrap(DenseHighwayEnv(config={"difficulty": "easy", "lanes_count": 4}))
    assert env.highway_id == "dense-highway-v0"
    assert env.unwrapped.config["difficulty"] == "easy" and env.unwrapped.config["lanes_count"] == 4
    env.reset(seed=0)
    assert env.unwrapped.drawn_params["leader_gap"] >= DIFFICULTIES["easy"].leader_gap[0]
    assert env.unwrapped.drawn_params["ev_lane"] in range(4)


@pytest.mark.slow
@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_oracles_plan_in_the_env_on_100_seeds(difficulty):
    """The oracle's plan driven for whole episodes behind the env's own leader, seeds 0-99: never a collision at the
    EV's fault, and the least gap to the leader while it stays in the EV's lane at least d_min. What the
    oracle does not cover (traffic changing into the EV's lane between the EV and its leader, OV-OV crashes,
    traffic running into the braking or standing EV) happens on some seeds; docs/suite.md counts it."""
    env = gym.make(ID, config={"difficulty": difficulty})
    for seed in range(100):
        obs, _ = env.reset(seed=seed)
        base = env.unwrapped
        ev, leader, policy = base.vehicle, base.leader, BrakeAtTheBounds(env)
        least = np.inf
        while True:
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            if leader.lane_index == ev.lane_index:
                least = min(least, float(leader.position[0] - ev.position[0]) - VEHICLE_LENGTH)
            if info["collision"]:
                assert info["contact"] is not None and not contact_at_fault(info["contact"]), seed
            if terminated or truncated:
                break
        # Not the oracle's least gap: on hard seeds 75 and 95 it fell below it (49.1 and 29.6 m against 59.6 and
        # 36.7), with traffic crashed ahead (a leader crashing brakes harder than 6 m/s^2); d_min is the safety claim.
        assert least >= B.d_min, seed
