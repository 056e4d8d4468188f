"""The tables ``bimp report`` renders (:mod:`bimp.agents.evaluation.report`), each built from committed results
folders: every number through the same statistics as ``bimp evaluate``'s summary, ``bimp compare``, ``bimp aggregate``
and ``bimp leaderboard``. Arms of a learning algorithm's training seeds (labels ``NAME-s1``, ``NAME-s2``, ...) are one
column: the mean over the seeds, with the range of the seeds' own values. A table whose arms were made at more than
one code version marks with ``†`` each arm that ``bimp verify`` did not find the same at a later one.

A table returns its markdown and its cells (the marked arms among them). Some are fixed (the README's); the kinds a
marker parameterizes (``summary``, ``paired``, ``variants``, ``bench``) take their folders and choices as
``KEY=VALUE`` arguments, every value a string.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.compare import compare, label_results
from bimp.agents.evaluation.leaderboard import leaderboard
from bimp.agents.evaluation.metrics import code_version, record_label, summarize
from bimp.agents.evaluation.provenance import REPO_ROOT
from bimp.agents.evaluation.records import format_stat, latest_records, read_records
from bimp.agents.evaluation.verification import arm_key, read_verified
from bimp.agents.files import read_json

SEEDED = re.compile(r"^(.+)-s(\d+)$")  # a training seed's arm: ppo-s1
MARK = "†"
NAMES = {"enkts": "EnKTS", "enks": "EnKS", "mppi": "MPPI", "nmpc": "NMPC", "nmpc-t": "NMPC-t", "idm": "IDM/MOBIL",
         "lane-keep": "lane keeping", "ppo": "PPO", "sac": "SAC", "enkts-unguarded": "EnKTS, no guard",
         "enks-unguarded": "EnKS, no guard", "idm-yield": "IDM/MOBIL + yield", "inf": "inf (EnKS)"}


@dataclass
class Cell:
    """A column's records on one scenario: one label, or a learning algorithm's training seeds (``runs``)."""

    scenario: str
    column: str
    runs: dict[str, list[dict]]  # label -> its latest ok records
    marked: list[str]  # the labels made at an unverified older code version (see the module doc)

    @functools.cached_property
    def summaries(self) -> dict[str, dict]:
        """Each label's summary (:func:`bimp.agents.evaluation.metrics.summarize`), computed once for every metric
        read."""
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
    source: dict[tuple[str, str], Path] = {}  # (scenario, label) -> the folder it is read from
    for folder in folders:
        verified = read_verified(folder)
        for r in latest_records(read_records(folder)):
            if r["status"] != "ok":
                continue
            label = record_label(r)
            if source.setdefault((r["scenario"], label), folder) != folder:
                raise EvaluationError(f"report: {label} on {r['scenario']} is in both {source[r['scenario'], label]} "
                                      f"and {folder}: one cell reads one folder (choose one, or labels=)")
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


def grid_table(folders: list[Path], with_score: bool, rows_of: Path | None = None,
               extra: tuple[str, dict[str, str]] | None = None) -> tuple[str, list[Cell]]:
    """A row per scenario, a column per policy: success (Wilson 95%; over training seeds their range) and, with
    ``with_score``, the mean closed-loop score after a semicolon; ``-`` where a policy did not run. ``rows_of``: only
    the scenarios that folder (one of ``folders``, a study beside the main folders) ran. ``extra``: a last column,
    its header and a cell per scenario (``-`` where it has none)."""
    arms = _arms(folders)
    if rows_of is not None:
        rows = {r["scenario"] for r in read_records(rows_of)}
        arms = [a for a in arms if a.scenario in rows]
    columns = list(dict.fromkeys(a.column for a in arms))
    by = {(a.scenario, a.column): a for a in arms}
    runs = {a.column: a.runs for a in arms}
    header, extra_cells = extra if extra is not None else (None, {})
    names = [_column_name(c, runs[c]) for c in columns] + ([header] if header is not None else [])
    lines = ["| scenario | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for scenario in sorted({a.scenario for a in arms}):
        cells = []
        for column in columns:
            a = by.get((scenario, column))
            if a is None:
                cells.append("-")
                continue
            score = _stat(a, "score") if with_score else None
            cells.append(_short(_stat(a, "success_rate")) + (f"; {score['mean']:.2f}" if score else "") + _mark(a))
        if header is not None:
            cells.append(extra_cells.get(scenario, "-"))
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


def collisions_table(folder: Path, label_a: str, label_b: str) -> tuple[str, list[Cell]]:
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


# --- tables a marker parameterizes: `<!-- report: KIND folders=A,B KEY=VALUE ... -->` -----------------------------
COLUMNS = {  # summary's columns: name -> (metric, heading)
    "success": ("success_rate", "success"), "collision": ("collision_rate", "collision"),
    "offroad": ("offroad_rate", "off road"), "overtake": ("overtake_rate", "overtake"),
    "input": ("input_violation_rate", "steps over an input bound"),
    "rate": ("rate_violation_rate", "steps over a rate bound"), "progress": ("progress_m", "progress [m]"),
    "plan": ("plan_time_ms_p50", "plan time p50 [ms]"), "score": ("score", "score"),
    "at_fault": ("at_fault_collision_rate", "at-fault collision"),
}


def _names(value: str) -> list[str]:
    return [v for v in value.split(",") if v]


def _yes(name: str, value: str) -> bool:
    if value not in ("yes", "no"):
        raise EvaluationError(f"report: {name}={value!r}: yes or no")
    return value == "yes"


def _known(kind: str, given: list[str], present: list[str]) -> None:
    """Refuse a name the folders do not hold (a typo would render an empty table), listing those they do."""
    missing = [name for name in given if name not in present]
    if missing:
        raise EvaluationError(f"report: no {kind} {missing[0]!r} in these folders; they hold: {', '.join(present)}")


def _folder_paths(folders: str) -> list[Path]:
    paths = [results(name) for name in _names(folders)]
    if not paths:
        raise EvaluationError("report: folders= names no folder")
    for path in paths:
        if not (path / "episodes.jsonl").is_file():
            raise EvaluationError(f"report: {path} holds no episodes.jsonl (folders are named under results/)")
    return paths


def _cell(stat: dict | None, metric: str) -> str:
    if metric in ("input_violation_rate", "rate_violation_rate"):
        return "-" if not stat or stat.get("mean") is None else f"{100 * stat['mean']:.1f}%"
    return format_stat(stat)


def summary_table(folders: str, columns: str = "success,collision,offroad,progress", labels: str = "",
                  per_seed: str = "", scenarios: str = "") -> tuple[str, list[Cell]]:
    """A row per scenario and arm of ``folders`` (under results/): episodes, then ``columns`` (names of
    :data:`COLUMNS`) with their intervals; over training seeds the mean of the seeds' means and their range.
    ``labels``: only these arms (their column names), in this order; ``scenarios``: only these, in this order;
    ``per_seed``: a last column with each training seed's values of these columns, in seed order."""
    chosen = _names(columns)
    unknown = [c for c in chosen + _names(per_seed) if c not in COLUMNS]
    if unknown:
        raise EvaluationError(f"report summary: unknown column {unknown[0]!r}; the columns: {', '.join(COLUMNS)}")
    every = _arms(_folder_paths(folders))
    scenario_order, label_order = _names(scenarios), _names(labels)
    _known("scenario", scenario_order, list(dict.fromkeys(a.scenario for a in every)))
    _known("label", label_order, list(dict.fromkeys(a.column for a in every)))
    arms = [a for a in every if (not scenario_order or a.scenario in scenario_order)
            and (not label_order or a.column in label_order)]
    if scenario_order or label_order:
        arms.sort(key=lambda a: (scenario_order.index(a.scenario) if scenario_order else a.scenario,
                                 label_order.index(a.column) if label_order else a.column))
    heads = [COLUMNS[c][1] for c in chosen] + (["per seed: " + " / ".join(_names(per_seed))] if per_seed else [])
    lines = ["| scenario | policy | episodes | " + " | ".join(heads) + " |", "|---|---|---|" + "---|" * len(heads)]
    for a in arms:
        counts = {len(records) for records in a.runs.values()}
        episodes = f"{len(a.runs)} x {counts.pop()}" if len(a.runs) > 1 and len(counts) == 1 else \
            str(sum(len(records) for records in a.runs.values()))
        cells = [_cell(_stat(a, COLUMNS[c][0]), COLUMNS[c][0]) for c in chosen]
        if per_seed:
            by_seed = sorted(a.summaries.items(), key=lambda item: _seed_number(item[0]))
            cells.append(", ".join(" / ".join(_seed_value(s, COLUMNS[c][0]) for c in _names(per_seed))
                                   for _, s in by_seed))
        lines.append(f"| {a.scenario} | {_column_name(a.column, a.runs)}{_mark(a)} | {episodes} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines + _footnote(arms)), arms


def _seed_number(label: str) -> tuple[int, str]:
    match = SEEDED.match(label)
    return (int(match.group(2)), label) if match else (0, label)


def _seed_value(summary: dict, metric: str) -> str:
    mean = (summary.get(metric) or {}).get("mean")
    return "-" if mean is None else f"{mean:.3f}"


def _variant(label: str, prefix: str) -> str | None:
    """What ``label`` adds to ``prefix`` ("enkts N=30" -> "N=30", "nu4-plain" -> "plain", "enkts" -> ""), or None
    where it is another arm's ("nu30" is not a variant of "nu3")."""
    if label == prefix:
        return ""
    if label.startswith(prefix) and label[len(prefix)] in " -":
        return label[len(prefix) + 1:]
    return None


def _shown_folder(path: Path) -> str:
    try:
        return str(path.relative_to(REPO_ROOT / "results"))
    except ValueError:
        return path.name


def _verdict(success: dict, score: dict | None, a: str, b: str) -> str:
    ahead = (a if success["only_a"] > success["only_b"] else b) if success["p_value"] < 0.05 else None
    lead = None if not score or score.get("mean_diff") is None or score["ci_low"] <= 0 <= score["ci_high"] else \
        (a if score["mean_diff"] > 0 else b)
    if ahead and lead in (None, ahead):
        return f"{ahead} ahead on success" + (" and the score" if lead else "")
    if ahead:
        return f"{ahead} ahead on success, {lead} on the score"
    return f"{lead} ahead on the score" if lead else "no difference"


def _compare(path: Path, label_a: str, label_b: str) -> dict:
    try:
        return compare(label_results(path, label_a), label_results(path, label_b))
    except ValueError as err:  # a label under two configs: bimp compare's own refusal
        raise EvaluationError(f"report: {path}: {err}") from None


def paired_table(folders: str, a: str, b: str, scenarios: str = "") -> tuple[str, list[Cell]]:
    """Arms ``a`` against ``b`` seed by seed (``bimp compare``), a row per folder, scenario and variant (labels
    ``a VARIANT`` / ``b VARIANT``): paired seeds, success of each, the seeds only one succeeded on with the exact
    McNemar p, the paired bootstrap 95% interval of the score difference, and a verdict at the 5% level."""
    paths = _folder_paths(folders)
    wanted = _names(scenarios)
    present = [r for path in paths for r in read_records(path)]
    _known("scenario", wanted, list(dict.fromkeys(r["scenario"] for r in present)))
    labels_present = list(dict.fromkeys(record_label(r) for r in present))
    for prefix in (a, b):
        if not any(_variant(label, prefix) is not None for label in labels_present):
            _known("label", [prefix], labels_present)
    na, nb = NAMES.get(a, a), NAMES.get(b, b)
    lines = [f"| folder | scenario | paired seeds | success {na} / {nb} | only {na} / only {nb} | exact McNemar p | "
             f"score {na} - {nb} [paired 95%] | verdict |", "|---|---|---|---|---|---|---|---|"]
    for path in paths:
        labels = list(dict.fromkeys(record_label(r) for r in read_records(path)))
        of_b = {v: label for label in labels if (v := _variant(label, b)) is not None}
        for label_a in labels:
            variant = _variant(label_a, a)
            if variant is None or variant not in of_b:
                continue
            for scenario, e in _compare(path, label_a, of_b[variant]).items():
                if wanted and scenario not in wanted:
                    continue
                s, score = e["success_rate"], e.get("score")
                diff = "-" if not score or score.get("mean_diff") is None else \
                    f"{score['mean_diff']:+.3f} [{score['ci_low']:+.3f}, {score['ci_high']:+.3f}]"
                lines.append(f"| {_shown_folder(path)} | {scenario}"
                             f"{f' ({variant})' if variant else ''} | {e['pairs']} | {s['a']:.3f} / {s['b']:.3f} | "
                             f"{s['only_a']} / {s['only_b']} | {s['p_value']:.2g} | {diff} | "
                             f"{_verdict(s, score, na, nb)} |")
    return "\n".join(lines), []


def variants_table(folders: str, prefixes: str, pair: str = "no", intervals: str = "yes") -> tuple[str, list[Cell]]:
    """A row per variant (what a label adds to a prefix: ``enkts N=30`` is variant ``N=30`` of ``enkts``; the bare
    prefix is ``shipped``), a column per scenario and prefix: success [Wilson 95%]. ``pair=yes``: after each scenario's
    columns, the exact McNemar p of the first two prefixes on their paired seeds; ``intervals=no``: the rates alone."""
    paths = _folder_paths(folders)
    heads, paired, with_interval = _names(prefixes), _yes("pair", pair), _yes("intervals", intervals)
    if paired and len(heads) < 2:
        raise EvaluationError(f"report: pair=yes pairs the first two prefixes; prefixes={prefixes!r} names "
                              f"{len(heads)}")
    arms = {(a.scenario, a.column): a for a in _arms(paths)}
    labels = list(dict.fromkeys(label for path in paths for label in map(record_label, read_records(path))))
    found = {(v, p): label for label in labels for p in heads if (v := _variant(label, p)) is not None}
    _known("label prefix", [p for p in heads if not any(q == p for _, q in found)], labels)
    rows = list(dict.fromkeys(v for v, _ in found))
    scenarios = list(dict.fromkeys(s for s, _ in arms))
    head = [f"{s} {NAMES.get(p, p)}" for s in scenarios for p in heads] if not paired else \
        [h for s in scenarios for h in [f"{s} {NAMES.get(p, p)}" for p in heads] + ["McNemar p"]]
    lines = ["| variant | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    for v in rows:
        cells = []
        pairs = _pairs(paths, found.get((v, heads[0])), found.get((v, heads[1]))) if paired else {}
        for s in scenarios:
            cells += [(_rate(_stat(arms[s, found[v, p]], "success_rate"), with_interval)
                       + _mark(arms[s, found[v, p]]))
                      if (v, p) in found and (s, found[v, p]) in arms else "-" for p in heads]
            if paired:
                cells.append(f"{pairs[s]['success_rate']['p_value']:.2g}" if s in pairs else "-")
        lines.append(f"| {v or 'shipped'} | " + " | ".join(cells) + " |")
    return "\n".join(lines + _footnote(list(arms.values()))), list(arms.values())


def _rate(stat: dict | None, with_interval: bool) -> str:
    return _short(stat) if with_interval or not stat or stat.get("mean") is None else f"{stat['mean']:.2f}"


def _pairs(paths: list[Path], a: str | None, b: str | None) -> dict[str, dict]:
    """``bimp compare`` of labels ``a`` and ``b`` per scenario, from the first folder that pairs them there."""
    if a is None or b is None:
        return {}
    found: dict[str, dict] = {}
    for path in paths:
        for scenario, entry in _compare(path, a, b).items():
            found.setdefault(scenario, entry)
    return found


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}" if value < 1 else f"{value:.1f}" if value < 100 else f"{value:.0f}"


def bench_table(runs: str) -> tuple[str, list[Cell]]:
    """``bimp bench`` runs side by side (``runs``: their JSON files under results/): a row per ensemble size N, each
    planner's median plan-step time [ms] and the floor's, run by run, then EnKTS's ratio to the floor and to MPPI
    within each run (the ratios are what a shared machine's load leaves comparable)."""
    data = []
    for name in _names(runs):
        d = read_json(results(name))
        if not isinstance(d, dict) or not isinstance(d.get("rows"), list) or not all(
                isinstance(r, dict) and {"planner", "n_particles", "median_ms"} <= set(r) for r in d["rows"]):
            raise EvaluationError(f"report: {results(name)} is not a `bimp bench` result (rows of planner, "
                                  "n_particles, median_ms)")
        data.append(d)
    if not data:
        raise EvaluationError("report: runs= names no file")
    planners = list(dict.fromkeys(row["planner"] for d in data for row in d["rows"]))
    sizes = sorted({row["n_particles"] for d in data for row in d["rows"]})

    def ms(d: dict, planner: str, n: int) -> float | None:
        return next((r["median_ms"] for r in d["rows"] if r["planner"] == planner and r["n_particles"] == n), None)

    def runs_of(values: list, unit: str = "") -> str:
        return "-" if all(v is None for v in values) else " / ".join(map(_ms, values)) + unit

    lines = ["| N | " + " | ".join(NAMES.get(p, p) for p in planners) + " | floor | EnKTS / floor | EnKTS / MPPI |",
             "|---|" + "---|" * (len(planners) + 3)]
    for n in sizes:
        floors = [(d.get("floor_ms") or {}).get(str(n)) for d in data]
        enkts, mppi = [ms(d, "enkts", n) for d in data], [ms(d, "mppi", n) for d in data]
        cells = [runs_of([ms(d, p, n) for d in data]) for p in planners] + [runs_of(floors)]
        cells += [runs_of([a / b if a and b else None for a, b in zip(enkts, floors)], "x"),
                  runs_of([a / b if a and b else None for a, b in zip(enkts, mppi)], "x")]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines), []


def results(name: str) -> Path:
    return REPO_ROOT / "results" / name
