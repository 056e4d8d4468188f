"""The ``two-way-overtake`` family (issue 27 item 1): every drawn instance leaves a safe plan (braking behind the slow
vehicle: the oracle on 1000 draws per difficulty and every corner) and a plan that meets the goal (a pass once the
oncoming stream has gone by, driven through the env); the goal ends the episode and success needs it; the reference
overtakes on its critical gap and falls back when the pass no longer fits; what the oracles do not cover is
refused."""

from __future__ import annotations

import dataclasses
import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import bimp  # noqa: F401  (registers bimp/two-way-overtake-v0)
from bimp import make_policy
from bimp.agents.idm import _adapter
from bimp.agents.metrics import episode_metrics
from bimp.agents.rollout import rollout
from bimp.envs.highway.behaviour import OvertakeDriver, pass_time
from bimp.envs.oracle import NEVER, brake_at_the_bounds
from bimp.envs.scene import VEHICLE_LENGTH, Bounds
from bimp.envs.suite.family import EV_X
from bimp.envs.suite.two_way_overtake import (
    CLEAR_PASS,
    DIFFICULTIES,
    DURATION,
    ONCOMING,
    PASSED,
    RIGHT,
    TwoWayOvertakeRanges,
)
from tests.envs.test_suite_families import BrakeAtTheBounds, drawn_params

pytestmark = pytest.mark.filterwarnings("ignore")

ID = "bimp/two-way-overtake-v0"
B = Bounds()


def safe_gap(ev, distance, slow):
    """The oracle's least gap [m] braking behind the slow vehicle from the first step."""
    return brake_at_the_bounds(ev, distance, slow, NEVER, 0.0, react=False)


@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_every_draw_and_corner_leaves_a_safe_stop_and_a_clear_road_in_time(difficulty):
    params = drawn_params(ID, {"difficulty": difficulty})
    ranges = DIFFICULTIES[difficulty]
    for p in params:
        for key in ("ev_speed", "slow_speed", "slow_distance", "oncoming_first", "oncoming_until"):
            lo, hi = getattr(ranges, key)  # oncoming_speed and oncoming_gap: per vehicle (the stream's test)
            assert lo <= p[key] <= hi, (key, p)
        assert p["oncoming_count"] >= 1
    gaps = safe_gap(*(np.array([p[k] for p in params]) for k in ("ev_speed", "slow_distance", "slow_speed")))
    assert gaps.min() >= B.d_min
    corners = [float(safe_gap(*c)) for c in itertools.product(ranges.ev_speed, ranges.slow_distance,
                                                               ranges.slow_speed)]
    assert min(corners) == pytest.approx(ranges.least_gap()) and min(corners) >= B.d_min
    clear = [(until + VEHICLE_LENGTH) / (v_o + v_s) for until, v_o, v_s in itertools.product(
        ranges.oncoming_until, ranges.oncoming_speed, ranges.slow_speed)]
    assert max(clear) == pytest.approx(ranges.clear_time()) and max(clear) + CLEAR_PASS <= DURATION


def test_the_stream_is_the_drawn_one():
    """The slow vehicle ahead in the EV's lane at its drawn distance and speed; every oncoming vehicle in the other
    lane, heading at the EV, between oncoming_first and oncoming_until ahead, at least oncoming_gap's low apart."""
    env = gym.make(ID, config={"difficulty": "hard"})
    for seed in range(5):
        env.reset(seed=seed)
        base = env.unwrapped
        p, ev, slow = base.drawn_params, base.vehicle, base.slow_vehicle
        assert ev.lane_index == RIGHT and slow.lane_index == RIGHT
        assert slow.position[0] - ev.position[0] == pytest.approx(p["slow_distance"])
        assert slow.speed == pytest.approx(p["slow_speed"]) and ev.speed == pytest.approx(p["ev_speed"])
        oncoming = sorted(v.position[0] - EV_X for v in base.road.vehicles if v.lane_index == ONCOMING)
        assert len(oncoming) == p["oncoming_count"]
        assert oncoming[0] == pytest.approx(p["oncoming_first"]) and oncoming[-1] <= p["oncoming_until"] + 1e-9
        assert np.diff(oncoming).min(initial=np.inf) >= DIFFICULTIES["hard"].oncoming_gap[0] - 1e-9
        assert all(np.cos(v.heading) < -0.99 for v in base.road.vehicles if v.lane_index == ONCOMING)
        lo, hi = DIFFICULTIES["hard"].oncoming_speed
        assert all(lo <= v.speed <= hi for v in base.road.vehicles if v.lane_index == ONCOMING)


def drive_the_oracle(env, seed: int) -> dict:
    """The goal oracle's plan: the idm policy clipped to the planning bounds, its reference pulling out only onto a
    road clear of oncoming traffic. Returns what the episode ended with."""
    policy = make_policy("idm", env, clip_to_bounds=True)
    adapter = _adapter(env)

    def clear_road_only(env, obs, info):
        adapter.behaviour.shadow.PASS_GAP = np.inf

    episode = rollout(env, policy, seed, on_step=clear_road_only)
    metrics = episode_metrics(episode.trace, 0.1, episode.truncated)
    return {"goal": bool(episode.trace["goal"][-1]), "collision": bool(np.any(episode.trace["collision"])),
            "success": metrics["success_rate"], "time": episode.steps * 0.1}


@pytest.mark.parametrize("seed", [0, 1])
def test_the_goal_oracle_passes_once_the_road_is_clear(seed):
    out = drive_the_oracle(gym.make(ID, config={"difficulty": "hard"}), seed)
    assert out["goal"] and not out["collision"] and out["success"] == 1.0, out


