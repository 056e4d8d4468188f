"""``bimp bench``: plan-step time of the planners side by side, and with ``--env`` env steps per second of every
scenario (:mod:`bimp.agents.evaluation.bench`, :mod:`bimp.agents.evaluation.bench_env`).

    bimp bench                        # EnKTS, EnKS, MPPI, NMPC and the floor on the overtaking scenario
    bimp bench --scenario highway-v0  # EnKTS on a highway-env road vs the number of OVs and road points
    bimp bench --env                  # env steps per second, bimp's fast traffic core beside highway-env's
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from bimp.agents.errors import EvaluationError, check_out_dir
from bimp.agents.evaluation.bench import (
    SCENARIO,
    report,
    report_device,
    report_highway,
    run,
    run_device,
    run_highway,
)
from bimp.agents.evaluation.bench_env import report_env, run_env
from bimp.agents.files import write_atomic
from bimp.envs.highway.adapter import SUPPORTED as HIGHWAY_IDS


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per planner (default 30, quick 5)")
    parser.add_argument("--quick", action="store_true",
                        help="N in {50, 500} and 5 repeats (--scenario ID: K in {2, 8}, P in {40, 160})")
    parser.add_argument("--steps", type=int, default=5,
                        help="env steps before the timed ones (driven by EnKTS; by IDM with --scenario ID)")
    parser.add_argument("--device", action="store_true", help="EnKTS alone on JAX's default device, N up to 10^5")
    parser.add_argument("--scenario", default=SCENARIO, choices=(SCENARIO, *HIGHWAY_IDS),
                        help="overtaking (the paper's, default) or a wrapped highway-env id: EnKTS and EnKS on its "
                             "road, with K and P sweeps")
    parser.add_argument("--env", nargs="*", default=None, metavar="SCENARIO",
                        help="env steps per second of these scenarios (none named: every one), bimp's fast traffic "
                             "core beside highway-env's own (bimp.agents.evaluation.bench_env); --out also writes a "
                             ".md beside")
    parser.add_argument("--env-steps", type=int, default=50, help="with --env: steps per round (3 rounds a core)")
    parser.add_argument("--note", default=None, help="a remark stored in the JSON (e.g. what else loaded the machine)")
    parser.add_argument("--out", type=Path, default=None, help="also write the result as JSON here")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    repeats = args.repeats if args.repeats is not None else (5 if args.quick else 30)
    if repeats < 1 or args.steps < 0:
        parser.error("--repeats must be >= 1 and --steps >= 0")
    if args.device and args.scenario != SCENARIO:
        parser.error("--device times the overtaking scenario only")
    if args.out is not None:  # before minutes of timing, not after
        try:
            if args.out.is_dir() or not args.out.name:
                raise EvaluationError(f"--out {args.out} is a folder: name the JSON file to write")
            check_out_dir(args.out.parent, create=False)
        except EvaluationError as err:
            print(f"bimp bench: error: {err}", file=sys.stderr)
            return 2
    progress = lambda s: print(s, flush=True)  # noqa: E731
    if args.env is not None:
        return _env_command(args.env, args.env_steps, args.quick, args.out, args.note, progress)
    print(f"timing {'quick ' if args.quick else ''}benchmark ({repeats} repeats per planner)...", flush=True)
    if args.device:
        result, render = run_device(repeats, args.steps, progress=progress), report_device
    elif args.scenario != SCENARIO:
        result, render = run_highway(args.scenario, repeats, args.quick, args.steps, progress=progress), report_highway
    else:
        result, render = run(repeats, args.quick, args.steps, progress=progress), report
    if args.note:
        result["note"] = args.note
    text = render(result) + (f"\nnote: {args.note}" if args.note and render is not report_highway else "")
    print()
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(args.out, json.dumps(result, indent=2))
        print(f"wrote {args.out}")
    return 0


def _env_command(scenarios: Sequence[str], steps: int, quick: bool, out: Path | None, note: str | None,
            progress: Callable[[str], None]) -> int:
    """``bimp bench --env``: :func:`run_env` printed (and written to ``out`` as JSON, with the markdown beside it as
    ``.md``); the exit status (2: a bad request, refused before any timing)."""
    if steps < 1:
        print("bimp bench: error: --env-steps must be >= 1", file=sys.stderr)
        return 2
    try:
        result = run_env(scenarios, steps=steps, rounds=1 if quick else 3, progress=progress)
    except ValueError as err:  # an unknown scenario
        print(f"bimp bench: error: {err}", file=sys.stderr)
        return 2
    if note:
        result["note"] = note
    text = report_env(result) + (f"\nnote: {note}\n" if note else "")
    print()
    print(text)
    if out is not None:
        write_atomic(out, json.dumps(result, indent=2))
        write_atomic(out.with_suffix(".md"), text)
        print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0
