"""The gap plan of a mandatory lane change (bimp.envs.highway.gaps) and exit-v0's driver that executes it."""

import gymnasium as gym
import numpy as np
import pytest

import bimp.envs  # noqa: F401  (registers the envs)
from bimp.agents.registry import make_policy
from bimp.configs import ConfigError
from bimp.envs.highway.gaps import GapSearch, plan_gaps
from bimp.envs.highway.lanes import needed_lane

SEARCH = GapSearch()
WINDOW = (0.0, 95.0)  # exit-v0's exit lane, in its own frame


def test_on_an_empty_road_the_change_begins_at_once_and_arrives_in_the_window():
    plan = plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 3, WINDOW, np.zeros((0, 3)))
    assert plan is not None and plan.change
    # 250 m to the lane's start at no more than 30 m/s, and 3 changes of 2 s each: neither bound is beaten
    assert plan.arrival >= max(250.0 / SEARCH.top_speed, 3 * SEARCH.change_steps * SEARCH.step)


def test_a_vehicle_abreast_in_the_next_lane_holds_the_change_back():
    abreast = np.array([[1, -250.0, 25.0]])
    plan = plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 3, WINDOW, abreast)
    assert plan is not None and not plan.change  # it changes later, once past or behind the vehicle
    assert plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 3, WINDOW, np.zeros((0, 3))).change


def test_a_closed_lane_leaves_no_way_in():
    wall = np.array([[1, s, 25.0] for s in np.arange(-700.0, 200.0, 6.0)])  # bumper to bumper beside the EV
    assert plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 3, WINDOW, wall) is None


def test_past_the_window_out_of_the_goal_lane_the_goal_is_missed():
    assert plan_gaps(SEARCH, 120.0, 25.0, 2, 0, 3, WINDOW, np.zeros((0, 3))) is None


def test_a_change_under_way_arrives_by_the_steps_it_has_driven_sooner():
    open_now = (-400.0, 95.0)  # the goal lane open from here: the lane changes alone time the arrival
    settled = plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 3, open_now, np.zeros((0, 3)))
    under_way = plan_gaps(SEARCH, -250.0, 25.0, 0, 2, 3, open_now, np.zeros((0, 3)))
    assert settled.arrival == pytest.approx(3 * SEARCH.change_steps * SEARCH.step)
    assert under_way.arrival == pytest.approx(settled.arrival - 2 * SEARCH.step) and under_way.change


def test_the_goal_lane_is_reached_within_its_window_or_not_at_all():
    # the change's last step from 13 m before the window's end: at 30 m/s even braking overshoots it (14.5 m)
    assert plan_gaps(SEARCH, 82.0, 30.0, 2, 3, 3, WINDOW, np.zeros((0, 3))) is None
    assert plan_gaps(SEARCH, 82.0, 10.0, 2, 3, 3, WINDOW, np.zeros((0, 3))) is not None


def test_a_vehicle_beside_at_the_steps_start_is_not_cut_off():
    # 3 m behind the EV's centre in the next lane at 10 m/s: clear of it by the step's end, abreast at its start
    beside = np.array([[1, -253.0, 10.0]])
    assert not plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 1, (-400.0, 95.0), beside).change


def test_the_plan_never_closes_on_the_vehicle_ahead_faster_than_it_can_brake():
    # a slow vehicle 60 m ahead in the EV's own lane: the first step brakes or leaves the lane, never keeps on
    slow, open_lane = np.array([[0, -190.0, 9.0]]), (-400.0, 95.0)  # the goal lane open beside the EV
    plan = plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 1, open_lane, slow)
    assert plan is not None and (plan.accel < 0 or plan.change)
    # 30 m ahead it is too close to shed 16 m/s at the lattice's braking already: no plan, highway-env's driver brakes
    assert plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 1, open_lane, np.array([[0, -220.0, 9.0]])) is None


def test_bad_input_is_refused_naming_it():
    with pytest.raises(ConfigError, match="step"):
        GapSearch(step=0.0)
    with pytest.raises(ConfigError, match="change_steps"):
        GapSearch(change_steps=0)
    with pytest.raises(ConfigError, match="lag"):
        GapSearch(lag=-1.0)
    with pytest.raises(ValueError, match="phase0"):
        plan_gaps(SEARCH, 0.0, 20.0, 0, SEARCH.change_steps, 3, WINDOW, np.zeros((0, 3)))
    with pytest.raises(ValueError, match="goal lane"):
        plan_gaps(SEARCH, 0.0, 20.0, 3, 1, 3, WINDOW, np.zeros((0, 3)))


def test_the_needed_lane_is_the_one_the_route_goes_on_from():
    env = gym.make("bimp/exit-v0")
    env.reset(seed=0)
    network = env.unwrapped.road.network
    assert needed_lane(network, [("0", "1", 0), ("1", "2", None), ("2", "exit", None)], 0) == ("1", "2", 6)
    # on to road ("2", "3") every lane but the exit lane goes on: the EV's own lane does, and so none is needed
    assert needed_lane(network, [("0", "1", 0), ("1", "2", None), ("2", "3", None)], 0) is None
    assert needed_lane(network, [("1", "2", 6), ("2", "3", None)], 6) == ("1", "2", 5)  # out of the exit lane


