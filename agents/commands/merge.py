"""``bimp merge SRC [SRC ...] --into DIR``: copy evaluation folders' records into one, so that runs made apart (on two
machines, in two worktrees, a family rerun into a folder of its own) are read, resumed and ranked as one folder.

    bimp merge runs/a runs/b --into runs/all --dry-run                   # what would be copied; writes nothing
    bimp merge runs/cut-in --into runs/all --label idm lane-keep --scenario cut-in-hard   # only these arms
"""

from __future__ import annotations

import argparse
import sys

import bimp.agents.evaluation.merge as library
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.merge import merge


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what a merge does (the library's doc past its first paragraph)
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(
        prog="bimp merge", description=description, formatter_class=argparse.RawDescriptionHelpFormatter,
        usage="bimp merge SRC [SRC ...] --into DIR [--scenario S [S ...]] [--label L [L ...]] [--dry-run]")
    parser.add_argument("sources", nargs="+", metavar="SRC", help="evaluation folders to copy records from")
    parser.add_argument("--into", required=True, metavar="DIR", help="the folder they are copied into")
    parser.add_argument("--scenario", nargs="+", default=None, metavar="S", help="the scenarios whose records go")
    parser.add_argument("--label", nargs="+", default=None, metavar="L", help="the labels whose records go")
    parser.add_argument("--dry-run", action="store_true", help="print what would be copied; write nothing")
    args = parser.parse_args(argv)
    try:
        copied, skipped, added = merge(args.sources, args.into, args.scenario, args.label, dry_run=args.dry_run)
    except EvaluationError as err:
        print(f"bimp merge: error: {err}", file=sys.stderr)
        return 2
    verb = "would copy" if args.dry_run else "copied"
    for scenario, label in sorted(set(copied) | set(skipped)):
        print(f"{verb} {copied[scenario, label]:>5} record(s) of {label} on {scenario}"
              + (f" ({skipped[scenario, label]} already there)" if skipped[scenario, label] else ""))
    if added and not copied:  # entries only: a merge cut between arms.json and its records, mended
        print(f"{'would add' if args.dry_run else 'added'} {len(added)} config(s) to arms.json that records there name")
    print(f"{args.into}: {verb} {sum(copied.values())} record(s), {sum(skipped.values())} already there")
    return 0
