"""``bimp train-rl``: train the stable-baselines3 baseline (:mod:`bimp.agents.rl_train`), one run or a grid of
scenarios x seeds on a process pool or a Ray cluster, every run resumable.

    bimp train-rl --scenario overtaking --algo ppo --timesteps 150000 --seed 0 --vec-env subproc
    bimp train-rl --scenario cut-in-hard stalled-vehicle-hard --seed 1 2 3 --workers 2
    bimp train-rl --scenario cut-in-hard stalled-vehicle-hard --seed 1 2 3 --backend ray --address HEAD:6379
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, NoReturn

from bimp import envs
from bimp.agents import rl_train
from bimp.agents.commands.args import add_backend_arguments
from bimp.agents.errors import EvaluationError, check_out_dir
from bimp.agents.evaluation.backends import BackendError, check_backend, run_groups, start_backend
from bimp.agents.rl import ALGOS, RLConfig
from bimp.agents.rl_train import (
    check_model,
    check_same_run,
    job_crashed,
    report_line,
    run_name,
    train_job,
    wall_s,
)
from bimp.configs import load_config, read_yaml


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp train-rl", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", nargs="+", action="extend", required=True,
                        help=f"one or more of {sorted(envs.SCENARIOS)}")
    parser.add_argument("--algo", choices=ALGOS, default=None, help="ppo (default) or sac; or algo: in --config")
    parser.add_argument("--timesteps", type=int, default=None, help="total env steps (default: RLConfig's)")
    parser.add_argument("--seed", type=int, nargs="+", action="extend", default=None,
                        help="training seed(s) (default: RLConfig's)")
    parser.add_argument("--n-envs", type=int, default=None)
    parser.add_argument("--vec-env", choices=("dummy", "subproc"), default=None,
                        help="step the envs in this process (dummy, one core) or one process each (subproc)")
    parser.add_argument("--config", type=Path, help="YAML file of RLConfig overrides (unknown keys are errors)")
    # str, not Path: Path("") is "." and would pass the empty-name check as the current folder.
    parser.add_argument("--out", help="one run's output folder (default RUNS_DIR/{algo}_{scenario}_s{seed})")
    parser.add_argument("--runs-dir", default=None, help="where the runs' folders go, each under its "
                        "default name (default runs/rl); on a Ray cluster of several machines, a disk every node "
                        "mounts at the same path")
    parser.add_argument("--workers", type=int, default=1, help="runs trained at once on this machine (default 1)")
    add_backend_arguments(parser)
    parser.add_argument("--eval-seeds", type=int, default=5, help="episodes of the final check against the zero "
                        "action (0: skip)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    def fail(error: object) -> NoReturn:
        parser.exit(2, f"bimp train-rl: error: {error}\n")

    values: dict[str, Any] = {}
    if args.config:
        try:
            data = read_yaml(args.config)
        except ValueError as err:
            fail(err)
        if data is not None and not isinstance(data, dict):
            fail(f"{args.config}: expected a mapping of RLConfig overrides, got {type(data).__name__}")
        values.update({str(k): v for k, v in (data or {}).items()})  # YAML's `1:` or `yes:` named as the others
    if args.algo is not None:
        if values.get("algo", args.algo) != args.algo:  # neither may win silently
            fail(f"{args.config} sets algo: {values['algo']}, and --algo is {args.algo}: give it once")
        values["algo"] = args.algo
    for key in ("timesteps", "n_envs", "vec_env"):
        if getattr(args, key) is not None:
            values[key] = getattr(args, key)
    runs: list[tuple[RLConfig, Path]] = []
    try:
        if args.workers < 1 or args.eval_seeds < 0:
            raise ValueError(f"--workers must be >= 1 and --eval-seeds >= 0, got {args.workers} and "
                             f"{args.eval_seeds}")
        if args.out is not None and args.runs_dir is not None:
            raise ValueError("--out names one run's folder, --runs-dir the folder of the runs' folders: give one")
        check_backend(args.backend, args.address, args.ray_cpus)
        runs_dir = (check_out_dir(args.runs_dir, create=False, flag="--runs-dir") if args.runs_dir is not None
                    else Path("runs/rl"))
        one_out = check_out_dir(args.out, create=False) if args.out is not None else None
        for scenario in args.scenario:
            scenario = envs.scenario_name(envs.env_id(scenario)) or scenario  # one name per scenario, one folder
            for seed in args.seed or [values.get("seed")]:
                cfg = load_config(RLConfig, None, **{**values, "scenario": scenario,
                                             **({"seed": seed} if seed is not None else {})})
                runs.append((cfg, one_out or runs_dir / run_name(cfg)))
        if len(runs) > 1 and one_out:
            raise ValueError("--out names one run's folder; several runs each go to --runs-dir/"
                             "{algo}_{scenario}_s{seed}")
        names = [run_name(cfg) for cfg, _ in runs]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:
            raise ValueError(f"run(s) {twice} named twice: give each scenario and seed once")
        for cfg, out in runs:  # every run's folder before the first trains: no refusal hours in
            check_out_dir(out, create=False, flag="--out" if one_out else "--runs-dir")
            check_same_run(cfg, out)
    except (BackendError, EvaluationError, TypeError, ValueError) as err:
        fail(err)
    if len(runs) == 1 and args.backend == "local":
        return _train_one(*runs[0], args, fail)
    return _train_many(runs, args, fail)


def _train_one(cfg: RLConfig, out: Path, args: argparse.Namespace, fail: Callable[[object], NoReturn]) -> int:
    """One run in this process, with a progress bar over its timesteps."""
    try:
        path = rl_train.train(cfg, out, progress=not args.no_progress)  # as train_job's runs do: one to patch
    except (EvaluationError, ValueError) as err:  # a checkpoint that does not fit
        fail(err)
    print(f"model: {path}\ncurve: {out / 'curve.png'}\n"
          f"train wall time: {wall_s(out)} s")
    if args.eval_seeds:
        for who, r in check_model(cfg, path, out, args.eval_seeds).items():
            print(f"{who:>6}: progress {r['progress']:.1f} m, collisions {r['collision']:.2f}, "
                  f"off-road {r['offroad']:.2f}, return {r['return']:.1f}")
    return 0


def _train_many(runs: list[tuple[RLConfig, Path]], args: argparse.Namespace,
                fail: Callable[[object], NoReturn]) -> int:
    """The runs on the backend, a progress bar over runs and a line per run as it ends; 1 when any failed."""
    from tqdm import tqdm

    try:
        start_backend(args.backend, args.address, args.ray_cpus)
    except BackendError as err:
        fail(err)
    # Absolute: a Ray worker's working folder is not this one (on a cluster the folder must be on a shared disk).
    jobs = [(asdict(cfg), str(out.resolve()), args.eval_seeds) for cfg, out in runs]
    failed = []
    with tqdm(total=len(jobs), desc="runs", unit="run", disable=args.no_progress) as bar:
        def write(report: dict[str, Any]) -> None:
            failed.extend([report] if "error" in report else [])
            bar.update()
            tqdm.write(report_line(report))

        run_groups(jobs, train_job, job_crashed, write, backend=args.backend, workers=args.workers,
                   address=args.address, cpus=args.ray_cpus)
    if failed:
        print(f"{len(failed)} of {len(jobs)} runs failed; the same command trains them again, each from its last "
              f"checkpoint")
        return 1
    return 0
