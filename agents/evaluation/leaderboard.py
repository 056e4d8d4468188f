"""Every policy of one or more evaluation folders ranked per scenario and overall (the ``bimp leaderboard`` command:
:mod:`bimp.agents.commands.leaderboard`).

Per scenario (a suite family, a highway-env road or a paper scenario), one row per policy label: success, collision,
at-fault collision and off-road rates with their Wilson 95% intervals, the closed-loop score with its bootstrap 95%
interval (``n/a`` where a record lacks it: records made before the score existed), the plan time per step (each
episode's median, averaged over the episodes, bootstrap interval) and the episodes, all as
:func:`bimp.agents.evaluation.metrics.summarize` computes them. Rows are ranked by ``--metric`` (default: the score when
every record carries one, else the success rate; the output says which). Between each pair of neighbours in the ranking,
paired on the seeds both ran (:func:`bimp.agents.evaluation.compare.compare`): the exact McNemar test on success and the
paired bootstrap interval of the mean score difference.

Overall: for the policies that ran every scenario, the mean over scenarios of each scenario's mean, every scenario
weighted equally, with the percentile interval of a bootstrap stratified by scenario (each scenario's seeds resampled
within it: :func:`bimp.agents.evaluation.stats.stratified_bootstrap`); the neighbours' McNemar test pools every paired
(scenario, seed), their score difference gets the same stratified bootstrap over the per-seed differences.

A leaderboard compares like with like or says it does not: within one scenario, every policy must have results on
the same seeds, and every record must come from the same code version (the ``git_commit``, ``+dirty`` when the tree
had uncommitted changes; ``bimp_version`` where a record has no commit). Otherwise it prints what differs and exits
2; ``--allow-mixed`` ranks them anyway, the affected rows marked. A label that holds two configs in one folder's
scenario is refused always, as ``bimp compare`` refuses it: that is two arms under one name.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.compare import compare
from bimp.agents.evaluation.metrics import code_version, summarize
from bimp.agents.evaluation.records import format_stat, latest_records, read_records, record_label
from bimp.agents.evaluation.stats import mcnemar_exact, stratified_bootstrap
from bimp.agents.evaluation.verification import as_current
from bimp.agents.files import write_figure
from bimp.agents.registry import policy_color

# What a row shows, in its order: (metric, column heading). The four rates are per-episode 0/1 outcomes (Wilson),
# the score and the plan time per-episode numbers (bootstrap of the mean), as in every summary.
COLUMNS = (("success_rate", "success"), ("collision_rate", "collision"),
           ("at_fault_collision_rate", "at-fault collision"), ("offroad_rate", "off-road"), ("score", "score"),
           ("plan_time_ms_p50", "plan ms (p50)"))
RANKABLE = ("score", "success_rate")  # both in [0, 1], higher is better
# Metrics that older records lack (None or absent): a row shows them only when every one of its records has them.
OPTIONAL = ("score", "at_fault_collision_rate")
NA = "n/a"
INTERVALS = ("Intervals: 95%. Per scenario: Wilson for success, collision, at-fault collision and off-road (per "
             "episode); bootstrap of the mean (BCa) for the score and the plan time (each episode's median plan "
             "time per step). Overall: the mean over scenarios, each scenario weighted equally, with the percentile "
             "interval of a bootstrap stratified by scenario (each scenario's seeds resampled within it, 10,000 "
             "resamples). Neighbours: paired on the seeds both ran; exact McNemar test on success (only A / only B: "
             "the seeds only A or only B succeeded on), paired bootstrap of the mean score difference A - B (overall: "
             "McNemar over every paired (scenario, seed), the difference stratified by scenario).")


@dataclass
class ArmResults:
    """One row's records: a policy label on one scenario, from one folder."""

    scenario: str
    label: str  # as shown: the record's label, prefixed by its folder where two folders hold it (see load_arms)
    policy: str  # the registry name (the colour in the figure)
    folder: str
    config_hash: str | None
    results: list[dict]  # the latest ok record per seed, by seed
    error_seeds: list[int] = field(default_factory=list)  # seeds whose latest record is an error: no result

    @property
    def seeds(self) -> list[int]:
        return [r["seed"] for r in self.results]


