"""The results tables of the README and the manual, rendered from the committed folders (the ``bimp report``
command: :mod:`bimp.agents.commands.report`).

A table lives in a markdown file between two markers, its name in the first::

    <!-- report: suite -->
    (rendered: never edited by hand)
    <!-- /report -->

Every number a reader sees in such a table comes from the records of its folders (``episodes.jsonl``: the latest
record per seed, :func:`bimp.agents.records.latest_records`), through the same statistics as ``bimp evaluate``'s
summary (:func:`bimp.agents.metrics.summarize`), ``bimp aggregate`` and ``bimp leaderboard``. Arms of a learning
algorithm's training seeds (labels ``NAME-s1``, ``NAME-s2``, ...) are one column: the mean over the seeds, with
the range of the seeds' own values. A table whose arms were made at more than one code version marks with ``†``
each arm that ``bimp verify`` did not find the same at a later one, and the command names them.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bimp.agents.compare import compare, label_results
from bimp.agents.errors import EvaluationError
from bimp.agents.leaderboard import leaderboard
from bimp.agents.metrics import code_version, record_label, summarize
from bimp.agents.provenance import REPO_ROOT
from bimp.agents.records import format_stat, latest_records, read_records
from bimp.agents.verification import arm_key, read_verified

# A marker starts its line: an indented one (an example in a code block) is text.
BLOCK = re.compile(r"^(<!-- report: ([\w-]+) -->\n)(.*?)^(<!-- /report -->)$", re.S | re.M)
BLOCK_NAMES = re.compile(r"^<!-- report: ([\w-]+) -->", re.M)  # any opening marker, paired or not
SEEDED = re.compile(r"^(.+)-s(\d+)$")  # a training seed's arm: ppo-s1
MARK = "†"
NAMES = {"enkts": "EnKTS", "enks": "EnKS", "mppi": "MPPI", "nmpc": "NMPC", "nmpc-t": "NMPC-t", "idm": "IDM/MOBIL",
         "lane-keep": "lane keeping", "ppo": "PPO", "sac": "SAC", "enkts-guard": "EnKTS + guard",
         "enks-guard": "EnKS + guard"}


@dataclass
class Cell:
    """A column's records on one scenario: one label, or a learning algorithm's training seeds (``runs``)."""

    scenario: str
    column: str
    runs: dict[str, list[dict]]  # label -> its latest ok records
    marked: list[str]  # the labels made at an unverified older code version (see the module doc)

    @functools.cached_property
    def summaries(self) -> dict[str, dict]:
        """Each label's summary (:func:`bimp.agents.metrics.summarize`), computed once for every metric read."""
        return {label: summarize([{**r, "label": label} for r in records])[f"{label}/{self.scenario}"]
                for label, records in self.runs.items()}


def _arms(folders: list[Path]) -> list[Cell]:
    """The arms of ``folders`` grouped by scenario and column, marked where their code versions are mixed.

    Each record stands for its code version, or for the commit ``bimp verify`` found its arm the same at (in a
    checkout without uncommitted changes, from that record's version). The table is mixed when its records stand for
    more than one code; then every arm with a record not so verified is marked."""
    grouped: dict[tuple[str, str], dict[str, list[dict]]] = {}
    stands_for: set[str] = set()  # the codes the table's records stand for
    unverified: set[tuple[str, str]] = set()  # (scenario, label) with a record bimp verify did not find the same
    for folder in folders:
        verified = read_verified(folder)
        for r in latest_records(read_records(folder)):
            if r["status"] != "ok":
                continue
            label = record_label(r)
            grouped.setdefault((r["scenario"], SEEDED.sub(r"\1", label)), {}).setdefault(label, []).append(r)
            found = verified.get(arm_key(r["scenario"], label, r.get("config_hash")))
            if (found and found["outcome"] == "same" and found.get("dirty") is False
                    and code_version(r) in (found.get("versions") or ())):
                stands_for.add(found["commit"])
            else:
                stands_for.add(code_version(r))
                unverified.add((r["scenario"], label))
    mixed = len(stands_for) > 1
    return [Cell(scenario, column, runs, sorted(label for label in runs if mixed and (scenario, label) in unverified))
            for (scenario, column), runs in sorted(grouped.items())]


def _column_name(column: str, runs: dict) -> str:
    name = NAMES.get(column, column)
    return f"{name} ({len(runs)} seeds)" if len(runs) > 1 and any(SEEDED.match(label) for label in runs) else name


def _stat(arm: Cell, metric: str) -> dict | None:
    """The arm's ``metric``: its summary statistic with its interval; over training seeds, the mean of the seeds'
    means with their range as the interval."""
    means = []
    for summary in arm.summaries.values():
        entry = summary.get(metric)
        if not entry or entry.get("mean") is None:
            return None
        if len(arm.runs) == 1:
            return entry
        means.append(entry["mean"])
    return {"mean": float(np.mean(means)), "ci_low": float(min(means)), "ci_high": float(max(means))}


