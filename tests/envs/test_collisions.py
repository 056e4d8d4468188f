"""Collision semantics: ``info["collision"]`` is footprint overlap on the simulated state, nothing else."""

import gymnasium as gym
import numpy as np
import pytest
from highway_env import utils

from bimp import envs  # noqa: F401  (registers the ids)

L, W = 5.0, 2.0
FAR = {"ov1_gap": 300.0, "ov2_gap": 320.0}


def polygons_intersect(a, b) -> bool:
    """highway-env's own separating-axis test on the vehicles' polygons (an independent overlap check)."""
    return bool(utils.are_polygons_intersecting(a.polygon(), b.polygon(), np.zeros(2), np.zeros(2))[0])


def drive(env_id, config, actions, seed=0):
    """Steps ``actions`` until termination; per step the info, whether highway-env's polygons of the EV and each OV
    intersect, and the EV/OV states. Returns lists."""
    env = gym.make(env_id, config=config)
    env.reset(seed=seed)
    base = env.unwrapped
    infos, overlaps, ev_states, ov_states = [], [], [], []
    for a in actions:
        _, _, term, _, info = env.step(np.asarray(a, float))
        infos.append(info)
        overlaps.append([polygons_intersect(base.vehicle, ov) for ov in base.obstacles])
        ev_states.append([*base.vehicle.position, base.vehicle.heading, base.vehicle.speed])
        ov_states.append([[*ov.position, ov.heading, ov.speed] for ov in base.obstacles])
        if term:
            break
    return infos, np.array(overlaps), np.array(ev_states), np.array(ov_states)


def assert_collision_is_overlap(infos, overlaps):
    for k, (info, hit) in enumerate(zip(infos, overlaps)):
        gap = min(info["ov_distance"])
        assert info["collision"] == (gap <= 0.0), f"step {k}: collision {info['collision']} but gap {gap}"
        assert info["collision"] == bool(hit.any()), f"step {k}: collision {info['collision']}, polygons {hit}"


def test_full_throttle_into_ov1_collides_on_the_first_overlapping_step_without_being_pushed():
    config = {"ev_speed": 25.0, "ov1_gap": 30.0, "ov1_speed": 15.0, "ov2_gap": 110.0, "ov2_speed": 18.0,
              "radius": 200.0, "arc_angle_deg": 60.0}
    actions = [[1.0, 0.0]] * 60
    infos, overlaps, ev, ov = drive("bimp/Overtaking-v0", config, actions)
    assert_collision_is_overlap(infos, overlaps)
    assert infos[-1]["collision"] and sum(i["collision"] for i in infos) == 1  # terminates on the first one
    assert min(infos[-2]["ov_distance"]) > 0
    # Penetration, not a contact pushed back to exactly 0 (highway-env's impact impulse did that).
    assert infos[-1]["ov_distance"][0] < -0.1
    # Nothing moved anyone: the same actions with the OVs far away give the same EV states, and the OVs' motion
    # does not depend on the EV.
    _, _, far_ev, _ = drive("bimp/Overtaking-v0", {**config, **FAR}, actions[:len(infos)])
    np.testing.assert_array_equal(ev, far_ev)
    _, _, _, ov_idle = drive("bimp/Overtaking-v0", config, [[-0.2, 0.0]] * len(infos))
    np.testing.assert_array_equal(ov, ov_idle)


def test_steering_into_the_ov_in_the_other_lane_is_a_collision_of_turned_footprints():
    config = {"ev_speed": 25.0, "ov_speed": 20.0, "ov1_gap": 300.0, "ov2_gap": 8.0, "brake_onset": 100.0}
    infos, overlaps, ev, _ = drive("bimp/EmergencyBrake-v0", config, [[0.0, -0.05]] * 40)
    assert_collision_is_overlap(infos, overlaps)
    assert infos[-1]["collision"] and not infos[-1]["offroad"]
    assert abs(ev[-1, 2]) > 0.05  # the EV is turned: road-aligned boxes would not be exact here
    assert infos[-1]["ov_distance"][1] <= 0 < min(infos[-2]["ov_distance"])