def _short(version: str) -> str:
    return version[:7] + version[40:] if len(version) >= 40 else version  # a commit's 7 digits, +dirty kept


def seed_ranges(seeds) -> str:
    """``1000-1049, 1051, 1060-1099``: sorted seeds with runs of consecutive ones shortened."""
    ordered, parts = sorted(set(seeds)), []
    for seed in ordered:
        if parts and seed == parts[-1][1] + 1:
            parts[-1][1] = seed
        else:
            parts.append([seed, seed])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in parts) or "none"


def load_arms(folders: list[str | Path]) -> list[ArmResults]:
    """The arms of ``folders``: per folder, scenario and label, the latest record per seed
    (:func:`bimp.agents.evaluation.records.latest_records`), the ok ones as results and the errors' seeds.

    A label on a scenario of one folder must hold one config (``config_hash``): else :class:`EvaluationError`, as
    ``bimp compare`` refuses it. A label found on one scenario in two folders is shown as ``FOLDER:LABEL`` on every
    scenario, so the two stay two rows; a label in several folders on different scenarios stays one policy (the
    overall row joins its scenarios). :class:`EvaluationError` for a folder without any record."""
    grouped: dict[tuple[str, str, str], list[dict]] = {}
    for folder in map(str, folders):
        records = as_current(folder, latest_records(read_records(folder)))  # verified arms: the current code's
        if not records:
            raise EvaluationError(f"no episode records in {folder} (a folder written by bimp evaluate holds "
                                  "episodes.jsonl)")
        for r in records:
            grouped.setdefault((folder, r["scenario"], record_label(r)), []).append(r)
    places: dict[tuple[str, str], set[str]] = {}
    for folder, scenario, label in grouped:
        places.setdefault((scenario, label), set()).add(folder)
    qualified = {label for (_, label), where in places.items() if len(where) > 1}
    arms = []
    for (folder, scenario, label), rs in sorted(grouped.items(), key=lambda item: (item[0][1], item[0][2], item[0][0])):
        hashes = sorted({str(r.get("config_hash")) for r in rs})
        if len(hashes) > 1:
            raise EvaluationError(f"{folder} holds {label!r} on {scenario} under {len(hashes)} configs "
                                  f"({', '.join(hashes)}): two arms under one name; give each its own --label")
        ok = sorted((r for r in rs if r["status"] == "ok"), key=lambda r: r["seed"])
        done = {r["seed"] for r in ok}
        arms.append(ArmResults(scenario=scenario, label=f"{folder}:{label}" if label in qualified else label,
                        policy=rs[0]["policy"], folder=folder, config_hash=rs[0].get("config_hash"), results=ok,
                        error_seeds=sorted(r["seed"] for r in rs if r["status"] != "ok" and r["seed"] not in done)))
    return arms


# --- what may not be mixed ------------------------------------------------------------------------------------
@dataclass
class Mixing:
    """One scenario whose rows do not compare like with like: ``kind`` "seeds" or "code", the ``labels`` of the rows
    it marks, and ``detail``, what differs."""

    scenario: str
    kind: str
    labels: list[str]
    detail: str

    def message(self) -> str:
        what = "different seeds" if self.kind == "seeds" else "different code versions"
        return f"{self.scenario}: {what}: {self.detail}"


