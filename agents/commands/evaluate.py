"""``bimp evaluate``: policies x scenarios x seeds, safety metrics with intervals, written episode by episode.

    bimp evaluate --scenario overtaking emergency-brake --policy enkts enks --episodes 50 --seed 1000 \\
                  --workers 2 --out runs/eval
    bimp evaluate --scenario emergency-brake --policy enkts --set enkts.n_particles=10 --label enkts-n10 ...
    bimp evaluate ... --seeds 4 10 13 --video 1 --traces 1
    bimp evaluate ... --dry-run                  # what would run, per arm; writes nothing
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import bimp.agents.evaluation.evaluate as library
from bimp import envs
from bimp.agents.commands.args import (
    EvaluationError,
    add_backend_arguments,
    add_set_argument,
    backend_options,
    parse_labels,
    parse_overrides,
)
from bimp.agents.evaluation.evaluate import DryRun, evaluate
from bimp.agents.evaluation.records import EPISODES_FILE, markdown_table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", nargs="+", default=envs.default_scenarios())
    parser.add_argument("--policy", nargs="+", default=["enkts", "enks"])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0, help="first episode seed (seeds by role: docs/evaluation.md)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="an explicit list of episode seeds")
    parser.add_argument("--workers", type=int, default=max(1, min(2, os.cpu_count() or 1)))
    parser.add_argument("--traces", type=int, default=0,
                        help="episodes per arm that keep their per-step trace (for bimp plot; a traced record is "
                             "~50x larger)")
    parser.add_argument("--video", type=int, default=0, metavar="K", help="MP4 of the first K episodes per arm")
    add_set_argument(parser)
    parser.add_argument("--label", nargs="*", action="extend", default=[], metavar="[POLICY=]NAME",
                        help="the row name of a policy's config (default: the policy name)")
    parser.add_argument("--batch", type=int, default=1, metavar="B",
                        help="plan B episodes of an arm in one batched call (enkts, enks)")
    parser.add_argument("--all", dest="all_records", action="store_true",
                        help="summarize every episode in the folder, not only this request's")
    parser.add_argument("--out", default="runs/eval")
    parser.add_argument("--dry-run", action="store_true",
                        help="check the request against the folder and list what would run; write nothing")
    add_backend_arguments(parser)


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what the library's docstring says past its first paragraph
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp evaluate", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        if args.episodes < 1 or args.workers < 1 or args.traces < 0 or args.video < 0:
            raise EvaluationError("--episodes and --workers must be >= 1, --traces and --video >= 0")
        summary = evaluate(args.scenario, args.policy, args.episodes, args.seed, args.workers, args.out,
                           args.traces, parse_overrides(args.overrides), seeds=args.seeds,
                           labels=parse_labels(args.label, args.policy), video=args.video,
                           all_records=args.all_records, batch=args.batch, dry_run=args.dry_run,
                           **backend_options(args))
    except EvaluationError as err:
        print(f"bimp evaluate: error: {err}", file=sys.stderr)
        return 2
    if isinstance(summary, DryRun):
        print("\n".join(summary.lines()))
        return 0
    print(markdown_table(summary))
    print(f"wrote {Path(args.out) / EPISODES_FILE} and summary.{{json,csv,md}}")
    return 0
