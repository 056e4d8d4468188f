"""``bimp`` console script: one sub-command per job, each module parsing its own arguments, and the argument
helpers the commands share (``--set``, ``--label``, the backend options, ``--out``).

Modules load lazily so ``bimp --help`` stays instant and a command pulls in only what it uses: this module imports
nothing heavy and, of bimp, only :mod:`bimp.agents.errors` (what every command raises and checks) at its top.
"""

from __future__ import annotations

import importlib
import os
import sys
import tempfile

# Re-exported while commands move to bimp.agents.commands: what they raise and check (bimp.agents.errors) and the
# argument helpers they share (bimp.agents.commands.args).
from bimp.agents.commands.args import add_backend_arguments, add_set_argument, backend_options  # noqa: F401
from bimp.agents.errors import EvaluationError, check_out_dir, parse_labels, parse_overrides  # noqa: F401

COMMANDS = {
    "demo": ("bimp.agents.demo", "small evaluation of both scenarios and planners, with table and figures"),
    "evaluate": ("bimp.agents.evaluate", "run policies x scenarios x seeds and write safety metrics"),
    "compare": ("bimp.agents.compare", "paired per-seed comparison of two policies: McNemar, paired bootstrap"),
    "aggregate": ("bimp.agents.aggregate", "a learning algorithm over its training seeds, intervals over the seeds"),
    "leaderboard": ("bimp.agents.leaderboard", "policies ranked per scenario and overall, paired tests of neighbours"),
    "render": ("bimp.agents.video", "one episode as an MP4 video"),
    "plot": ("bimp.agents.plots", "draw the paper's figures from an evaluation folder"),
    "sweep": ("bimp.agents.sweep", "policies along one config key (any --param, or N with --n)"),
    "frontier": ("bimp.agents.sweep:frontier_main", "success and violations against plan time, across N / iterations"),
    "tune": ("bimp.agents.tune", "tune a policy's config with Optuna on training seeds (best to configs/tuned/)"),
    "bench": ("bimp.agents.bench", "plan-step timing of the planners, side by side"),
    "report": ("bimp.agents.report", "render the README's and the docs' results tables from the committed folders"),
    "verify": ("bimp.agents.verify", "rerun a sample of each arm's seeds at the current code, compare every metric"),
    "migrate": ("bimp.agents.migrate", "turn evaluation folders of older code into ones the current code resumes"),
    "drop": ("bimp.agents.drop", "take a scenario's or a label's records out of an evaluation folder"),
    "merge": ("bimp.agents.merge", "copy evaluation folders' records into one (runs made apart, ranked as one)"),
    "train-dynamics": ("bimp.planners.dynamics_train", "train the MLP vehicle model and print its accuracy"),
    "train-rl": ("bimp.agents.rl_train", "train the stable-baselines3 baseline"),
}


def main(argv: list[str] | None = None) -> int:
    # pygame (highway-env's renderer) on a headless machine: no audio device, no session runtime dir.
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.gettempdir())
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        print("usage: bimp COMMAND [options]   (bimp COMMAND --help for its options)\n\ncommands:")
        for name, (_, text) in COMMANDS.items():
            print(f"  {name:<15} {text}")
        if argv and argv[0] not in ("-h", "--help"):
            print(f"\nunknown command {argv[0]!r}", file=sys.stderr)
            return 2
        return 0
    module, _, function = COMMANDS[argv[0]][0].partition(":")
    try:
        return int(getattr(importlib.import_module(module), function or "main")(argv[1:]) or 0)
    except (EvaluationError, OSError) as err:  # the net under every command: a full disk is a line, not a traceback
        where = f"{err.filename}: " if isinstance(err, OSError) and err.filename else ""
        reason = err.strerror if isinstance(err, OSError) and err.strerror else err
        print(f"bimp {argv[0]}: error: {where}{reason}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
