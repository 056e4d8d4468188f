"""``bimp frontier``: success and bound violations against plan time, each policy along its compute axis (N, or
NMPC's iteration cap). Its usage, its help and the options it shares with ``bimp sweep``:
:mod:`bimp.agents.commands.sweep`."""

from __future__ import annotations

import argparse

from bimp.agents.commands.sweep import add_common_arguments, description, run_command
from bimp.agents.evaluation.sweep import axis_points
from bimp.agents.registry import is_policy_name, policy_spec


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp frontier", description=description(),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser, seed=2000)
    parser.add_argument("--policies", nargs="+", default=["enkts", "enks", "mppi", "nmpc", "ppo"])
    parser.add_argument("--n", nargs="+", type=int, default=[10, 20, 50, 100, 200, 500, 1000, 2000])
    parser.add_argument("--iters", nargs="+", type=int, default=[5, 10, 20, 40], help="NMPC's iteration caps")
    args = parser.parse_args(argv)
    values = {"n_particles": args.n, "max_iter": args.iters}
    axes = {p: policy_spec(p).frontier_axis for p in args.policies if is_policy_name(p)}
    axis = {p: (key, values[key]) for p, key in axes.items() if key in values}
    return run_command("frontier", args, lambda base: axis_points(args.policies, axis, base))
