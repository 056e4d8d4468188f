"""``bimp aggregate``: one learning algorithm over its training seeds, with intervals over the seeds.

    bimp aggregate results/rl --runs ppo-s1 ppo-s2 ppo-s3 --name ppo

writes ``DIR/aggregate_{name}.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import bimp.agents.evaluation.aggregate as library
from bimp.agents.evaluation.aggregate import aggregate, markdown
from bimp.agents.evaluation.compare import label_results
from bimp.agents.files import write_atomic


def main(argv: list[str] | None = None) -> int:
    # --help: the first line above, what the library's doc says past its first paragraph, then the usage
    head, _, usage = __doc__.partition("\n\n")
    description = head + "\n\n" + library.__doc__.partition("\n\n")[2] + "\n" + usage
    parser = argparse.ArgumentParser(prog="bimp aggregate", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", metavar="DIR", help="an evaluation folder holding every run's arm")
    parser.add_argument("--runs", nargs="+", required=True, metavar="LABEL", help="one label per training seed")
    parser.add_argument("--name", required=True, help="the algorithm's name in the output files")
    args = parser.parse_args(argv)
    folder = Path(args.folder)
    try:
        per_run = {label: label_results(folder, label) for label in args.runs}
        missing = [label for label, got in per_run.items() if not got]
        if missing:
            raise ValueError(f"no results of {missing} in {folder}")
        result = aggregate(per_run)
    except ValueError as err:
        print(f"bimp aggregate: error: {err}", file=sys.stderr)
        return 2
    text = markdown(result, args.name, args.runs)
    try:
        write_atomic(folder / f"aggregate_{args.name}.json", json.dumps(result, indent=2) + "\n")
        write_atomic(folder / f"aggregate_{args.name}.md", text)
    except OSError as err:
        print(f"bimp aggregate: error: cannot write into {folder}: {err.strerror or err}", file=sys.stderr)
        return 2
    print(text)
    return 0
