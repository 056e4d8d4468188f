"""``bimp tune``: a policy's config tuned by Optuna on training seeds, the same budget for every method.

    bimp tune --policy mppi --scenario overtaking emergency-brake --trials 40 --episodes 20 --seed 100 \\
              --out runs/tune/mppi
    # study: runs/tune/mppi/study.db; best config: runs/tune/mppi/best.yaml, loaded by
    # make_policy("mppi", env, config="runs/tune/mppi/best.yaml"); --yaml configs/tuned/mppi.yaml ships it
"""

from __future__ import annotations

import argparse
import sys

import bimp.agents.evaluation.tune as library
from bimp import envs
from bimp.agents.commands.args import add_backend_arguments, backend_options
from bimp.agents.evaluation.tune import OBJECTIVES, TuneError, tune


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what the library's docstring says past its first paragraph
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp tune", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True)
    parser.add_argument("--scenario", nargs="+", default=envs.default_scenarios())
    parser.add_argument("--trials", type=int, default=30, help="the study's total number of trials")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per scenario and trial")
    parser.add_argument("--seed", type=int, default=100, help="first training seed (100-199 by convention)")
    parser.add_argument("--rung", type=int, default=None, help="seeds per pruning step (default: no pruning)")
    parser.add_argument("--storage", default=None, help="Optuna RDB URL (default sqlite:///OUT/study.db)")
    parser.add_argument("--out", default="runs/tune")
    parser.add_argument("--yaml", default=None, help="where the best config goes (default OUT/best.yaml; "
                        "configs/tuned/POLICY.yaml makes it the policy's default)")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--sampler-seed", type=int, default=0)
    parser.add_argument("--objective", choices=OBJECTIVES, default="success",
                        help="what a trial maximizes: success (safety-first ties) or the closed-loop score")
    add_backend_arguments(parser)
    parser.add_argument("--parallel", type=int, default=None, metavar="N", help="with --backend ray: trials at "
                        "once, each on its own worker (default: the cluster's CPUs // --workers)")
    args = parser.parse_args(argv)
    try:
        study = tune(args.policy, args.scenario, args.trials, args.episodes, args.seed, out=args.out,
                     storage=args.storage, yaml_path=args.yaml, rung=args.rung, batch=args.batch,
                     workers=args.workers, sampler_seed=args.sampler_seed, parallel=args.parallel,
                     objective=args.objective,
                     **backend_options(args))
    except TuneError as err:
        print(f"bimp tune: error: {err}", file=sys.stderr)
        return 2
    for t in study.get_trials(deepcopy=False):
        shown = "-" if t.value is None else f"{t.value:.4f}"
        print(f"trial {t.number:>3} {t.state.name:<8} {shown:>8} {t.params} {t.user_attrs.get('error', '')}")
    return 0
