"""``bimp leaderboard`` on fixture folders of hand-written episode records with known outcomes: the ranking, the
intervals against bimp.agents.evaluation.stats, the neighbours' McNemar p-value against a hand computation, "n/a" for
records without the score, and the refusals (different seeds, mixed code versions, two configs under one label)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest

from bimp.agents.cli import EvaluationError, main
from bimp.agents.evaluation.leaderboard import code_version, leaderboard, report, seed_ranges
from bimp.agents.evaluation.records import EPISODES_FILE
from bimp.agents.evaluation.stats import bootstrap_mean_ci, paired_bootstrap, stratified_bootstrap, wilson

SEEDS = list(range(3000, 3020))
COMMIT = "a" * 40


def record(scenario: str, label: str, seed: int, success: bool, score: float | None, plan_ms: float = 5.0,
           commit: str | None = COMMIT, dirty: bool = False, config_hash: str | None = None, **extra) -> dict:
    """An ok episode record as bimp evaluate writes it, reduced to what the leaderboard reads: a failure is a
    collision the EV is at fault for."""
    metrics = {"success_rate": float(success), "collision_rate": float(not success), "offroad_rate": 0.0,
               "at_fault_collision_rate": float(not success), "plan_time_ms_p50": plan_ms}
    if score is not None:
        metrics["score"] = score
    return {"scenario": scenario, "label": label, "policy": label.split("-")[0], "seed": seed, "status": "ok",
            "config_hash": config_hash or f"{label}-{scenario}", "bimp_version": "0.1.0", "git_commit": commit,
            "git_dirty": dirty, "metrics": metrics, **extra}


# Known outcomes. cut-in: enkts fails on 3000-3001, enks on 3000 and 3002-3007 (so enkts alone succeeds on 6 seeds,
# enks alone on 1: 3001), idm on 3010-3019. stalled-vehicle: idm succeeds most often but scores low, enkts less often
# but high, so the score and the success rate rank them differently.
SUCCESS = {
    ("cut-in", "enkts"): lambda s: s not in (3000, 3001),
    ("cut-in", "enks"): lambda s: s != 3000 and not 3002 <= s <= 3007,
    ("cut-in", "idm"): lambda s: s < 3010,
    ("stalled-vehicle", "enkts"): lambda s: s < 3012,
    ("stalled-vehicle", "enks"): lambda s: s < 3008,
    ("stalled-vehicle", "idm"): lambda s: s < 3015,
}
PER_SUCCESS_SCORE = {"enkts": 0.95, "enks": 0.9, "idm": 0.5}
PLAN_MS = {"enkts": 5.0, "enks": 4.0, "idm": 0.02}


def score_of(label: str, seed: int, success: bool) -> float:
    return PER_SUCCESS_SCORE[label] - 0.01 * (seed % 3) if success else 0.0


def plan_of(label: str, seed: int) -> float:
    return PLAN_MS[label] * (1.0 + 0.05 * (seed % 4))


def fixture_records(with_score: bool = True, **kw) -> list[dict]:
    return [record(scenario, label, seed, ok(seed), score_of(label, seed, ok(seed)) if with_score else None,
                   plan_ms=plan_of(label, seed), **kw)
            for (scenario, label), ok in SUCCESS.items() for seed in SEEDS]


def write(folder: Path, records: list[dict]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / EPISODES_FILE, "a") as f:
        f.writelines(json.dumps(r) + "\n" for r in records)
    return folder


@pytest.fixture
def suite(tmp_path) -> Path:
    return write(tmp_path / "suite", fixture_records())


def rows(board: dict, scenario: str) -> list[str]:
    return [row["label"] for row in board["scenarios"][scenario]["rows"]]


def test_rows_are_ranked_by_the_score_and_by_success_on_request(suite):
    board = leaderboard([suite])
    assert board["metric"] == "score" and "every record carries one" in board["why"]
    assert rows(board, "cut-in") == ["enkts", "enks", "idm"]  # 18, 13, 10 successes at 0.95, 0.9, 0.5
    assert rows(board, "stalled-vehicle") == ["enkts", "idm", "enks"]  # mean score 0.56, 0.37, 0.36
    by_success = leaderboard([suite], metric="success_rate")
    assert by_success["metric"] == "success_rate"
    assert rows(by_success, "stalled-vehicle") == ["idm", "enkts", "enks"]  # 15, 12, 8 successes
    assert [r["label"] for r in board["overall"]["rows"]] == ["enkts", "enks", "idm"]
    assert [r["rank"] for r in board["scenarios"]["cut-in"]["rows"]] == [1, 2, 3]


def test_intervals_are_those_of_the_stats_module(suite, capsys):
    board = leaderboard([suite])
    row = board["scenarios"]["cut-in"]["rows"][0]  # enkts
    ok = [SUCCESS["cut-in", "enkts"](s) for s in SEEDS]
    assert (row["success_rate"]["ci_low"], row["success_rate"]["ci_high"]) == pytest.approx(wilson(18, 20))
    assert (row["collision_rate"]["ci_low"], row["collision_rate"]["ci_high"]) == pytest.approx(wilson(2, 20))
    assert row["at_fault_collision_rate"]["mean"] == pytest.approx(0.1)
    scores = [score_of("enkts", s, k) for s, k in zip(SEEDS, ok)]
    assert row["score"]["mean"] == pytest.approx(sum(scores) / 20)
    assert (row["score"]["ci_low"], row["score"]["ci_high"]) == pytest.approx(bootstrap_mean_ci(scores))
    plans = [plan_of("enkts", s) for s in SEEDS]
    assert (row["plan_time_ms_p50"]["ci_low"], row["plan_time_ms_p50"]["ci_high"]) == pytest.approx(
        bootstrap_mean_ci(plans))
    # overall: mean over the two scenarios, each weighted equally, stratified bootstrap over their seeds
    per_scenario = [[score_of("enkts", s, SUCCESS[sc, "enkts"](s)) for s in SEEDS]
                    for sc in ("cut-in", "stalled-vehicle")]
    overall = board["overall"]["rows"][0]["score"]
    expected = stratified_bootstrap(per_scenario)
    assert overall["mean"] == pytest.approx((sum(per_scenario[0]) / 20 + sum(per_scenario[1]) / 20) / 2)
    assert (overall["ci_low"], overall["ci_high"]) == pytest.approx((expected["ci_low"], expected["ci_high"]))
    text = report(board)
    low, high = wilson(18, 20)
    assert f"| 1 | enkts | 0.900 [{low:.3f}, {high:.3f}] |" in text  # printed as computed
    low, high = bootstrap_mean_ci(scores)
    assert f"{sum(scores) / 20:.3f} [{low:.3f}, {high:.3f}]" in text


def test_the_neighbours_mcnemar_p_value_is_the_hand_computed_one(suite):
    board = leaderboard([suite])
    first = board["scenarios"]["cut-in"]["neighbours"][0]
    assert (first["a"], first["b"], first["pairs"]) == ("enkts", "enks", 20)
    test = first["success_rate"]
    assert (test["only_a"], test["only_b"]) == (6, 1)
    # two-sided exact binomial test of 6 of 7 discordant pairs at 1/2: 2 P(X <= 1) = 2 (1 + 7) / 2^7
    assert test["p_value"] == pytest.approx(2 * (math.comb(7, 0) + math.comb(7, 1)) / 2 ** 7)
    assert test["p_value"] == pytest.approx(0.125)
    a = [score_of("enkts", s, SUCCESS["cut-in", "enkts"](s)) for s in SEEDS]
    b = [score_of("enks", s, SUCCESS["cut-in", "enks"](s)) for s in SEEDS]
    expected = paired_bootstrap(a, b)
    assert first["score"]["mean_diff"] == pytest.approx(expected["mean_diff"])
    assert (first["score"]["ci_low"], first["score"]["ci_high"]) == pytest.approx(
        (expected["ci_low"], expected["ci_high"]))
    assert "| 1. enkts vs 2. enks | 20 | 0.900 / 0.650 | 6 | 1 | 0.125 |" in report(board)


def test_records_without_the_score_show_na_and_rank_by_success(tmp_path, capsys):
    old = write(tmp_path / "old", fixture_records(with_score=False))
    board = leaderboard([old])
    assert board["metric"] == "success_rate" and "120 of 120 records carry no score" in board["why"]
    assert rows(board, "stalled-vehicle") == ["idm", "enkts", "enks"]
    assert all(row["score"] is None for b in board["scenarios"].values() for row in b["rows"])
    text = report(board)
    # the score column (7th of each table row) and the neighbours' difference: n/a, never a number
    table = [line.split(" | ") for line in text.splitlines() if re.match(r"\| \d+ \|", line)]
    assert len(table) == 9 and all(cells[6] == "n/a" for cells in table)  # 3 rows in 2 scenarios and overall
    tests = [line for line in text.splitlines() if re.match(r"\| \d+\. ", line)]
    assert len(tests) == 6 and all(line.endswith(" | n/a |") for line in tests)
    with pytest.raises(EvaluationError, match="--metric score: 120 of 120 records carry no score"):
        leaderboard([old], metric="score")
    # one arm scored on part of its seeds only: n/a for that row, and the default rank falls back to success
    part = fixture_records()
    for r in part:
        if r["label"] == "enks" and r["scenario"] == "cut-in" and r["seed"] < 3005:
            del r["metrics"]["score"]
    board = leaderboard([write(tmp_path / "part", part)])
    assert board["metric"] == "success_rate" and "5 of 120" in board["why"]
    cut_in = {row["label"]: row for row in board["scenarios"]["cut-in"]["rows"]}
    assert cut_in["enks"]["score"] is None and cut_in["enkts"]["score"] is not None
    assert next(r for r in board["overall"]["rows"] if r["label"] == "enks")["score"] is None


def test_different_seed_sets_are_refused_naming_them(tmp_path, capsys):
    records = [r for r in fixture_records() if not (r["label"] == "idm" and r["scenario"] == "cut-in"
                                                    and r["seed"] >= 3018)]
    records.append({**record("cut-in", "idm", 3018, False, None), "status": "error", "metrics": None})
    folder = write(tmp_path / "seeds", records)
    with pytest.raises(EvaluationError) as refused:
        leaderboard([folder])
    message = str(refused.value)
    assert "cut-in: different seeds" in message and "idm lacks 2 (3018-3019)" in message
    assert "1 of them episodes that raised (3018)" in message and "stalled-vehicle" not in message
    assert main(["leaderboard", str(folder)]) == 2
    assert "different seeds" in capsys.readouterr().err
    assert main(["leaderboard", str(folder), "--allow-mixed"]) == 0
    out = capsys.readouterr().out
    assert "idm (mixed: seeds)" in out and "enkts (mixed" not in out
    assert "| 2. enks vs 3. idm | 18 |" in out  # paired on the 18 seeds both ran


def test_mixed_code_versions_are_refused_within_an_arm_and_across_folders(tmp_path, capsys):
    records = fixture_records()
    for r in records:
        if r["label"] == "enks" and r["scenario"] == "stalled-vehicle" and r["seed"] >= 3010:
            r["git_commit"] = "b" * 40  # a resumed run after a code change
    folder = write(tmp_path / "resumed", records)
    with pytest.raises(EvaluationError) as refused:
        leaderboard([folder])
    message = str(refused.value)
    assert "stalled-vehicle: different code versions" in message and "cut-in" not in message
    assert "enks aaaaaaa (10 episodes), bbbbbbb (10 episodes)" in message
    assert main(["leaderboard", str(folder)]) == 2
    assert "different code versions" in capsys.readouterr().err
    board = leaderboard([folder], allow_mixed=True)
    marked = {row["label"]: row["mixed"] for row in board["scenarios"]["stalled-vehicle"]["rows"]}
    assert marked == {"enkts": ["code"], "enks": ["code"], "idm": ["code"]}  # every comparison there is mixed
    assert all(not row["mixed"] for row in board["scenarios"]["cut-in"]["rows"])
    # two folders, each of one version, but different ones: the same refusal
    one = write(tmp_path / "one", [r for r in fixture_records() if r["label"] != "idm"])
    other = write(tmp_path / "other", [r for r in fixture_records(commit="c" * 40) if r["label"] == "idm"])
    with pytest.raises(EvaluationError, match="idm ccccccc"):
        leaderboard([one, other])
    # a dirty tree is another version; a record without a commit falls back on the package version
    assert code_version(record("x", "a", 1, True, 1.0, dirty=True)) == COMMIT + "+dirty"
    assert code_version(record("x", "a", 1, True, 1.0, commit=None)) == "bimp 0.1.0 (no git commit)"


def test_a_label_with_two_configs_is_refused_and_a_label_in_two_folders_is_two_rows(tmp_path):
    records = fixture_records()
    records.append(record("cut-in", "enkts", 3020, True, 0.9, config_hash="another"))
    with pytest.raises(EvaluationError, match="'enkts' on cut-in under 2 configs"):
        leaderboard([write(tmp_path / "two", records)], allow_mixed=True)
    a = write(tmp_path / "a", [r for r in fixture_records() if r["label"] != "idm"])
    b = write(tmp_path / "b", [r for r in fixture_records() if r["label"] != "enks"])
    board = leaderboard([a, b])
    assert set(rows(board, "cut-in")) == {f"{a}:enkts", f"{b}:enkts", "enks", "idm"}


def test_the_cli_end_to_end_prints_writes_the_json_and_draws_the_plot(suite, tmp_path, capsys):
    assert main(["leaderboard", str(suite), "--json", str(tmp_path / "lb.json"),
                 "--plot", str(tmp_path / "lb.png")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"# Leaderboard: {suite}\n\nranked by score (every record carries one)")
    for heading in ("## cut-in", "## stalled-vehicle", "## overall: mean over 2 scenarios, each weighted equally"):
        assert heading in out
    saved = json.loads((tmp_path / "lb.json").read_text())
    assert [r["label"] for r in saved["scenarios"]["stalled-vehicle"]["rows"]] == ["enkts", "idm", "enks"]
    assert (tmp_path / "lb.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["leaderboard", str(tmp_path / "nothing")]) == 2
    assert "no episode records" in capsys.readouterr().err
    assert main(["leaderboard", str(suite), "--json", str(tmp_path)]) == 2  # a folder is not a file
    assert "--json" in capsys.readouterr().err


def test_seed_ranges():
    assert seed_ranges([3003, 3000, 3001, 3002, 3005, 3007, 3008]) == "3000-3003, 3005, 3007-3008"
    assert seed_ranges([]) == "none"
