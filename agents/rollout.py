"""The one episode loop: :func:`rollout` drives a :class:`~bimp.agents.policy.Policy` through one episode of a bimp env.

Evaluation, figures, the benchmark's recorded observations, the RL baseline's quick check and the demo all call
it, so every number in the project comes from the same loop and the same seeding. :func:`with_video` records the
episodes of an env as MP4 (``bimp evaluate --video``, ``bimp render``).

Seeding. One *episode seed* names an episode. The env's stream (scenario draws) and the policy's stream
(planner noise) are derived from it independently, :func:`episode_seeds`: gymnasium's ``np_random(seed)``
equals ``np.random.default_rng(seed)``, so handing both the same integer would make scenario draws and
planner noise consume the same random bits.
"""

from __future__ import annotations

import functools
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import gymnasium as gym
import numpy as np

SEEDING = "np.random.SeedSequence(seed).spawn(2) -> (env, policy); each: generate_state(1, uint64)[0] >> 1"

# Per-step trace keys read from ``info`` (the env measures; the loop never re-derives). ``contact`` and
# ``speed_limit``: what the closed-loop score reads (bimp.envs.scene.attribution_info; None from an env without them).
INFO_KEYS = ("input", "ov_distance", "edge_distance", "ttc", "lateral_error", "speed_error", "collision",
             "offroad", "constraints", "s", "reference", "ahead_of_ov1", "goal", "contact", "speed_limit")


