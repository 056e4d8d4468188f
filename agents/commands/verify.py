"""``bimp verify DIR [DIR ...]``: rerun a sample of each arm's seeds at the current code and compare every recorded
metric but timings; what it found goes into ``DIR/verified.json``.

    bimp verify results/suite --sample 2 --dry-run     # which arms, which seeds; refuses what it cannot rerun
    bimp verify results/suite --sample 1 --workers 2
"""

from __future__ import annotations

import argparse
import sys

import bimp.agents.evaluation.verify as library
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.verify import verify_folder


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what a verification does (the library's doc past its first paragraph)
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp verify", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", metavar="DIR", help="evaluation folders (each holding episodes.jsonl)")
    parser.add_argument("--sample", type=int, default=2, metavar="K", help="seeds rerun per arm (default 2)")
    parser.add_argument("--workers", type=int, default=1, help="processes the episodes run in")
    parser.add_argument("--trust-policy", action="append", default=[], metavar="MODULE:FACTORY",
                        help="rerun arms of this policy outside the policy table (code: only one you trust)")
    parser.add_argument("--dry-run", action="store_true", help="say what would be rerun; run and write nothing")
    args = parser.parse_args(argv)
    if args.sample < 1 or args.workers < 1:
        parser.error("--sample and --workers must be >= 1")
    status = 0
    try:
        plans = {d: verify_folder(d, args.sample, args.workers, args.trust_policy, dry_run=True)
                 for d in dict.fromkeys(args.folders)}  # every folder checked before anything runs
        for folder in plans:
            checks = plans[folder] if args.dry_run else verify_folder(folder, args.sample, args.workers,
                                                                     args.trust_policy)
            for c in checks:
                found = ("would rerun" if args.dry_run else c.outcome if not c.differences
                         else f"{c.outcome.upper()}: " + "; ".join(c.differences[:5]))
                batches = f" (batches {c.groups})" if c.batch > 1 else ""
                elsewhere = [m for m in c.machines if m != library.machine()] if c.differences else []
                where = ""
                if elsewhere:  # the machine lines hold "; ": the note's parts stand in brackets of their own
                    ran = " | ".join(m for m in elsewhere if m != "unknown")
                    where = (f" [records ran on: {ran}] [this machine: {library.machine()}] (a rerun on the records'"
                             " machine tells the code from the machine)" if ran else
                             " [records ran on an unrecorded machine: the code or the machine may have moved them]")
                print(f"{folder}: {c.name}: seeds {c.seeds}{batches}: {found}{where}")
                status = max(status, 1 if c.differences else 0)
            if not args.dry_run:
                counts = {k: sum(c.outcome == k for c in checks) for k in ("same", "drift", "different")}
                print(f"{folder}: {len(checks)} arm(s): " + ", ".join(f"{n} {k}" for k, n in counts.items()))
    except EvaluationError as err:
        print(f"bimp verify: error: {err}", file=sys.stderr)
        return 2
    return status
