"""``bimp demo``: the main job on a small default: a few episodes of the default scenarios with EnKTS and EnKS,
then a short table with intervals, the figures and one MP4 per policy and scenario. The full table (every
metric, the failed seeds) is the run folder's ``summary.md``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bimp import envs
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluate import evaluate
from bimp.agents.plots import plot_all, render_episode
from bimp.agents.records import format_stat

# The columns a terminal shows whole: (header, summary key). Every other metric is in summary.md.
SHORT_COLUMNS = (
    ("success", "success_rate"),
    ("collision", "collision_rate"),
    ("off road", "offroad_rate"),
    ("progress [m]", "progress_m"),
    ("plan time p50 [ms]", "plan_time_ms_p50"),
)


def short_table(summary: dict) -> str:
    """One row per scenario and policy of a summary (``bimp.agents.metrics.summarize``): episodes, then success,
    collision, off road (Wilson 95% intervals), progress and median plan time per step (bootstrap 95%
    intervals), as Markdown."""
    head = ["scenario", "policy", "episodes"] + [name for name, _ in SHORT_COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for e in sorted(summary.values(), key=lambda e: (e["scenario"], e["policy"])):
        cells = [e["scenario"], e["policy"], str(e["episodes"])] + [format_stat(e.get(key)) for _, key in SHORT_COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


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
