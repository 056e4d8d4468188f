"""The closed-loop score (docs/suite.md) against hand-built episodes: every expected value is computed by hand from
the formula, not by the code under test."""

import math

import pytest

from bimp.agents.evaluation.metrics import (
    BINARY,
    MAX_LAT_ACCEL,
    METRICS,
    OVERSPEED_BOUND,
    SCORE_METRICS,
    at_fault_collision,
    closed_loop_score,
    contact_at_fault,
    episode_metrics,
    record_missed_goal,
    summarize,
)

DT = 0.1
OK = {"accel_min": -1.0, "accel_max": -1.0, "steer": -0.01, "accel_rate": -0.5, "steer_rate": -0.001}


def episode(n=40, speed=20.0, limit=20.0, **changes) -> dict:
    """A straight episode at a constant ``speed`` under a constant ``limit``, nothing closing in, on the road: what a
    perfect driver does when the limit is the speed to drive at. ``s`` advances by speed x dt per step."""
    t = {
        "collision": [False] * n, "offroad": [False] * n, "ov_distance": [[30.0]] * n, "edge_distance": [1.0] * n,
        "ttc": [math.inf] * n, "lateral_error": [0.0] * n, "speed_error": [0.0] * n, "input": [[0.0, 0.0]] * n,
        "constraints": [dict(OK) for _ in range(n)], "plan_ms": [1.0] * n,
        "x": [speed * DT * k for k in range(n)], "y": [0.0] * n, "heading": [0.0] * n, "speed": [speed] * n,
        "s": [speed * DT * k for k in range(n)], "contact": [None] * n, "speed_limit": [limit] * n,
    }
    t.update(changes)
    return t


def contact(rel_x=5.0, rel_y=0.0, rel_heading=0.0, ev_speed=20.0, ov_speed=10.0, ev_lateral_speed=0.0) -> dict:
    return {"rel_x": rel_x, "rel_y": rel_y, "rel_heading": rel_heading, "ev_speed": ev_speed, "ov_speed": ov_speed,
            "ev_lateral_speed": ev_lateral_speed}


def crashed(n=40, **kw) -> dict:
    """:func:`episode` ending in a collision at its last step with the contact ``kw`` describes."""
    return episode(n, collision=[False] * (n - 1) + [True], contact=[None] * (n - 1) + [contact(**kw)])


def weighted(progress=1.0, ttc=1.0, speed=1.0, comfort=1.0) -> float:
    return (5 * progress + 5 * ttc + 4 * speed + 2 * comfort) / 16


def test_metrics_table_has_the_score():
    assert set(SCORE_METRICS) <= set(METRICS) and "at_fault_collision_rate" in BINARY
    assert not set(SCORE_METRICS[1:]) & set(BINARY)  # the score and its parts are continuous


def test_a_perfect_episode_scores_exactly_one():
    m = episode_metrics(episode(), dt=DT, truncated=True)
    assert m["score"] == 1.0 and m["at_fault_collision_rate"] == 0.0
    assert m["score_progress"] == m["score_ttc"] == m["score_speed"] == m["score_comfort"] == 1.0


def test_an_at_fault_collision_zeroes_the_score():
    # the EV at 20 m/s drives into the back of a 10 m/s OV ahead in its lane; nothing else wrong
    m = episode_metrics(crashed(), dt=DT, truncated=False)
    assert m["collision_rate"] == 1.0 and m["at_fault_collision_rate"] == 1.0
    assert m["score"] == 0.0 and m["score_progress"] == m["score_speed"] == 1.0  # the parts are still measured


def test_leaving_the_road_zeroes_the_score():
    m = closed_loop_score(episode(offroad=[False] * 39 + [True]), DT, True)
    assert m["score"] == 0.0 and m["at_fault_collision_rate"] == 0.0 and m["score_ttc"] == 1.0


