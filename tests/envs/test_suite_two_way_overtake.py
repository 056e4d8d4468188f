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
from bimp.agents.evaluation.metrics import episode_metrics, record_missed_goal
from bimp.agents.idm import _adapter
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
    PASSING,
    RIGHT,
    SPEED_LIMIT,
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
    road clear of oncoming traffic. Returns what the episode ended with, and ``pass_time``: from the step the last
    oncoming vehicle was behind the EV to the goal [s]."""
    policy = make_policy("idm", env, clip_to_bounds=True)
    adapter = _adapter(env)
    clear = []

    def clear_road_only(env, obs, info):
        adapter.behaviour.shadow.PASS_GAP = np.inf
        base = env.unwrapped
        ahead = [v for v in base.road.vehicles if v.lane_index == ONCOMING
                 and v.position[0] > base.vehicle.position[0] - VEHICLE_LENGTH]
        clear.append(not ahead)

    episode = rollout(env, policy, seed, on_step=clear_road_only)
    metrics = episode_metrics(episode.trace, 0.1, episode.truncated)
    return {"goal": bool(episode.trace["goal"][-1]), "collision": bool(np.any(episode.trace["collision"])),
            "success": metrics["success_rate"], "pass_time": (len(clear) - clear.index(True)) * 0.1}


@pytest.mark.parametrize("seed", [0, 1])
def test_the_goal_oracle_passes_once_the_road_is_clear(seed):
    out = drive_the_oracle(gym.make(ID, config={"difficulty": "hard"}), seed)
    assert out["goal"] and not out["collision"] and out["success"] == 1.0, out
    assert out["pass_time"] <= CLEAR_PASS


@pytest.mark.slow
@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_the_goal_oracle_on_a_hundred_seeds(difficulty):
    env = gym.make(ID, config={"difficulty": difficulty})
    runs = {seed: drive_the_oracle(env, seed) for seed in range(100)}
    assert not {seed: out for seed, out in runs.items() if not out["success"] or out["pass_time"] > CLEAR_PASS}


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
    metrics = episode_metrics(episode.trace, 0.1, episode.truncated)
    assert metrics["success_rate"] == 0.0 and metrics["score"] == 0.0  # the score's goal gate
    assert record_missed_goal({"truncated": episode.truncated, "metrics": metrics})


def test_the_reward_pays_the_goal_the_steps_it_ends_and_never_the_oncoming_lane():
    """The family's reward (for learners) is its own, not two-way-v0's, whose goal ended the episode unpaid: a pass
    that returns to its lane must never earn less than racing on in the oncoming lane to the time limit."""
    env = gym.make(ID)
    env.reset(seed=0)
    base = env.unwrapped
    assert dict(base.REWARD_WEIGHTS) == {"high_speed_reward": 0.8, "right_lane_reward": 0.2, "goal_reward": 1.0}
    _, reward, _, _, info = env.step(np.zeros(2, np.float32))
    assert set(info["rewards"]) == {"high_speed_reward", "right_lane_reward", "goal_reward"}
    assert info["rewards"]["right_lane_reward"] == 1.0 and info["rewards"]["goal_reward"] == 0.0
    assert reward == pytest.approx(0.8 * min(base.vehicle.speed / SPEED_LIMIT, 1.0) + 0.2)
    ev, slow = base.vehicle, base.slow_vehicle
    ev.position = np.array([slow.position[0] + PASSED + 0.5, slow.position[1]])
    _, reward, terminated, _, info = env.step(np.zeros(2, np.float32))
    left = (DURATION - base.time) * base.config["policy_frequency"]
    assert terminated and info["goal"] and info["rewards"]["goal_reward"] == pytest.approx(left)
    assert reward >= left  # every step left, at the most any step pays (0.8 + 0.2)


def test_pass_time_against_a_stepped_pass():
    for distance, v, v_l, top, a in [(45.0, 15.0, 15.0, 25.0, 3.0), (10.0, 20.0, 15.0, 25.0, 3.0),
                                     (60.0, 25.0, 14.0, 25.0, 3.0), (50.0, 10.0, 16.0, 25.0, 2.0)]:
        t, gained, speed, dt = 0.0, 0.0, v, 1e-4
        while gained < distance:
            gained += (speed - v_l) * dt
            speed, t = min(speed + a * dt, top), t + dt
        assert pass_time(distance, v, v_l, top, a) == pytest.approx(t, abs=1e-2)
    assert pass_time(10.0, 15.0, 20.0, 20.0, 3.0) == np.inf and pass_time(-1.0, 1.0, 1.0, 1.0, 1.0) == 0.0


def reference_at(seed: int = 0):
    """A hard episode with a 15 m/s slow vehicle 30 m ahead of a 22 m/s EV: the adapter, its env, the shadow driver,
    the EV and the nearest oncoming vehicle."""
    env = gym.make(ID, config={"difficulty": "hard", "slow_distance": 30.0, "slow_speed": 15.0, "ev_speed": 22.0})
    env.reset(seed=seed)
    adapter, base = _adapter(env), env.unwrapped
    oncoming = min((v for v in base.road.vehicles if v.lane_index == ONCOMING), key=lambda v: v.position[0])
    return adapter, base, adapter.behaviour.shadow, base.vehicle, oncoming


def place(ev, oncoming, seconds: float) -> None:
    """The oncoming vehicle put ``seconds`` from meeting the EV at today's speeds."""
    oncoming.position = np.array([ev.position[0] + VEHICLE_LENGTH + seconds * (ev.speed + oncoming.speed),
                                  oncoming.position[1]])


