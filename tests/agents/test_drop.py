"""``bimp drop``: a folder's records of a scenario or a label taken out, so that the label can be rerun with another
config; what stays is untouched, a typo removes nothing, and a running evaluation's folder is not touched."""

import json

import pytest

from bimp.agents.cli import EvaluationError, main
from bimp.agents.commands import evaluate as ev
from bimp.agents.evaluation import drop as dr
from bimp.agents.evaluation import records
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.records import ARMS_FILE, EPISODES_FILE, folder_lock, read_arms, read_records

TOY = "tests.agents.toys:AlwaysBrake"
ARGS = dict(scenarios=["emergency-brake"], episodes=2, seed=5, workers=1, traces=0, progress=False)


@pytest.fixture
def folder(tmp_path):
    """Two arms on one scenario: lane keeping (label lane-keep) and the toy brake (label brake)."""
    evaluate(out=tmp_path, policies=["lane-keep", TOY], labels={TOY: "brake"}, **ARGS)
    return tmp_path


def lines_of(folder, label: str) -> list[bytes]:
    return [line for line in (folder / EPISODES_FILE).read_bytes().splitlines(keepends=True)
            if json.loads(line)["label"] == label]


def test_a_label_dropped_can_be_rerun_with_another_config_and_the_rest_is_untouched(folder, capsys):
    with pytest.raises(EvaluationError, match="bimp drop .* --scenario emergency-brake --label lane-keep"):
        evaluate(out=folder, policies=["lane-keep"], overrides={"lane-keep": {"k_lat": 0.01}}, **ARGS)
    brake = lines_of(folder, "brake")
    (old_hash,) = {r["config_hash"] for r in read_records(folder) if r["label"] == "lane-keep"}
    assert main(["drop", str(folder), "--label", "lane-keep"]) == 0
    assert "dropped     2 record(s) of lane-keep on emergency-brake" in capsys.readouterr().out
    assert lines_of(folder, "lane-keep") == [] and lines_of(folder, "brake") == brake  # byte for byte
    assert old_hash not in read_arms(folder) and len(read_arms(folder)) == 1
    summary = evaluate(out=folder, policies=["lane-keep"], overrides={"lane-keep": {"k_lat": 0.01}}, **ARGS)
    new = {r["config_hash"] for r in read_records(folder) if r["label"] == "lane-keep"}
    assert len(new) == 1 and old_hash not in new and summary["lane-keep/emergency-brake"]["episodes"] == 2


def test_the_summary_keeps_its_rows_but_the_dropped_ones(folder):
    """A summary is of the last request: drop takes the dropped rows out and adds none of the folder's others."""
    evaluate(out=folder, policies=["lane-keep"], overrides={"lane-keep": {"k_lat": 0.01}}, labels={"lane-keep": "k"},
             **ARGS)
    assert list(json.loads((folder / "summary.json").read_text())) == ["k/emergency-brake"]
    dr.drop(folder, labels=["brake"])
    assert list(json.loads((folder / "summary.json").read_text())) == ["k/emergency-brake"]
    evaluate(out=folder, policies=["lane-keep"], all_records=True, **ARGS)  # every row of the folder
    dr.drop(folder, labels=["k"])
    assert list(json.loads((folder / "summary.json").read_text())) == ["lane-keep/emergency-brake"]
    rows = (folder / "summary.csv").read_text().splitlines()[1:]
    assert [row.split(",")[0] for row in rows] == ["lane-keep"]


