"""highway-env's IDM + MOBIL driver as the ``idm`` policy (issue 26 item 4), on every supported id."""

from __future__ import annotations

import gymnasium as gym
import highway_env  # noqa: F401  (registers highway-env's ids)
import numpy as np
import pytest

import bimp  # noqa: F401  (registers bimp/ID)
from bimp import make_policy
from bimp.envs.highway.adapter import SUPPORTED

pytestmark = pytest.mark.filterwarnings("ignore")


@pytest.mark.parametrize("highway_id", SUPPORTED)
def test_short_seeded_episode(highway_id):
    env = gym.make(f"bimp/{highway_id}")
    policy = make_policy("idm", env)
    obs, _ = env.reset(seed=1)
    policy.reset(1)
    for _ in range(30):
        action = policy.act(obs)
        assert action.shape == (2,) and action.dtype == np.float32
        assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
        obs, _, terminated, truncated, info = env.step(action)
        assert np.all(np.isfinite(obs))
        if terminated or truncated:
            break


def test_same_observation_and_seed_same_action():
    envs = [gym.make("bimp/highway-fast-v0") for _ in range(2)]
    policies = [make_policy("idm", env) for env in envs]
    observations = [env.reset(seed=5)[0] for env in envs]
    for _ in range(10):
        actions = [policy.act(obs) for policy, obs in zip(policies, observations)]
        np.testing.assert_array_equal(observations[0], observations[1])
        np.testing.assert_array_equal(actions[0], actions[1])
        observations = [env.step(action)[0] for env, action in zip(envs, actions)]


@pytest.mark.parametrize("make_env", [
    lambda: gym.make("highway-v0"),                                                 # raw highway-env
    lambda: gym.make("highway-v0", config={"action": {"type": "DiscreteMetaAction"}}),  # discrete actions
    lambda: gym.make("CartPole-v1"),                                                # another package
])
@pytest.mark.parametrize("name", ["idm", "lane-keep"])
def test_refuses_an_env_that_is_not_bimp(make_env, name):
    with pytest.raises(ValueError, match=r"bimp.envs.wrap"):
        make_policy(name, make_env())


def test_clip_to_bounds():
    env = gym.make("bimp/intersection-v0")
    policy = make_policy("idm", env, clip_to_bounds=True)
    obs, _ = env.reset(seed=0)
    scene = env.unwrapped.scene
    u = scene.to_physical(policy.act(obs))
    assert scene.bounds.accel[0] - 1e-6 <= u[0] <= scene.bounds.accel[1] + 1e-6
    assert abs(u[1]) <= scene.bounds.steer + 1e-6