def _short(stat: dict | None, digits: int = 2) -> str:
    if not stat or stat.get("mean") is None:
        return "-"
    return f"{stat['mean']:.{digits}f} [{stat['ci_low']:.{digits}f}, {stat['ci_high']:.{digits}f}]"


def _mark(arm: Cell) -> str:
    return MARK if arm.marked else ""


def _footnote(arms: list[Cell]) -> list[str]:
    marked = [a for a in arms if a.marked]
    if not marked:
        return []
    return ["", f"{MARK} {len(marked)} of {len(arms)} cells: the table's arms were made at more than one code "
            "version, and `bimp verify` has not found these the same at a later one (`bimp report` names them)."]


def metrics_table(folders: list[Path]) -> tuple[str, list[Cell]]:
    """A row per scenario and policy: episodes, success, collision, off road and progress, with their intervals
    (Wilson 95% for rates, bootstrap of the mean for progress; over training seeds, the seeds' range)."""
    arms = _arms(folders)
    lines = ["| scenario | policy | episodes | success | collision | off road | progress [m] |",
             "|---|---|---|---|---|---|---|"]
    for a in arms:
        counts = {len(records) for records in a.runs.values()}
        episodes = f"{len(a.runs)} x {counts.pop()}" if len(a.runs) > 1 and len(counts) == 1 else \
            str(sum(len(records) for records in a.runs.values()))
        cells = [format_stat(_stat(a, m)) for m in ("success_rate", "collision_rate", "offroad_rate", "progress_m")]
        lines.append(f"| {a.scenario} | {_column_name(a.column, a.runs)}{_mark(a)} | {episodes} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines + _footnote(arms)), arms


def grid_table(folders: list[Path], with_score: bool, rows_of: Path | None = None) -> tuple[str, list[Cell]]:
    """A row per scenario, a column per policy: success (Wilson 95%; over training seeds their range) and, with
    ``with_score``, the mean closed-loop score after a semicolon; ``-`` where a policy did not run. ``rows_of``: only
    the scenarios that folder (one of ``folders``, a study beside the main folders) ran."""
    arms = _arms(folders)
    if rows_of is not None:
        rows = {r["scenario"] for r in read_records(rows_of)}
        arms = [a for a in arms if a.scenario in rows]
    columns = list(dict.fromkeys(a.column for a in arms))
    by = {(a.scenario, a.column): a for a in arms}
    runs = {a.column: a.runs for a in arms}
    lines = ["| scenario | " + " | ".join(_column_name(c, runs[c]) for c in columns) + " |",
             "|---|" + "---|" * len(columns)]
    for scenario in sorted({a.scenario for a in arms}):
        cells = []
        for column in columns:
            a = by.get((scenario, column))
            if a is None:
                cells.append("-")
                continue
            score = _stat(a, "score") if with_score else None
            cells.append(_short(_stat(a, "success_rate")) + (f"; {score['mean']:.2f}" if score else "") + _mark(a))
        lines.append(f"| {scenario} | " + " | ".join(cells) + " |")
    return "\n".join(lines + _footnote(arms)), arms


def overall_table(folder: Path) -> tuple[str, list[Cell]]:
    """``bimp leaderboard``'s overall ranking of ``folder`` (every scenario weighted equally): rank, policy, score
    and success with their stratified bootstrap intervals, the policies that ran every scenario; a row whose records
    are of mixed code versions (the leaderboard's own check) marked."""
    board = leaderboard([folder], metric="score", allow_mixed=True)["overall"]
    lines = ["| rank | policy | score | success | episodes |", "|---|---|---|---|---|"]
    marked = 0
    for row in board["rows"]:
        mark = MARK if row["mixed"] else ""
        marked += bool(mark)
        lines.append(f"| {row['rank']} | {NAMES.get(row['label'], row['label'])}{mark} | "
                     f"{_short(row['score'], 3)} | {_short(row['success_rate'], 3)} | {row['episodes']} |")
    if marked:
        lines += ["", f"{MARK} {marked} of {len(board['rows'])} rows: their scenarios' records are of more than one "
                  "code version (`bimp leaderboard --allow-mixed` says which)."]
    return "\n".join(lines), []


def episodes_table(folder: Path) -> tuple[str, list[Cell]]:
    """A row per scenario and policy of ``folder``: episodes, success (Wilson 95%), collision and off-road counts,
    progress (bootstrap 95%), the median plan time per step (mean over episodes) and the first failed seeds."""
    arms = _arms([folder])
    order = {name: i for i, name in enumerate(NAMES)}
    lines = ["| env | policy | episodes | success | collisions | off road | progress [m] | plan ms (median) | "
             "failed seeds |", "|---|---|---|---|---|---|---|---|---|"]
    for a in sorted(arms, key=lambda a: (a.scenario, order.get(a.column, len(order)), a.column)):
        (summary,) = a.summaries.values()
        failed = summary["failed_seeds"]["success"]
        seeds = ", ".join(map(str, failed[:10])) + (" ..." if len(failed) > 10 else "")
        progress, plan = summary.get("progress_m") or {}, summary.get("plan_time_ms_p50") or {}
        lines.append(f"| {a.scenario} | {NAMES.get(a.column, a.column)}{_mark(a)} | {summary['episodes']} | "
                     f"{_short(summary['success_rate'])} | {summary['collision_rate']['k']} | "
                     f"{summary['offroad_rate']['k']} | {_short(progress, 0)} | "
                     f"{plan.get('mean', float('nan')):.1f} | {seeds} |")
    return "\n".join(lines + _footnote(arms)), arms


def paired_table(folder: Path, label_a: str, label_b: str) -> tuple[str, list[Cell]]:
    """``label_a`` against ``label_b`` in ``folder``, seed by seed per scenario (``bimp compare``): collisions of
    each with the exact McNemar p, and the paired bootstrap 95% interval of the progress difference."""
    result = compare(label_results(folder, label_a), label_results(folder, label_b))
    a, b = NAMES.get(label_a, label_a), NAMES.get(label_b, label_b)
    lines = [f"| env | collisions {a} vs {b} (McNemar p) | progress {a} - {b} [m] |", "|---|---|---|"]
    for scenario, e in result.items():
        c, d = e["collision_rate"], e["progress_m"]
        n = e["pairs"]
        lines.append(f"| {scenario} | {round(c['a'] * n)} vs {round(c['b'] * n)} (p = {c['p_value']:.2g}) | "
                     f"{d['mean_diff']:+.0f} [{d['ci_low']:+.0f}, {d['ci_high']:+.0f}] |")
    return "\n".join(lines), []


def folders_table(root: Path) -> tuple[str, list[Cell]]:
    """Every evaluation folder under ``root`` (each with an ``episodes.jsonl``): its episodes (the latest record per
    seed), arms, code versions and the arms ``bimp verify`` found the same; a tuning study's trial folders left out
    (``bimp tune``'s own, one per sampled config)."""
    lines = ["| folder | episodes | arms | code versions | verified the same |", "|---|---|---|---|---|"]
    for path in sorted(root.rglob("episodes.jsonl")):
        folder = path.parent
        if "trials" in folder.relative_to(root).parts:
            continue
        latest = latest_records(read_records(folder))
        arms = {(r["scenario"], record_label(r), r.get("config_hash")) for r in latest}
        same = sum(v["outcome"] == "same" for v in read_verified(folder).values())
        lines.append(f"| {folder.relative_to(root.parent)} | {len(latest)} | {len(arms)} | "
                     f"{len({code_version(r) for r in latest})} | {same} |")
    return "\n".join(lines), []


def _results(name: str) -> Path:
    return REPO_ROOT / "results" / name


TABLES: dict[str, Callable[[], tuple[str, list[Cell]]]] = {
    "paper": lambda: metrics_table([_results("paper"), _results("peers"), _results("rl")]),
    "highway": lambda: grid_table([_results("highway")], with_score=False),
    "highway-episodes": lambda: episodes_table(_results("highway")),
    "highway-paired": lambda: paired_table(_results("highway"), "enkts", "idm"),
    "suite": lambda: grid_table([_results("suite")], with_score=True),
    "suite-overall": lambda: overall_table(_results("suite")),
    # EnKTS and EnKS with the road-edge guard where they left the road, beside every policy's row from the main folders
    "road-guard": lambda: grid_table([_results("suite"), _results("highway"), _results("road-guard")], with_score=True,
                                     rows_of=_results("road-guard")),
    "folders": lambda: folders_table(REPO_ROOT / "results"),
}


def render(text: str, tables: dict[str, Callable] = TABLES, cache: dict | None = None,
           where: str = "text") -> tuple[str, list[str]]:
    """``text`` with every report block rendered, and the marked arms' names (``where``: the file, for messages).
    :class:`EvaluationError` naming a block of an unknown table."""
    cache = {} if cache is None else cache
    notes: list[str] = []

    def block(match: re.Match) -> str:
        name = match.group(2)
        if name not in tables:
            raise EvaluationError(f"{where}: a report block names table {name!r}; the tables: {', '.join(tables)}")
        if name not in cache:
            cache[name] = tables[name]()
        table, arms = cache[name]
        notes.extend(f"table {name}: {a.scenario} {label}: not verified, in a table of mixed code versions"
                     for a in arms for label in a.marked)
        return match.group(1) + table + "\n" + match.group(4)

    # Every marker must pair, checked before any table is built: one left open would swallow the next block.
    opened, closed = len(BLOCK_NAMES.findall(text)), len(re.findall(r"^<!-- /report -->", text, re.M))
    if opened != len(BLOCK.findall(text)) or closed != opened or BLOCK_NAMES.findall(
            "".join(m.group(3) for m in BLOCK.finditer(text))):
        raise EvaluationError(f"{where}: report markers do not pair: each `<!-- report: NAME -->` needs its own "
                              "`<!-- /report -->` before the next block, each marker the whole of its line")
    return BLOCK.sub(block, text), notes


def default_files() -> list[Path]:
    return [REPO_ROOT / "README.md", REPO_ROOT / "results" / "README.md", *sorted((REPO_ROOT / "docs").rglob("*.md"))]
