import math

import pytest

from bimp.agents.evaluation.metrics import METRICS, episode_metrics, summarize
from bimp.agents.evaluation.records import markdown_table

OK = {"accel_min": -1.0, "accel_max": -1.0, "steer": -0.01, "accel_rate": -0.5, "steer_rate": -0.001}


def trace(n=10, **changes):
    t = {
        "collision": [False] * n, "offroad": [False] * n, "ov_distance": [[20.0, 30.0]] * n,
        "edge_distance": [1.0] * n, "ttc": [math.inf] * n, "lateral_error": [0.0] * n,
        "speed_error": [0.0] * n, "input": [[0.0, 0.0]] * n, "constraints": [dict(OK) for _ in range(n)],
        "plan_ms": [1.0] * n, "s": [20.0 * k for k in range(n)],
    }
    t.update(changes)
    return t


def test_clean_episode():
    m = episode_metrics(trace(), dt=0.1, truncated=True)
    assert m["success_rate"] == 1.0 and m["collision_rate"] == m["offroad_rate"] == 0.0
    assert m["input_violation_rate"] == m["rate_violation_rate"] == 0.0
    assert m["min_distance_m"] == 20.0 and m["min_ttc_s"] is None and m["max_abs_jerk"] == 0.0
    assert m["progress_m"] == 180.0


def test_known_collision_offroad_and_early_termination():
    collided = trace(collision=[False] * 9 + [True], ov_distance=[[20.0, 30.0]] * 9 + [[-0.2, 30.0]])
    m = episode_metrics(collided, dt=0.1, truncated=False)
    assert m["collision_rate"] == 1.0 and m["success_rate"] == 0.0 and m["min_distance_m"] == -0.2
    m = episode_metrics(trace(offroad=[False] * 4 + [True]), dt=0.1, truncated=False)
    assert m["offroad_rate"] == 1.0 and m["success_rate"] == 0.0
    assert episode_metrics(trace(), dt=0.1, truncated=False)["success_rate"] == 0.0


def test_known_number_of_bound_violations_and_jerk():
    c = [dict(OK) for _ in range(10)]
    c[2]["steer"] = 0.01
    c[5]["accel_min"] = 0.5
    c[7]["accel_rate"] = 0.3
    c[8]["accel_rate"] = 1e-9  # float round-off on the bound is not a violation
    inputs = [[0.0, 0.0]] * 5 + [[-2.0, 0.0]] * 5
    m = episode_metrics(trace(constraints=c, input=inputs), dt=0.1, truncated=True)
    assert m["input_violation_rate"] == pytest.approx(0.2)
    assert m["rate_violation_rate"] == pytest.approx(0.1)
    assert m["max_abs_jerk"] == pytest.approx(20.0)


def test_known_minimum_ttc_and_errors():
    m = episode_metrics(trace(ttc=[math.inf, 4.0, 2.5, math.inf] + [math.inf] * 6,
                              lateral_error=[3.0] + [0.0] * 9, speed_error=[1.0] * 10,
                              plan_ms=list(range(1, 11))), dt=0.1, truncated=True)
    assert m["min_ttc_s"] == 2.5
    assert m["rms_lateral_error_m"] == pytest.approx(math.sqrt(0.9))
    assert m["rms_speed_error_mps"] == pytest.approx(1.0)
    assert m["plan_time_ms_p50"] == pytest.approx(5.5)


def test_summary_intervals_and_errors_that_are_not_results():
    ok = {"scenario": "s", "policy": "p", "status": "ok", "metrics": episode_metrics(trace(), dt=0.1, truncated=True)}
    crashed = episode_metrics(trace(collision=[False] * 9 + [True], ov_distance=[[20.0, 30.0]] * 9 + [[-0.2, 30.0]]),
                              dt=0.1, truncated=False)
    records = [{**ok, "seed": s} for s in range(4)] + [{**ok, "seed": 4, "metrics": crashed},
                                                      {"scenario": "s", "policy": "p", "status": "error",
                                                       "error": "boom", "seed": 9}]
    e = summarize(records)["p/s"]
    assert e["episodes"] == 5 and e["errors"] == 1 and e["error_seeds"] == [9]
    assert e["failed_seeds"] == {"success": [4], "collision": [4], "offroad": []}
    for name in METRICS:
        assert {"mean", "ci_low", "ci_high", "n"} <= set(e[name])
    # 4 of 5 successes: the error is not a result; Wilson (0.376, 0.964) for 4/5
    assert e["success_rate"]["mean"] == pytest.approx(0.8) and e["success_rate"]["n"] == 5
    assert e["success_rate"]["ci_low"] == pytest.approx(0.3755, abs=1e-3)
    assert e["success_rate"]["ci_high"] == pytest.approx(0.9638, abs=1e-3)
    d = e["min_distance_m"]
    assert d["mean"] == pytest.approx((4 * 20.0 - 0.2) / 5) and d["ci_low"] <= d["mean"] <= d["ci_high"]
    assert e["min_ttc_s"]["mean"] is None
    assert e["code_versions"] == ["None"]  # records without a commit


