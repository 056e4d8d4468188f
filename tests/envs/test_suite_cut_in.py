"""The ``cut-in`` family (issue 27 item 1): every drawn instance leaves a safe plan (the oracle, on 1000 draws per
difficulty and every corner, checked against the env), a seeded reset is deterministic, the scripted cutter starts
beside the EV and is in its lane ahead after its cut, what the oracle does not cover is refused, and the policies
drive it."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import bimp  # noqa: F401  (registers bimp/cut-in-v0)
from bimp.envs import scenario_spec
from bimp.envs.scene import DT, VEHICLE_LENGTH, Bounds
from bimp.envs.suite import FAMILIES
from bimp.envs.suite.cut_in import (
    DIFFICULTIES,
    ENVELOPE,
    LANE_CHANGE,
    CutInEnv,
    cutter_speed,
    least_gap,
    on_the_step,
)
from tests.envs.test_suite_families import drawn_params

pytestmark = pytest.mark.filterwarnings("ignore")

ID = "bimp/cut-in-v0"
DRAWS = 1000
B = Bounds()
ORACLE_KEYS = ("ev_speed", "cutter_start", "cut_time", "time_gap", "cutter_decel", "brake_duration")


def draws(difficulty: str, n: int = DRAWS) -> list[dict]:
    """The drawn parameters of ``n`` seeded resets of the registered env at ``difficulty``."""
    return drawn_params(ID, {"difficulty": difficulty}, n)


@pytest.mark.parametrize("difficulty", list(DIFFICULTIES))
def test_a_safe_plan_exists_on_every_draw_and_corner(difficulty):
    """Braking at the planning bounds from the cut's start keeps at least d_min to the cutter: on 1000 drawn
    instances of each difficulty and on every corner of its ranges."""
    params = draws(difficulty)
    ranges = DIFFICULTIES[difficulty]
    for p in params:  # the draws are the documented ranges'
        for key in (*ORACLE_KEYS, "density", "aggressive_share", "defensive_share"):
            lo, hi = getattr(ranges, key)
            assert lo <= p[key] <= hi, (key, p)
        assert abs(p["cutter_lane"] - p["ev_lane"]) == 1
    gaps = least_gap(*(np.array([p[k] for p in params]) for k in ORACLE_KEYS))
    assert gaps.min() >= B.d_min, f"{int(np.sum(gaps < B.d_min))} draws infeasible, e.g. {params[int(gaps.argmin())]}"
    assert ranges.least_gap() >= B.d_min and gaps.min() >= ranges.least_gap() - 1e-9  # the corners bound the draws


def test_hard_is_near_the_edge_of_the_oracles_cover():
    """A shorter time gap or a cutter that stands at 8 m/s^2 from the cut's end is refused on hard's other ranges."""
    hard = DIFFICULTIES["hard"]
    assert 1.0 < hard.least_gap() < 10.0
    with pytest.raises(ValueError, match="time_gap"):
        dataclasses.replace(hard, time_gap=(0.2, 0.6), cutter_start=(5.0, 40.0))


class OraclePlan:
    """The oracle's plan as a policy: input 0 until the cutter's lane change starts, then the acceleration ramped to
    a_min by the rate bound, straight on."""

    def __init__(self, env):
        self.env, self.a, self.k = env, 0.0, 0
        self.cut_step = round(env.unwrapped.cutter.cut_time / DT)

    def act(self, obs):
        if self.k >= self.cut_step:
            self.a = max(self.a - B.accel_rate, B.accel[0])
        self.k += 1
        return self.env.unwrapped.scene.to_normalized(np.array([self.a, 0.0])).astype(np.float32)


@pytest.mark.parametrize(("difficulty", "seed"),
                         [("hard", 0), ("hard", 3), ("medium", 1), ("extreme", 0), ("extreme", 2)])
def test_the_oracle_is_the_env(difficulty, seed):
    """Driven by the oracle's plan, the env's least footprint gap to the cutter from its cut on is the oracle's, the
    cutter keeps to its script (never braked for traffic), and no vehicle comes within d_min of the EV."""
    env = gym.make(ID, config={"difficulty": difficulty})
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    p, ev, cutter = base.drawn_params, base.vehicle, base.cutter
    policy, least = OraclePlan(env), np.inf
    for k in range(120):
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        if k >= policy.cut_step:
            least = min(least, float(cutter.position[0] - ev.position[0]) - VEHICLE_LENGTH)
        assert not info["collision"] and min(info["ov_distance"]) >= B.d_min
        if terminated or truncated:
            break
    assert ev.speed == 0.0 and cutter.guarded_steps == 0 and least >= B.d_min
    assert least == pytest.approx(float(least_gap(*(p[k] for k in ORACLE_KEYS))), abs=1e-6)


def test_check_env_and_the_scenario_table():
    env = gym.make(ID)
    check_env(env, skip_render_check=True)
    spec = scenario_spec("cut-in")
    assert spec.id == ID and spec.max_episode_steps == 150 and not spec.default
    assert FAMILIES["cut-in"] is CutInEnv
    assert env.unwrapped.scene.bounds == Bounds()


def test_the_cutter_starts_beside_and_is_ahead_in_the_evs_lane_after_its_cut():
    """At reset the cutter is in the lane beside at its drawn start and speed; it keeps that lane and speed until
    its cut time (whatever the EV does: it is scripted), and once its lane change has ended it is in the EV's lane
    ahead of the EV, time_gap ahead of where an EV holding its speed would be, braking at its deceleration."""
    env = gym.make(ID, config={"difficulty": "hard"})
    for seed in range(3):
        env.reset(seed=seed)
        base = env.unwrapped
        p, ev, cutter = base.drawn_params, base.vehicle, base.cutter
        assert cutter.lane_index[2] == p["cutter_lane"] != ev.lane_index[2] == p["ev_lane"]
        assert cutter.position[0] - ev.position[0] == pytest.approx(p["cutter_start"])
        assert cutter.speed == pytest.approx(p["cutter_speed"]) == pytest.approx(
            float(cutter_speed(p["ev_speed"], p["cutter_start"], p["cut_time"], p["time_gap"])))
        cut, end = round(float(on_the_step(p["cut_time"])) / DT), round(LANE_CHANGE / DT)
        x0 = cutter.position[0]
        for k in range(cut + end + 3):
            env.step(np.array([0.3 if k % 2 else -0.3, 0.0], np.float32))  # an EV that does not hold its speed
            if k + 1 == cut:
                assert cutter.lane_index[2] == p["cutter_lane"] and cutter.speed == pytest.approx(p["cutter_speed"])
                assert cutter.position[0] - x0 == pytest.approx(p["cutter_speed"] * cut * DT)
                assert cutter.position[1] == pytest.approx(4.0 * p["cutter_lane"])
        assert cutter.lane_index == ev.lane_index and cutter.position[0] > ev.position[0] + VEHICLE_LENGTH
        assert cutter.position[1] == pytest.approx(4.0 * p["ev_lane"])
        assert cutter.speed == pytest.approx(p["cutter_speed"] - 3 * DT * p["cutter_decel"])
        # time_gap: where the cut started, the gap to an EV that had held ev_speed
        start = x0 + p["cutter_speed"] * cut * DT
        ev_held = 200.0 + p["ev_speed"] * cut * DT
        assert start - ev_held - VEHICLE_LENGTH == pytest.approx(p["time_gap"] * p["ev_speed"])


def test_difficulty_sets_the_ranges_and_a_range_overrides_one():
    base = gym.make(ID, config={"difficulty": "easy"}).unwrapped
    assert {k: base.config[k] for k in CutInEnv.range_keys()} == dataclasses.asdict(DIFFICULTIES["easy"])
    env = gym.make(ID, config={"difficulty": "hard", "density": 0, "time_gap": [0.5, 0.6]})
    env.reset(seed=0)
    p = env.unwrapped.drawn_params
    assert p["density"] == 0.0 and 0.5 <= p["time_gap"] <= 0.6
    assert len(env.unwrapped.road.vehicles) == 2  # the EV and the cutter
    assert env.unwrapped.config["cutter_decel"] == DIFFICULTIES["hard"].cutter_decel
    # Harder: a faster EV, a shorter time gap, harder and longer braking, denser traffic, more aggressive drivers.
    easy, medium, hard = (DIFFICULTIES[k] for k in ("easy", "medium", "hard"))
    for key, sign in (("ev_speed", 1), ("time_gap", -1), ("cutter_decel", 1), ("brake_duration", 1),
                      ("density", 1), ("aggressive_share", 1)):
        assert sign * getattr(easy, key)[0] < sign * getattr(medium, key)[0] < sign * getattr(hard, key)[0] or \
            sign * getattr(easy, key)[1] < sign * getattr(medium, key)[1] < sign * getattr(hard, key)[1], key


def test_extreme_is_hard_with_the_cutter_at_the_edge_of_its_envelope():
    """extreme keeps hard's road, EV and traffic and moves only the cutter: the envelope's shortest time gap and
    hardest braking, long enough to stop any cutter it draws; nearer the oracle's edge than hard, and a slower EV
    (more room to close on the cutter before its cut) falls outside the oracle's cover."""
    hard, extreme = DIFFICULTIES["hard"], DIFFICULTIES["extreme"]
    for key in ("ev_speed", "cutter_start", "cut_time", "density", "traffic_speed", "aggressive_share",
                "defensive_share"):
        assert getattr(extreme, key) == getattr(hard, key), key
    assert extreme.time_gap[0] == ENVELOPE["time_gap"].low and extreme.time_gap[1] < hard.time_gap[0]
    assert extreme.cutter_decel[1] == ENVELOPE["cutter_decel"].high and extreme.cutter_decel[0] > hard.cutter_decel[0]
    corners = extreme.corners()
    fastest = float(cutter_speed(*(corners[k] for k in ("ev_speed", "cutter_start", "cut_time", "time_gap"))).max())
    assert fastest / extreme.cutter_decel[0] <= extreme.brake_duration[0]  # every cutter brakes to a stop
    assert B.d_min <= extreme.least_gap() < hard.least_gap()
    with pytest.raises(ValueError, match="time_gap must be .*oracle"):
        dataclasses.replace(extreme, ev_speed=(22.0, 30.0))


@pytest.mark.parametrize(("config", "match"), [
    ({"ev_speed": [20, 35]}, "ev_speed"),
    ({"time_gap": [1.0, 0.8]}, "time_gap"),
    ({"cutter_decel": "hard"}, "cutter_decel"),
    ({"brake_duration": [1.0, np.nan]}, "brake_duration"),
    ({"aggressive_share": [0.5, 0.6], "defensive_share": [0.3, 0.5]}, "defensive_share"),
    ({"difficulty": "hard", "time_gap": [0.2, 0.6], "cutter_start": [5, 40]}, "time_gap must be .*oracle"),
    ({"difficulty": "hard", "cutter_start": [5, 40]}, "time_gap must be .*worst corner .*cutter_start 40"),
    ({"difficulty": "hard", "density": [40, 50]}, "density"),
    ({"difficulty": "hard", "cut_time": [1.0, 5.0]}, "cut_time"),
    ({"difficulty": "extreme", "ev_speed": [22, 30]}, "time_gap must be .*worst corner .*ev_speed 22"),
])
def test_what_the_oracle_does_not_cover_is_refused(config, match):
    with pytest.raises(ValueError, match=match):
        gym.make(ID, config=config)

