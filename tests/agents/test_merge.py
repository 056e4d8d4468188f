"""``bimp merge``: folders made apart become one that reads, resumes and ranks as if one run had made it; two arms
never end up under one name, an edited config is not let in, and a second merge copies nothing."""

import json

import pytest

from bimp.agents.cli import EvaluationError, main
from bimp.agents.commands import evaluate as ev
from bimp.agents.evaluation import merge as mg
from bimp.agents.evaluation import records
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.records import (
    ARMS_FILE,
    EPISODES_FILE,
    folder_lock,
    latest_records,
    read_arms,
    read_records,
)

TOY = "tests.agents.toys:AlwaysBrake"
ARGS = dict(scenarios=["emergency-brake"], episodes=2, workers=1, traces=0, progress=False)
OUTCOME = ("seed", "status", "steps", "metrics", "env_seed", "policy_seed", "config_hash")


def outcomes(folder) -> dict:
    """What a record says about its episode, per (label, seed): its timing is not part of it."""
    return {(r["label"], r["seed"]): {k: r[k] for k in OUTCOME if k != "metrics"}
            | {"metrics": {m: v for m, v in r["metrics"].items() if not m.startswith("plan_time")}}
            for r in latest_records(read_records(folder))}


@pytest.fixture
def apart(tmp_path):
    """The same two arms on seeds 5-6 in one folder and 7-8 in another, as two machines would make them."""
    a, b = tmp_path / "a", tmp_path / "b"
    evaluate(out=a, policies=["lane-keep", TOY], labels={TOY: "brake"}, seed=5, **ARGS)
    evaluate(out=b, policies=["lane-keep", TOY], labels={TOY: "brake"}, seed=7, **ARGS)
    return a, b


def test_two_runs_merged_are_the_run_over_all_their_seeds_and_it_resumes(apart, tmp_path, capsys):
    a, b = apart
    into = tmp_path / "all"
    assert main(["merge", str(a), str(b), "--into", str(into)]) == 0
    assert "copied 8 record(s), 0 already there" in capsys.readouterr().out
    whole = tmp_path / "whole"
    evaluate(out=whole, policies=["lane-keep", TOY], labels={TOY: "brake"}, seed=5,
             **{**ARGS, "episodes": 4})
    assert outcomes(into) == outcomes(whole)
    assert read_arms(into) == read_arms(whole)
    summary = json.loads((into / "summary.json").read_text())
    assert sorted(summary) == ["brake/emergency-brake", "lane-keep/emergency-brake"]
    assert summary["lane-keep/emergency-brake"]["episodes"] == 4
    # the merged folder resumes: the same request over seeds 5-8 has nothing left to run
    assert ev.main(["--policy", "lane-keep", TOY, "--label", f"{TOY}=brake", "--scenario", "emergency-brake",
                    "--episodes", "4", "--seed", "5", "--workers", "1", "--out", str(into), "--dry-run"]) == 0
    assert "0 episode(s) would run" in capsys.readouterr().out


def test_a_second_merge_copies_nothing_and_filters_pick_what_goes(apart, tmp_path, capsys):
    a, b = apart
    into = tmp_path / "all"
    copied, skipped, _ = mg.merge([a], into, labels=["brake"])
    assert copied == {("emergency-brake", "brake"): 2} and not skipped
    assert {r["label"] for r in read_records(into)} == {"brake"} and len(read_arms(into)) == 1
    before = (into / EPISODES_FILE).read_bytes()
    copied, skipped, _ = mg.merge([a, b], into, labels=["brake"])
    assert copied == {("emergency-brake", "brake"): 2} and skipped == {("emergency-brake", "brake"): 2}
    copied, skipped, _ = mg.merge([a, b, a], into, scenarios=["emergency-brake"], labels=["brake"])
    assert not copied and skipped == {("emergency-brake", "brake"): 6}
    assert (into / EPISODES_FILE).read_bytes().startswith(before) and len(read_records(into)) == 4