def test_rear_end_of_a_stopped_ev_is_not_its_fault_and_the_ev_rear_ending_a_stopped_ov_is():
    rear_ended = contact(rel_x=-4.9, ev_speed=0.0, ov_speed=8.0)  # an OV drives into the back of the stopped EV
    assert not contact_at_fault(rear_ended)
    m = closed_loop_score(crashed(**rear_ended), DT, False)
    assert m["at_fault_collision_rate"] == 0.0 and m["score"] == 1.0  # not the EV's fault: no gate
    # stopped, the EV is never at fault: not even where an OV cutting in meets its front corner
    assert not contact_at_fault(contact(rel_x=4.0, rel_y=1.5, ev_speed=0.0, ov_speed=5.0, rel_heading=-0.3))
    assert contact_at_fault(contact(rel_x=4.0, rel_y=1.5, ev_speed=0.5, ov_speed=5.0, rel_heading=-0.3))
    rear_ending = contact(rel_x=4.9, ev_speed=8.0, ov_speed=0.0)  # the EV drives into the back of a stopped OV
    assert contact_at_fault(rear_ending)
    assert closed_loop_score(crashed(**rear_ending), DT, False)["score"] == 0.0
    # passing a stopped OV too close, in lane: a side contact, and the EV's fault although it moves straight on
    assert contact_at_fault(contact(rel_x=0.5, rel_y=2.0, ev_speed=15.0, ov_speed=0.0, ev_lateral_speed=0.0))


def test_rear_end_by_a_faster_ov_while_driving_is_not_the_evs_fault():
    assert not contact_at_fault(contact(rel_x=-4.9, rel_y=0.3, ev_speed=15.0, ov_speed=20.0))
    # 45 deg off straight behind is not "behind" (a side contact): the EV keeps its lane, so not its fault either
    assert not contact_at_fault(contact(rel_x=-2.0, rel_y=2.0, ev_speed=15.0, ov_speed=20.0))
    # behind but not closing (the EV is faster: it cut in front of the OV and moved into it) is lateral
    assert contact_at_fault(contact(rel_x=-4.9, rel_y=1.0, ev_speed=20.0, ov_speed=15.0, ev_lateral_speed=1.0))


def test_a_moving_ev_hitting_a_vehicle_ahead_is_at_fault():
    assert contact_at_fault(contact(rel_x=4.9, rel_y=0.5, ev_speed=20.0, ov_speed=15.0))
    assert contact_at_fault(contact(rel_x=4.9, rel_y=0.0, ev_speed=20.0, ov_speed=25.0, rel_heading=0.2))


def test_lateral_contact_is_at_fault_when_the_ev_changes_lanes_into_the_ov():
    # the OV beside the EV on its left (y < 0: left, as the road's l); the EV moving left at 1 m/s
    assert contact_at_fault(contact(rel_x=1.0, rel_y=-2.0, ev_speed=20.0, ov_speed=20.0, ev_lateral_speed=-1.0))
    m = closed_loop_score(crashed(rel_x=1.0, rel_y=-2.0, ev_speed=20.0, ov_speed=20.0, ev_lateral_speed=-1.0),
                          DT, False)
    assert m["at_fault_collision_rate"] == 1.0 and m["score"] == 0.0
    # on its right, the EV moving right
    assert contact_at_fault(contact(rel_x=-1.0, rel_y=2.1, ev_speed=20.0, ov_speed=21.0, ev_lateral_speed=0.5))
    # the EV keeps its lane (swaying across it slower than 0.5 m/s) or moves away: the OV came across, not its fault
    assert not contact_at_fault(contact(rel_x=1.0, rel_y=-2.0, ev_speed=20.0, ov_speed=20.0, ev_lateral_speed=-0.4))
    assert not contact_at_fault(contact(rel_x=1.0, rel_y=-2.0, ev_speed=20.0, ov_speed=20.0, ev_lateral_speed=1.0))


