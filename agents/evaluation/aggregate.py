"""One learning algorithm over its training seeds, with intervals over the seeds (the ``bimp aggregate`` command:
:mod:`bimp.agents.commands.aggregate`).

Each training seed's model is evaluated as its own labelled arm of one folder (``bimp evaluate --policy ppo
--set ppo.model=PATH --label ppo-s1``); this command reports, per scenario and over both, the mean over
training seeds of each arm's episode mean, with the stratified bootstrap interval over training seeds
(:func:`bimp.agents.evaluation.stats.stratified_bootstrap`), and every seed's own value. A single training seed says
little about an algorithm (Henderson et al. 2018): the interval is over seeds, not episodes. Every arm must have run the
same episode seeds, so the seeds compare like with like.
"""

from __future__ import annotations

import numpy as np

from bimp.agents.evaluation.stats import stratified_bootstrap

METRICS = ("success_rate", "collision_rate", "offroad_rate", "overtake_rate", "at_fault_collision_rate", "score",
           "progress_m")
# Rates, and the closed-loop score (in [0, 1], as nuPlan averages it over scenarios), are on one scale in every
# scenario; progress is not (a 110 m brake against a 300 m pass), so it is not averaged over scenarios. Runs recorded
# before the score have none: a scenario where no record has it is left out, as overtake_rate is outside overtaking.
RATES = ("success_rate", "collision_rate", "offroad_rate", "overtake_rate", "at_fault_collision_rate", "score")
# Added after records were made without them: a scenario whose records have them only in part is left without them
# (a run resumed across the score's commit), never refused as a whole.
SCORED = ("at_fault_collision_rate", "score")


def aggregate(per_run: dict[str, dict[tuple[str, int], dict]], metrics=METRICS) -> dict[str, dict]:
    """``{scenario or "all": {metric: {mean, ci_low, ci_high, runs, per_run}}}`` from ``{run label:
    {(scenario, seed): episode metrics}}``. Raises ``ValueError`` when the runs did not run the same seeds."""
    labels = list(per_run)
    if len(labels) < 2:
        raise ValueError(f"aggregate needs at least 2 runs (training seeds), got {labels}")
    keys = {label: set(per_run[label]) for label in labels}
    first = keys[labels[0]]
    for label in labels[1:]:
        if keys[label] != first:
            raise ValueError(f"{label!r} and {labels[0]!r} have results on different episodes "
                             f"({len(keys[label] ^ first)} (scenario, seed) pairs differ): evaluate every run on "
                             "the same seeds, and rerun the evaluation to retry an episode that raised")
    scenarios = sorted({scenario for scenario, _ in first})
    # scores[metric][scenario]: one value per run, the run's mean over its episodes
    scores: dict[str, dict[str, list[float]]] = {m: {} for m in metrics}
    for metric in metrics:
        for scenario in scenarios:
            values = [[per_run[label][k].get(metric) for k in sorted(first) if k[0] == scenario] for label in labels]
            missing = sum(v is None for row in values for v in row)
            if missing == sum(len(row) for row in values):
                continue  # a metric the scenario does not have (overtake in the emergency brake)
            if missing and metric in SCORED:
                continue  # some runs recorded before the score (resumed after it): no score, as summarize says
            if missing:
                raise ValueError(f"{metric} is missing in {missing} episode record(s) of {scenario}")
            scores[metric][scenario] = [float(np.mean(row)) for row in values]
    out: dict[str, dict] = {}
    for scenario in scenarios + ["all"]:
        out[scenario] = {}
        for metric, by_task in scores.items():
            if scenario == "all":
                if metric not in RATES or len(by_task) < len(scenarios):
                    continue  # not on one scale, or not in every scenario
                tasks = list(by_task.values())
            elif scenario in by_task:
                tasks = [by_task[scenario]]
            else:
                continue
            entry = stratified_bootstrap(tasks)
            entry["per_run"] = dict(zip(labels, by_task[scenario])) if scenario != "all" else None
            out[scenario][metric] = entry
    return out


# How a shipped model's default training seed is chosen (docs/rl.md), on tuning seeds: the best run by success,
# then overtakes (where the scenario counts them), then progress.
CHOICE = ("success_rate", "overtake_rate", "progress_m")


def best_run(result: dict, scenario: str) -> str:
    """The label of the best run on ``scenario`` of an :func:`aggregate` result, by :data:`CHOICE` in order (a
    metric the scenario does not have is skipped); ties go to the first label."""
    row = result[scenario]
    labels = list(row["success_rate"]["per_run"])
    keys = [m for m in CHOICE if m in row]
    return max(labels, key=lambda label: tuple(row[m]["per_run"][label] for m in keys))


def markdown(result: dict, name: str, labels: list[str]) -> str:
    metrics = [m for m in METRICS if any(m in row for row in result.values())]
    lines = [f"| scenario | {' | '.join(metrics)} |", "|---" * (len(metrics) + 1) + "|"]
    for scenario, row in result.items():
        cells = [f"{row[m]['mean']:.3f} [{row[m]['ci_low']:.3f}, {row[m]['ci_high']:.3f}]" if m in row else "-"
                 for m in metrics]
        lines.append(f"| {scenario} | {' | '.join(cells)} |")
    lines += ["", f"{name}: mean over the training-seed runs {', '.join(labels)} of each run's mean over its "
              "episodes; 95% stratified bootstrap interval over the runs (runs resampled within each scenario). "
              "Per run:", ""]
    for scenario, row in result.items():
        if scenario == "all":
            continue
        for m in metrics:
            if m in row:
                per = ", ".join(f"{k} {v:.3f}" for k, v in row[m]["per_run"].items())
                lines.append(f"- {scenario} {m}: {per}")
    lines += ["", "Best run per scenario (success, then overtakes, then progress: how a default training seed is "
              "chosen on tuning seeds):", ""]
    lines += [f"- {scenario}: {best_run(result, scenario)}" for scenario in result if scenario != "all"]
    return "\n".join(lines) + "\n"


__all__ = ["CHOICE", "aggregate", "best_run", "markdown"]
