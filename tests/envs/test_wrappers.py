"""The planning-features view of the envs that the RL baseline trains and acts through."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs
from bimp.envs.scene import bound_constraints
from bimp.envs.wrappers import features, n_features, to_env_action, to_physical


@pytest.fixture
def overtaking():
    env = gym.make(envs.env_id("overtaking"))
    yield env
    env.close()


def test_features_are_ego_relative_and_scaled(overtaking):
    # keep-lane: the reference at reset is the EV's own lane (the behaviour layer may already name the other)
    obs, _ = overtaking.reset(seed=0, options={"config": {"reference": "keep-lane"}})
    scene = overtaking.unwrapped.scene
    f = features(obs, scene)
    assert f.shape == (n_features(scene),) and f.dtype == np.float32
    assert np.all(np.abs(f) <= 5.0)
    # At reset the EV sits on its reference lane, along the road, at the reference speed, no previous input.
    np.testing.assert_allclose(f[[0, 2, 3, 7, 8]], 0.0, atol=1e-5)
    # OV1 is ahead in the same lane, OV2 ahead one lane to the left.
    ov1, ov2 = f[11:16], f[16:21]
    assert ov1[0] == 1 and ov1[1] > 0 and abs(ov1[2]) < 1e-5
    assert ov2[0] == 1 and ov2[1] > ov1[1] and ov2[2] == pytest.approx(-1.0, abs=1e-4)  # the polyline road: 0.1 mm


def test_an_oncoming_ov_closes_at_both_speeds_and_traffic_our_way_at_the_difference():
    """On a two-way road a speed is a magnitude: without the road's direction an oncoming car at 23 m/s read as one
    driving our way at our speed (relative speed 0), and every RL policy drove into the overtake blind."""
    env = gym.make(envs.env_id("two-way-overtake-hard"))
    obs, _ = env.reset(seed=3000)
    scene = env.unwrapped.scene
    ego, _, ovs, _ = scene.split_obs(obs)
    f = features(obs, scene)[11:].reshape(scene.n_obstacles, 5)
    road = scene.road.project(ovs[:, 1:3])
    against = np.cos(ovs[:, 3] - road.heading) < 0
    present = ovs[:, 0] > 0
    assert np.any(present & against) and np.any(present & ~against)  # oncoming traffic and the car ahead
    expected = np.clip(np.where(against, -ovs[:, 4], ovs[:, 4]) - ego[3], -50, 50) / 10
    np.testing.assert_allclose(f[present, 3], expected[present], atol=1e-5)
    assert np.all(f[present & against, 3] < -ego[3] / 10)  # closing faster than the EV drives
    np.testing.assert_allclose(f[present, 4], np.clip(np.where(against, -ovs[:, 5], ovs[:, 5]), -35, 35)[present] / 7,
                               atol=1e-6)
    env.close()


def test_actions_map_inside_the_planning_bounds(overtaking):
    obs, _ = overtaking.reset(seed=0)
    scene = overtaking.unwrapped.scene
    b, rng = scene.bounds, np.random.default_rng(0)
    for _ in range(200):
        obs = obs.copy()
        obs[4:6] = [rng.uniform(*b.accel), rng.uniform(-b.steer, b.steer)]  # previous input
        u = to_physical(rng.uniform(-1.5, 1.5, 2), obs, scene)
        c = bound_constraints(b, u, u - scene.split_obs(obs)[1])  # eq. 4-5 as the env reports them
        assert c[:3].max() <= 1e-9 and c[3:].max() <= 1e-6
        a = to_env_action(rng.uniform(-1, 1, 2), obs, scene)
        assert a.dtype == np.float32 and overtaking.action_space.contains(a)
    # 0 means coast straight on; +-1 reach the bounds when the rate allows.
    obs[4:6] = 0.0
    np.testing.assert_allclose(to_physical(np.zeros(2), obs, scene), 0.0)
    obs[4:6] = [b.accel[1], b.steer]
    np.testing.assert_allclose(to_physical(np.ones(2), obs, scene), [b.accel[1], b.steer])
