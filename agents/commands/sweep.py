"""``bimp sweep`` and ``bimp frontier``: policies evaluated along one axis of their configs.

    bimp sweep --param enkts.problem.sigma_barrier=0.05,0.1,0.2 --scenario overtaking --episodes 20 --seed 200 --out DIR
    bimp sweep --policy enkts enks --n 10 20 50 100 200 --episodes 10 --out DIR        # N, for each policy
    bimp frontier --scenario overtaking --policies enkts enks mppi nmpc ppo --n 10 20 50 100 200 500 1000 2000 \\
                  --iters 5 10 20 40 --episodes 20 --seed 2000 --out DIR

This module is ``bimp sweep`` and what both commands share; ``bimp frontier``: :mod:`bimp.agents.commands.frontier`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import bimp.agents.evaluation.sweep as library
from bimp import envs
from bimp.agents.commands.args import (
    EvaluationError,
    add_backend_arguments,
    add_set_argument,
    backend_options,
    parse_overrides,
)
from bimp.agents.evaluation.evaluate import DryRun
from bimp.agents.evaluation.sweep import Point, axis_points, param_points, run_points, table, write


def description() -> str:
    """``--help``'s text, for both commands: their usage (this docstring less its last paragraph), then the
    library's docstring past its first paragraph (what a sweep and a frontier are, what they write)."""
    return __doc__.rsplit("\n\n", 1)[0] + "\n\n" + library.__doc__.partition("\n\n")[2]


def add_common_arguments(parser: argparse.ArgumentParser, seed: int) -> None:
    """The options of both commands (``seed``: the default ``--seed``)."""
    parser.add_argument("--scenario", nargs="+", default=envs.default_scenarios())
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=seed, help="first episode seed (seeds by role: docs/evaluation.md)")
    add_set_argument(parser, help="overrides under every point (as bimp evaluate --set)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", required=True)
    parser.add_argument("--dry-run", action="store_true",
                        help="check every point against the folder and list what would run; write nothing")
    add_backend_arguments(parser)


def run_command(name: str, args: argparse.Namespace, points_of: Callable[[dict], list[Point]], batch: int = 1) -> int:
    """The points ``points_of(--set overrides)`` run into ``--out`` and reported; exit status 2 with the reason,
    before any episode, for a request that cannot run."""
    try:
        base = parse_overrides(args.overrides)
        points = points_of(base)
        stray = sorted(set(base) - {p.policy for p in points})
        if stray:
            raise EvaluationError(f"--set names {stray}, which no point evaluates")
        rows = run_points(points, args.scenario, args.episodes, args.seed, args.out, workers=args.workers,
                          batch=batch, dry_run=args.dry_run, **backend_options(args))
    except EvaluationError as err:
        print(f"bimp {name}: error: {err}", file=sys.stderr)
        return 2
    if isinstance(rows, DryRun):
        print("\n".join(rows.lines()))
        return 0
    for path in write(rows, Path(args.out), name):
        print(path)
    print(table(rows))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp sweep", description=description(),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser, seed=0)
    parser.add_argument("--param", nargs="*", action="extend", default=[], metavar="POLICY.KEY=V1,V2,...")
    parser.add_argument("--policy", nargs="+", default=["enkts", "enks"], help="the policies --n sweeps")
    parser.add_argument("--n", nargs="*", type=int, default=[], help="sweep n_particles of every --policy")
    parser.add_argument("--batch", type=int, default=1)
    args = parser.parse_args(argv)
    if bool(args.param) == bool(args.n):
        parser.error("give either --param or --n")
    return run_command("sweep", args, lambda base: param_points(args.param, base) if args.param
                       else axis_points(args.policy, {p: ("n_particles", args.n) for p in args.policy}, base),
                       args.batch)
