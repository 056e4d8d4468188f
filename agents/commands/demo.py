"""``bimp demo``: the main job on a small default: a few episodes of the default scenarios with EnKTS and EnKS,
then a short table with intervals, the figures and one MP4 per policy and scenario. The full table (every
metric, the failed seeds) is the run folder's ``summary.md``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bimp import envs
from bimp.agents.commands.args import EvaluationError
from bimp.agents.evaluation.demo import short_table
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.plots import plot_all, render_episode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp demo", description=__doc__)
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--policy", nargs="+", default=["enkts", "enks"])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default="runs/demo")
    args = parser.parse_args(argv)
    scenarios = envs.default_scenarios()
    try:
        summary = evaluate(scenarios, args.policy, args.episodes, seed=0,
                           workers=args.workers, out=args.out, traces=1, video=1)
    except EvaluationError as err:
        print(f"bimp demo: error: {err}", file=sys.stderr)
        return 2
    print(short_table(summary))
    print(f"Intervals: 95%, Wilson for the rates, bootstrap of the mean for progress and plan time. "
          f"Every metric with its interval and the failed seeds: {Path(args.out) / 'summary.md'}")
    figures = plot_all(args.out)
    for scenario in scenarios:
        figures.append(render_episode(scenario, args.policy[0], 0, Path(args.out) / "figures" /
                                      f"render_{scenario}.png"))
    for path in figures:
        print(f"figure: {path}")
    for path in sorted((Path(args.out) / "videos").glob("*.mp4")):
        print(f"video: {path}")
    print(f"table: {Path(args.out) / 'summary.md'}")
    return 0