@pytest.mark.slow
@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_goal_oracle_on_a_hundred_seeds(difficulty):
    env = gym.make(ID, config={"difficulty": difficulty})
    failed = {seed: out for seed in range(100) if not (out := drive_the_oracle(env, seed))["success"]}
    assert not failed


def test_the_goal_ends_the_episode_and_waiting_never_meets_it():
    """Put ahead of the slow vehicle in its lane, the EV has met the goal: the episode ends there as a success; the
    time limit behind the slow vehicle is a failure."""
    env = gym.make(ID)
    env.reset(seed=0)
    base = env.unwrapped
    assert not base.goal_reached()
    ev, slow = base.vehicle, base.slow_vehicle
    ev.position = np.array([slow.position[0] + PASSED - 0.5, slow.position[1]])
    assert not base.goal_reached()
    ev.position = np.array([slow.position[0] + PASSED + 0.5, slow.position[1]])
    _, _, terminated, _, info = env.step(np.zeros(2, np.float32))
    assert info["goal"] is True and terminated and not info["collision"]
    episode = rollout(env, BrakeAtTheBounds(env), 0)  # stopped behind the slow vehicle to the time limit
    assert episode.truncated and not any(episode.trace["goal"]) and not any(episode.trace["collision"])
    assert episode_metrics(episode.trace, 0.1, episode.truncated)["success_rate"] == 0.0


def test_pass_time_against_a_stepped_pass():
    for distance, v, v_l, top, a in [(45.0, 15.0, 15.0, 25.0, 3.0), (10.0, 20.0, 15.0, 25.0, 3.0),
                                     (60.0, 25.0, 14.0, 25.0, 3.0), (50.0, 10.0, 16.0, 25.0, 2.0)]:
        t, gained, speed, dt = 0.0, 0.0, v, 1e-4
        while gained < distance:
            gained += (speed - v_l) * dt
            speed, t = min(speed + a * dt, top), t + dt
        assert pass_time(distance, v, v_l, top, a) == pytest.approx(t, abs=1e-2)
    assert pass_time(10.0, 15.0, 20.0, 20.0, 3.0) == np.inf and pass_time(-1.0, 1.0, 1.0, 1.0, 1.0) == 0.0


def test_the_reference_pulls_out_on_its_critical_gap_and_falls_back():
    """Behind the slow vehicle the reference pulls out only where the nearest oncoming vehicle is PASS_GAP s away or
    more; once out, with the oncoming vehicle brought close, it falls back behind the slow vehicle and returns."""
    env = gym.make(ID, config={"difficulty": "hard", "slow_distance": 30.0, "slow_speed": 15.0, "ev_speed": 22.0})
    env.reset(seed=0)
    adapter, base = _adapter(env), env.unwrapped
    shadow, ev = adapter.behaviour.shadow, base.vehicle
    oncoming = min((v for v in base.road.vehicles if v.lane_index == ONCOMING), key=lambda v: v.position[0])
    meet = shadow._time_to_meet()
    closing = ev.speed + oncoming.speed
    assert meet == pytest.approx((oncoming.position[0] - ev.position[0] - VEHICLE_LENGTH) / closing)
    passing = ("a", "b", 0)
    for ahead_s, expected in [(OvertakeDriver.PASS_GAP + 0.5, True), (OvertakeDriver.PASS_GAP - 0.5, False)]:
        oncoming.position = np.array([ev.position[0] + VEHICLE_LENGTH + ahead_s * closing, oncoming.position[1]])
        adapter.behaviour.decide(0.0)
        assert bool(shadow.mobil(passing)) is expected
    # Out in the passing lane beside the slow vehicle's tail, the oncoming vehicle 3 s away: the pass does not fit.
    ev.position = np.array([base.slow_vehicle.position[0] - 12.0, 0.0])
    oncoming.position = np.array([ev.position[0] + VEHICLE_LENGTH + 3.0 * closing, oncoming.position[1]])
    ev.lane_index, ev.lane = passing, base.road.network.get_lane(passing)
    adapter.behaviour.decide(0.0)
    assert shadow._must_fall_back()
    assert adapter.behaviour.action["acceleration"] < 0  # IDM behind the slow vehicle
    assert not shadow.mobil(RIGHT)  # 12 m behind it at 22 m/s against 15: not yet safe to return
    # Fallen back 40 m behind it at its speed: IDM's gap; safe to return.
    ev.position, ev.speed = np.array([base.slow_vehicle.position[0] - 40.0, 0.0]), base.slow_vehicle.speed
    adapter.behaviour.decide(0.0)
    assert shadow.mobil(RIGHT)


@pytest.mark.parametrize(("config", "match"), [
    ({"slow_distance": (10.0, 40.0)}, "slow_distance must be a range .* 20 <= lo"),
    ({"slow_distance": 21.0, "ev_speed": 25.0, "slow_speed": 5.0}, "slow_distance must be .*d_min"),
    ({"oncoming_until": (700.0, 1100.0)}, "oncoming_until must be .*clears the road by 25 s"),
    ({"oncoming_first": (600.0, 800.0), "oncoming_until": 700.0}, "oncoming_until must be .*oncoming_first"),
    ({"slow_speed": (5.0, 21.0)}, "slow_speed must be"),
])
def test_refused_naming_the_key(config, match):
    with pytest.raises(ValueError, match=match):
        gym.make(ID, config=config)


def test_ranges_are_the_documented_dataclass():
    with pytest.raises(TypeError):
        TwoWayOvertakeRanges(**{**dataclasses.asdict(DIFFICULTIES["easy"]), "speed": (1.0, 2.0)})


def test_check_env():
    check_env(gym.make(ID).unwrapped, skip_render_check=True)
    check_env(gym.make(ID), skip_render_check=True)