def find_mixing(arms: list[ArmResults]) -> list[Mixing]:
    """Per scenario: the rows that lack some seed another row of the scenario has a result on (a seed set of its
    own, or an episode that raised: its seed has no result), and whether its records come from more than one
    code version (:func:`code_version`), within one arm or between arms (two folders made by different code). A
    code mix marks every row of the scenario: each comparison there rests on records of two codes."""
    found = []
    for scenario in sorted({a.scenario for a in arms}):
        rows = [a for a in arms if a.scenario == scenario]
        union = set().union(*(a.seeds for a in rows))
        short = [(a, sorted(union - set(a.seeds))) for a in rows if union - set(a.seeds)]
        if short:
            parts = [f"{a.label} has {len(a.seeds)} seeds ({seed_ranges(a.seeds)})" for a in rows]
            parts += [f"{a.label} lacks {len(missing)} ({seed_ranges(missing)})"
                      + (f", {len(a.error_seeds)} of them episodes that raised ({seed_ranges(a.error_seeds)})"
                         if a.error_seeds else "") for a, missing in short]
            found.append(Mixing(scenario, "seeds", [a.label for a, _ in short], "; ".join(parts)))
        versions = {a.label: Counter(code_version(r) for r in a.results) for a in rows}
        if len(set().union(*versions.values())) > 1:
            detail = "; ".join(f"{label} " + ", ".join(f"{_short(v)} ({n} episodes)" for v, n in sorted(c.items()))
                               for label, c in versions.items())
            found.append(Mixing(scenario, "code", [a.label for a in rows], detail))
    return found


# --- the ranking ----------------------------------------------------------------------------------------------
def has_all(results: list[dict], metric: str) -> bool:
    """Whether every record of ``results`` carries ``metric`` (older records lack the score: None or absent)."""
    return bool(results) and all(r["metrics"].get(metric) is not None for r in results)


def ranking_metric(arms: list[ArmResults], requested: str | None = None) -> tuple[str, str]:
    """``(metric, why)``: ``requested``, else the score where every record carries one, else the success rate.
    :class:`EvaluationError` for ``--metric score`` over records some of which lack it (a rank by a score some rows
    do not have would put them anywhere)."""
    results = [r for a in arms for r in a.results]
    lacking = sum(r["metrics"].get("score") is None for r in results)
    if requested is not None and requested not in RANKABLE:
        raise EvaluationError(f"--metric {requested!r}: choose one of {', '.join(RANKABLE)}")
    if requested == "score" and lacking:
        raise EvaluationError(f"--metric score: {lacking} of {len(results)} records carry no score (made before the "
                              "score existed, or by an env that does not report what it needs); rank by "
                              "--metric success_rate")
    if requested:
        return requested, f"ranked by {requested} (--metric)"
    if lacking:
        return "success_rate", (f"ranked by success_rate: {lacking} of {len(results)} records carry no score (made "
                                "before the score existed), so the score shows n/a")
    return "score", "ranked by score (every record carries one)"


def _rank_key(row: dict, metric: str) -> tuple:
    # Ties on the metric: the success rate (when ranking by the score), then fewer collisions, then the label, so
    # the same records always give the same order.
    second = -row["success_rate"]["mean"] if metric == "score" else 0.0
    return -row[metric]["mean"], second, row["collision_rate"]["mean"], row["label"]


def _results_by_seed(arm_results: list[dict], scenario: str) -> dict[tuple[str, int], dict]:
    return {(scenario, r["seed"]): r["metrics"] for r in arm_results}


def _neighbour(a: dict, b: dict, entry: dict | None) -> dict:
    """The paired test of two neighbours from :func:`bimp.agents.evaluation.compare.compare`'s entry for their
    scenario."""
    if entry is None:
        return {"a": a["label"], "b": b["label"], "pairs": 0, "success_rate": None, "score": None,
                "collision_rate": None}
    both_scored = a["score"] is not None and b["score"] is not None  # a difference over some seeds only: no
    return {"a": a["label"], "b": b["label"], "pairs": entry["pairs"], "success_rate": entry["success_rate"],
            "collision_rate": entry["collision_rate"], "score": entry["score"] if both_scored else None}


