"""``bimp report``: every results table of the README and the docs is what its folders render, and the rendering
marks arms of mixed, unverified code versions."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bimp.agents.commands import report as report_command
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation import report
from bimp.agents.evaluation import report_tables as tables
from bimp.agents.evaluation.verification import arm_key

ROOT = Path(__file__).resolve().parents[2]


def test_every_committed_table_is_what_its_folders_render(capsys):
    """A hand edit of a rendered table, or a folder changed without `bimp report`, fails here."""
    assert report_command.main(["--check"]) == 0, capsys.readouterr().out
    rendered = {name for path in report.default_files() for name in report.BLOCK_NAMES.findall(path.read_text())}
    assert set(report.TABLES) <= rendered  # every table is shown somewhere


def _table(rows):
    return lambda: ("| a |\n|---|\n" + "\n".join(f"| {r} |" for r in rows), [])


def test_blocks_are_rendered_in_place_and_unknown_tables_refused():
    text = "before\n<!-- report: t -->\nstale\n<!-- /report -->\nafter\n"
    out, notes = report.render(text, {"t": _table([1, 2])})
    assert out == "before\n<!-- report: t -->\n| a |\n|---|\n| 1 |\n| 2 |\n<!-- /report -->\nafter\n"
    assert notes == [] and report.render(out, {"t": _table([1, 2])})[0] == out  # a fixed point
    example = "    <!-- report: t -->\n    kept\n    <!-- /report -->\n"  # indented: an example in a code block
    assert report.render(example, {"t": _table([1])})[0] == example
    with pytest.raises(EvaluationError, match="names table 'nope'"):
        report.render("<!-- report: nope -->\n<!-- /report -->", {"t": _table([])}, where="x.md")


@pytest.mark.parametrize("text", [
    "<!-- report: t -->\nopen\n<!-- report: t -->\nx\n<!-- /report -->\n",  # the first never closed
    "<!-- report: t -->\nx\n<!-- /report -->\n<!-- /report -->\n",  # a stray closing marker
    "<!-- report: t -->\nx\n<!-- /report --><!-- report: t -->\ny\n<!-- /report -->\n",  # two on a line
])
def test_unpaired_markers_are_refused_before_anything_is_written(text):
    with pytest.raises(EvaluationError, match="markers do not pair"):
        report.render(text, {"t": _table([1])}, where="x.md")


def test_a_bad_file_stops_the_run_before_any_file_is_written(tmp_path, monkeypatch):
    good, bad = tmp_path / "a.md", tmp_path / "b.md"
    good.write_text("<!-- report: t -->\nold\n<!-- /report -->\n")
    bad.write_text("<!-- report: t -->\nnever closed\n")
    monkeypatch.setattr(report_command, "TABLES", {"t": _table(["new"])})
    with pytest.raises(EvaluationError, match="do not pair"):
        report_command.main([str(good), str(bad)])
    assert "old" in good.read_text()


def test_check_writes_nothing_and_fails_where_a_block_differs(tmp_path, monkeypatch, capsys):
    page = tmp_path / "page.md"
    page.write_text("<!-- report: t -->\nold\n<!-- /report -->\n")
    monkeypatch.setattr(report_command, "TABLES", {"t": _table(["new"])})  # where the command looks it up
    assert report_command.main(["--check", str(page)]) == 1
    assert "old" in page.read_text() and "differs" in capsys.readouterr().out
    assert report_command.main([str(page)]) == 0 and "| new |" in page.read_text()
    assert report_command.main(["--check", str(page)]) == 0


def _folder(tmp_path, commits: dict[str, str]) -> Path:
    """Two arms of results/highway on highway-v0, each label's records stamped with ``commits[label]``."""
    folder = tmp_path / "f"
    folder.mkdir()
    lines = []
    for line in (ROOT / "results/highway/episodes.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r["scenario"] == "highway-v0" and r["label"] in commits and r["status"] == "ok":
            lines.append(json.dumps({**r, "git_commit": commits[r["label"]], "git_dirty": False}))
    (folder / "episodes.jsonl").write_text("\n".join(lines) + "\n")
    return folder


def test_arms_of_mixed_unverified_code_versions_are_marked_and_named(tmp_path):
    a, b = "a" * 40, "b" * 40
    folder = _folder(tmp_path, {"idm": a, "lane-keep": b})
    table, arms = tables.grid_table([folder], with_score=False)
    assert {(x.column, tuple(x.marked)) for x in arms} == {("idm", ("idm",)), ("lane-keep", ("lane-keep",))}
    assert table.count(tables.MARK) == 3 and "2 of 2 cells" in table  # two cells and the footnote
    _, notes = report.render("<!-- report: g -->\n<!-- /report -->",
                             {"g": lambda: tables.grid_table([folder], with_score=False)}, where="p.md")
    assert notes == ["table g: highway-v0 idm: not verified, in a table of mixed code versions",
                     "table g: highway-v0 lane-keep: not verified, in a table of mixed code versions"]
    # lane-keep found the same at the code idm was made at: one code version, nothing marked.
    lane = next(json.loads(x) for x in (folder / "episodes.jsonl").read_text().splitlines()
                if json.loads(x)["label"] == "lane-keep")
    verified = {arm_key("highway-v0", "lane-keep", lane.get("config_hash")):
                {"commit": a, "outcome": "same", "versions": [b], "dirty": False, "seeds": [1000]}}
    (folder / "verified.json").write_text(json.dumps(verified))
    table, arms = tables.grid_table([folder], with_score=False)
    assert all(not x.marked for x in arms) and tables.MARK not in table


def test_an_arm_of_two_code_versions_is_marked_whatever_the_order(tmp_path):
    a, b = "a" * 40, "b" * 40
    folder = _folder(tmp_path, {"idm": a, "lane-keep": a})
    lines = (folder / "episodes.jsonl").read_text().splitlines()
    records = [json.loads(x) for x in lines]
    half = [r for r in records if r["label"] == "lane-keep"][::2]
    for r in half:
        r["git_commit"] = b
    for order in (records, records[::-1]):
        (folder / "episodes.jsonl").write_text("\n".join(json.dumps(r) for r in order) + "\n")
        _, arms = tables.grid_table([folder], with_score=False)
        assert {(x.column, tuple(x.marked)) for x in arms} == {("idm", ("idm",)), ("lane-keep", ("lane-keep",))}


def test_training_seeds_are_one_column_with_their_range(tmp_path):
    table, arms = tables.summary_table(str(ROOT / "results/rl"))
    ppo = next(x for x in arms if x.column == "ppo" and x.scenario == "overtaking")
    assert sorted(ppo.runs) == ["ppo-s1", "ppo-s2", "ppo-s3"]
    means = [tables._stat(tables.Cell("overtaking", "ppo", {k: v}, []), "success_rate")["mean"]
             for k, v in ppo.runs.items()]
    stat = tables._stat(ppo, "success_rate")
    assert stat["ci_low"] == min(means) and stat["ci_high"] == max(means)
    assert "| overtaking | PPO (3 seeds)" in table and "3 x 200" in table


def test_the_episodes_table_counts_each_arms_outcomes_and_names_its_failed_seeds(tmp_path):
    folder = _folder(tmp_path, {"idm": "a" * 40, "lane-keep": "a" * 40})
    records = [json.loads(x) for x in (folder / "episodes.jsonl").read_text().splitlines()]
    lane = [r for r in records if r["label"] == "lane-keep"]
    failed = sorted(r["seed"] for r in lane if not r["metrics"]["success_rate"])
    table, _ = tables.episodes_table(folder)
    row = next(line for line in table.splitlines() if "| lane keeping |" in line)
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[:2] == ["highway-v0", "lane keeping"] and cells[2] == str(len(lane))
    assert cells[4] == str(sum(bool(r["metrics"]["collision_rate"]) for r in lane))
    assert cells[8].startswith(", ".join(map(str, failed[:10]))) and cells[8].endswith("...") == (len(failed) > 10)
    idm = next(line for line in table.splitlines() if "| IDM/MOBIL |" in line)
    assert idm.index("IDM/MOBIL") > 0 and table.index("IDM/MOBIL") < table.index("lane keeping")  # the NAMES order


def test_the_paired_table_is_bimp_compare_of_the_two_labels(tmp_path):
    folder = _folder(tmp_path, {"idm": "a" * 40, "lane-keep": "a" * 40})
    table, _ = tables.collisions_table(folder, "lane-keep", "idm")
    result = tables.compare(tables.label_results(folder, "lane-keep"), tables.label_results(folder, "idm"))
    c, n = result["highway-v0"]["collision_rate"], result["highway-v0"]["pairs"]
    assert f"| highway-v0 | {round(c['a'] * n)} vs {round(c['b'] * n)} (p = {c['p_value']:.2g}) |" in table
    assert round(c["a"] * n) > 0 and round(c["b"] * n) == 0  # lane keeping collides, IDM/MOBIL does not


def test_a_study_table_shows_only_the_scenarios_its_folder_ran(tmp_path):
    main = _folder(tmp_path, {"idm": "a" * 40})
    study = tmp_path / "study"
    study.mkdir()
    line = next(x for x in (main / "episodes.jsonl").read_text().splitlines())
    (study / "episodes.jsonl").write_text(json.dumps({**json.loads(line), "label": "idm-x"}) + "\n")
    with (main / "episodes.jsonl").open("a") as f:
        f.write(json.dumps({**json.loads(line), "scenario": "merge-v0"}) + "\n")
    table, arms = tables.grid_table([main, study], with_score=False, rows_of=study)
    assert {a.scenario for a in arms} == {"highway-v0"} and "merge-v0" not in table and "idm-x" in table


def _relabelled(tmp_path, labels: dict[str, str]) -> Path:
    """results/highway's highway-v0 records of each ``labels`` key, under its value as label."""
    folder = _folder(tmp_path, {label: "a" * 40 for label in labels})
    records = [json.loads(x) for x in (folder / "episodes.jsonl").read_text().splitlines()]
    (folder / "episodes.jsonl").write_text("".join(json.dumps({**r, "label": labels[r["label"]]}) + "\n"
                                                   for r in records))
    return folder


def test_a_summary_shows_the_chosen_columns_of_the_chosen_arms_in_their_order(tmp_path):
    folder = _folder(tmp_path, {"idm": "a" * 40, "lane-keep": "a" * 40})
    table, arms = tables.summary_table(str(folder), columns="collision,rate", labels="lane-keep,idm")
    lines = table.splitlines()
    assert lines[0] == "| scenario | policy | episodes | collision | steps over a rate bound |"
    assert [line.split("|")[2].strip() for line in lines[2:]] == ["lane keeping", "IDM/MOBIL"]
    lane = next(a for a in arms if a.column == "lane-keep")
    assert tables.format_stat(tables._stat(lane, "collision_rate")) in lines[2]
    assert lines[2].endswith(f"| {100 * tables._stat(lane, 'rate_violation_rate')['mean']:.1f}% |")
    only, _ = tables.summary_table(str(folder), labels="idm")
    assert "lane keeping" not in only and "IDM/MOBIL" in only
    with pytest.raises(EvaluationError, match="no scenario 'merge-v0' in these folders; they hold: highway-v0"):
        tables.summary_table(str(folder), scenarios="merge-v0")  # a typo would render an empty table
    with pytest.raises(EvaluationError, match="no label 'idn'"):
        tables.summary_table(str(folder), labels="idm,idn")
    with pytest.raises(EvaluationError, match="unknown column 'speed'; the columns: success"):
        tables.summary_table(str(folder), columns="success,speed")
    with pytest.raises(EvaluationError, match="holds no episodes.jsonl"):
        tables.summary_table(str(tmp_path / "none"))


def test_a_paired_table_pairs_each_variant_and_reads_its_verdict(tmp_path):
    folder = _relabelled(tmp_path, {"lane-keep": "lk N=5", "idm": "mobil N=5"})
    table, _ = tables.paired_table(str(folder), a="lk", b="mobil")
    result = tables.compare(tables.label_results(folder, "lk N=5"), tables.label_results(folder, "mobil N=5"))
    s = result["highway-v0"]["success_rate"]
    row = table.splitlines()[2]
    assert row.startswith("| f | highway-v0 (N=5) |") and f"| {s['only_a']} / {s['only_b']} |" in row
    assert s["p_value"] < 0.05 and s["only_b"] > s["only_a"]
    sc = result["highway-v0"]["score"]
    assert sc["ci_high"] < 0  # the records carry the closed-loop score: mobil leads on it too
    assert row.endswith(f"| {sc['mean_diff']:+.3f} [{sc['ci_low']:+.3f}, {sc['ci_high']:+.3f}] | "
                        "mobil ahead on success and the score |")
    # records made before the score: no score cell, the verdict on success alone
    records = [json.loads(x) for x in (folder / "episodes.jsonl").read_text().splitlines()]
    (folder / "episodes.jsonl").write_text("".join(
        json.dumps({**r, "metrics": {k: v for k, v in r["metrics"].items() if not k.startswith("score")}}) + "\n"
        for r in records))
    unscored, _ = tables.paired_table(str(folder), a="lk", b="mobil")
    assert unscored.splitlines()[2].endswith("| - | mobil ahead on success |")
    with pytest.raises(EvaluationError, match="no label 'nobody'"):
        tables.paired_table(str(folder), a="lk", b="nobody")


@pytest.mark.parametrize("success, score, verdict", [
    ({"only_a": 9, "only_b": 1, "p_value": 0.02}, {"mean_diff": 0.1, "ci_low": 0.05, "ci_high": 0.2},
     "A ahead on success and the score"),
    ({"only_a": 9, "only_b": 1, "p_value": 0.02}, {"mean_diff": -0.1, "ci_low": -0.2, "ci_high": -0.05},
     "A ahead on success, B on the score"),
    ({"only_a": 3, "only_b": 1, "p_value": 0.6}, {"mean_diff": -0.1, "ci_low": -0.2, "ci_high": -0.05},
     "B ahead on the score"),
    ({"only_a": 3, "only_b": 1, "p_value": 0.6}, {"mean_diff": 0.1, "ci_low": -0.2, "ci_high": 0.3}, "no difference"),
    ({"only_a": 3, "only_b": 1, "p_value": 0.6}, {"mean_diff": None, "ci_low": float("nan")}, "no difference"),
])
def test_a_verdict_names_who_leads_at_the_5_percent_level(success, score, verdict):
    assert tables._verdict(success, score, "A", "B") == verdict


def test_variants_are_rows_and_prefixes_columns_with_the_paired_p(tmp_path):
    folder = _relabelled(tmp_path, {"lane-keep": "lk-fast", "idm": "mobil"})
    table, _ = tables.variants_table(str(folder), prefixes="lk,mobil", pair="yes")
    lines = table.splitlines()
    assert lines[0] == "| variant | highway-v0 lk | highway-v0 IDM/MOBIL | McNemar p |" or "McNemar p" in lines[0]
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in lines[2:]}
    assert sorted(rows) == ["fast", "shipped"]  # in the order the records name them
    assert rows["fast"][1:] == ["-", "-"] and rows["fast"][0].startswith("0.")  # no mobil-fast arm to show or pair
    assert rows["shipped"][0] == "-" and rows["shipped"][2] == "-"
    assert tables._variant("nu30-plain", "nu3") is None and tables._variant("enkts N=3", "enkts") == "N=3"
    assert "[" not in tables.variants_table(str(folder), prefixes="lk", intervals="no")[0].splitlines()[2]
    for args, message in (({"prefixes": "lk3"}, "no label prefix 'lk3'"), ({"prefixes": "lk", "pair": "yes"},
                          "pair=yes pairs the first two"), ({"prefixes": "lk", "pair": "true"}, "yes or no")):
        with pytest.raises(EvaluationError, match=message):
            tables.variants_table(str(folder), **args)


