"""``bimp migrate DIR [DIR ...]``: evaluation folders written by older code, turned into ones the current code resumes.

    bimp migrate results/safety results/peers --dry-run      # what would change, per folder; writes nothing
    bimp migrate $(dirname $(git ls-files 'results/*episodes.jsonl'))
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import bimp.agents.migrate as library
from bimp.agents.migrate import migrate_folder
from bimp.agents.records import EPISODES_FILE


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what a migration does (the library's doc past its first paragraph)
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp migrate", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", metavar="DIR", help="evaluation folders (each holding episodes.jsonl)")
    parser.add_argument("--dry-run", action="store_true", help="report what would change; write nothing")
    parser.add_argument("--trust-policy", action="append", default=[], metavar="MODULE:FACTORY",
                        help="rebuild arms of this policy, not in the policy table, by importing and calling it "
                             "(code: only one you trust; a folder alone never names code to run)")
    parser.add_argument("--drop-traces", action="store_true",
                        help="drop the per-step traces of the migrated records (folders no figure is drawn from)")
    args = parser.parse_args(argv)
    missing = [d for d in args.folders if not (Path(d) / EPISODES_FILE).is_file()]
    if missing:
        print(f"bimp migrate: error: no {EPISODES_FILE} in {', '.join(missing)}", file=sys.stderr)
        return 2
    reports = [migrate_folder(d, dry_run=args.dry_run, drop_traces=args.drop_traces, trusted=args.trust_policy)
               for d in dict.fromkeys(args.folders)]
    for report in reports:
        print(report.line())
    before, after = sum(r.bytes_before for r in reports), sum(r.bytes_after for r in reports)
    failed = [r for r in reports if r.problem]
    print(f"{'dry run: ' if args.dry_run else ''}{len(reports) - len(failed)} folder(s) migrated, {len(failed)} "
          f"left as they were; records and arms.json {before / 1e6:.1f} MB -> {after / 1e6:.1f} MB")
    return 1 if failed else 0
