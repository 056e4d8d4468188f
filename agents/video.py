"""``bimp render``: one episode as an MP4 video, through gymnasium's ``RecordVideo`` (moviepy), headless, at real time.

    bimp render --scenario overtaking --policy enkts --seed 0 --out runs/render

``bimp evaluate --video K`` records the first K episodes of every arm the same way
(:func:`bimp.agents.rollout.with_video`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym

from bimp import envs
from bimp.agents.cli import EvaluationError, add_set_argument, check_out_dir, parse_overrides
from bimp.agents.evaluate import resolve_arms
from bimp.agents.registry import make_policy
from bimp.agents.rollout import episode_seeds, rollout, with_video


def render_video(scenario: str, policy: str, seed: int, out: str | Path, overrides: dict | None = None) -> Path:
    """One episode of ``policy`` on ``scenario`` from episode ``seed`` as an MP4 in ``out``; returns its path.
    :class:`bimp.agents.cli.EvaluationError` in one line, before anything is written, for a request that cannot run
    (a bad seed, scenario, policy, override or ``out``)."""
    try:
        episode_seeds(seed)  # the check every episode makes, here before anything is built
    except ValueError as err:
        raise EvaluationError(str(err)) from None
    check_out_dir(out, create=False)
    resolve_arms([scenario], [policy], {policy: overrides or {}})  # the request checked as bimp evaluate checks it
    out = check_out_dir(out)
    name = f"{policy}_{scenario}_seed{seed}"
    env = with_video(gym.make(envs.env_id(scenario), render_mode="rgb_array"), out, name)
    rollout(env, make_policy(policy, env, **(overrides or {})), seed)
    env.close()  # writes the file
    return out / f"{name}-episode-0.mp4"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp render", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default=envs.default_scenarios()[0])
    parser.add_argument("--policy", default="enkts")
    parser.add_argument("--seed", type=int, default=0)
    add_set_argument(parser, help=None)
    parser.add_argument("--out", default="runs/render")
    args = parser.parse_args(argv)
    try:
        overrides = parse_overrides(args.overrides)
        stray = sorted(set(overrides) - {args.policy})
        if stray:
            raise EvaluationError(f"--set names {stray}, not the policy {args.policy!r}")
        path = render_video(args.scenario, args.policy, args.seed, args.out, overrides.get(args.policy))
    except EvaluationError as err:
        print(f"bimp render: error: {err}", file=sys.stderr)
        return 2
    print(path)
    return 0