def test_a_label_in_two_folders_is_refused_not_pooled(tmp_path):
    folder = _folder(tmp_path, {"idm": "a" * 40})
    other = tmp_path / "g"
    other.mkdir()
    (other / "episodes.jsonl").write_text((folder / "episodes.jsonl").read_text())
    with pytest.raises(EvaluationError, match="idm on highway-v0 is in both"):
        tables.summary_table(f"{folder},{other}")


def test_a_bench_table_reads_the_runs_and_refuses_another_file(tmp_path):
    run = {"rows": [{"planner": "enkts", "n_particles": 50, "median_ms": 2.92},
                    {"planner": "mppi", "n_particles": 50, "median_ms": 10.36}], "floor_ms": {"50": 1.44}}
    (tmp_path / "r.json").write_text(json.dumps(run))
    table, _ = tables.bench_table(str(tmp_path / "r.json"))
    assert table.splitlines()[2] == "| 50 | 2.9 | 10.4 | 1.4 | 2.0x | 0.28x |"
    (tmp_path / "s.json").write_text(json.dumps({"overtaking": {}}))
    with pytest.raises(EvaluationError, match="is not a `bimp bench` result"):
        tables.bench_table(str(tmp_path / "s.json"))


def test_a_marker_passes_its_arguments_and_a_wrong_one_is_named():
    seen = {}

    def table(folders, columns="x"):
        seen.update(folders=folders, columns=columns)
        return "| t |", []

    out, _ = report.render("<!-- report: k folders=a,b columns=y -->\n<!-- /report -->", {"k": table})
    assert seen == {"folders": "a,b", "columns": "y"} and "| t |" in out
    with pytest.raises(EvaluationError, match="no argument 'colour'; it takes folders, columns"):
        report.render("<!-- report: k folders=a colour=y -->\n<!-- /report -->", {"k": table})
    with pytest.raises(EvaluationError, match="argument 'folders' missing"):
        report.render("<!-- report: k columns=y -->\n<!-- /report -->", {"k": table})
    with pytest.raises(EvaluationError, match="it takes none"):
        report.render("<!-- report: t x=1 -->\n<!-- /report -->", {"t": _table([1])})
    for marker, message in (("k folders=a folders=b", "given twice"), ("k folders=a flag", "malformed"),
                            ("k folders=", "malformed"), ("k  folders=a", "malformed"), ("t ", "malformed")):
        with pytest.raises(EvaluationError, match=message):
            report.render(f"<!-- report: {marker} -->\n<!-- /report -->", {"k": table, "t": _table([1])}, where="p.md")

    def failing(folders):
        raise EvaluationError("report: no label 'x'")

    with pytest.raises(EvaluationError, match="^p.md: report: no label 'x'"):
        report.render("<!-- report: f folders=a -->\n<!-- /report -->", {"f": failing}, where="p.md")