def test_a_dry_run_counts_and_writes_nothing(apart, tmp_path, capsys):
    a, b = apart
    into = tmp_path / "all"
    assert main(["merge", str(a), str(b), "--into", str(into), "--label", "lane-keep", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "would copy     4 record(s) of lane-keep on emergency-brake" in out and "would copy 4 record(s)" in out
    assert not into.exists()


def test_two_configs_under_one_label_are_refused_and_nothing_is_written(apart, tmp_path, capsys):
    a, b = apart
    other = tmp_path / "other"
    evaluate(out=other, policies=["lane-keep"], overrides={"lane-keep": {"k_lat": 0.01}}, seed=9, **ARGS)
    before = {p.name: p.read_bytes() for p in a.iterdir()}
    assert main(["merge", str(other), "--into", str(a)]) == 2
    assert "'lane-keep' on emergency-brake holds config" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in a.iterdir() if p.name != ".lock"} == {
        k: v for k, v in before.items() if k != ".lock"}
    with pytest.raises(EvaluationError, match="two arms under one name"):  # between sources too
        mg.merge([b, other], tmp_path / "new")
    assert not (tmp_path / "new").exists()


def test_an_edited_config_is_not_let_in(apart, tmp_path):
    """An arms.json entry that no longer hashes to its key would vouch, in the merged folder, for records it did not
    make: refused, as evaluate refuses to resume on it."""
    a, _ = apart
    arms = read_arms(a)
    key = next(k for k, e in arms.items() if e["policy"] == "lane-keep")
    arms[key]["config"]["config"]["k_lat"] = 0.01
    (a / ARMS_FILE).write_text(json.dumps(arms))
    with pytest.raises(EvaluationError, match=f"the arms.json entry {key}: its config does not hash to {key}"):
        mg.merge([a], tmp_path / "all")
    (a / ARMS_FILE).write_text(json.dumps({k: v for k, v in arms.items() if k != key}))
    with pytest.raises(EvaluationError, match=f"names config {key}, which its arms.json does not hold"):
        mg.merge([a], tmp_path / "all", labels=["lane-keep"])
    assert not (tmp_path / "all").exists()


@pytest.mark.parametrize("argv, named", [
    (["--label", "lane-kep"], "--label lane-kep: no record .*it holds: brake, lane-keep"),
    (["--scenario", "overtaking"], "--scenario overtaking: no record .*it holds: emergency-brake"),
])
def test_a_name_that_matches_nothing_is_refused(apart, tmp_path, capsys, argv, named):
    a, _ = apart
    assert main(["merge", str(a), "--into", str(tmp_path / "all"), *argv]) == 2
    assert "bimp merge: error:" in capsys.readouterr().err
    with pytest.raises(EvaluationError, match=named):
        mg.merge([a], tmp_path / "all", **{"scenarios" if argv[0] == "--scenario" else "labels": [argv[1]]})


def test_a_folder_in_use_itself_or_without_records_is_refused(apart, tmp_path):
    a, b = apart
    with folder_lock(b), pytest.raises(EvaluationError, match="in use by another bimp run"):
        mg.merge([a], b)
    with pytest.raises(EvaluationError, match="is the folder merged into"):
        mg.merge([b, a], a)
    with pytest.raises(EvaluationError, match="not an evaluation folder"):
        mg.merge([tmp_path / "nothing"], b)
    assert len(read_records(b)) == 4


def test_records_appended_between_the_read_and_the_lock_are_not_lost(apart, monkeypatch):
    a, b = apart
    extra = (a / EPISODES_FILE).read_bytes().splitlines(keepends=True)[0]

    def late_append(out, **kw):
        with open(out / EPISODES_FILE, "ab") as f:
            f.write(extra)
        return folder_lock(out, **kw)

    monkeypatch.setattr(records, "folder_lock", late_append)  # the lock taken before the reread
    with pytest.raises(EvaluationError, match="changed while it was read"):
        mg.merge([a], b)
    assert len(read_records(b)) == 5


def test_an_error_record_does_not_hide_a_result_and_a_cut_last_line_stays_apart(apart, tmp_path):
    """DIR's failed episode is retried by a source's result (the result is copied; readers take it over the error);
    a source's error where DIR has the result is skipped. DIR's last line cut by an interruption stays a line of its
    own, reported and skipped by readers, not glued to the first copied record."""
    a, b = apart
    first = read_records(a)[0]
    failed = {k: v for k, v in first.items() if k not in ("metrics", "steps", "truncated")} | {"status": "error"}
    into = tmp_path / "all"
    into.mkdir()
    (into / EPISODES_FILE).write_text(json.dumps(failed) + "\n" + '{"scenario": "cut')
    (into / ARMS_FILE).write_text((a / ARMS_FILE).read_text())
    copied, skipped, _ = mg.merge([a], into)
    assert sum(copied.values()) == 4 and not skipped
    assert [r["status"] for r in latest_records(read_records(into)) if r["seed"] == first["seed"]
            and r["label"] == first["label"]] == ["ok"]
    assert (into / EPISODES_FILE).read_bytes().count(b"\n") == 6
    with open(b / EPISODES_FILE, "a") as f:
        f.write(json.dumps(failed) + "\n")
    copied, skipped, _ = mg.merge([b], into, labels=[first["label"]])
    assert sum(copied.values()) == 2 and sum(skipped.values()) == 1


def test_the_usage_puts_the_sources_first(capsys):
    with pytest.raises(SystemExit):
        main(["merge", "--help"])
    assert "usage: bimp merge SRC [SRC ...] --into DIR" in capsys.readouterr().out


def test_a_name_need_only_be_in_one_source(apart, tmp_path):
    a, _ = apart
    other = tmp_path / "other"
    evaluate(out=other, policies=["lane-keep"], seed=9, **{**ARGS, "scenarios": ["overtaking"], "episodes": 1})
    copied, *_ = mg.merge([a, other], tmp_path / "all", scenarios=["overtaking"])
    assert copied == {("overtaking", "lane-keep"): 1}
    with pytest.raises(EvaluationError, match=f"--label nobody: no record in {a} or {other}"):
        mg.merge([a, other], tmp_path / "all", labels=["nobody"])


def test_a_merge_cut_before_its_configs_is_mended_by_the_next(apart, tmp_path, capsys):
    """arms.json goes first; were it lost after the records (as a cut between two writes would leave it), the next
    merge finds the records there and writes the entries they name."""
    a, b = apart
    into = tmp_path / "all"
    mg.merge([a], into)
    (into / ARMS_FILE).unlink()
    assert main(["merge", str(a), "--into", str(into), "--dry-run"]) == 0
    assert "would add 2 config(s) to arms.json" in capsys.readouterr().out and not (into / ARMS_FILE).exists()
    copied, skipped, added = mg.merge([a], into)
    assert not copied and sum(skipped.values()) == 4 and added == sorted(read_arms(a))
    assert read_arms(into) == read_arms(a)
    assert ev.main(["--policy", "lane-keep", "--scenario", "emergency-brake", "--episodes", "2", "--seed", "5",
                    "--workers", "1", "--out", str(into), "--dry-run"]) == 0


def test_an_entry_held_with_another_seeding_is_refused(apart, tmp_path):
    """A record leaves its seeding to its arms.json entry: copied beside another entry of the same hash whose seeding
    differs, it would be read with that one."""
    a, b = apart
    arms = read_arms(b)
    key = next(iter(arms))
    arms[key]["seeding"] = "something else"
    (b / ARMS_FILE).write_text(json.dumps(arms))
    with pytest.raises(EvaluationError, match=f"entry {key} differs from the merged folder's in its seeding"):
        mg.merge([a], b)
    assert len(read_records(b)) == 4


def test_a_record_without_a_config_hash_is_refused(apart, tmp_path):
    """Records from before config hashes cannot be told apart by config: two of them under one label could be two
    arms."""
    a, _ = apart
    old = {k: v for k, v in read_records(a)[0].items() if k != "config_hash"}
    old["config"] = read_arms(a)[read_records(a)[0]["config_hash"]]["config"]
    with open(a / EPISODES_FILE, "a") as f:
        f.write(json.dumps(old) + "\n")
    with pytest.raises(EvaluationError, match="without a config hash .*bimp migrate"):
        mg.merge([a], tmp_path / "all")


def test_a_sources_cut_last_line_is_not_copied_and_a_file_is_no_folder(apart, tmp_path):
    a, b = apart
    whole = (a / EPISODES_FILE).read_bytes()
    last = whole.splitlines(keepends=True)[-1]
    (a / EPISODES_FILE).write_bytes(whole[: -len(last)] + last[: len(last) // 2])  # a run cut mid-line
    copied, *_ = mg.merge([a], tmp_path / "all")
    assert sum(copied.values()) == 3
    assert all(line.endswith(b"}") for line in (tmp_path / "all" / EPISODES_FILE).read_bytes().splitlines())
    (tmp_path / "file").write_text("")
    with pytest.raises(EvaluationError, match="is not a folder"):
        mg.merge([b], tmp_path / "file")


def test_a_mend_from_two_sources_that_disagree_is_refused(apart, tmp_path):
    """Every source naming a config DIR lacks is compared with the first, skipped records or not."""
    a, b = apart
    into = tmp_path / "all"
    mg.merge([a, b], into)
    (into / ARMS_FILE).unlink()  # every record of both is there now: all skipped, only the entries to mend
    arms = read_arms(b)
    for entry in arms.values():
        entry["seeding"] = "something else"
    (b / ARMS_FILE).write_text(json.dumps(arms))
    with pytest.raises(EvaluationError, match="differs from the merged folder's in its seeding"):
        mg.merge([a, b], into)
    assert not (into / ARMS_FILE).exists()


def test_a_target_it_cannot_use_is_refused_before_anything_is_written(apart, tmp_path):
    a, _ = apart
    odd = tmp_path / "odd"
    (odd / EPISODES_FILE).mkdir(parents=True)
    with pytest.raises(EvaluationError, match="is not a regular file"):
        mg.merge([a], odd)
    assert sorted(p.name for p in odd.iterdir()) == [EPISODES_FILE]
    old = tmp_path / "old"
    old.mkdir()
    record = {k: v for k, v in read_records(a)[0].items() if k != "config_hash"}
    (old / EPISODES_FILE).write_text(json.dumps(record) + "\n")
    with pytest.raises(EvaluationError, match=f"{old} holds records without a config hash .*bimp migrate {old}"):
        mg.merge([a], old)