@pytest.mark.parametrize("brake_step, touches", [(26, False), (27, True)])
def test_a_near_miss_is_not_a_collision_and_touching_is(brake_step, touches):
    """Closing at 5 m/s on OV1, full braking from ``brake_step``: 0.5 m short of it, or exactly touching."""
    config = {"ev_speed": 25.0, "ov_speed": 20.0, "ov1_gap": 20.0, "ov2_gap": 300.0, "brake_onset": 100.0}
    actions = [[0.0, 0.0]] * brake_step + [[-1.0, 0.0]] * 30
    infos, overlaps, _, _ = drive("bimp/EmergencyBrake-v0", config, actions)
    assert_collision_is_overlap(infos, overlaps)
    closest = min(min(i["ov_distance"]) for i in infos)
    if touches:
        assert infos[-1]["collision"] and closest == pytest.approx(0.0, abs=1e-9)
    else:
        assert len(infos) == len(actions) and not any(i["collision"] for i in infos)
        assert 0.0 < closest < 0.6


def test_contact_is_checked_at_every_simulation_step():
    """At 20 Hz simulation / 10 Hz policy the policy step ends at the first overlapping simulation step."""
    env = gym.make("bimp/Overtaking-v0", config={"ev_speed": 25.0, "ov1_gap": 30.0, "ov1_speed": 15.0,
                                                 "simulation_frequency": 20})
    env.reset(seed=0)
    base = env.unwrapped
    substep_gaps, road_step = [], base.road.step

    def logged_step(dt):
        road_step(dt)
        ev = base.vehicle
        substep_gaps.append(base.scene.ov_gaps(np.array([*ev.position, ev.heading, ev.speed]), base._ov_rows()).min())

    base.road.step = logged_step
    for n in range(1, 60):
        _, _, term, _, info = env.step(np.array([1.0, 0.0]))
        assert info["collision"] == (min(info["ov_distance"]) <= 0)
        if term:
            break
    assert info["collision"]
    first = int(np.argmax(np.array(substep_gaps) <= 0))
    assert first == len(substep_gaps) - 1 and info["ov_distance"][0] == substep_gaps[-1]
    assert base.time == pytest.approx(len(substep_gaps) / 20)


def test_crashed_vehicles_keep_their_dynamics_and_are_drawn_crashed():
    config = {"ev_speed": 25.0, "ov1_gap": 30.0, "ov1_speed": 15.0}
    env = gym.make("bimp/Overtaking-v0", config=config).unwrapped
    env.reset(seed=0)
    while not env.step(np.array([1.0, 0.0]))[4]["collision"]:
        pass
    ov1, ev = env.obstacles[0], env.vehicle
    assert ev.crashed and ov1.crashed and not env.obstacles[1].crashed
    v_ev, v_ov = ev.speed, ov1.speed
    env._ended = False  # step on past the termination (which the env refuses) to see the motion after contact
    env.step(np.array([0.5, 0.0]))  # highway-env would brake both to a stop and steer them straight
    assert ev.speed == pytest.approx(v_ev + 0.5) and ov1.speed == pytest.approx(v_ov)


def test_ov_contact_does_not_push_the_ovs():
    env = gym.make("bimp/EmergencyBrake-v0", config={**FAR, "brake_onset": 100.0, "ov_speed": 20.0}).unwrapped
    env.reset(seed=0)
    ov1, ov2 = env.obstacles
    ov2.position = ov1.position + np.array([3.0, 0.0])  # overlapping OV1, same lane and speed
    ov2.target_lane_index = ov1.target_lane_index
    start = np.array([ov1.position, ov2.position])
    for k in range(1, 6):
        info = env.step(np.array([-0.3, 0.0]))[4]
        np.testing.assert_allclose([ov1.position, ov2.position], start + [[2.0 * k, 0.0]] * 2, atol=1e-9)
        assert not info["collision"] and not ov1.crashed and not ov2.crashed