@contextmanager
def one_thread() -> Iterator[None]:
    """Run the enclosed episodes in this process as a worker runs them: one BLAS / OpenMP thread
    (``threadpoolctl``; a worker gets it from
    :data:`bimp.agents.evaluation.backends.THREADS` before numpy loads) and one torch thread. The episode
    loops (:func:`bimp.agents.rollout.rollout` and ``rollout_batch``) run under it, whoever calls them: ``bimp
    evaluate --workers 1``, ``bimp render``, the demo's figures. Why: OpenBLAS
    splits a product differently over more threads, the floats change in their last digits, and a sampling planner's
    trajectory then drifts apart (MPPI on lane-drop-hard seed 3001: score 0.75 on one thread, 0.44 on this 2-core
    machine's two), so a record would depend on ``--workers`` and on the cores of the machine that made it. XLA's
    threads are fixed when JAX starts and stay as they are; they changed no action in the cases measured
    (``docs/scaling.md``)."""
    import scipy.linalg  # noqa: F401  (its own OpenBLAS, which JAX's CPU LAPACK loads at a planner's first solve)
    import torch
    from threadpoolctl import threadpool_limits

    # threadpoolctl limits the libraries loaded when the limit starts: one loaded later inside would keep its cores.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        torch.set_num_threads(threads)


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
    positions ``ov_xy``, ``reference_speed``, ``reward``, ``plan_ms`` (ms in ``act``), the ``INFO_KEYS`` and,
    where the policy says something, ``policy_info`` (its ``step_info``)); ``params``: the scenario's drawn
    parameters; ``truncated``: the episode reached its time limit."""

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


def _new_trace() -> dict[str, list]:
    return {k: [] for k in ("x", "y", "heading", "speed", "ov_xy", "reference_speed", "reward", "plan_ms", *INFO_KEYS,
                                "policy_info")}


def _record(episode: Episode, scene, obs, reward, terminated, truncated, info, plan_ms: float) -> None:
    """Append one step to ``episode``: the EV state and OV positions from ``obs``, the rest from ``info``."""
    trace = episode.trace
    ego, _, ovs, ref = scene.split_obs(obs)
    for name, value in zip(("x", "y", "heading", "speed"), ego):
        trace[name].append(float(value))
    trace["ov_xy"].append(ovs[:, 1:3].tolist())
    trace["reference_speed"].append(float(ref[0]))
    trace["reward"].append(float(reward))
    trace["plan_ms"].append(plan_ms)
    for name in INFO_KEYS:
        trace[name].append(info.get(name))
    episode.steps += 1
    episode.terminated, episode.truncated = bool(terminated), bool(truncated)


def _start(env: gym.Env, seed: int) -> tuple[Episode, np.ndarray, dict]:
    env_seed, policy_seed = episode_seeds(seed)
    obs, info = env.reset(seed=env_seed)
    episode = Episode(seed=int(seed), env_seed=env_seed, policy_seed=policy_seed,
                      params=dict(getattr(env.unwrapped, "drawn_params", {})), trace=_new_trace())
    return episode, obs, info


@one_thread()
def rollout(env: gym.Env, policy, seed: int, *, max_steps: int | None = None,
            on_step: Callable[[gym.Env, np.ndarray, dict], None] | None = None,
            observations: list | None = None) -> Episode:
    """Run ``policy`` on ``env`` from the episode ``seed`` until termination, truncation or ``max_steps``.

    The policy's ``step_info`` (what its last ``act`` did, e.g. NMPC's solver status and fallback) is recorded per
    step in ``trace["policy_info"]``, unless it said nothing at every step (``{}``: the baselines).

    ``on_step(env, obs, info)`` is called after the reset (``info`` of the reset) and after every step (for
    rendering); ``observations``, if given, receives every observation the policy acted on.
    """
    _show_plan(env, None)  # the first frames draw no plan, and none of the episode before
    episode, obs, info = _start(env, seed)
    policy.reset(episode.policy_seed)
    scene = env.unwrapped.scene
    if on_step:
        on_step(env, obs, info)
    done = False
    while not done and (max_steps is None or episode.steps < max_steps):
        if observations is not None:
            observations.append(obs)
        start = time.perf_counter()
        action = policy.act(obs)
        plan_ms = 1e3 * (time.perf_counter() - start)
        _show_plan(env, policy)  # the frame of this step (a video's, bimp render's) draws the plan just made
        obs, reward, terminated, truncated, info = env.step(action)
        _record(episode, scene, obs, reward, terminated, truncated, info, plan_ms)
        episode.trace["policy_info"].append(dict(policy.step_info))
        done = terminated or truncated
        if on_step:
            on_step(env, obs, info)
    return _said(episode)


@one_thread()
def rollout_batch(envs: list[gym.Env], policy, seeds: list[int]) -> list[Episode]:
    """Episodes of a batched ``policy`` on ``envs`` (one per seed) in lockstep: one ``act(obs (B, d))`` per step
    after ``reset(seed=[...])`` with the episodes' policy seeds, row ``i`` planning for ``envs[i]``. An env whose
    episode has ended is no longer stepped (its row keeps planning on its last observation, unused). Each episode's
    ``plan_ms`` is the time of the whole batched call.

    A list of envs rather than a gymnasium vector env: a vector env resets an ended env itself, and an episode
    here must end as the single-env loop ends it. Row ``i`` equals :func:`rollout` of ``seeds[i]`` (the planner's
    rows are independent; a test pins it). A batched policy's ``step_info`` holds one value per row for each key
    (``{"fallback": (b_1, .., b_B)}``): episode ``i`` records row ``i``'s in ``trace["policy_info"]``, as
    :func:`rollout` records a single policy's."""
    if len(envs) != len(seeds) or not envs:
        raise ValueError(f"one env per seed: got {len(envs)} envs and {len(seeds)} seeds")
    started = [_start(env, seed) for env, seed in zip(envs, seeds)]
    episodes = [e for e, _, _ in started]
    obs = [o for _, o, _ in started]
    policy.reset([e.policy_seed for e in episodes])
    done = [False] * len(envs)
    while not all(done):
        start = time.perf_counter()
        actions = policy.act(np.stack(obs))
        plan_ms = 1e3 * (time.perf_counter() - start)
        for i, env in enumerate(envs):
            if done[i]:
                continue
            obs[i], reward, terminated, truncated, info = env.step(actions[i])
            _record(episodes[i], env.unwrapped.scene, obs[i], reward, terminated, truncated, info, plan_ms)
            # one value per row: episode i records row i's
            episodes[i].trace["policy_info"].append({key: value[i] for key, value in policy.step_info.items()})
            done[i] = terminated or truncated
    return [_said(episode) for episode in episodes]


