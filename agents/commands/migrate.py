"""``bimp migrate DIR|FILE.yaml ...``: evaluation folders written by older code, turned into ones the current code
resumes, and config files brought to today's shape.

    bimp migrate results/safety results/peers --dry-run      # what would change, per folder; writes nothing
    bimp migrate $(dirname $(git ls-files 'results/*episodes.jsonl'))
    bimp migrate runs/tune/mppi/best.yaml                     # a tuned config: the config alone, its tuning beside it
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import bimp.agents.evaluation.migrate as library
from bimp.agents.evaluation.migrate import migrate_folder
from bimp.agents.evaluation.records import EPISODES_FILE


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what a migration does (the library's doc past its first paragraph)
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp migrate", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", metavar="DIR|FILE.yaml",
                        help="evaluation folders (each holding episodes.jsonl) and YAML config files (a file is "
                             "migrated before any folder)")
    parser.add_argument("--dry-run", action="store_true", help="report what would change; write nothing")
    parser.add_argument("--trust-policy", action="append", default=[], metavar="MODULE:FACTORY",
                        help="rebuild arms of this policy, not in the policy table, by importing and calling it "
                             "(code: only one you trust; a folder alone never names code to run)")
    parser.add_argument("--drop-traces", action="store_true",
                        help="drop the per-step traces of the migrated records (folders no figure is drawn from)")
    args = parser.parse_args(argv)
    files = [f for f in args.folders if Path(f).is_file() and Path(f).suffix in (".yaml", ".yml")]
    folders = [d for d in args.folders if d not in files]
    missing = [d for d in folders if not (Path(d) / EPISODES_FILE).is_file()]
    if missing:
        print(f"bimp migrate: error: no {EPISODES_FILE} in {', '.join(missing)} (nor a .yaml config file)",
              file=sys.stderr)
        return 2
    failed_files = 0
    for path in dict.fromkeys(files):  # first: a folder's arm may name a config file
        try:
            print(library.migrate_config_file(path, dry_run=args.dry_run))
        except library.MigrationError as err:
            print(f"{path}: not migrated: {err}")
            failed_files += 1
    if not folders:
        return 1 if failed_files else 0
    reports = [migrate_folder(d, dry_run=args.dry_run, drop_traces=args.drop_traces, trusted=args.trust_policy)
               for d in dict.fromkeys(folders)]
    for report in reports:
        print(report.line())
    before, after = sum(r.bytes_before for r in reports), sum(r.bytes_after for r in reports)
    failed = [r for r in reports if r.problem]
    print(f"{'dry run: ' if args.dry_run else ''}{len(reports) - len(failed)} folder(s) migrated, {len(failed)} "
          f"left as they were; records and arms.json {before / 1e6:.1f} MB -> {after / 1e6:.1f} MB")
    return 1 if failed or failed_files else 0
