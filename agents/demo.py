"""``bimp demo``: the main job on a small default: a few episodes of both scenarios with EnKTS and EnKS,
then the table with intervals, the figures and one MP4 per policy and scenario."""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.evaluate import evaluate, markdown_table
from agents.plots import plot_all, render_episode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp demo", description=__doc__)
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--policy", nargs="+", default=["enkts", "enks"])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default="runs/demo")
    args = parser.parse_args(argv)
    summary = evaluate(["overtaking", "emergency-brake"], args.policy, args.episodes, seed=0,
                       workers=args.workers, out=args.out, traces=1, video=1)
    print(markdown_table(summary))
    figures = plot_all(args.out)
    for scenario in ("overtaking", "emergency-brake"):
        figures.append(render_episode(scenario, args.policy[0], 0, Path(args.out) / "figures" /
                                      f"render_{scenario}.png"))
    for path in figures:
        print(f"figure: {path}")
    for path in sorted((Path(args.out) / "videos").glob("*.mp4")):
        print(f"video: {path}")
    print(f"table: {Path(args.out) / 'summary.md'}")
    return 0