def scenario_board(arms: list[ArmResults], metric: str, marks: dict[str, list[str]]) -> dict:
    """One scenario's rows (``summarize``'s statistics for :data:`COLUMNS`, ``None`` for an optional metric some
    record lacks), ranked by ``metric``, and the paired tests of neighbours. ``marks``: ``{label: [kinds]}`` of
    the rows mixed (:func:`find_mixing`)."""
    scenario = arms[0].scenario
    summary = summarize([{**r, "label": a.label} for a in arms for r in a.results])
    rows = []
    for a in arms:
        if not a.results:
            continue  # only errors: nothing to rank; find_mixing names its seeds
        entry = summary[f"{a.label}/{scenario}"]
        row = {"label": a.label, "policy": a.policy, "folder": a.folder, "config_hash": a.config_hash,
               "episodes": entry["episodes"], "errors": len(a.error_seeds), "error_seeds": a.error_seeds,
               "seeds": seed_ranges(a.seeds), "code_versions": sorted({code_version(r) for r in a.results}),
               "mixed": marks.get(a.label, [])}
        for name, _ in COLUMNS:
            row[name] = entry[name] if name not in OPTIONAL or has_all(a.results, name) else None
        rows.append(row)
    rows.sort(key=lambda row: _rank_key(row, metric))
    by_label = {a.label: a for a in arms}
    neighbours = []
    for rank, (a, b) in enumerate(zip(rows, rows[1:]), start=1):
        paired = compare(_results_by_seed(by_label[a["label"]].results, scenario),
                         _results_by_seed(by_label[b["label"]].results, scenario))
        neighbours.append({"ranks": [rank, rank + 1], **_neighbour(a, b, paired.get(scenario))})
    for rank, row in enumerate(rows, start=1):
        row["rank"] = rank
    return {"scenario": scenario, "rows": rows, "neighbours": neighbours}


def overall_board(arms: list[ArmResults], metric: str, marks: dict[tuple[str, str], list[str]]) -> dict:
    """The policies that ran every scenario, each metric the mean over scenarios of its per-scenario mean (every
    scenario weighted equally) with the stratified bootstrap interval over the seeds, ranked by ``metric``; the
    neighbours' McNemar test on success pooled over every (scenario, seed) both ran, their score difference the
    mean over scenarios of the mean per-seed difference, with the same stratified bootstrap. The others are listed
    in ``left_out`` with the scenarios they lack."""
    scenarios = sorted({a.scenario for a in arms})
    per_label: dict[str, dict[str, ArmResults]] = {}
    for a in arms:
        if a.results:
            per_label.setdefault(a.label, {})[a.scenario] = a
    left_out = {label: [s for s in scenarios if s not in got] for label, got in per_label.items()
                if len(got) < len(scenarios)}
    rows = []
    for label, got in per_label.items():
        if label in left_out:
            continue
        first = next(iter(got.values()))
        row = {"label": label, "policy": first.policy, "episodes": sum(len(a.results) for a in got.values()),
               "errors": sum(len(a.error_seeds) for a in got.values()),
               "mixed": sorted({k for a in got.values() for k in marks.get((a.scenario, label), [])})}
        for name, _ in COLUMNS:
            if not all(has_all(got[s].results, name) for s in scenarios):
                row[name] = None
                continue
            row[name] = stratified_bootstrap([[r["metrics"][name] for r in got[s].results] for s in scenarios])
        rows.append(row)
    rows.sort(key=lambda row: _rank_key(row, metric))
    neighbours = []
    for rank, (a, b) in enumerate(zip(rows, rows[1:]), start=1):
        arms_a, arms_b = per_label[a["label"]], per_label[b["label"]]
        successes, differences = [], []
        for s in scenarios:
            ma = {r["seed"]: r["metrics"] for r in arms_a[s].results}
            mb = {r["seed"]: r["metrics"] for r in arms_b[s].results}
            seeds = sorted(set(ma) & set(mb))
            successes += [(bool(ma[x]["success_rate"]), bool(mb[x]["success_rate"])) for x in seeds]
            if seeds and a["score"] is not None and b["score"] is not None:
                differences.append([ma[x]["score"] - mb[x]["score"] for x in seeds])
        test = mcnemar_exact([p for p, _ in successes], [q for _, q in successes]) if successes else None
        if test is not None:
            test.update(a=float(np.mean([p for p, _ in successes])), b=float(np.mean([q for _, q in successes])))
        score = None
        if differences and a["score"] is not None and b["score"] is not None:
            boot = stratified_bootstrap(differences)
            score = {"mean_diff": boot["mean"], "ci_low": boot["ci_low"], "ci_high": boot["ci_high"],
                     "n": sum(map(len, differences))}
        neighbours.append({"ranks": [rank, rank + 1], "a": a["label"], "b": b["label"], "pairs": len(successes),
                           "success_rate": test, "score": score})
    for rank, row in enumerate(rows, start=1):
        row["rank"] = rank
    return {"scenarios": scenarios, "rows": rows, "neighbours": neighbours, "left_out": left_out}


