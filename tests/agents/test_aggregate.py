"""Aggregating a learning algorithm over training seeds: the stratified bootstrap against hand computation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from bimp.agents.evaluation.aggregate import aggregate, best_run, markdown
from bimp.agents.evaluation.stats import stratified_bootstrap


def test_three_runs_of_one_task_give_their_range():
    # Each of the 27 equally likely resamples has probability 1/27 = 3.7% > 2.5%: the all-lowest and the
    # all-highest resample sit beyond the 2.5% and 97.5% quantiles, so the interval is the runs' range.
    got = stratified_bootstrap([[0.90, 0.96, 0.99]])
    assert got["mean"] == pytest.approx(0.95)
    assert (got["ci_low"], got["ci_high"]) == pytest.approx((0.90, 0.99))
    assert got["runs"] == [3]


def test_two_tasks_match_the_exact_bootstrap_distribution():
    a, b = np.array([0.2, 0.6, 1.0]), np.array([0.0, 0.5, 0.5, 1.0])
    # every resample of a (27) with every resample of b (256), equally likely: the exact distribution
    exact = np.array([(np.mean(ra) + np.mean(rb)) / 2 for ra in itertools.product(a, repeat=3)
                      for rb in itertools.product(b, repeat=4)])
    low, high = np.quantile(exact, [0.025, 0.975])
    got = stratified_bootstrap([a, b], n_resamples=200_000)
    assert got["mean"] == pytest.approx((0.6 + 0.5) / 2)
    assert got["ci_low"] == pytest.approx(low, abs=0.02) and got["ci_high"] == pytest.approx(high, abs=0.02)
    assert low > 0.2 and high < 0.85  # strictly inside the range: the test can tell a wrong resampling


def test_bad_scores_are_refused():
    for bad in ([], [[]], [[[0.1, 0.2]]]):
        with pytest.raises(ValueError, match="one non-empty 1-D sequence"):
            stratified_bootstrap(bad)


def _runs(success: dict[str, list[float]], scenario="overtaking", seeds=(1000, 1001)):
    return {label: {(scenario, seed): {"success_rate": s, "collision_rate": 1 - s, "offroad_rate": 0.0,
                                       "overtake_rate": s, "progress_m": 100 * s}
                    for seed, s in zip(seeds, values)} for label, values in success.items()}


def test_aggregate_averages_each_runs_mean_and_lists_the_runs():
    per_run = _runs({"s1": [1, 1], "s2": [1, 0], "s3": [0, 0]})
    out = aggregate(per_run)
    row = out["overtaking"]["success_rate"]
    assert row["mean"] == pytest.approx(0.5) and row["per_run"] == {"s1": 1.0, "s2": 0.5, "s3": 0.0}
    assert (row["ci_low"], row["ci_high"]) == pytest.approx((0.0, 1.0))
    assert out["all"]["success_rate"]["mean"] == pytest.approx(0.5)


def test_runs_on_different_seeds_are_refused():
    per_run = {**_runs({"s1": [1, 1]}), **_runs({"s2": [1, 1]}, seeds=(1000, 1002))}
    with pytest.raises(ValueError, match="'s2' and 's1' have results on different episodes"):
        aggregate(per_run)
    with pytest.raises(ValueError, match="at least 2 runs"):
        aggregate(_runs({"s1": [1, 1]}))


def test_progress_is_not_averaged_over_scenarios_and_a_partly_missing_metric_is_an_error():
    per_run = _runs({"s1": [1, 1], "s2": [1, 0]})
    brake = _runs({"s1": [1, 1], "s2": [0, 1]}, scenario="emergency-brake")
    for label in per_run:
        per_run[label].update(brake[label])
        for key in per_run[label]:
            if key[0] == "emergency-brake":
                per_run[label][key]["overtake_rate"] = None  # the emergency brake has no OV1 to pass
    out = aggregate(per_run)
    assert "overtake_rate" not in out["emergency-brake"] and "overtake_rate" in out["overtaking"]
    assert "progress_m" in out["overtaking"] and "progress_m" not in out["all"]
    assert out["all"]["success_rate"]["mean"] == pytest.approx((0.75 + 0.75) / 2)
    per_run["s1"][("overtaking", 1000)]["progress_m"] = None
    with pytest.raises(ValueError, match="progress_m is missing in 1 episode record"):
        aggregate(per_run)


def test_the_closed_loop_score_is_aggregated_and_averaged_over_scenarios_where_the_records_have_it():
    per_run = _runs({"s1": [1, 1], "s2": [1, 0]})
    brake = _runs({"s1": [1, 1], "s2": [0, 1]}, scenario="emergency-brake")
    for label in per_run:
        per_run[label].update(brake[label])
        for key, metrics in per_run[label].items():
            metrics.update(score=0.5 * metrics["success_rate"], at_fault_collision_rate=metrics["collision_rate"])
    out = aggregate(per_run)
    # per run: s1 scores 0.5 on both scenarios, s2 0.25 on each: the mean over runs is 0.375 on each and over both
    assert out["overtaking"]["score"]["per_run"] == {"s1": 0.5, "s2": 0.25}
    assert out["all"]["score"]["mean"] == pytest.approx(0.375)
    assert out["all"]["at_fault_collision_rate"]["mean"] == pytest.approx(0.25)
    # records from before the score: no row for it, no error
    assert "score" not in aggregate(_runs({"s1": [1, 1], "s2": [1, 0]}))["overtaking"]


def test_a_run_resumed_across_the_score_has_no_score_and_keeps_every_other_metric():
    """Records with the score in part (a run resumed after the score's commit): the score is left out for that
    scenario, as summarize leaves it n/a; the other metrics aggregate, and a partly missing old metric still raises."""
    per_run = _runs({"s1": [1, 1], "s2": [1, 0]})
    first = sorted(per_run["s1"])[0]
    per_run["s1"][first].update(score=1.0, at_fault_collision_rate=0.0)
    out = aggregate(per_run)
    assert "score" not in out["overtaking"] and "at_fault_collision_rate" not in out["overtaking"]
    assert out["overtaking"]["success_rate"]["mean"] == pytest.approx(0.75)


def test_the_best_run_goes_by_success_then_overtakes_then_progress():
    def run(success, overtake, progress):
        return {("overtaking", 1000): {"success_rate": success, "collision_rate": 1 - success, "offroad_rate": 0.0,
                                       "overtake_rate": overtake, "progress_m": progress}}

    # s1 is ahead by progress, s2 by overtakes, s3 by success: success decides, then overtakes, then progress
    out = aggregate({"s1": run(0.0, 0.0, 300.0), "s2": run(1.0, 0.0, 250.0), "s3": run(1.0, 1.0, 200.0)})
    assert best_run(out, "overtaking") == "s3"
    out = aggregate({"s1": run(1.0, 0.0, 300.0), "s2": run(1.0, 0.0, 250.0)})
    assert best_run(out, "overtaking") == "s1"
    assert "- overtaking: s1" in markdown(out, "ppo", ["s1", "s2"])
    brake = {label: {("emergency-brake", 1000): {**rows[("overtaking", 1000)], "overtake_rate": None}}
             for label, rows in {"s1": run(1.0, 0.0, 100.0), "s2": run(1.0, 0.0, 110.0)}.items()}
    assert best_run(aggregate(brake), "emergency-brake") == "s2"  # no overtakes there: progress decides
