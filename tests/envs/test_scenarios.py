import gymnasium as gym
import numpy as np
import pytest
from gymnasium.error import ResetNeeded
from gymnasium.utils.env_checker import check_env

from bimp import envs
from bimp.agents.baselines import LaneKeeping
from bimp.envs.scenarios import MAX_GAP, MAX_SPEED, MIN_CENTRE_GAP, REFERENCE_COLOUR
from bimp.envs.scene import ACTUATOR_ACCEL, ACTUATOR_STEER, DT

# The paper's envs (the wrapped highway-env ids have their own tests: tests/envs/test_highway.py).
IDS = [s.id for s in envs.SCENARIOS.values() if s.entry_point.startswith("bimp.envs.scenarios:")]


def rollout(env, actions, seed):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, *_ = env.step(a)
        out.append(obs)
    return np.array(out)


@pytest.mark.parametrize("env_id", IDS)
def test_check_env_passes(env_id):
    check_env(gym.make(env_id).unwrapped, skip_render_check=False)


@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_same_observations_different_seed_differs(env_id):
    actions = np.random.default_rng(0).uniform(-0.1, 0.1, size=(50, 2))
    env = gym.make(env_id, config={"ov1_gap": 300.0, "ov2_gap": 320.0})
    a, b = rollout(env, actions, 3), rollout(env, actions, 3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, rollout(env, actions, 4))


def test_constant_action_follows_kinematic_bicycle():
    env = gym.make("bimp/EmergencyBrake-v0", config={"ov1_gap": 300.0, "ov2_gap": 320.0})
    obs, _ = env.reset(seed=0)
    # Toward the left lane: on the road for all 40 steps (a terminated episode can no longer be stepped).
    action = np.array([-0.1, -0.005])
    a, delta = env.unwrapped.scene.to_physical(action)
    x, y, h, v = obs[:4].astype(float)
    dt, half = 0.1, 2.5
    for _ in range(40):
        obs, *_ = env.step(action)
        beta = np.arctan(0.5 * np.tan(delta))
        x, y = x + v * np.cos(h + beta) * dt, y + v * np.sin(h + beta) * dt
        h, v = h + v * np.sin(beta) / half * dt, max(v + a * dt, 0.0)
        np.testing.assert_allclose(obs[:4], [x, y, h, v], rtol=1e-5, atol=1e-3)


def test_speed_never_negative_under_full_braking():
    env = gym.make("bimp/EmergencyBrake-v0", config={"ov1_gap": 300.0, "ov2_gap": 320.0})
    env.reset(seed=0)
    speeds = [env.step(np.array([-1.0, 0.0]))[0][3] for _ in range(40)]
    assert min(speeds) == 0.0 and speeds[-1] == 0.0


def test_overtaking_ovs_slower_than_ev_and_hold_lanes():
    env = gym.make("bimp/Overtaking-v0")
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        scene = env.unwrapped.scene
        ego, _, ovs, ref = scene.split_obs(obs)
        assert np.all(ovs[:, 4] < ego[3])
        # The behaviour layer passes at the EV's speed, or first follows OV1 at its speed (too close to pass).
        passing = ref[2] != scene.geometry.lane_offset(1)
        assert ref[0] == pytest.approx(ego[3] if passing else ovs[0, 4], rel=1e-6)
        lanes = scene.geometry.lane_offset(np.array([1, 0]))
        for _ in range(100):  # the EV idles behind: steer straight, brake gently; OVs must not care
            obs, _, term, _, _ = env.step(np.array([-0.3, 0.0]))
            _, _, ovs2, _ = scene.split_obs(obs)
            _, lat = scene.geometry.to_frenet(ovs2[:, 1:3])
            np.testing.assert_allclose(lat, lanes, atol=0.15)
            np.testing.assert_allclose(ovs2[:, 4], ovs[:, 4], atol=1e-6)
            if term:
                break


def test_emergency_brake_ovs_stop_and_reference_falls_to_zero_by_step_80():
    env = gym.make("bimp/EmergencyBrake-v0")
    obs, _ = env.reset(seed=1)
    scene = env.unwrapped.scene
    cruise = scene.split_obs(obs)[3][0]
    refs, ov_speeds = [], []
    for _ in range(120):
        obs, _, term, trunc, _ = env.step(np.array([-0.5, 0.0]))
        _, _, ovs, ref = scene.split_obs(obs)
        refs.append(ref[0])
        ov_speeds.append(ovs[:, 4])
        if term or trunc:
            break
    refs = np.array(refs)
    assert len(refs) == 120, "gentle braking from far behind must not end the episode"
    np.testing.assert_allclose(refs[:29], cruise)  # steps 1..29: t < 3 s
    assert np.all(np.diff(refs) <= 1e-9)
    np.testing.assert_array_equal(refs[79:], 0.0)  # step 80 onward
    assert refs[78] > 0
    np.testing.assert_array_equal(np.array(ov_speeds)[-1], [0.0, 0.0])


