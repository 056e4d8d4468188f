import gymnasium as gym
import numpy as np
import pytest

from bimp import envs
from bimp.agents.baselines import LaneKeeping
from bimp.agents.rollout import episode_seeds, rollout, rollout_batch


class Recorder(LaneKeeping):
    """Lane keeping that draws from its own generator, as a planner does, and keeps the draws."""

    def reset(self, seed=None):
        self.seed = seed
        self.draws = np.random.default_rng(seed).random(8)


@pytest.fixture
def env():
    e = gym.make(envs.env_id("emergency-brake"))
    yield e
    e.close()


def test_episode_seeds_are_independent_streams_of_one_seed():
    a, b = episode_seeds(7)
    assert a != b and (a, b) == episode_seeds(7) and episode_seeds(8) != (a, b)
    assert 0 <= a < 2 ** 63 and 0 <= b < 2 ** 63
    for bad in (-1, 1.5, True, "3"):
        with pytest.raises(ValueError, match="seed"):
            episode_seeds(bad)


def test_env_draws_and_policy_draws_differ_for_the_same_episode_seed(env):
    policy = Recorder(env)
    episode = rollout(env, policy, 7, max_steps=3)
    assert policy.seed == episode.policy_seed and env.unwrapped.np_random_seed == episode.env_seed
    env_draws = np.random.default_rng(env.unwrapped.np_random_seed).random(8)
    assert not np.allclose(env_draws, policy.draws)
    # what the previous loop did: both from the same integer, i.e. the same bits
    assert np.array_equal(np.random.default_rng(7).random(8), gym.utils.seeding.np_random(7)[0].random(8))


def test_rollout_is_reproducible_and_records_every_step(env):
    first, obs = rollout(env, LaneKeeping(env), 3), []
    again = rollout(env, LaneKeeping(env), 3, observations=obs)
    assert first.trace["x"] == again.trace["x"] and first.params == again.params
    assert len(obs) == first.steps == len(first.trace["reward"]) == len(first.trace["collision"])
    assert first.terminated or first.truncated
    other = rollout(env, LaneKeeping(env), 4)
    assert other.params != first.params


def test_on_step_sees_the_reset_and_every_step(env):
    seen = []
    episode = rollout(env, LaneKeeping(env), 1, max_steps=5, on_step=lambda e, o, i: seen.append(i["s"]))
    assert episode.steps == 5 and len(seen) == 6


class RowFlags:
    """A batched policy doing nothing whose ``step_info`` flags row 1 as a fallback on every step."""

    batched = True

    def reset(self, seed=None):
        self.rows = len(seed)

    def act(self, obs):
        self.step_info = {"fallback": tuple(i == 1 for i in range(self.rows))}
        return np.zeros((self.rows, 2), np.float32)


def test_rollout_batch_records_each_rows_step_info():
    envs_ = [gym.make(envs.env_id("emergency-brake")) for _ in range(2)]
    episodes = rollout_batch(envs_, RowFlags(), [3, 4])
    for i, episode in enumerate(episodes):
        assert episode.trace["policy_info"] == [{"fallback": i == 1}] * episode.steps
