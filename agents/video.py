"""``bimp render``: one episode as an MP4 video, through gymnasium's ``RecordVideo`` (moviepy), headless, at real time;
or, with ``--frame K``, the frame after K steps as a PNG. Each frame draws the planner's plan (EnKTS, EnKS: the
mean plan in magenta and a few of its particles in light magenta; NMPC: its plan; MPPI and the baselines: none) and,
on the paper's scenarios, the reference lane in orange.

    bimp render --scenario overtaking --policy enkts --seed 0 --out runs/render
    bimp render --scenario highway-v0 roundabout-v0 --frame 15 --out docs/img/highway   # highway-v0.png ...

``bimp evaluate --video K`` records the first K episodes of every arm the same way
(:func:`bimp.agents.rollout.with_video`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import matplotlib.image

from bimp import envs
from bimp.agents.cli import EvaluationError, add_set_argument, check_out_dir, parse_overrides
from bimp.agents.evaluate import resolve_arms
from bimp.agents.registry import make_policy
from bimp.agents.rollout import episode_seeds, rollout, with_video


def _checked(scenario: str, policy: str, seed: int, out: str | Path, overrides: dict | None) -> Path:
    """``out``, made, once the request is checked: :class:`bimp.agents.cli.EvaluationError` in one line, before
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
    :class:`bimp.agents.cli.EvaluationError` for a request that cannot run (:func:`_checked`)."""
    return _video(scenario, policy, seed, _checked(scenario, policy, seed, out, overrides), overrides)


def _video(scenario: str, policy: str, seed: int, out: Path, overrides: dict | None) -> Path:
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
    returns its path. :class:`bimp.agents.cli.EvaluationError` for a request that cannot run."""
    if isinstance(step, bool) or not isinstance(step, int) or step < 1:
        raise EvaluationError(f"--frame must be an int >= 1, got {step!r}")
    return _frame(scenario, policy, seed, _checked(scenario, policy, seed, out, overrides), step, overrides)


def _frame(scenario: str, policy: str, seed: int, out: Path, step: int, overrides: dict | None) -> Path:
    gym_id = envs.env_id(scenario)
    env = gym.make(gym_id, render_mode="rgb_array")
    rollout(env, make_policy(policy, env, **(overrides or {})), seed, max_steps=step)
    path = out / f"{gym_id.rpartition('/')[2]}.png"
    matplotlib.image.imsave(path, env.render())
    env.close()
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp render", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", nargs="+", default=envs.default_scenarios()[:1], metavar="ID",
                        help="one or more scenarios (short names or gym ids), one file each")
    parser.add_argument("--policy", default="enkts")
    parser.add_argument("--seed", type=int, default=0)
    add_set_argument(parser, help=None)
    parser.add_argument("--frame", type=int, default=None, metavar="K",
                        help="write the frame after K steps as OUT/<id>.png instead of the video")
    parser.add_argument("--out", default="runs/render")
    args = parser.parse_args(argv)
    try:
        overrides = parse_overrides(args.overrides)
        stray = sorted(set(overrides) - {args.policy})
        if stray:
            raise EvaluationError(f"--set names {stray}, not the policy {args.policy!r}")
        if args.frame is not None and args.frame < 1:
            raise EvaluationError(f"--frame must be >= 1, got {args.frame}")
        given = overrides.get(args.policy)
        # Every scenario checked before the first file is written.
        out = [_checked(scenario, args.policy, args.seed, args.out, given) for scenario in args.scenario][0]
        for scenario in args.scenario:
            print(_video(scenario, args.policy, args.seed, out, given) if args.frame is None else
                  _frame(scenario, args.policy, args.seed, out, args.frame, given), flush=True)
    except EvaluationError as err:
        print(f"bimp render: error: {err}", file=sys.stderr)
        return 2
    return 0