def test_exit_v0_success_is_highway_envs_own_and_the_driver_reaches_the_exit_lane():
    """highway-env's driver executing the gap plan (the ``idm`` baseline) on a development seed: in the exit lane,
    which is highway-env's ``is_success``, with no collision; without the plan it never left lane 0 (every policy,
    seeds 1000-1099)."""
    env = gym.make("bimp/exit-v0")
    obs, info = env.reset(seed=3)
    policy = make_policy("idm", env)
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        done = terminated or truncated
    assert info["goal"] and info["is_success"] and not info["collision"]
    assert env.unwrapped.vehicle.lane_index in (("1", "2", 6), ("2", "exit", 0))


def test_the_plan_is_remade_every_lattice_step_and_leaves_mobils_timer_to_mobil(monkeypatch):
    from bimp.envs.highway import behaviour

    calls = []
    monkeypatch.setattr(behaviour, "plan_gaps", lambda *a: calls.append(a) or None)  # no plan: MOBIL decides
    env = gym.make("bimp/exit-v0")
    env.reset(seed=0)
    adapter = env
    while not hasattr(adapter, "behaviour"):
        adapter = adapter.env
    shadow = adapter.behaviour.shadow
    before, timers = len(calls), [shadow.timer]
    for _ in range(15):
        adapter.behaviour.decide(0.1)
        timers.append(shadow.timer)
    assert len(calls) - before == 3  # at 0.5, 1.0 and 1.5 s (the reset's decision made the first)
    # MOBIL's timer ran up to its delay and MOBIL, deciding (past it, within a step), reset it: the planning left
    # MOBIL's clock alone (with the clock shared, the timer went back to 0 every 0.5 s and MOBIL never decided)
    peak = max(range(len(timers)), key=timers.__getitem__)
    assert timers[peak] > shadow.LANE_CHANGE_DELAY - 0.05 and min(timers[peak:]) < 0.2


def test_the_plan_runs_up_to_the_behaviour_layers_target_speed(monkeypatch):
    from bimp.envs.highway import behaviour

    searches = []
    monkeypatch.setattr(behaviour, "plan_gaps", lambda search, *a: searches.append(search) or None)
    env = gym.make("bimp/exit-v0")
    env.reset(seed=0)
    behaviour.Behaviour(env.unwrapped, 20.0, drive_on=True, gap_plan=True).decide(0.0)
    assert searches[-1].top_speed == 20.0


def test_the_profile_records_the_gap_plan_only_where_it_is_set():
    assert "gap_plan" not in gym.make("bimp/highway-fast-v0").unwrapped.BEHAVIOUR.profile
    assert "('gap_plan', True)" in gym.make("bimp/exit-v0").unwrapped.BEHAVIOUR.profile


def test_the_plan_reports_where_it_holds_the_ev_at_the_lookahead():
    """``GapPlan.ahead``: the place across the lanes the plan holds the EV at ``lookahead`` s (2 s: one change of
    four 0.5 s steps), a fraction mid-change; the goal lane where it arrives sooner."""
    open_now = (-400.0, 95.0)
    assert plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 3, open_now, np.zeros((0, 3))).ahead == pytest.approx(1.0)
    assert plan_gaps(SEARCH, -250.0, 25.0, 0, 2, 3, open_now, np.zeros((0, 3))).ahead == pytest.approx(1.5)
    assert plan_gaps(SEARCH, -250.0, 25.0, 2, 2, 3, open_now, np.zeros((0, 3))).ahead == pytest.approx(3.0)
    abreast = np.array([[1, -250.0, 25.0]])  # the change held back: less far across at the lookahead
    assert plan_gaps(SEARCH, -250.0, 25.0, 0, 0, 3, open_now, abreast).ahead < 1.0


def _adapter(env):
    while not hasattr(env, "behaviour"):
        env = env.env
    return env


def test_on_exit_v0_the_reference_leads_where_the_plan_holds_the_ev_in_2_s():
    env = gym.make("bimp/exit-v0")
    obs, _ = env.reset(seed=0)
    adapter = _adapter(env)
    scene, shadow = env.unwrapped.scene, adapter.behaviour.shadow
    assert scene.lane_path and not gym.make("bimp/highway-fast-v0").unwrapped.scene.lane_path
    assert shadow.plan is not None and shadow.plan.ahead > 0.0  # on its way right from lane 0
    lead = shadow.lead_point()
    l_ref = float(scene.split_obs(obs)[3][2])
    assert l_ref == pytest.approx(float(scene.road.project(lead[None]).l[0]), abs=1e-6)
    assert l_ref > 0.5 * shadow.plan.ahead * 4.0  # further across than the EV's own lane


def test_enkts_reaches_exit_v0s_exit_lane():
    """EnKTS on the reference that leads through the lanes and with its path's heading (development seed 1): in the
    exit lane within the episode, no collision; on the reference of the next lane alone it reached lane 3 of 6."""
    env = gym.make("bimp/exit-v0")
    obs, info = env.reset(seed=1)
    policy = make_policy("enkts", env)
    policy.reset(1)
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        done = terminated or truncated
    assert info["goal"] and not info["collision"] and not info["offroad"]


def test_a_lookahead_off_the_lattice_and_a_lane_path_without_a_gap_plan_are_refused():
    with pytest.raises(ConfigError, match="lookahead"):
        GapSearch(lookahead=1.2)
    from bimp.envs.highway.profiles import PROFILES, Profile

    exit_ = PROFILES["exit-v0"]
    with pytest.raises(ValueError, match="gap_plan"):
        Profile(exit_.bounds, exit_.actuator_steer, exit_.target_speed, exit_.duration, lane_path=True)
