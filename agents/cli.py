"""``bimp`` console script: the table of commands, each a module of :mod:`bimp.agents.commands` with its own
``main(argv)``, and the net under them all (an :class:`EvaluationError` or an ``OSError`` is one line, exit 2).

Commands load lazily so ``bimp --help`` stays instant and a command pulls in only what it uses: this module imports
nothing heavy and, of bimp, only :mod:`bimp.agents.errors` (what every command raises) at its top.
"""

from __future__ import annotations

import importlib
import os
import sys
import tempfile

from bimp.agents.errors import EvaluationError

# Each command is the module bimp.agents.commands.<name, '-' as '_'> and its main(argv).
COMMANDS = {
    "demo": "small evaluation of both scenarios and planners, with table and figures",
    "evaluate": "run policies x scenarios x seeds and write safety metrics",
    "compare": "paired per-seed comparison of two policies: McNemar, paired bootstrap",
    "aggregate": "a learning algorithm over its training seeds, intervals over the seeds",
    "leaderboard": "policies ranked per scenario and overall, paired tests of neighbours",
    "render": "one episode as an MP4 video",
    "plot": "draw the paper's figures from an evaluation folder",
    "sweep": "policies along one config key (any --param, or N with --n)",
    "frontier": "success and violations against plan time, across N / iterations",
    "tune": "tune a policy's config with Optuna on training seeds (best to configs/tuned/)",
    "bench": "plan-step timing of the planners, side by side",
    "report": "render the README's and the docs' results tables from the committed folders",
    "verify": "rerun a sample of each arm's seeds at the current code, compare every metric",
    "migrate": "turn evaluation folders of older code into ones the current code resumes",
    "drop": "take a scenario's or a label's records out of an evaluation folder",
    "merge": "copy evaluation folders' records into one (runs made apart, ranked as one)",
    "train-dynamics": "train the MLP vehicle model and print its accuracy",
    "train-rl": "train the stable-baselines3 baseline",
    "curves": "learning curves of train-rl runs over training seeds, and their hours",
}


def command_module(name: str) -> str:
    """The module of the command ``name`` (one of :data:`COMMANDS`)."""
    return f"bimp.agents.commands.{name.replace('-', '_')}"


def main(argv: list[str] | None = None) -> int:
    # pygame (highway-env's renderer) on a headless machine: no audio device, no session runtime dir.
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.gettempdir())
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        print("usage: bimp COMMAND [options]   (bimp COMMAND --help for its options)\n\ncommands:")
        for name, text in COMMANDS.items():
            print(f"  {name:<15} {text}")
        if argv and argv[0] not in ("-h", "--help"):
            print(f"\nunknown command {argv[0]!r}", file=sys.stderr)
            return 2
        return 0
    try:
        return int(importlib.import_module(command_module(argv[0])).main(argv[1:]) or 0)
    except (EvaluationError, OSError) as err:  # the net under every command: a full disk is a line, not a traceback
        where = f"{err.filename}: " if isinstance(err, OSError) and err.filename else ""
        reason = err.strerror if isinstance(err, OSError) and err.strerror else err
        print(f"bimp {argv[0]}: error: {where}{reason}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
