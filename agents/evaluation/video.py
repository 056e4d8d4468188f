"""One episode as an MP4 video, through gymnasium's ``RecordVideo`` (moviepy), headless, at real time
(:func:`render_video`); or the frame after K steps as a PNG (:func:`render_frame`). Each frame draws the planner's
plan (EnKTS, EnKS: the mean plan in magenta and a few of its particles in light magenta; NMPC: its plan; MPPI and the
baselines: none) and, on the paper's scenarios, the reference lane in orange. The command ``bimp render``:
:mod:`bimp.agents.commands.render`.

``bimp evaluate --video K`` records the first K episodes of every arm the same way
(:func:`bimp.agents.rollout.with_video`).
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import matplotlib.image

from bimp import envs
from bimp.agents.errors import EvaluationError, check_out_dir
from bimp.agents.evaluation.evaluate import resolve_arms
from bimp.agents.registry import make_policy
from bimp.agents.rollout import episode_seeds, rollout, with_video


def check_request(scenario: str, policy: str, seed: int, out: str | Path, overrides: dict | None) -> Path:
    """``out``, made, once the request is checked: :class:`bimp.agents.errors.EvaluationError` in one line, before
    anything is written, for a request that cannot run (a bad seed, scenario, policy, override or ``out``)."""
    try:
        episode_seeds(seed)  # the check every episode makes, here before anything is built
    except ValueError as err:
        raise EvaluationError(str(err)) from None
    check_out_dir(out, create=False)
    resolve_arms([scenario], [policy], {policy: overrides or {}})  # the request checked as bimp evaluate checks it
    return check_out_dir(out)


def render_video(scenario: str, policy: str, seed: int, out: str | Path, overrides: dict | None = None) -> Path:
    """One episode of ``policy`` on ``scenario`` from episode ``seed`` as an MP4 in ``out``; returns its path.
    :class:`bimp.agents.errors.EvaluationError` for a request that cannot run (:func:`check_request`)."""
    return write_video(scenario, policy, seed, check_request(scenario, policy, seed, out, overrides), overrides)


def write_video(scenario: str, policy: str, seed: int, out: Path, overrides: dict | None) -> Path:
    """:func:`render_video` into ``out``, a folder :func:`check_request` returned."""
    name = f"{policy}_{scenario}_seed{seed}"
    env = with_video(gym.make(envs.env_id(scenario), render_mode="rgb_array"), out, name)
    rollout(env, make_policy(policy, env, **(overrides or {})), seed)
    env.close()  # writes the file
    return out / f"{name}-episode-0.mp4"


def render_frame(scenario: str, policy: str, seed: int, out: str | Path, step: int,
                 overrides: dict | None = None) -> Path:
    """The frame of ``policy`` on ``scenario`` from episode ``seed`` after ``step`` steps (or at the episode's end,
    if it ends sooner), as the video shows it (the plan made at the last step drawn), as a PNG
    ``out/<id>.png`` (``<id>``: the gym id without ``bimp/``, e.g. ``highway-v0.png``, ``Overtaking-v0.png``);
    returns its path. :class:`bimp.agents.errors.EvaluationError` for a request that cannot run."""
    if isinstance(step, bool) or not isinstance(step, int) or step < 1:
        raise EvaluationError(f"--frame must be an int >= 1, got {step!r}")
    return write_frame(scenario, policy, seed, check_request(scenario, policy, seed, out, overrides), step, overrides)


def write_frame(scenario: str, policy: str, seed: int, out: Path, step: int, overrides: dict | None) -> Path:
    """:func:`render_frame` into ``out``, a folder :func:`check_request` returned."""
    gym_id = envs.env_id(scenario)
    env = gym.make(gym_id, render_mode="rgb_array")
    rollout(env, make_policy(policy, env, **(overrides or {})), seed, max_steps=step)
    path = out / f"{gym_id.rpartition('/')[2]}.png"
    matplotlib.image.imsave(path, env.render())
    env.close()
    return path