def leaderboard(folders: list[str | Path], metric: str | None = None, allow_mixed: bool = False) -> dict:
    """The leaderboard of ``folders`` (see the module doc) as a JSON-ready dict: ``metric`` and ``why`` (the ranking
    rule), ``mixed`` (:class:`Mixing` as dicts), ``scenarios`` (:func:`scenario_board` per scenario) and
    ``overall`` (:func:`overall_board`; None with one scenario). :class:`EvaluationError` for unreadable or empty
    folders, a label holding two configs, an impossible ``--metric``, and, without ``allow_mixed``, for any
    :class:`Mixing` (its message names each)."""
    arms = load_arms(folders)
    mixing = find_mixing(arms)
    if mixing and not allow_mixed:
        raise EvaluationError("refused: a leaderboard compares like with like, and "
                              f"{len(mixing)} scenario check(s) failed:\n"
                              + "\n".join(f"  {m.message()}" for m in mixing)
                              + "\nRerun the arms into a fresh folder on the same seeds with one code version (a "
                              "code version: the git commit, +dirty for uncommitted changes), or give --allow-mixed "
                              "to rank them anyway, the rows marked.")
    chosen, why = ranking_metric(arms, metric)
    marks: dict[tuple[str, str], list[str]] = {}
    for m in mixing:
        for label in m.labels:
            marks.setdefault((m.scenario, label), []).append(m.kind)
    boards = {}
    for scenario in sorted({a.scenario for a in arms}):
        mine = [a for a in arms if a.scenario == scenario]
        boards[scenario] = scenario_board(mine, chosen, {label: k for (s, label), k in marks.items()
                                                           if s == scenario})
    return {"folders": [str(f) for f in folders], "metric": chosen, "why": why, "intervals": INTERVALS,
            "mixed": [vars(m) for m in mixing], "scenarios": boards,
            "overall": overall_board(arms, chosen, marks) if len(boards) > 1 else None}


# --- the text ---------------------------------------------------------------------------------------------------
def _cell(stat: dict | None) -> str:
    return NA if stat is None else format_stat(stat)


def _name(row: dict) -> str:
    return row["label"] + (f" (mixed: {', '.join(row['mixed'])})" if row["mixed"] else "")


