"""``bimp plot DIR``: figures like the paper's from the traced episodes of an evaluation folder."""

from __future__ import annotations

import argparse
import sys

import bimp.agents.evaluation.plots as library
from bimp.agents.commands.args import EvaluationError
from bimp.agents.evaluation.plots import plot_all


def main(argv: list[str] | None = None) -> int:
    # --help: the line above, then what the library's docstring says past its first paragraph (the figures)
    description = __doc__ + "\n\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp plot", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", help="an evaluation folder (holding episodes.jsonl)")
    parser.add_argument("--out", default=None, help="where to write the PNGs (default FOLDER/figures)")
    args = parser.parse_args(argv)
    try:
        written = plot_all(args.folder, args.out)
    except EvaluationError as err:
        print(f"bimp plot: error: {err}", file=sys.stderr)
        return 2
    if not written:
        print(f"no traced episodes in {args.folder} (bimp evaluate keeps no per-step trace unless asked): run "
              "`bimp evaluate --traces 1 ...` into it first")
        return 1
    for path in written:
        print(path)
    return 0