def test_speeding_lowers_the_speed_term_by_the_formula():
    # 21 m/s under a 20 m/s limit throughout: 1 m/s over at every step
    m = closed_loop_score(episode(speed=21.0), DT, True)
    assert m["score_speed"] == pytest.approx(1.0 - 1.0 / OVERSPEED_BOUND)
    assert m["score_progress"] == 1.0  # faster than the limit is no more than all of the reachable progress
    assert m["score"] == pytest.approx(weighted(speed=1.0 - 1.0 / OVERSPEED_BOUND))
    # 2.23 m/s over for a quarter of the steps (the rest at the limit): the mean overspeed is a quarter of the bound
    speeds = [20.0] * 30 + [20.0 + OVERSPEED_BOUND] * 10
    m = closed_loop_score(episode(speed_limit=[20.0] * 40, speed=20.0) | {"speed": speeds}, DT, True)
    assert m["score_speed"] == pytest.approx(0.75)
    # far over: the term stops at 0
    assert closed_loop_score(episode(speed=30.0), DT, True)["score_speed"] == 0.0


def test_progress_against_driving_at_the_limit():
    # half the limit: half the reachable progress; s covers steps 2..n, and so does the reachable progress
    m = closed_loop_score(episode(speed=10.0, limit=20.0), DT, True)
    assert m["score_progress"] == pytest.approx(0.5) and m["score_speed"] == 1.0
    assert m["score"] == pytest.approx(weighted(progress=0.5))
    # a limit that changes: reachable = dt x (sum of the limits of steps 2..n)
    limits = [20.0] * 20 + [10.0] * 20
    m = closed_loop_score(episode(speed=10.0, speed_limit=limits), DT, True)
    assert m["score_progress"] == pytest.approx(39 * 10.0 / (19 * 20.0 + 20 * 10.0))


def test_time_to_collision_below_the_bound_at_one_step_zeroes_its_term():
    m = closed_loop_score(episode(ttc=[math.inf] * 20 + [0.9] + [math.inf] * 19), DT, True)
    assert m["score_ttc"] == 0.0 and m["score"] == pytest.approx(weighted(ttc=0.0))
    assert closed_loop_score(episode(ttc=[math.inf] * 20 + [0.95] + [5.0] * 19), DT, True)["score_ttc"] == 1.0
    # a stored trace writes inf as None (JSON): no OV closing
    assert closed_loop_score(episode(ttc=[None] * 40), DT, True)["score_ttc"] == 1.0


def test_comfort_lateral_acceleration_on_a_curve():
    # a constant curve at 20 m/s: lateral acceleration v^2 / R, the heading turning by v dt / R per step
    def curve(radius):
        return episode(heading=[20.0 * DT * k / radius for k in range(40)])

    assert 20.0 ** 2 / 50.0 > MAX_LAT_ACCEL > 20.0 ** 2 / 100.0
    assert closed_loop_score(curve(50.0), DT, True)["score_comfort"] == 0.0  # 8 m/s^2
    assert closed_loop_score(curve(100.0), DT, True)["score_comfort"] == 1.0  # 4 m/s^2
    m = closed_loop_score(curve(50.0), DT, True)
    assert m["score"] == pytest.approx(weighted(comfort=0.0))
    # headings as a simulator may wrap them (into [-pi, pi)): a gentle curve through pi is still gentle
    wrapped = [(3.0 + 20.0 * DT * k / 100.0 + math.pi) % (2 * math.pi) - math.pi for k in range(40)]
    assert max(wrapped) - min(wrapped) > math.pi  # it wraps
    assert closed_loop_score(episode(heading=wrapped), DT, True)["score_comfort"] == 1.0