def _table(rows: list[dict], overall: bool) -> list[str]:
    head = ["rank", "policy", *(title for _, title in COLUMNS), "episodes"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        episodes = str(row["episodes"]) + (f" ({row['errors']} errors)" if row["errors"] else "")
        if not overall:
            episodes += f", seeds {row['seeds']}"
        lines.append("| " + " | ".join([str(row["rank"]), _name(row), *(_cell(row[m]) for m, _ in COLUMNS),
                                        episodes]) + " |")
    return lines


def _tests(neighbours: list[dict]) -> list[str]:
    if not neighbours:
        return []
    lines = ["", "| neighbours (A vs B) | paired seeds | success A / B | only A | only B | McNemar exact p | "
             "score A - B [95% paired bootstrap] |", "|---|---|---|---|---|---|---|"]
    for n in neighbours:
        test, score = n["success_rate"], n["score"]
        success = ["-"] * 4 if test is None else [f"{test['a']:.3f} / {test['b']:.3f}", str(test["only_a"]),
                                                  str(test["only_b"]), f"{test['p_value']:.3g}"]
        diff = NA if score is None or score["mean_diff"] is None else (
            f"{score['mean_diff']:+.3f} [{score['ci_low']:+.3f}, {score['ci_high']:+.3f}]")
        lines.append(f"| {n['ranks'][0]}. {n['a']} vs {n['ranks'][1]}. {n['b']} | {n['pairs']} | "
                     + " | ".join(success) + f" | {diff} |")
    return lines


def report(board: dict) -> str:
    """The leaderboard as markdown: the ranking rule, a table and the neighbours' tests per scenario, then overall,
    then the interval rules and what was mixed (with ``--allow-mixed``)."""
    lines = [f"# Leaderboard: {', '.join(board['folders'])}", "", board["why"] + "; best first.", ""]
    for scenario, b in board["scenarios"].items():
        lines += [f"## {scenario}", "", *_table(b["rows"], overall=False), *_tests(b["neighbours"]), ""]
    overall = board["overall"]
    if overall is not None:
        lines += [f"## overall: mean over {len(overall['scenarios'])} scenarios, each weighted equally", ""]
        lines += _table(overall["rows"], overall=True) if overall["rows"] else ["no policy ran every scenario"]
        lines += _tests(overall["neighbours"])
        for label, missing in overall["left_out"].items():
            lines.append(f"\n{label}: not in the overall ranking, no results on {', '.join(missing)}")
        lines.append("")
    lines.append(board["intervals"] + " n/a: some record of the row carries no such value (made before it "
                 "existed): never a number over part of the episodes.")
    if board["mixed"]:
        lines += ["", "**Mixed (--allow-mixed)**: these rows do not compare like with like:"]
        lines += [f"- {Mixing(**m).message()}" for m in board["mixed"]]
    return "\n".join(lines) + "\n"


# --- the figure ---------------------------------------------------------------------------------------------------
def plot(board: dict, path: str | Path) -> Path:
    """One panel per scenario (and overall): the ranking metric of every policy with its 95% interval, best on top,
    in the policy's colour of every bimp figure (:func:`bimp.agents.registry.policy_color`); a mixed row hollow."""
    import matplotlib  # heavy: only when a figure is drawn

    matplotlib.use("Agg")  # headless: files only
    import matplotlib.pyplot as plt  # after the backend's choice

    metric = board["metric"]
    panels = [(s, b["rows"]) for s, b in board["scenarios"].items()]
    if board["overall"] is not None and board["overall"]["rows"]:
        panels.append(("overall (scenarios weighted equally)", board["overall"]["rows"]))
    cols = min(3, len(panels))
    nrows = math.ceil(len(panels) / cols)
    height = max(len(rows) for _, rows in panels) * 0.35 + 1.2
    # Constrained layout leaves the suptitle its own room (tight_layout drew it over the top row's titles).
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, height * nrows), squeeze=False, layout="constrained")
    for ax, (title, rows) in zip(axes.flat, panels):
        for y, row in enumerate(rows):
            stat = row[metric]
            color = policy_color(row["policy"])
            ax.errorbar(stat["mean"], y, xerr=[[stat["mean"] - stat["ci_low"]], [stat["ci_high"] - stat["mean"]]],
                        fmt="o", color=color, mfc="white" if row["mixed"] else color, capsize=3)
        ax.set_yticks(range(len(rows)), [_name(row) for row in rows], fontsize=8)
        ax.set_ylim(len(rows) - 0.5, -0.5)  # rank 1 on top
        ax.set_xlim(-0.03, 1.03)
        ax.set_xlabel(f"{metric} (95% interval)", fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.grid(axis="x", alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.set_axis_off()
    hollow = "; hollow: a mixed row (--allow-mixed)" if board["mixed"] else ""
    fig.suptitle(f"{', '.join(board['folders'])}: ranked by {metric}, best on top{hollow}", fontsize=10)
    path = Path(path)
    write_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["ArmResults", "Mixing", "code_version", "find_mixing", "leaderboard", "load_arms", "overall_board", "plot",
           "ranking_metric", "report", "scenario_board", "seed_ranges"]
