"""The one episode loop: :func:`rollout` drives a :class:`~agents.policy.Policy` through one episode of a bimp env.

Evaluation, figures, the benchmark's recorded observations, the RL baseline's quick check and the demo all call
it, so every number in the project comes from the same loop and the same seeding.

Seeding. One *episode seed* names an episode. The env's stream (scenario draws) and the policy's stream
(planner noise) are derived from it independently, :func:`episode_seeds`: gymnasium's ``np_random(seed)``
equals ``np.random.default_rng(seed)``, so handing both the same integer would make scenario draws and
planner noise consume the same random bits.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import gymnasium as gym
import numpy as np

SEEDING = "np.random.SeedSequence(seed).spawn(2) -> (env, policy); each: generate_state(1, uint64)[0] >> 1"

# Per-step trace keys read from ``info`` (the env measures; the loop never re-derives).
INFO_KEYS = ("input", "ov_distance", "edge_distance", "ttc", "lateral_error", "speed_error", "collision",
             "offroad", "constraints", "s")


def episode_seeds(seed: int) -> tuple[int, int]:
    """``(env_seed, policy_seed)``: two independent 63-bit seeds spawned from the episode seed (see ``SEEDING``)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    children = np.random.SeedSequence(int(seed)).spawn(2)
    env_seed, policy_seed = (int(c.generate_state(1, np.uint64)[0]) >> 1 for c in children)
    return env_seed, policy_seed


@dataclass
class Episode:
    """What one :func:`rollout` saw. ``trace``: equal-length per-step lists (EV ``x, y, heading, speed``, OV
    positions ``ov_xy``, ``reference_speed``, ``reward``, ``plan_ms`` (ms in ``act``) and the ``INFO_KEYS``);
    ``params``: the scenario's drawn parameters; ``truncated``: the episode reached its time limit."""

    seed: int
    env_seed: int
    policy_seed: int
    params: dict
    trace: dict[str, list] = field(default_factory=dict)
    steps: int = 0
    terminated: bool = False
    truncated: bool = False

    @property
    def total_reward(self) -> float:
        return float(np.sum(self.trace["reward"]))


def rollout(env: gym.Env, policy, seed: int, *, max_steps: int | None = None,
            on_step: Callable[[gym.Env, np.ndarray, dict], None] | None = None,
            observations: list | None = None) -> Episode:
    """Run ``policy`` on ``env`` from the episode ``seed`` until termination, truncation or ``max_steps``.

    ``on_step(env, obs, info)`` is called after the reset (``info`` of the reset) and after every step (for
    rendering); ``observations``, if given, receives every observation the policy acted on.
    """
    env_seed, policy_seed = episode_seeds(seed)
    obs, info = env.reset(seed=env_seed)
    policy.reset(policy_seed)
    scene = env.unwrapped.scene
    episode = Episode(seed=int(seed), env_seed=env_seed, policy_seed=policy_seed,
                      params=dict(getattr(env.unwrapped, "drawn_params", {})))
    trace = episode.trace = {k: [] for k in (
        "x", "y", "heading", "speed", "ov_xy", "reference_speed", "reward", "plan_ms", *INFO_KEYS)}
    if on_step:
        on_step(env, obs, info)
    done = False
    while not done and (max_steps is None or episode.steps < max_steps):
        if observations is not None:
            observations.append(obs)
        start = time.perf_counter()
        action = policy.act(obs)
        trace["plan_ms"].append(1e3 * (time.perf_counter() - start))
        obs, reward, terminated, truncated, info = env.step(action)
        ego, _, ovs, ref = scene.split_obs(obs)
        for name, value in zip(("x", "y", "heading", "speed"), ego):
            trace[name].append(float(value))
        trace["ov_xy"].append(ovs[:, 1:3].tolist())
        trace["reference_speed"].append(float(ref[0]))
        trace["reward"].append(float(reward))
        for name in INFO_KEYS:
            trace[name].append(info[name])
        episode.steps += 1
        episode.terminated, episode.truncated = bool(terminated), bool(truncated)
        done = terminated or truncated
        if on_step:
            on_step(env, obs, info)
    return episode


__all__ = ["Episode", "INFO_KEYS", "SEEDING", "episode_seeds", "rollout"]
