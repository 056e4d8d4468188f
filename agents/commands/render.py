"""``bimp render``: one episode as an MP4 video, through gymnasium's ``RecordVideo`` (moviepy), headless, at real time;
or, with ``--frame K``, the frame after K steps as a PNG. Each frame draws the planner's plan (EnKTS, EnKS: the
mean plan in magenta and a few of its particles in light magenta; NMPC: its plan; MPPI and the baselines: none) and,
on the paper's scenarios, the reference lane in orange.

    bimp render --scenario overtaking --policy enkts --seed 0 --out runs/render
    bimp render --scenario highway-v0 roundabout-v0 --frame 15 --out docs/img/highway   # highway-v0.png ...
"""

from __future__ import annotations

import argparse
import sys

import bimp.agents.evaluation.video as library
from bimp import envs
from bimp.agents.commands.args import EvaluationError, add_set_argument, parse_overrides
from bimp.agents.evaluation.video import check_request, write_frame, write_video


def main(argv: list[str] | None = None) -> int:
    # --help: the usage above, then what the library's docstring says past its first paragraph
    description = __doc__ + "\n" + library.__doc__.partition("\n\n")[2]
    parser = argparse.ArgumentParser(prog="bimp render", description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", nargs="+", default=envs.default_scenarios()[:1], metavar="ID",
                        help="one or more scenarios (short names or gym ids), one file each")
    parser.add_argument("--policy", default="enkts")
    parser.add_argument("--seed", type=int, default=0)
    add_set_argument(parser, help=None)
    parser.add_argument("--frame", type=int, default=None, metavar="K",
                        help="write the frame after K steps as OUT/<id>.png instead of the video")
    parser.add_argument("--out", default="runs/render")
    args = parser.parse_args(argv)
    try:
        overrides = parse_overrides(args.overrides)
        stray = sorted(set(overrides) - {args.policy})
        if stray:
            raise EvaluationError(f"--set names {stray}, not the policy {args.policy!r}")
        if args.frame is not None and args.frame < 1:
            raise EvaluationError(f"--frame must be >= 1, got {args.frame}")
        given = overrides.get(args.policy)
        # Every scenario checked before the first file is written.
        out = [check_request(scenario, args.policy, args.seed, args.out, given) for scenario in args.scenario][0]
        for scenario in args.scenario:
            print(write_video(scenario, args.policy, args.seed, out, given) if args.frame is None else
                  write_frame(scenario, args.policy, args.seed, out, args.frame, given), flush=True)
    except EvaluationError as err:
        print(f"bimp render: error: {err}", file=sys.stderr)
        return 2
    return 0
