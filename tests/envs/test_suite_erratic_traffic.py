"""The ``erratic-traffic`` family (issue 27 item 1): every drawn instance leaves a safe plan (the oracle, on 1000 draws
per difficulty and every corner, exact against the env where the leader brakes at the cap, and a bound on env episodes
with the traffic's own noise), the traffic's hard brakes and lane changes are heavy-tailed, capped and drawn from the
env's generator alone, an erratic lane change keeps its safety bound, what the oracle does not cover is refused, and
the env is a Gymnasium env."""

from __future__ import annotations

import dataclasses
import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import bimp  # noqa: F401  (registers bimp/erratic-traffic-v0)
from bimp.envs import scenario_spec
from bimp.envs.scene import VEHICLE_LENGTH, Bounds
from bimp.envs.suite import FAMILIES
from bimp.envs.suite.erratic_traffic import (
    BRAKE_CAP,
    DIFFICULTIES,
    ENVELOPE,
    ErraticTrafficEnv,
    ErraticVehicle,
    gap_is_safe,
    least_gap,
)
from tests.envs.test_suite_families import BrakeAtTheBounds, drawn_params

pytestmark = pytest.mark.filterwarnings("ignore")

ID = "bimp/erratic-traffic-v0"
DRAWS = 1000
B = Bounds()
ORACLE_KEYS = ("ev_speed", "leader_gap", "leader_speed")
# The traffic's ranges and which way is harder (+1: higher, -1: lower): denser, more, heavier and longer brakes,
# heavier tails, noisier lane changes.
TRAFFIC_HARDER = (("density", 1), ("brake_rate", 1), ("brake_scale", 1), ("brake_duration", 1), ("nu", -1),
                  ("lane_noise", 1))


def draws(difficulty: str, n: int = DRAWS) -> list[dict]:
    """The drawn parameters of ``n`` seeded resets of the registered env at ``difficulty``."""
    return drawn_params(ID, {"difficulty": difficulty}, n)


@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_a_safe_plan_exists_on_every_draw_and_corner(difficulty):
    """Braking at the planning bounds from the first step keeps at least d_min to a leader that brakes at the cap to a
    stop at once: on 1000 drawn instances of each difficulty and on every corner of its ranges."""
    params = draws(difficulty)
    ranges = DIFFICULTIES[difficulty]
    for p in params:  # the draws are the documented ranges'
        for key in (*(k for k in ErraticTrafficEnv.range_keys() if k != "traffic_speed"), "leader_speed"):
            lo, hi = getattr(ranges, "traffic_speed" if key == "leader_speed" else key)
            assert lo <= p[key] <= hi, (key, p)
    gaps = least_gap(*(np.array([p[k] for p in params]) for k in ORACLE_KEYS))
    assert gaps.min() >= B.d_min, f"{int(np.sum(gaps < B.d_min))} draws infeasible, e.g. {params[int(gaps.argmin())]}"
    corners = [float(least_gap(*c)) for c in itertools.product(ranges.ev_speed, ranges.leader_gap,
                                                               ranges.traffic_speed)]
    assert min(corners) == pytest.approx(ranges.least_gap()) and min(corners) >= B.d_min
    assert gaps.min() >= ranges.least_gap() - 1e-9  # the worst corner bounds the draws


