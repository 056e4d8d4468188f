"""``bimp curves RUN [RUN ...] --out PNG``: learning curves of ``bimp train-rl`` runs over their training seeds,
and the hours each algorithm and scenario trained."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bimp.agents import rl_curves
from bimp.agents.errors import EvaluationError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp curves", description=rl_curves.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of `bimp train-rl` (--out or --runs-dir's)")
    parser.add_argument("--out", type=Path, required=True, help="the figure (PNG)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON, not a table")
    args = parser.parse_args(argv)
    try:
        rows = rl_curves.plot_curves(args.runs, args.out)
    except EvaluationError as err:
        print(f"bimp curves: error: {err}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{args.out}\n\n| algo | scenario | seeds | timesteps | hours | final return per seed | still climbing |\n"
          "|---|---|---|---|---|---|---|")
    for row in rows:
        finals = " / ".join("-" if r is None else f"{r:.1f}" for r in row["final_return"])
        print(f"| {row['algo']} | {row['scenario']} | {', '.join(map(str, row['seeds']))} | "
              f"{', '.join(f'{t:,}' for t in row['timesteps'])} | {row['hours']:.2f} | {finals} | "
              f"{'yes' if row['climbing'] else 'no'} |")
    return 0
