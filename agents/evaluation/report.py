"""The results tables of the README and the manual, rendered from the committed folders (the ``bimp report``
command: :mod:`bimp.agents.commands.report`; the tables themselves: :mod:`bimp.agents.evaluation.report_tables`).

A table lives in a markdown file between two markers, its name in the first, then its arguments where its kind takes
them::

    <!-- report: suite -->
    (rendered: never edited by hand)
    <!-- /report -->
    <!-- report: paired folders=suite,suite-tuned a=enkts b=enks -->
    <!-- /report -->

A marker's argument the table does not take, or a required one left out, is refused naming what the table takes.
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable
from pathlib import Path

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.provenance import REPO_ROOT
from bimp.agents.evaluation.report_rl import rl_verdict_table, training_table, verdict_column
from bimp.agents.evaluation.report_tables import (
    Cell,
    bench_table,
    collisions_table,
    episodes_table,
    folders_table,
    grid_table,
    overall_table,
    paired_table,
    results,
    summary_table,
    variants_table,
)

# A marker starts its line: an indented one (an example in a code block) is text.
# A table's name, then its arguments as KEY=VALUE (lists comma-separated; no spaces in a value).
MARKER = r"<!-- report: ([\w-]+)((?: [^\s=]+=[^\s]+)*) -->"
BLOCK = re.compile(rf"^({MARKER}\n)(.*?)^(<!-- /report -->)$", re.S | re.M)
BLOCK_NAMES = re.compile(r"^<!-- report: ([\w-]+)", re.M)  # any opening marker, paired or not
OPENING = re.compile(r"^<!-- report: .*$", re.M)  # an opening marker's whole line, well formed or not
WELL_FORMED = re.compile(MARKER)
TABLES: dict[str, Callable[[], tuple[str, list[Cell]]]] = {
    "paper": lambda: summary_table("paper,peers,rl"),
    "highway": lambda: grid_table([results("highway")], with_score=False),
    "highway-episodes": lambda: episodes_table(results("highway")),
    "highway-paired": lambda: collisions_table(results("highway"), "enkts", "idm"),
    "suite": lambda: grid_table([results("suite")], with_score=True),
    "suite-overall": lambda: overall_table(results("suite")),
    "rl-verdict": lambda: rl_verdict_table(results("suite")),
    # the suite's grid with the planning-vs-learning verdict as its last column (the README's)
    "suite-verdict": lambda: grid_table([results("suite")], with_score=True, extra=verdict_column(results("suite"))),
    "rl-training": lambda: training_table(results("training")),
    # EnKTS and EnKS with the road-edge guard where they left the road, beside every policy's row from the main folders
    "road-guard": lambda: grid_table([results("suite"), results("highway"), results("road-guard")], with_score=True,
                                     rows_of=results("road-guard")),
    "folders": lambda: folders_table(REPO_ROOT / "results"),
    "summary": summary_table,
    "paired": paired_table,
    "variants": variants_table,
    "bench": bench_table,
}


def render(text: str, tables: dict[str, Callable] = TABLES, cache: dict | None = None,
           where: str = "text") -> tuple[str, list[str]]:
    """``text`` with every report block rendered, and the marked arms' names (``where``: the file, for messages).
    :class:`EvaluationError` naming a block of an unknown table."""
    cache = {} if cache is None else cache
    notes: list[str] = []

    def block(match: re.Match) -> str:
        name, spec = match.group(2), match.group(2) + match.group(3)
        if name not in tables:
            raise EvaluationError(f"{where}: a report block names table {name!r}; the tables: {', '.join(tables)}")
        if spec not in cache:
            pairs = [arg.split("=", 1) for arg in match.group(3).split()]
            args = dict(pairs)
            if len(args) < len(pairs):
                raise EvaluationError(f"{where}: table {spec!r}: an argument given twice")
            try:
                cache[spec] = _build(tables[name], args, f"{where}: table {spec!r}")
            except EvaluationError as err:
                message = str(err)
                raise EvaluationError(message if message.startswith(where) else f"{where}: {message}") from None
        table, arms = cache[spec]
        notes.extend(f"table {spec}: {a.scenario} {label}: not verified, in a table of mixed code versions"
                     for a in arms for label in a.marked)
        return match.group(1) + table + "\n" + match.group(5)

    for line in OPENING.findall(text):
        if not WELL_FORMED.fullmatch(line):
            raise EvaluationError(f"{where}: malformed report marker {line!r}: `<!-- report: NAME KEY=VALUE ... -->`, "
                                  "one space between arguments, none in a value")
    # Every marker must pair, checked before any table is built: one left open would swallow the next block.
    opened, closed = len(BLOCK_NAMES.findall(text)), len(re.findall(r"^<!-- /report -->", text, re.M))
    if opened != len(BLOCK.findall(text)) or closed != opened or BLOCK_NAMES.findall(
            "".join(m.group(4) for m in BLOCK.finditer(text))):
        raise EvaluationError(f"{where}: report markers do not pair: each `<!-- report: NAME -->` needs its own "
                              "`<!-- /report -->` before the next block, each marker the whole of its line")
    return BLOCK.sub(block, text), notes


def _build(table: Callable, args: dict[str, str], where: str) -> tuple[str, list[Cell]]:
    """``table`` built with the marker's arguments; one it does not take refused naming the ones it does."""
    parameters = inspect.signature(table).parameters
    takes = list(parameters)
    extra = sorted(set(args) - set(takes))
    if extra:
        raise EvaluationError(f"{where}: no argument {extra[0]!r}"
                              + (f"; it takes {', '.join(takes)}" if takes else "; it takes none"))
    missing = [name for name, p in parameters.items() if p.default is inspect.Parameter.empty and name not in args]
    if missing:
        raise EvaluationError(f"{where}: argument {missing[0]!r} missing; it takes {', '.join(takes)}")
    return table(**args)


def default_files() -> list[Path]:
    return [REPO_ROOT / "README.md", REPO_ROOT / "results" / "README.md", *sorted((REPO_ROOT / "docs").rglob("*.md"))]
