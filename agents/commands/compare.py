"""``bimp compare``: two arms on the same episode seeds, paired.

    bimp compare runs/eval --policies enkts enks
    bimp compare runs/a runs/b --policies enkts enkts       # A from the first folder, B from the second
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import bimp.agents.evaluation.compare as library
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.compare import code_version_note, compare, label_records, paired_code_versions, report
from bimp.agents.files import write_atomic


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what the comparison computes (the library's doc past its first paragraph)
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp compare", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", metavar="DIR", help="one folder, or two (A from the first)")
    parser.add_argument("--policies", nargs=2, required=True, metavar=("A", "B"), help="the two labels")
    parser.add_argument("--json", default=None, help="also write the comparison to this JSON file")
    args = parser.parse_args(argv)
    if len(args.folders) > 2:
        parser.error("give one or two folders")
    folder_a, folder_b = Path(args.folders[0]), Path(args.folders[-1])
    label_a, label_b = args.policies
    if folder_a == folder_b and label_a == label_b:
        parser.error("comparing an arm with itself: name two labels, or two folders")
    try:
        a, b = label_records(folder_a, label_a), label_records(folder_b, label_b)
    except ValueError as err:
        print(f"bimp compare: error: {err}", file=sys.stderr)
        return 2
    for label, folder, got in ((label_a, folder_a, a), (label_b, folder_b, b)):
        if not got:
            print(f"bimp compare: error: no results of {label!r} in {folder}", file=sys.stderr)
            return 2
    result = compare({k: r["metrics"] for k, r in a.items()}, {k: r["metrics"] for k, r in b.items()})
    versions = paired_code_versions(result, a, b)
    note = code_version_note(versions, label_a, label_b)
    print(report(result, label_a, label_b, note))
    if args.json:
        # Beside the scenarios: the code versions of the paired records per arm, and the note when they are mixed.
        kept = {**result, "code_versions": {**versions, "note": note}}
        try:
            write_atomic(args.json, json.dumps(kept, indent=2))
        except EvaluationError as err:
            print(f"bimp compare: error: --json: {err}", file=sys.stderr)
            return 2
    return 0 if result else 1