def test_comfort_longitudinal_jerk():
    # a constant deceleration (speed linear in time) has no jerk, however hard; a sudden full brake from a cruise has
    ramp = [20.0 - 5.0 * DT * k for k in range(40)]
    s = [sum(ramp[1:k + 1]) * DT for k in range(40)]
    assert closed_loop_score(episode(speed=20.0) | {"speed": ramp, "s": s}, DT, True)["score_comfort"] == 1.0
    brake = [20.0] * 20 + [20.0 - 7.0 * DT * k for k in range(1, 21)]  # 0 to -7 m/s^2 in one step
    assert closed_loop_score(episode() | {"speed": brake}, DT, True)["score_comfort"] == 0.0
    gentle = [20.0] * 20 + [20.0 - 0.5 * DT * k for k in range(1, 21)]  # 0 to -0.5 m/s^2
    assert closed_loop_score(episode() | {"speed": gentle}, DT, True)["score_comfort"] == 1.0


def test_old_traces_give_none():
    old = episode()
    for key in ("contact", "speed_limit"):
        del old[key]
    m = episode_metrics(old, dt=DT, truncated=True)
    assert all(m[name] is None for name in SCORE_METRICS) and m["success_rate"] == 1.0
    # contact recorded but no speed_limit (an env without one): the attribution still, no score
    m = closed_loop_score(episode(speed_limit=[None] * 40), DT, True)
    assert m["at_fault_collision_rate"] == 0.0 and m["score"] is None and m["score_speed"] is None
    # a collision the env said nothing about: fault unknown, so no score
    silent = episode(collision=[False] * 39 + [True])
    assert at_fault_collision(silent) is None and closed_loop_score(silent, DT, True)["score"] is None


def test_summary_intervals_and_old_records():
    perfect = episode_metrics(episode(), dt=DT, truncated=True)
    slow = episode_metrics(episode(speed=10.0), dt=DT, truncated=True)
    at_fault = episode_metrics(crashed(), dt=DT, truncated=False)
    old = {k: v for k, v in perfect.items() if k not in SCORE_METRICS}  # a record from before the score
    records = [{"scenario": "s", "policy": "p", "status": "ok", "seed": i, "metrics": m}
               for i, m in enumerate([perfect, slow, at_fault, old])]
    e = summarize(records)["p/s"]
    assert e["episodes"] == 4
    assert e["at_fault_collision_rate"]["n"] == 3 and e["at_fault_collision_rate"]["k"] == 1  # Wilson, old left out
    score = e["score"]
    assert score["n"] == 3 and score["mean"] == pytest.approx((1.0 + weighted(progress=0.5) + 0.0) / 3)
    assert score["ci_low"] <= score["mean"] <= score["ci_high"] and "std" in score  # bootstrap of the mean


def test_a_goal_missed_at_the_time_limit_zeroes_the_score_and_a_goal_reached_or_a_collision_does_not():
    waited = episode(goal=[False] * 40)  # an env with a goal (two-way-overtake's pass): time ran out without it
    m = episode_metrics(waited, dt=DT, truncated=True)
    assert m["success_rate"] == 0.0 and m["score"] == 0.0
    assert m["score_progress"] == m["score_ttc"] == m["score_speed"] == m["score_comfort"] == 1.0  # still measured
    passed = episode(goal=[False] * 39 + [True])  # the goal ends the episode: terminated, not truncated
    assert episode_metrics(passed, dt=DT, truncated=False)["score"] == 1.0
    # rear-ended while waiting, before the goal: the collision gate judges it (not at fault), not the goal's
    hit = crashed(rel_x=-4.9, ev_speed=0.0, ov_speed=8.0) | {"goal": [False] * 40}
    assert episode_metrics(hit, dt=DT, truncated=False)["score"] == 1.0
    assert closed_loop_score(hit, DT, True)["score"] == 1.0  # a collision at the time limit's step as well
    # without a goal (None every step, as the families without one report) the time limit is the success
    assert episode_metrics(episode(goal=[None] * 40), dt=DT, truncated=True)["score"] == 1.0
    # a record of the waiting episode: the migration's reading of it agrees
    record = {"truncated": True, "metrics": m}
    assert record_missed_goal(record) and not record_missed_goal({"truncated": False, "metrics": m})
    assert not record_missed_goal({"truncated": True, "metrics": episode_metrics(episode(), dt=DT, truncated=True)})