def test_rows_that_mix_code_versions_are_flagged():
    ok = {"scenario": "s", "policy": "p", "status": "ok", "metrics": episode_metrics(trace(), dt=0.1, truncated=True)}
    same = summarize([{**ok, "seed": 0, "git_commit": "a"}, {**ok, "seed": 1, "git_commit": "a"}])
    assert "Mixed code versions" not in markdown_table(same)
    mixed = summarize([{**ok, "seed": 0, "git_commit": "a"}, {**ok, "seed": 1, "git_commit": "b", "git_dirty": True}])
    assert mixed["p/s"]["code_versions"] == ["a", "b+dirty"] and "Mixed code versions" in markdown_table(mixed)


def test_overtake_rate_is_the_last_step_ahead_of_ov1_and_none_elsewhere():
    passed = episode_metrics(trace(ahead_of_ov1=[False] * 6 + [True] * 4), dt=0.1, truncated=True)
    followed = episode_metrics(trace(ahead_of_ov1=[False] * 10), dt=0.1, truncated=True)
    braking = episode_metrics(trace(ahead_of_ov1=[None] * 10), dt=0.1, truncated=True)
    assert (passed["overtake_rate"], followed["overtake_rate"], braking["overtake_rate"]) == (1.0, 0.0, None)


def test_fallbacks_are_counted_and_shown_only_when_a_planner_fell_back():
    """Issue 24: six of six episodes driven on fallbacks (nu rounding to 2 in float32) showed only as collisions."""
    ok = {"scenario": "s", "policy": "p", "status": "ok", "steps": 10,
          "metrics": episode_metrics(trace(), dt=0.1, truncated=True)}
    every_step = {"fallback_steps": list(range(10))}
    fell_back = summarize([{**ok, "seed": s, "policy_info": every_step} for s in range(6)])
    e = fell_back["p/s"]
    assert e["fallback_seeds"] == [0, 1, 2, 3, 4, 5] and (e["fallback_steps"], e["steps"]) == (60, 60)
    table = markdown_table(fell_back)
    assert "| fallbacks |" in table and "6 (0, 1, 2, 3, 4, 5); 60 of 60 steps" in table
    clean = summarize([{**ok, "seed": 0, "policy_info": {"fallback_steps": []}}, {**ok, "seed": 1}])
    assert clean["p/s"]["fallback_seeds"] == [] and clean["p/s"]["fallback_steps"] == 0
    assert "fallbacks" not in markdown_table(clean)  # no column for policies that never fell back


def test_a_goal_reached_is_a_success_before_the_time_limit_but_not_with_a_collision():
    """A wrapped highway-env env ends at its goal (exit taken, intersection crossed): that episode succeeded; a goal
    reached in a collision did not; the paper's envs report no goal (None) and need the time limit; an env with a
    goal needs it."""
    reached = [False] * 9 + [True]
    assert episode_metrics(trace(goal=reached), dt=0.1, truncated=False)["success_rate"] == 1.0
    assert episode_metrics(trace(goal=reached, collision=[False] * 9 + [True]), dt=0.1,
                           truncated=False)["success_rate"] == 0.0
    assert episode_metrics(trace(goal=[None] * 10), dt=0.1, truncated=False)["success_rate"] == 0.0
    assert episode_metrics(trace(goal=[None] * 10), dt=0.1, truncated=True)["success_rate"] == 1.0
    # an env with a goal: the time limit without it is no success (exit-v0 driven on past the exit)
    assert episode_metrics(trace(goal=[False] * 10), dt=0.1, truncated=True)["success_rate"] == 0.0