def test_driving_into_an_ov_sets_collision_and_terminates():
    env = gym.make("bimp/Overtaking-v0")
    env.reset(seed=0)
    for _ in range(100):
        _, reward, term, _, info = env.step(np.array([0.3, 0.0]))
        if term:
            break
    assert term and info["collision"] and not info["offroad"] and reward < -10


def test_steering_off_the_road_sets_offroad_and_terminates():
    env = gym.make("bimp/EmergencyBrake-v0", config={"ov1_gap": 300.0, "ov2_gap": 320.0})
    env.reset(seed=0)
    for _ in range(60):
        _, _, term, _, info = env.step(np.array([0.0, 0.2]))
        if term:
            break
    assert term and info["offroad"] and info["edge_distance"] < 0 and not info["collision"]


def test_config_fixes_parameters_and_rejects_typos():
    env = gym.make("bimp/Overtaking-v0", config={"ov1_speed": 16.0, "radius": 250.0})
    obs, _ = env.reset(seed=0)
    assert env.unwrapped.scene.geometry.radius == 250.0
    assert env.unwrapped.scene.split_obs(obs)[2][0, 4] == pytest.approx(16.0)
    with pytest.raises(ValueError, match="ov1_sped"):
        gym.make("bimp/Overtaking-v0", config={"ov1_sped": 16.0})
    with pytest.raises(ValueError, match="brake_decel"):
        env.reset(options={"config": {"brake_decel": 5.0}})  # an emergency-brake key on overtaking
    with pytest.raises(ValueError, match="range"):
        gym.make("bimp/Overtaking-v0", config={"radius": (1.0, 2.0, 3.0)})


def test_actions_are_clipped_and_non_finite_actions_raise():
    env = gym.make("bimp/EmergencyBrake-v0")
    env.reset(seed=0)
    big = env.step(np.array([5.0, -3.0]))[4]["input"]
    env.reset(seed=0)
    unit = env.step(np.array([1.0, -1.0]))[4]["input"]
    assert big == unit == [10.0, -0.3]
    for bad in (np.array([np.nan, 0.0]), np.array([0.0, np.inf])):
        with pytest.raises(ValueError, match="finite"):
            env.step(bad)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))