def _said(episode: Episode) -> Episode:
    """``episode`` without ``trace["policy_info"]`` when the policy said nothing at any step: a record holds no
    column of empty entries (and a baseline's records stay as they were before every policy had ``step_info``)."""
    if not any(episode.trace["policy_info"]):
        del episode.trace["policy_info"]
    return episode


def with_video(env: gym.Env, folder: str | Path, name: str) -> gym.Env:
    """``env`` (made with ``render_mode="rgb_array"``) wrapped to write every episode to
    ``folder/{name}-episode-{i}.mp4`` at one frame per control step, i.e. real time (10 fps for dt = 0.1 s), through
    gymnasium's ``RecordVideo`` (moviepy), headless. Run by :func:`rollout`, each frame draws the policy's latest
    plan (:func:`plan_overlay`)."""
    if env.render_mode != "rgb_array":
        raise ValueError(f"video needs an env made with render_mode='rgb_array', got {env.render_mode!r}")
    with warnings.catch_warnings():  # many episodes share one folder; each file has its own name
        warnings.filterwarnings("ignore", message=".*Overwriting existing videos.*")
        return gym.wrappers.RecordVideo(env, str(folder), episode_trigger=lambda _: True, name_prefix=name,
                                        fps=env.unwrapped.config["policy_frequency"], disable_logger=True)


# The plan in a frame: colours no road marking, vehicle or reference lane (bimp.envs.scenarios) is drawn in.
PLAN_COLOUR = (255, 0, 255)  # magenta, 3 px: the mean plan's positions
PARTICLE_COLOUR = (255, 175, 255)  # light magenta, 1 px: a few of the ensemble's particles rolled out
PLAN_PARTICLES = 6


def plan_overlay(policy, particles: int = PLAN_PARTICLES) -> list:
    """The latest plan of ``policy`` as lines for a frame (:mod:`bimp.envs.overlay`, world ``[x, y]``): the mean
    plan's states (EnKTS, EnKS: ``plan.states``; NMPC: ``plan[0]``) and, under them, the first ``particles`` of the
    ensemble's controls (``plan.control_particles``) rolled out from the plan's first state with the planner's own
    model (:func:`bimp.planners.core.roll_out`, as the mean's states are). Nothing for a policy that exposes no plan
    (MPPI, the baselines), before its first ``act``, or for a batch."""
    plan = getattr(policy, "plan", None)
    states = plan[0] if isinstance(plan, tuple) else getattr(plan, "states", None)
    if states is None or np.ndim(states) != 2:
        return []
    states = np.asarray(states, dtype=float)
    lines = []
    controls = getattr(plan, "control_particles", None)
    model = getattr(policy, "_model", None)  # the EnKTS planner's vehicle model (bicycle or learned)
    if particles > 0 and controls is not None and model is not None:
        x0, u = np.asarray(states[0], np.float32), np.asarray(controls[:particles], np.float32)
        rolled = np.asarray(_particle_roll_out()(model, x0, u), dtype=float)
        lines += [(x[:, :2], PARTICLE_COLOUR, 1) for x in rolled]
    return lines + [(states[:, :2], PLAN_COLOUR, 3)]


@functools.cache
def _particle_roll_out():
    """:func:`bimp.planners.core.roll_out` over particles ``(n, H, 2)``, compiled once (un-compiled, a call traced
    the scan anew: 0.2 s a frame)."""
    import jax

    from bimp.planners import core  # lazy: JAX, needed only for a rendered episode

    return jax.jit(jax.vmap(core.roll_out, in_axes=(None, None, 0)))


def _show_plan(env: gym.Env, policy) -> None:
    """The frame hook: ``env``'s next frames draw the latest plan of ``policy`` (None: no plan), through
    ``env.unwrapped.overlay``; only for an env rendering into arrays (videos, ``bimp render``): no cost otherwise."""
    if env.render_mode == "rgb_array":
        env.unwrapped.overlay = plan_overlay(policy) if policy is not None else []


__all__ = ["Episode", "INFO_KEYS", "PARTICLE_COLOUR", "PLAN_COLOUR", "SEEDING", "episode_seeds", "plan_overlay",
           "rollout", "rollout_batch", "with_video"]
