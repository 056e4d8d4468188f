"""The suite's verdict between planning and learning (``<!-- report: rl-verdict -->``): per scenario, the best
planner against the best RL policy and against each RL algorithm over its training seeds, paired on the same
episode seeds.

- The best planner: of EnKTS, EnKS, MPPI and NMPC, the highest mean closed-loop score on the scenario; the best RL
  policy: of the training-seed arms (``ppo-s1``, ``sac-s2``, ...), the same. Both are picked on the seeds they are
  then compared on (every arm of the suite runs the same leaderboard seeds), as the leaderboard ranks them: the
  tests do not correct for that pick, so "ahead" leans optimistic for both sides; the stability seeds (3100+) are
  what checks the pick.
- Best against best, on the seeds both ran: the exact McNemar test of success (the seeds only one of them met) and
  the paired bootstrap 95% interval of the score difference.
- An algorithm over its seeds (PPO, SAC), on the seeds the planner and all its runs ran: per episode seed, its mean
  over the training seeds of success and score; the planner minus that mean, paired bootstrap 95% over the
  episode seeds. A training seed is not resampled here: ``bimp aggregate`` gives the interval over training seeds.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from bimp.agents import rl_curves
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.compare import label_results
from bimp.agents.evaluation.records import read_records, record_label
from bimp.agents.evaluation.stats import mcnemar_exact, paired_bootstrap

PLANNERS = {"enkts": "EnKTS", "enks": "EnKS", "mppi": "MPPI", "nmpc": "NMPC"}
RL_LABEL = re.compile(r"^(ppo|sac)-s(\d+)$")


def _best(arms: dict[str, dict[int, dict]]) -> str:
    """The label of the highest mean score (ties: the first by name)."""
    return max(sorted(arms), key=lambda label: np.mean([m["score"] for m in arms[label].values()]))


def _shown(d: dict) -> str:
    """A paired bootstrap difference as ``+0.012 [-0.003, +0.027]``."""
    return f"{d['mean_diff']:+.3f} [{d['ci_low']:+.3f}, {d['ci_high']:+.3f}]"


def verdict_rows(folder: Path) -> list[dict]:
    """One row per scenario holding a planner and at least one RL arm: what :func:`rl_verdict_table` shows."""
    labels = list(dict.fromkeys(record_label(r) for r in read_records(folder)))
    results = {label: label_results(folder, label) for label in labels
               if label in PLANNERS or RL_LABEL.match(label)}
    rows = []
    for scenario in sorted({s for got in results.values() for s, _ in got}):
        arms = {label: {seed: m for (s, seed), m in got.items() if s == scenario and m.get("score") is not None}
                for label, got in results.items()}
        arms = {label: got for label, got in arms.items() if got}
        planners = {k: v for k, v in arms.items() if k in PLANNERS}
        learners = {k: v for k, v in arms.items() if RL_LABEL.match(k)}
        if not planners or not learners:
            continue
        planner, learner = _best(planners), _best(learners)
        p, r = planners[planner], learners[learner]
        seeds = sorted(set(p) & set(r))
        if not seeds:
            continue
        test = mcnemar_exact([p[s]["success_rate"] for s in seeds], [r[s]["success_rate"] for s in seeds])
        row = {"scenario": scenario, "seeds": len(seeds), "planner": planner, "learner": learner,
               "planner_success": np.mean([p[s]["success_rate"] for s in seeds]),
               "planner_score": np.mean([p[s]["score"] for s in seeds]),
               "learner_success": np.mean([r[s]["success_rate"] for s in seeds]),
               "learner_score": np.mean([r[s]["score"] for s in seeds]), **test,
               "score_diff": paired_bootstrap([p[s]["score"] for s in seeds], [r[s]["score"] for s in seeds]),
               "algos": {}}
        for algo in ("ppo", "sac"):
            runs = [v for k, v in learners.items() if RL_LABEL.match(k).group(1) == algo]
            both = sorted(set(p).intersection(*(set(run) for run in runs))) if runs else []
            if not both:
                continue
            success = [np.mean([run[s]["success_rate"] for run in runs]) for s in both]
            score = [np.mean([run[s]["score"] for run in runs]) for s in both]
            row["algos"][algo] = {"runs": len(runs), "success": float(np.mean(success)),
                                  "success_diff": paired_bootstrap([p[s]["success_rate"] for s in both], success),
                                  "score_diff": paired_bootstrap([p[s]["score"] for s in both], score)}
        rows.append(row)
    return rows


def _word(row: dict) -> str:
    """Who is ahead at the 5% level, on success first, then on the score."""
    planner, learner = PLANNERS[row["planner"]], row["learner"].upper().replace("-S", " seed ")
    if row["p_value"] < 0.05:
        return f"{planner if row['only_a'] > row['only_b'] else learner} ahead on success"
    low, high = row["score_diff"]["ci_low"], row["score_diff"]["ci_high"]
    if low > 0 or high < 0:
        return f"{planner if low > 0 else learner} ahead on the score"
    return "no difference shown"


def _evidence(row: dict) -> str:
    """What decided :func:`_word`: the exact McNemar p of success, and where success shows no difference, the
    paired score difference (planner - RL) with its 95% interval."""
    diff = row["score_diff"]
    score = f"score {diff['mean_diff']:+.2f} [{diff['ci_low']:+.2f}, {diff['ci_high']:+.2f}]"
    return f"p = {row['p_value']:.2g}" if row["p_value"] < 0.05 else f"p = {row['p_value']:.2g}; {score}"


def verdict_column(folder: Path) -> tuple[str, dict[str, str]]:
    """``grid_table``'s extra column for ``folder``: who is ahead per scenario, the best planner or the best RL arm
    (:func:`verdict_rows`), with what decided it (:func:`_evidence`)."""
    return "best planner vs best RL", {row["scenario"]: f"{_word(row)} ({_evidence(row)})"
                                       for row in verdict_rows(folder)}


def training_table(root: Path) -> tuple[str, list]:
    """The finished training runs under ``root`` (``bimp train-rl --runs-dir``), a row per algorithm and scenario:
    the training seeds, the timesteps each reached, and the hours they trained (:func:`bimp.agents.rl_curves.hours`:
    the training process's CPU time where the run kept it, else its wall time: an upper bound where runs
    outnumbered the cores), with a total per algorithm; the runs still training are named below (a finished run's
    folder does not change, so the table is what its committed folders render)."""
    if not root.is_dir():
        raise EvaluationError(f"no training runs folder {root}")
    every = sorted(p for p in root.iterdir() if (p / "config.json").is_file())
    runs = [p for p in every if rl_curves.finished(p)]
    lines = ["| algorithm | scenario | training seeds | timesteps | core-hours | measured as |",
             "|---|---|---|---|---|---|"]
    totals: dict[str, float] = {}
    for (algo, scenario), seeds in rl_curves.groups(runs).items():
        reached = [rl_curves.trained(out) for _, out in seeds]
        spent = sum(rl_curves.hours(out) for _, out in seeds)
        totals[algo] = totals.get(algo, 0.0) + spent
        lines.append(f"| {algo.upper()} | {scenario} | {', '.join(str(seed) for seed, _ in seeds)} | "
                     f"{', '.join(f'{n:,}' for n in reached)} | {spent:.2f} | "
                     f"{'CPU' if all(rl_curves.measured_cpu(out) for _, out in seeds) else 'wall (at most)'} |")
    lines += [f"| {algo.upper()} | all | | | {hours:.2f} | |" for algo, hours in totals.items()]
    training = [p.name for p in every if p not in runs]
    if training:
        lines += ["", f"Still training (not counted): {', '.join(training)}."]
    return "\n".join(lines), []


def rl_verdict_table(folder: Path) -> tuple[str, list]:
    """The verdict table (module doc) of the evaluation folder ``folder``."""
    lines = ["| scenario | best planner: success; score | best RL: success; score | only planner / only RL, "
             "McNemar p | score planner - RL [95%] | PPO over seeds: success; planner - PPO score | "
             "SAC over seeds: success; planner - SAC score | verdict (best vs best) |",
             "|---|---|---|---|---|---|---|---|"]
    for row in verdict_rows(folder):
        algos = []
        for algo in ("ppo", "sac"):
            a = row["algos"].get(algo)
            algos.append(f"{a['success']:.2f} ({a['runs']} seeds); {_shown(a['score_diff'])}" if a else "-")
        lines.append(
            f"| {row['scenario']} | {PLANNERS[row['planner']]} {row['planner_success']:.2f}; "
            f"{row['planner_score']:.2f} | {row['learner']} {row['learner_success']:.2f}; {row['learner_score']:.2f} "
            f"| {row['only_a']} / {row['only_b']}, {row['p_value']:.2g} | {_shown(row['score_diff'])} | {algos[0]} | "
            f"{algos[1]} | {_word(row)} |")
    return "\n".join(lines), []


__all__ = ["PLANNERS", "rl_verdict_table", "training_table", "verdict_column", "verdict_rows"]