def test_a_dry_run_counts_and_writes_nothing(folder, capsys):
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert main(["drop", str(folder), "--scenario", "emergency-brake", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "would drop     2 record(s) of brake" in out and "would drop 4 record(s)" in out
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before


@pytest.mark.parametrize("argv, named", [
    (["--label", "lane-kep"], "--label lane-kep: no record .*it holds: brake, lane-keep"),
    (["--scenario", "overtaking"], "--scenario overtaking: no record .*it holds: emergency-brake"),
    ([], "name what to drop"),
])
def test_a_name_that_matches_nothing_is_refused_and_nothing_is_written(folder, capsys, argv, named):
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    with pytest.raises(EvaluationError, match=named):
        dr.drop(folder, **{"scenarios" if a == "--scenario" else "labels": [v] for a, v in zip(argv[::2], argv[1::2])})
    assert main(["drop", str(folder), *argv]) == 2
    assert "bimp drop: error:" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in folder.iterdir() if p.name != ".lock"} == {
        k: v for k, v in before.items() if k != ".lock"}


def test_a_folder_in_use_or_without_records_is_refused(folder, tmp_path_factory):
    with folder_lock(folder), pytest.raises(EvaluationError, match="in use by another bimp run"):
        dr.drop(folder, labels=["brake"])
    assert len(read_records(folder)) == 4
    with pytest.raises(EvaluationError, match="not an evaluation folder"):
        dr.drop(tmp_path_factory.mktemp("empty"), labels=["brake"])


def test_lines_that_are_not_records_and_unnamed_arms_entries_are_kept(folder):
    """Only what the dropped records named goes: a foreign line stays (readers report it), and so does an arms.json
    entry no record names (a run interrupted before its first episode)."""
    with open(folder / EPISODES_FILE, "ab") as f:
        f.write(b"not a record\n")
    arms = read_arms(folder)
    (folder / ARMS_FILE).write_text(json.dumps({**arms, "0" * 16: {"policy": "zero", "config": {}}}))
    dr.drop(folder, labels=["lane-keep"])
    assert (folder / EPISODES_FILE).read_bytes().endswith(b"not a record\n")
    assert "0" * 16 in read_arms(folder) and len(read_arms(folder)) == 2
    assert {r["label"] for r in read_records(folder)} == {"brake"}
    assert ev.main(["--policy", "lane-keep", "--scenario", "emergency-brake", "--episodes", "1", "--seed", "5",
                    "--workers", "1", "--out", str(folder), "--dry-run"]) == 0


def test_records_appended_between_the_read_and_the_lock_are_not_lost(folder, monkeypatch):
    """A run that appends after drop read the folder and before it locked it: drop refuses, the new line stays."""
    def late_append(out, **kw):
        with open(out / EPISODES_FILE, "ab") as f:
            f.write(lines_of(out, "brake")[0])
        return folder_lock(out, **kw)

    monkeypatch.setattr(records, "folder_lock", late_append)  # the lock taken before the reread
    with pytest.raises(EvaluationError, match="changed while it was read"):
        dr.drop(folder, labels=["lane-keep"])
    assert len(read_records(folder)) == 5


def test_an_unreadable_arms_json_is_refused_before_anything_is_written(folder, capsys):
    (folder / ARMS_FILE).write_text("{bad")
    before = (folder / EPISODES_FILE).read_bytes()
    assert main(["drop", str(folder), "--label", "brake"]) == 2
    assert "arms.json" in capsys.readouterr().err
    assert (folder / EPISODES_FILE).read_bytes() == before


def test_the_usage_puts_the_folder_first(capsys):
    with pytest.raises(SystemExit):
        main(["drop", "--help"])
    assert "usage: bimp drop DIR [--scenario" in capsys.readouterr().out


def test_old_records_blank_lines_a_cut_last_line_and_a_shared_hash(folder):
    """Records from before labels and arms.json (the config inline, no label, no hash) drop by their policy name; a
    blank line and the final newline stay; a hash that a kept record on another scenario names stays in arms.json;
    a last line without its newline drops like any other."""
    arms = read_arms(folder)
    (lane,) = [r for r in read_records(folder) if r["label"] == "lane-keep"][:1]
    elsewhere = {**lane, "scenario": "elsewhere"}  # the same arm's hash on another scenario
    old = {k: v for k, v in lane.items() if k not in ("label", "config_hash")}
    old.update(policy="zero", config=arms[lane["config_hash"]]["config"])
    with open(folder / EPISODES_FILE, "ab") as f:
        f.write(b"\n" + json.dumps(elsewhere).encode() + b"\n" + json.dumps(old).encode() + b"\n")
    assert dr.drop(folder, labels=["zero"]) == {("emergency-brake", "zero"): 1}
    data = (folder / EPISODES_FILE).read_bytes()
    assert data.endswith(b"}\n") and b"\n\n" in data and b'"zero"' not in data
    assert dr.drop(folder, scenarios=["emergency-brake"], labels=["lane-keep"]) == {("emergency-brake", "lane-keep"): 2}
    assert lane["config_hash"] in read_arms(folder)  # still named by the record on "elsewhere"
    with open(folder / EPISODES_FILE, "ab") as f:
        f.write(json.dumps({**elsewhere, "seed": 99}).encode())  # cut: no newline
    assert dr.drop(folder, scenarios=["elsewhere"]) == {("elsewhere", "lane-keep"): 2}
    assert lane["config_hash"] not in read_arms(folder)
    assert {r["label"] for r in read_records(folder)} == {"brake"}


def test_names_that_each_match_but_not_together_drop_nothing(folder, capsys):
    records = read_records(folder)
    for r in records:  # move the brake arm to a scenario of its own
        r["scenario"] = "other" if r["label"] == "brake" else r["scenario"]
    (folder / EPISODES_FILE).write_text("".join(json.dumps(r) + "\n" for r in records))
    before = (folder / EPISODES_FILE).read_bytes()
    assert main(["drop", str(folder), "--scenario", "other", "--label", "lane-keep"]) == 0
    assert "nothing matched both" in capsys.readouterr().out
    assert (folder / EPISODES_FILE).read_bytes() == before


def test_a_folder_that_cannot_be_written_is_named_not_a_traceback(folder, monkeypatch):
    def denied(path, text):
        raise PermissionError(13, "Permission denied", str(path))

    before = (folder / EPISODES_FILE).read_bytes()
    monkeypatch.setattr(dr, "write_atomic", denied)  # chmod would not stop root
    with pytest.raises(EvaluationError, match=f"cannot write into {folder}"):
        dr.drop(folder, labels=["lane-keep"])
    assert (folder / EPISODES_FILE).read_bytes() == before  # nothing dropped
