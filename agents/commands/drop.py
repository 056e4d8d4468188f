"""``bimp drop DIR --scenario S ... --label L ...``: take records out of an evaluation folder, so that it can be rerun
under the same labels after a config or a scenario's ranges changed.

    bimp drop results/suite --scenario lane-drop-hard --dry-run        # what would go; writes nothing
    bimp drop results/suite --scenario lane-drop-hard stalled-vehicle-hard
    bimp drop results/suite-tuned --scenario cut-in-hard --label mppi-tuned
"""

from __future__ import annotations

import argparse
import sys

import bimp.agents.evaluation.drop as library
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.drop import drop


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what a drop does (the library's doc past its first paragraph)
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp drop", description=description,
                                     usage="bimp drop DIR [--scenario S [S ...]] [--label L [L ...]] [--dry-run]",
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", metavar="DIR", help="an evaluation folder (holding episodes.jsonl)")
    parser.add_argument("--scenario", nargs="+", default=None, metavar="S", help="the scenarios whose records go")
    parser.add_argument("--label", nargs="+", default=None, metavar="L", help="the labels whose records go")
    parser.add_argument("--dry-run", action="store_true", help="print what would go; write nothing")
    args = parser.parse_args(argv)
    try:
        counts = drop(args.folder, args.scenario, args.label, dry_run=args.dry_run)
    except EvaluationError as err:
        print(f"bimp drop: error: {err}", file=sys.stderr)
        return 2
    verb = "would drop" if args.dry_run else "dropped"
    for (scenario, label), n in sorted(counts.items()):
        print(f"{verb} {n:>5} record(s) of {label} on {scenario}")
    print(f"{args.folder}: {verb} {sum(counts.values())} record(s)"
          + ("" if counts else " (nothing matched both --scenario and --label)"))
    return 0