def into_passing_lane(ev, base, behind_slow: float) -> None:
    ev.position = np.array([base.slow_vehicle.position[0] - behind_slow, 0.0])
    ev.lane_index, ev.lane = PASSING, base.road.network.get_lane(PASSING)


def test_the_reference_pulls_out_on_its_critical_gap_and_withdraws_a_stale_pull_out():
    adapter, base, shadow, ev, oncoming = reference_at()
    assert shadow._time_to_meet() == pytest.approx(
        (oncoming.position[0] - ev.position[0] - VEHICLE_LENGTH) / (ev.speed + oncoming.speed))
    for seconds, expected in [(OvertakeDriver.PASS_GAP + 0.5, True), (OvertakeDriver.PASS_GAP - 0.5, False)]:
        place(ev, oncoming, seconds)
        adapter.behaviour.decide(0.0)
        assert shadow.mobil(PASSING) is expected
    # Pulling out (still in its lane, the passing lane its target): kept down to PASS_GAP - HESITATION, then
    # withdrawn (a planner that did not follow is not sent out into a gap that is gone).
    hesitation = OvertakeDriver.PASS_GAP - OvertakeDriver.HESITATION
    for seconds, target in [(hesitation + 0.3, PASSING), (hesitation - 0.3, RIGHT)]:
        shadow.target_lane_index = PASSING
        place(ev, oncoming, seconds)
        adapter.behaviour.decide(0.0)
        assert shadow.target_lane_index == target


def test_out_in_the_oncoming_lane_the_reference_passes_falls_back_and_returns():
    adapter, base, shadow, ev, oncoming = reference_at()
    into_passing_lane(ev, base, behind_slow=12.0)
    shadow.target_lane_index = PASSING
    place(ev, oncoming, 60.0)  # far: the pass fits; IDM accelerates, the oncoming vehicle ignored
    adapter.behaviour.decide(0.0)
    assert not shadow._must_fall_back() and adapter.behaviour.action["acceleration"] > 0
    assert shadow.target_lane_index == PASSING  # the pass goes on
    place(ev, oncoming, 3.0)  # near: it no longer fits; IDM brakes behind the slow vehicle, too near to return yet
    adapter.behaviour.decide(0.0)
    assert shadow._must_fall_back() and adapter.behaviour.action["acceleration"] < -3.0
    assert shadow.target_lane_index == PASSING and not shadow._may_return(RIGHT)
    ev.position, ev.speed = np.array([base.slow_vehicle.position[0] - 40.0, 0.0]), base.slow_vehicle.speed
    place(ev, oncoming, 3.0)
    adapter.behaviour.decide(0.0)  # fallen back 40 m behind it at its speed: back to its lane at once
    assert shadow.target_lane_index == RIGHT


def test_past_the_slow_vehicle_the_reference_returns_at_the_lead_its_idm_accepts():
    """Past the slow vehicle the EV returns once the slow vehicle's IDM brakes at most 2 m/s^2 for it (return_gap),
    checked at every step in the oncoming lane."""
    adapter, base, shadow, ev, oncoming = reference_at()
    slow = base.slow_vehicle
    into_passing_lane(ev, base, behind_slow=0.0)
    ev.speed = 25.0
    adapter.behaviour.decide(0.0)  # the shadow synced to the EV's speed, which the return gap depends on
    gap = shadow.return_gap(slow)
    assert 15.0 < gap < 30.0
    for lead, returns in [(gap - 3.0, False), (gap + 1.0, True)]:
        ev.position = np.array([slow.position[0] + lead, 0.0])
        place(ev, oncoming, 60.0)
        shadow.target_lane_index = PASSING
        adapter.behaviour.decide(0.0)
        assert (shadow.target_lane_index == RIGHT) is returns
        braking = slow.acceleration(slow, ev)  # what the slow vehicle's IDM does for the EV ahead
        assert bool(braking >= -shadow.LANE_CHANGE_MAX_BRAKING_IMPOSED) is returns


def test_a_behaviour_layer_is_not_both_drive_on_and_overtake():
    from bimp.envs.highway.behaviour import Behaviour

    with pytest.raises(ValueError, match="not both"):
        Behaviour(gym.make(ID).unwrapped, 25.0, drive_on=True, overtake=True)


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
