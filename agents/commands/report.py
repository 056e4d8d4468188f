"""``bimp report``: the results tables of the README and the manual, rendered from the committed folders.

    bimp report                      # rewrite every block of README.md, results/README.md and docs/
    bimp report --check              # write nothing; exit 1 naming each block that differs from its folders
    bimp report docs/suite.md        # only these files
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bimp.agents.evaluation.report import TABLES, default_files, render
from bimp.agents.files import write_atomic


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp report", description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="*", type=Path,
                        help="markdown files (default: README.md, results/README.md and docs/)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 where a block differs")
    args = parser.parse_args(argv)
    cache: dict = {}
    stale, notes = [], {}
    for path in args.files or default_files():  # every file rendered before any is written: all or nothing
        text = path.read_text()
        rendered, found = render(text, TABLES, cache, where=str(path))
        notes.update(dict.fromkeys(found))  # a table shown in several files is named once
        if rendered != text:
            stale.append((path, rendered))
    if not args.check:
        for path, rendered in stale:
            write_atomic(path, rendered)
    for note in notes:
        print(f"bimp report: {note}", file=sys.stderr)
    for path, _ in stale:
        print(f"{path}: {'differs from its folders (run bimp report)' if args.check else 'rendered'}")
    return 1 if args.check and stale else 0