def test_hard_is_at_the_edge_of_the_oracles_cover():
    """hard's worst corner (30 m/s, the leader 56 m ahead at 20 m/s) keeps d_min with little to spare; 2 m nearer
    it would not."""
    hard = DIFFICULTIES["hard"]
    assert B.d_min <= hard.least_gap() < 3.0
    with pytest.raises(ValueError, match="leader_gap must be .*oracle"):
        dataclasses.replace(hard, leader_gap=(hard.leader_gap[0] - 2.0, hard.leader_gap[1]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_oracle_is_the_env_when_the_leader_brakes_at_the_cap(seed):
    """The oracle's worst case made real: the leader brakes at the cap to a stop from the first step (and keeps its
    lane); the EV driven by the oracle's plan. The env's least footprint gap is the oracle's, at least d_min."""
    env = gym.make(ID, config={"difficulty": "hard", "density": 0})
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    p, ev, leader = base.drawn_params, base.vehicle, base.leader
    leader.brake, leader.brake_until, leader.next_brake = 100.0, np.inf, np.inf  # capped at BRAKE_CAP by act
    leader.enable_lane_change = False
    policy, least = BrakeAtTheBounds(env), np.inf
    for _ in range(80):  # both stand within 6 s from 30 m/s
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        least = min(least, float(leader.position[0] - ev.position[0]) - VEHICLE_LENGTH)
        assert not info["collision"]
    assert ev.speed == 0.0 and leader.speed == 0.0 and least >= B.d_min
    assert least == pytest.approx(float(least_gap(*(p[k] for k in ORACLE_KEYS))), abs=1e-6)


def ahead_in_lane(base) -> list:
    """The vehicles in the EV's lane ahead of it."""
    ev = base.vehicle
    return [v for v in base.road.vehicles if v is not ev and v.lane_index == ev.lane_index
            and v.position[0] > ev.position[0]]


@pytest.mark.parametrize("seed", [0, 2])
def test_the_oracle_bounds_the_env_with_its_noise(seed):
    """On hard seeds (whose leaders brake and whose traffic changes in ahead of the EV, when written), driven by the
    oracle's plan until the EV stands: the leader never comes nearer than the oracle's least gap for the draw (its
    worst case bounds it), no vehicle ahead in the EV's lane within d_min, and no collision."""
    env = gym.make(ID, config={"difficulty": "hard"})
    run = oracle_episode(env, seed, whole=False)
    assert run["leader"] >= run["bound"] - 1e-6 and run["least"] >= B.d_min
    assert not run["collision"] and not run["crash_ahead"]


def test_check_env_and_the_scenario_table():
    env = gym.make(ID)
    check_env(env, skip_render_check=True)
    spec = scenario_spec("erratic-traffic")
    assert spec.id == ID and spec.max_episode_steps == 200 and not spec.default
    assert FAMILIES["erratic-traffic"] is ErraticTrafficEnv
    assert env.unwrapped.scene.bounds == Bounds()


def test_traffic_in_every_lane_and_the_leader_ahead():
    env = gym.make(ID, config={"difficulty": "hard"})
    for seed in range(3):
        env.reset(seed=seed)
        base = env.unwrapped
        p, ev, leader = base.drawn_params, base.vehicle, base.leader
        assert leader.lane_index == ev.lane_index and ev.lane_index[2] == p["ev_lane"]
        assert leader.position[0] - ev.position[0] == pytest.approx(p["leader_gap"])
        assert leader.speed == pytest.approx(p["leader_speed"]) and ev.speed == pytest.approx(p["ev_speed"])
        traffic = [v for v in base.road.vehicles if v is not ev]
        assert all(isinstance(v, ErraticVehicle) for v in traffic)
        assert {v.lane_index[2] for v in traffic} == set(range(base.config["lanes_count"]))
        assert len(traffic) == p["traffic_idm"] + 1  # and the leader
        between = [v for v in ahead_in_lane(base) if v.position[0] < leader.position[0]]
        assert not between  # the leader is the EV's nearest vehicle ahead


def test_hard_brakes_are_heavy_tailed_capped_and_held():
    """On hard (with brakes more often), the traffic's brakes: magnitudes brake_scale x |t_nu| capped at 8 m/s^2
    (some at the cap), each held for its drawn time at that deceleration or harder (IDM's), never beyond the cap,
    never into reverse."""
    env = gym.make(ID, config={"difficulty": "hard", "brake_rate": 0.5, "nu": 1.2, "density": 10})
    obs, _ = env.reset(seed=0)
    base = env.unwrapped
    traffic = [v for v in base.road.vehicles if isinstance(v, ErraticVehicle)]
    for _ in range(30):
        before = {id(v): v.speed for v in traffic}
        obs, _, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        for v in traffic:
            if v.crashed:
                continue
            assert v.speed >= 0.0 and v.action["acceleration"] >= -BRAKE_CAP - 1e-9
            t = (v.steps - 1) * v.dt
            if t < v.brake_until - 1e-9 and before[id(v)] > 0.0:
                assert v.speed <= max(before[id(v)] - v.brake * v.dt, 0.0) + 1e-9
        if terminated or truncated:
            break
    magnitudes = np.array([b[1] for v in traffic for b in v.brakes])
    holds = np.array([b[2] for v in traffic for b in v.brakes]) / base.drawn_params["brake_duration"]
    assert len(magnitudes) > 5 and magnitudes.max() == BRAKE_CAP and magnitudes.min() < 1.0
    assert 0.5 - 1e-9 <= holds.min() and holds.max() <= 1.5 + 1e-9


def test_every_draw_is_the_envs_own_generator():
    """Seeded episodes do not touch numpy's global generator (highway-env's vehicles would draw from it otherwise),
    and a global draw in between changes nothing."""
    runs = []
    for disturb in (False, True):
        np.random.seed(123)
        state = np.random.get_state()[1].copy()
        env = gym.make(ID, config={"difficulty": "hard"})
        obs, _ = env.reset(seed=5)
        seq = [obs]
        for _ in range(30):
            if disturb:
                np.random.uniform()
            obs, *_ = env.step(np.zeros(2, np.float32))
            seq.append(obs)
        if not disturb:
            assert np.array_equal(np.random.get_state()[1], state)
        base = env.unwrapped
        runs.append((np.array(seq), [v.brakes for v in base.road.vehicles if isinstance(v, ErraticVehicle)]))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]


def test_the_safety_bound_of_a_lane_change():
    """gap_is_safe is the oracle from the follower's input; and however large the noise, an erratic vehicle beside
    the EV never decides to change in ahead of it into a gap the bound refuses, and does into one it allows."""
    assert gap_is_safe(25.0, 60.0, 20.0) and not gap_is_safe(25.0, 30.0, 20.0)
    assert gap_is_safe(25.0, 40.0, 20.0, a0=-7.0) and not gap_is_safe(25.0, 40.0, 20.0, a0=3.0)
    assert not gap_is_safe(0.0, 5.5, 0.0)  # footprints nearer than d_min
    env = gym.make(ID, config={"difficulty": "hard", "density": 0, "lane_noise": 5.0, "nu": 1.0})
    env.reset(seed=0)
    base = env.unwrapped
    ev, leader = base.vehicle, base.leader
    base.road.vehicles.remove(leader)
    lanes = base.road.network.graph["0"]["1"]
    side = lanes[ev.lane_index[2] - 1 if ev.lane_index[2] > 0 else ev.lane_index[2] + 1]
    decided = {}
    for ahead in (8.0, 15.0, 60.0):
        x = ev.position[0] + ahead
        changer = base._erratic(side, x, ev.speed)
        safe = gap_is_safe(ev.speed, ahead, changer.speed, a0=float(ev.action["acceleration"]))
        decided[ahead] = (safe, sum(changer.mobil(ev.lane_index) for _ in range(50)), changer.refused_lane_changes)
        base.road.vehicles.remove(changer)
    # Where the bound refuses, the noise did want the change (so the bound, not MOBIL, said no) and it never happened.
    assert all(n == 0 and refused > 0 for safe, n, refused in decided.values() if not safe), decided
    assert decided[60.0][0] and decided[60.0][1] > 0, decided  # a lane change for no gain, now and then


def test_difficulty_sets_the_ranges_and_a_range_overrides_one():
    base = gym.make(ID, config={"difficulty": "easy"}).unwrapped
    assert {k: base.config[k] for k in ErraticTrafficEnv.range_keys()} == dataclasses.asdict(DIFFICULTIES["easy"])
    env = gym.make(ID, config={"difficulty": "hard", "density": 0, "brake_rate": 0})
    env.reset(seed=0)
    base = env.unwrapped
    assert base.drawn_params["density"] == 0.0 and len(base.road.vehicles) == 2  # the EV and its leader
    assert base.leader.next_brake == np.inf and base.config["nu"] == DIFFICULTIES["hard"].nu
    # Harder: a faster EV, denser traffic, more, heavier and longer brakes, heavier tails, noisier lane changes.
    easy, medium, hard = (DIFFICULTIES[k] for k in ("easy", "medium", "hard"))
    for key, sign in (("ev_speed", 1), *TRAFFIC_HARDER):
        assert sign * getattr(easy, key)[0] <= sign * getattr(medium, key)[0] <= sign * getattr(hard, key)[0] and \
            sign * getattr(easy, key)[1] < sign * getattr(medium, key)[1] < sign * getattr(hard, key)[1], key


def test_extreme_is_hard_with_the_noise_at_the_top_of_its_envelope():
    """extreme keeps hard's road, EV and leader (the same oracle corner) and moves only the traffic: denser, with every
    noise range starting harder than hard's and reaching its envelope's edge (brake_duration: 4 s of the 5 s edge)."""
    hard, extreme = DIFFICULTIES["hard"], DIFFICULTIES["extreme"]
    for key in ("ev_speed", "leader_gap", "traffic_speed"):
        assert getattr(extreme, key) == getattr(hard, key), key
    assert extreme.least_gap() == hard.least_gap()
    for key, sign in TRAFFIC_HARDER:
        assert sign * getattr(extreme, key)[0] > sign * getattr(hard, key)[0], key
        assert sign * getattr(extreme, key)[1] >= sign * getattr(hard, key)[1], key  # density: both at 20
    for key, edge in (("density", 1), ("brake_rate", 1), ("brake_scale", 1), ("nu", 0), ("lane_noise", 1)):
        bound = (ENVELOPE[key].low, ENVELOPE[key].high)[edge]
        assert getattr(extreme, key)[edge] == bound, key


@pytest.mark.parametrize(("config", "match"), [
    ({"ev_speed": [20, 35]}, "ev_speed"),
    ({"nu": [0.5, 2.0]}, "nu"),
    ({"brake_scale": [1.0, 9.0]}, "brake_scale"),
    ({"brake_rate": [0.2, 0.1]}, "brake_rate"),
    ({"lane_noise": "wild"}, "lane_noise"),
    ({"brake_duration": [1.0, np.nan]}, "brake_duration"),
    ({"density": [15, 30]}, "density"),
    ({"difficulty": "hard", "leader_gap": [40, 70]}, "leader_gap must be .*oracle"),
    ({"difficulty": "hard", "traffic_speed": [15, 28]}, "leader_gap must be .*traffic_speed from 15"),
    ({"aggressive_share": 0.5}, "aggressive_share"),
])
def test_what_the_oracle_does_not_cover_is_refused(config, match):
    with pytest.raises(ValueError, match=match):
        gym.make(ID, config=config)


def test_the_ranges_refuse_themselves_where_the_oracle_fails():
    with pytest.raises(ValueError, match="leader_gap"):
        dataclasses.replace(DIFFICULTIES["medium"], ev_speed=(22.0, 30.0))


def oracle_episode(env, seed: int, whole: bool = True) -> dict:
    """One episode driven by the oracle's plan (until the EV stands unless ``whole``), with what it saw: ``leader``
    (the least footprint gap to the leader of reset while it is in the EV's lane: the oracle's ``bound`` holds for it
    there; one that changes lanes as it brakes turns, its x slower than its speed, up to 45 degrees where it stops
    mid-change, extreme seed 56, and is then no longer the EV's to keep clear of),
    ``least`` (to any vehicle ahead in the EV's lane), ``cut_ins`` (vehicles that changed into the EV's lane ahead of
    it while it moved, within their safety bound), ``crash_ahead`` (traffic crashed ahead of the EV: the one thing
    that brakes harder than the cap), ``collision`` and ``at_fault``."""
    from bimp.agents.evaluation.metrics import contact_at_fault

    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    ev, leader, policy = base.vehicle, base.leader, BrakeAtTheBounds(env)
    seen = {id(v) for v in ahead_in_lane(base)}
    out = {"cut_ins": 0, "least": np.inf, "leader": np.inf, "crash_ahead": False, "collision": False,
           "at_fault": False, "bound": float(least_gap(*(base.drawn_params[k] for k in ORACLE_KEYS)))}
    while True:
        moving = ev.speed > 0.0
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        if leader.lane_index == ev.lane_index:
            out["leader"] = min(out["leader"], float(leader.position[0] - ev.position[0]) - VEHICLE_LENGTH)
        out["crash_ahead"] |= any(v.crashed for v in base.road.vehicles
                                  if v is not ev and v.position[0] > ev.position[0])
        for v in ahead_in_lane(base):
            out["least"] = min(out["least"], float(v.position[0] - ev.position[0]) - VEHICLE_LENGTH)
            if id(v) not in seen and moving:
                out["cut_ins"] += 1
            seen.add(id(v))
        if info["collision"]:
            out["collision"] = True
            out["at_fault"] = contact_at_fault(info["contact"])
        if terminated or truncated or (not whole and ev.speed == 0.0):
            return out


@pytest.mark.slow
@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_oracles_plan_in_the_env_on_100_seeds(difficulty):
    """The oracle's plan driven for whole episodes, seeds 0-99: never a collision at the EV's fault; no vehicle ahead
    in its lane nearer than d_min (the leader, and those that change in ahead of it within their safety bound),
    unless traffic crashed ahead of it; what the oracle does not cover within the documented counts (docs: the
    erratic-traffic subsection; when written, nothing rear-ended the EV on easy seeds 0-99, medium 0-44 and hard
    0-59 and extreme 0-99, and traffic crashed ahead of it on none of the easy and medium ones, 10 of the hard ones
    and 17 of the extreme ones)."""
    env = gym.make(ID, config={"difficulty": difficulty})
    runs = [oracle_episode(env, seed) for seed in range(100)]
    assert not [s for s, r in enumerate(runs) if r["at_fault"]]
    assert not [s for s, r in enumerate(runs) if r["leader"] < r["bound"] - 1e-6 and not r["crash_ahead"]]
    assert not [s for s, r in enumerate(runs) if r["least"] < B.d_min and not r["crash_ahead"]]
    rear_ended = [s for s, r in enumerate(runs) if r["collision"]]
    crashes_ahead = [s for s, r in enumerate(runs) if r["crash_ahead"]]
    assert len(rear_ended) <= {"easy": 2, "medium": 5, "hard": 15, "extreme": 15}[difficulty], rear_ended
    assert len(crashes_ahead) <= {"easy": 2, "medium": 5, "hard": 30, "extreme": 40}[difficulty], crashes_ahead