@pytest.mark.parametrize("env_id", IDS)
def test_rgb_array_render(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(env.action_space.sample())
    frame = env.render()
    config = env.unwrapped.config  # the paper's 800 x 240; a wrapped highway-env env's own size
    assert frame.shape == (config["screen_height"], config["screen_width"], 3)
    assert frame.dtype == np.uint8 and frame.std() > 0
    if env_id in envs.ENV_IDS.values():
        assert frame.shape == (240, 800, 3)


def test_the_frame_draws_the_reference_lane():
    """Videos show the behaviour layer's lane: at the start it names the left lane (OV1 slower, the left lane free),
    the keep-lane variant the EV's own, one lane width apart on the frame."""
    rows = {}
    for reference in ("behaviour", "keep-lane"):
        env = gym.make("bimp/Overtaking-v0", render_mode="rgb_array", config={"reference": reference})
        env.reset(seed=0)
        drawn = np.all(env.render() == REFERENCE_COLOUR, axis=-1)
        assert drawn.sum() > 100
        rows[reference] = np.nonzero(drawn)[0].mean()
    lane_px = env.unwrapped.config["scaling"] * env.unwrapped.scene.geometry.lane_width
    assert rows["keep-lane"] - rows["behaviour"] == pytest.approx(lane_px, abs=2)


def test_the_scene_defines_the_vehicle_that_highway_env_simulates():
    """bimp.envs.scene holds the vehicle and actuator numbers once, so that the vehicle models read them without
    loading highway-env: they must be highway-env's and the env's own."""
    from highway_env.vehicle.kinematics import Vehicle

    env = gym.make("bimp/Overtaking-v0")
    env.reset(seed=0)
    scene, action = env.unwrapped.scene, env.unwrapped.action_type
    assert (scene.vehicle_length, scene.vehicle_width, MAX_SPEED) == (Vehicle.LENGTH, Vehicle.WIDTH, Vehicle.MAX_SPEED)
    assert scene.dt == DT and type(env.unwrapped.vehicle).MAX_SPEED == MAX_SPEED
    assert tuple(action.acceleration_range) == ACTUATOR_ACCEL and tuple(action.steering_range) == ACTUATOR_STEER


def test_info_carries_safety_quantities_and_constraints():
    env = gym.make("bimp/Overtaking-v0")
    env.reset(seed=0)
    info = env.step(np.array([0.0, 0.0]))[4]
    for key in ("collision", "offroad", "ov_distance", "edge_distance", "ttc", "reference", "constraints"):
        assert key in info
    assert len(info["ov_distance"]) == 2 and info["ttc"] > 0
    c = info["constraints"]
    assert c["accel_rate"] == pytest.approx(-1.0)  # input 0 after input 0: rate 0, bound 1
    assert c["road_edge"] == pytest.approx(-info["edge_distance"])


def test_braking_hard_at_the_onset_is_enough_on_every_seed():
    """The emergency brake's parameter ranges leave a safe solution: brake at a_min when the OV brakes."""

    class BrakeWhenTheyBrake(LaneKeeping):
        braking = False

        def act(self, obs):
            scene = self.env.unwrapped.scene
            action = super().act(obs)
            self.braking |= scene.split_obs(obs)[2][:, 5].min() < -1.0
            if self.braking:
                action[0] = scene.to_normalized([scene.bounds.accel[0], 0.0])[0]
            return action

    env = gym.make("bimp/EmergencyBrake-v0", config={"ev_speed": 27.0, "ov1_gap": 40.0, "ov_speed": 20.0,
                                                     "brake_decel": 7.0})
    policy = BrakeWhenTheyBrake(env)
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        policy.braking, done = False, False
        while not done:
            obs, _, term, trunc, info = env.step(policy.act(obs))
            done = term or trunc
        assert not info["collision"] and not info["offroad"] and obs[3] == 0.0


def test_keep_lane_variant_is_overtaking_with_the_lane_kept_as_reference():
    variant = gym.make(envs.env_id("overtaking-keep-lane"))
    base = gym.make("bimp/Overtaking-v0", config={"reference": "keep-lane"})
    behaviour = gym.make("bimp/Overtaking-v0")
    (obs_v, _), (obs_b, _), (obs_p, _) = (e.reset(seed=2000) for e in (variant, base, behaviour))
    np.testing.assert_array_equal(obs_v, obs_b)  # the same draws, the same reference
    road = variant.unwrapped.scene.geometry
    assert obs_v[-1] == pytest.approx(road.lane_offset(1))  # the EV's own (right) lane
    assert obs_p[-1] != obs_v[-1]  # here the behaviour layer asks for the pass at once
    switched = gym.make(envs.env_id("overtaking-keep-lane"), config={"reference": "behaviour"})
    np.testing.assert_array_equal(switched.reset(seed=2000)[0], obs_p)
    with pytest.raises(ValueError, match="unknown scenario"):
        envs.env_id("overtaking-keep-left")


def test_stepping_a_terminated_episode_raises_until_reset():
    """The env kept simulating after a collision, with no warning; the check is in the env, so env.unwrapped
    (no gym.make wrappers) has it too."""
    made = gym.make("bimp/Overtaking-v0")
    for env in (made, made.unwrapped):
        env.reset(seed=0)
        term = False
        for _ in range(100):
            _, _, term, _, info = env.step(np.array([0.3, 0.0]))
            if term:
                break
        assert term and info["collision"]
        with pytest.raises(ResetNeeded, match="reset"):
            env.step(np.array([0.0, 0.0]))
        env.reset(seed=0)
        env.step(np.array([0.0, 0.0]))  # a new episode steps again


def test_the_largest_accepted_gaps_keep_the_observation_inside_its_space():
    """ov2_gap = 1e9 was accepted and the observation left observation_space."""
    with pytest.raises(ValueError, match="ov2_gap"):
        gym.make("bimp/Overtaking-v0", config={"ov2_gap": 1e9})
    with pytest.raises(ValueError, match="ov1_gap"):
        gym.make("bimp/EmergencyBrake-v0", config={"ov1_gap": MAX_GAP + 1.0})
    fastest = {"ev_speed": MAX_SPEED, "ov1_speed": MAX_SPEED - 1.0, "ov2_speed": MAX_SPEED,
               "ov1_gap": MAX_GAP - MIN_CENTRE_GAP, "ov2_gap": MAX_GAP}
    env = gym.make("bimp/Overtaking-v0", config=fastest)
    obs, _ = env.reset(seed=0)
    done, observations = False, [obs]
    while not done:  # the whole episode: the OVs drive on at up to MAX_SPEED
        obs, _, term, trunc, _ = env.step(np.array([0.0, 0.0]))
        observations.append(obs)
        done = term or trunc
    assert all(env.observation_space.contains(o) for o in observations)
    env = gym.make("bimp/EmergencyBrake-v0", config={"ov1_gap": MAX_GAP, "ov2_gap": MAX_GAP})
    assert env.observation_space.contains(env.reset(seed=0)[0])


@pytest.mark.parametrize("config", ["x", [("ov1_gap", 30.0)], 3])
def test_a_config_that_is_not_a_mapping_is_named(config):
    with pytest.raises(ValueError, match="config must be a mapping"):
        gym.make("bimp/Overtaking-v0", config=config)
    env = gym.make("bimp/Overtaking-v0")
    with pytest.raises(ValueError, match="config must be a mapping"):
        env.reset(options={"config": config})
