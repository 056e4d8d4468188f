"""``bimp leaderboard DIR [DIR ...]``: every policy of one or more evaluation folders ranked per scenario and overall.

    bimp leaderboard results/highway
    bimp leaderboard results/suite results/suite-rl --metric success_rate --json lb.json --plot lb.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import bimp.agents.evaluation.leaderboard as library
from bimp.agents.errors import EvaluationError, check_out_dir
from bimp.agents.evaluation.leaderboard import RANKABLE, leaderboard, plot, report
from bimp.agents.evaluation.records import finite
from bimp.agents.files import write_atomic


def _check_file(value: str, flag: str) -> Path:
    """``value`` as a file this command can write, checked before anything is computed."""
    path = Path(value)
    if not value.strip() or path.is_dir():
        raise EvaluationError(f"{flag} {value!r} is not a file name")
    check_out_dir(path.parent, create=False, flag=flag)
    return path


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what the leaderboard computes (the library's doc past its first paragraph)
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp leaderboard", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", metavar="DIR", help="evaluation folders (written by bimp evaluate)")
    parser.add_argument("--metric", choices=RANKABLE, default=None,
                        help="rank by this (default: score where every record carries one, else success_rate)")
    parser.add_argument("--allow-mixed", action="store_true",
                        help="rank scenarios whose policies ran different seeds or code versions, marking the rows")
    parser.add_argument("--json", default=None, metavar="FILE", help="also write the leaderboard to this JSON file")
    parser.add_argument("--plot", default=None, metavar="FILE.png", help="also draw it into this PNG")
    args = parser.parse_args(argv)
    if len({Path(f).resolve() for f in args.folders}) < len(args.folders):
        parser.error("a folder is given twice")
    try:
        outputs = [(_check_file(value, flag), flag) for value, flag in ((args.json, "--json"), (args.plot, "--plot"))
                   if value is not None]
        board = leaderboard(args.folders, args.metric, args.allow_mixed)
        for path, flag in outputs:
            check_out_dir(path.parent, flag=flag)
    except EvaluationError as err:
        print(f"bimp leaderboard: error: {err}", file=sys.stderr)
        return 2
    print(report(board), end="")
    for path, flag in outputs:
        try:
            if flag == "--json":
                write_atomic(path, json.dumps(finite(board), indent=1) + "\n")
            else:
                plot(board, path)
        except OSError as err:
            print(f"bimp leaderboard: error: cannot write {flag} {path}: {err.strerror or err}", file=sys.stderr)
            return 2
    return 0