def test_the_rl_verdict_pairs_the_best_planner_with_the_best_rl_arm_and_each_algorithm_over_its_seeds(tmp_path):
    from bimp.agents.evaluation.report_rl import rl_verdict_table, verdict_column, verdict_rows

    folder = _relabelled(tmp_path, {"enkts": "enkts", "mppi": "mppi", "idm": "ppo-s1", "lane-keep": "ppo-s2",
                                    "enks": "sac-s1"})
    results = {label: tables.label_results(folder, label) for label in ("enkts", "mppi", "ppo-s1", "ppo-s2", "sac-s1")}
    score = {label: sum(m["score"] for m in got.values()) / len(got) for label, got in results.items()}
    [row] = verdict_rows(folder)
    assert row["planner"] == max(("enkts", "mppi"), key=score.get)
    assert row["learner"] == max(("ppo-s1", "ppo-s2", "sac-s1"), key=score.get)
    paired = tables.compare(results[row["planner"]], results[row["learner"]])["highway-v0"]
    assert (row["only_a"], row["only_b"]) == (paired["success_rate"]["only_a"], paired["success_rate"]["only_b"])
    assert row["score_diff"]["mean_diff"] == pytest.approx(paired["score"]["mean_diff"])
    # PPO over its two seeds: per episode seed the mean of IDM/MOBIL's and lane keeping's outcomes
    seeds = sorted(seed for _, seed in results["ppo-s1"])
    mean = sum((results["ppo-s1"]["highway-v0", s]["success_rate"] + results["ppo-s2"]["highway-v0", s]["success_rate"])
               / 2 for s in seeds) / len(seeds)
    assert row["algos"]["ppo"]["runs"] == 2 and row["algos"]["ppo"]["success"] == pytest.approx(mean)
    assert row["algos"]["sac"]["runs"] == 1
    table, _ = rl_verdict_table(folder)
    assert table.count("\n| highway-v0 |") == 1 and ("ahead" in table or "no difference shown" in table)
    # the grid with the verdict as its last column
    grid, _ = tables.grid_table([folder], with_score=True, extra=verdict_column(folder))
    header, rule, line = grid.splitlines()[:3]
    assert header.endswith("| best planner vs best RL |") and rule.count("---") == header.count("|") - 1
    assert line.startswith("| highway-v0 |") and f"(p = {row['p_value']:.2g}" in line
    diff = row["score_diff"]
    if row["p_value"] >= 0.05:  # no difference on success: the score difference and its interval say the rest
        assert line.endswith(f"; score {diff['mean_diff']:+.2f} [{diff['ci_low']:+.2f}, {diff['ci_high']:+.2f}]) |")
    assert grid.splitlines()[2].count("|") == header.count("|")
    # a scenario the extra column has no cell for shows "-"
    grid, _ = tables.grid_table([folder], with_score=True, extra=("x", {}))
    assert grid.splitlines()[0].endswith("| x |") and grid.splitlines()[2].endswith("| - |")
    # a folder without RL arms has no row
    (tmp_path / "x").mkdir()
    assert verdict_rows(_folder(tmp_path / "x", {"enkts": "a" * 40, "idm": "a" * 40})) == []
