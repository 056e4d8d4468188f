"""``bimp demo``'s short table: the columns a terminal shows whole, built from a summary."""

from bimp.agents.evaluation.demo import SHORT_COLUMNS, short_table
from bimp.agents.evaluation.metrics import METRICS, summarize


def rate(mean, low, high):
    return {"mean": mean, "ci_low": low, "ci_high": high, "k": 0, "n": 200}


def stat(mean, low, high):
    return {"mean": mean, "ci_low": low, "ci_high": high, "std": 0.0, "min": low, "max": high, "n": 200}


def entry(scenario, policy, **over):
    e = {"scenario": scenario, "policy": policy, "episodes": 200,
         "success_rate": rate(1.0, 0.981, 1.0), "collision_rate": rate(0.0, 0.0, 0.019),
         "offroad_rate": rate(0.0, 0.0, 0.019), "progress_m": stat(333.0, 330.9, 334.8),
         "plan_time_ms_p50": stat(4.657, 4.589, 4.738),
         # columns the short table leaves to summary.md
         "min_ttc_s": stat(2.489, 2.427, 2.553), "overtake_rate": rate(1.0, 0.981, 1.0)}
    e.update(over)
    return e


def rows(table):
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in table.strip().splitlines()]


def test_the_short_table_has_the_five_metrics_with_their_intervals_and_nothing_else():
    summary = {"enkts/overtaking": entry("overtaking", "enkts"),
               "enks/emergency-brake": entry("emergency-brake", "enks", progress_m=stat(110.9, 109.8, 112.1),
                                             collision_rate=rate(0.055, 0.031, 0.096))}
    head, rule, *body = rows(short_table(summary))
    assert head == ["scenario", "policy", "episodes", "success", "collision", "off road", "progress [m]",
                    "plan time p50 [ms]"]
    assert rule == ["---"] * len(head)
    assert len(body) == 2 and all(len(r) == len(head) for r in body)
    # sorted by scenario, then policy; numbers as summary.md prints them (3 digits below 10, 1 above)
    assert body[0] == ["emergency-brake", "enks", "200", "1.000 [0.981, 1.000]", "0.055 [0.031, 0.096]",
                       "0.000 [0.000, 0.019]", "110.9 [109.8, 112.1]", "4.657 [4.589, 4.738]"]
    assert body[1][:2] == ["overtaking", "enkts"] and body[1][6] == "333.0 [330.9, 334.8]"
    assert "ttc" not in short_table(summary) and "2.489" not in short_table(summary)


def test_a_metric_without_values_is_a_dash():
    summary = {"p/s": entry("s", "p", progress_m=stat(None, None, None), plan_time_ms_p50=None)}
    *_, row = rows(short_table(summary))
    assert row[-2:] == ["-", "-"]


def test_the_columns_are_summary_keys_and_a_real_summary_fills_them():
    assert {key for _, key in SHORT_COLUMNS} <= set(METRICS)
    trace_metrics = {m: 0.0 for m in METRICS} | {"success_rate": 1.0, "progress_m": 100.0, "plan_time_ms_p50": 2.0}
    records = [{"scenario": "s", "policy": "p", "seed": k, "status": "ok", "steps": 10, "metrics": trace_metrics}
               for k in range(3)]
    *_, row = rows(short_table(summarize(records)))
    assert row == ["s", "p", "3", "1.000 [0.439, 1.000]", "0.000 [0.000, 0.561]", "0.000 [0.000, 0.561]",
                   "100.0 [100.0, 100.0]", "2.000 [2.000, 2.000]"]
