"""Records are checked, not trusted (issue 24, item 3): a record whose own config does not hash to its
``config_hash`` is refused by a resume, naming its line; a line that is not a record is reported with its number and
skipped by every reader, never a traceback, and nothing already recorded is lost."""

import json
import math
import shutil

import pytest

from bimp.agents.cli import EvaluationError
from bimp.agents.commands import aggregate, compare
from bimp.agents.commands import evaluate as ev_command
from bimp.agents.commands import plot as plot_command
from bimp.agents.evaluation import evaluate as ev
from bimp.agents.evaluation import records
from bimp.agents.evaluation.evaluate import evaluate, resolve_arms
from bimp.agents.evaluation.records import (
    ARMS_FILE,
    EPISODES_FILE,
    episode_bytes,
    finite,
    folder_lock,
    read_arms,
    read_records,
    record_config,
    unchanged_lock,
    write_arms,
)

ARGS = dict(scenarios=["emergency-brake"], episodes=2, seed=5, workers=1, traces=1, progress=False)
CLI = ["--scenario", "emergency-brake", "--episodes", "2", "--seed", "5", "--workers", "1"]


def test_a_record_whose_config_does_not_hash_to_its_config_hash_is_refused_naming_its_line(tmp_path, capsys):
    """The issue's case: episodes made under another config, given the default arm's hash, were taken as done."""
    evaluate(out=tmp_path / "other", policies=["lane-keep"], overrides={"lane-keep": {"k_lat": 0.01}}, **ARGS)
    (arm,) = resolve_arms(["emergency-brake"], ["lane-keep"])
    out = tmp_path / "out"
    out.mkdir()
    other = read_arms(tmp_path / "other")  # an old-format record: its config inline
    forged = [{**r, "config": record_config(r, other), "config_hash": arm.config_hash}
              for r in read_records(tmp_path / "other")]
    (out / EPISODES_FILE).write_text("".join(json.dumps(r) + "\n" for r in forged))
    before = (out / EPISODES_FILE).read_bytes()
    with pytest.raises(EvaluationError, match=r"episodes\.jsonl line 1: .*k_lat: 0\.01 -> 0\.004"):
        evaluate(out=out, policies=["lane-keep"], **ARGS)
    assert ev_command.main(["--policy", "lane-keep", *CLI, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "line 1" in err and "k_lat" in err and "Traceback" not in err
    assert (out / EPISODES_FILE).read_bytes() == before  # refused: nothing ran, nothing written


def test_a_genuine_record_resumes_even_with_infinities_written_as_null():
    """The check recomputes the hash from the record's config as it was written (JSON has no inf: null), so the
    records of an arm with an infinite value (EnKS's nu) still resume; a changed value is still refused."""
    toy = "tests.agents.toys:AlwaysBrake"  # a policy whose config takes any number
    (arm,) = resolve_arms(["emergency-brake"], [toy], {toy: {"brake": math.inf}})
    record = json.loads(json.dumps(finite({**ev._base_record(ev.Job(arm, 5)), "config": arm.resolved,
                                           "status": "error"})))
    assert record["config"]["config"]["brake"] is None
    ev.check_conflicts([arm], [(1, record)])  # accepted
    record["config"]["config"]["brake"] = 0.5
    with pytest.raises(EvaluationError, match="line 7: .*brake"):
        ev.check_conflicts([arm], [(7, record)])


def test_a_record_with_the_arms_hash_but_no_config_is_refused():
    """A forged record that drops its config (so there is nothing to recompute) is foreign too (review finding)."""
    (arm,) = resolve_arms(["emergency-brake"], ["lane-keep"])
    record = {**ev._base_record(ev.Job(arm, 5)), "status": "ok"}  # compact, and its hash not in arms.json
    with pytest.raises(EvaluationError, match="line 3: .*not in arms.json and it carries no config"):
        ev.check_conflicts([arm], [(3, record)], entries={})


def test_an_arms_json_entry_that_does_not_hash_to_its_key_is_refused_naming_the_hash(tmp_path):
    """arms.json vouches for every record of its arm: an entry edited to another config is foreign, and the
    folder's records with that hash with it."""
    evaluate(out=tmp_path, policies=["lane-keep"], **ARGS)
    arms = read_arms(tmp_path)
    (key,) = arms
    arms[key]["config"]["config"]["k_lat"] = 0.01
    (tmp_path / ARMS_FILE).write_text(json.dumps(arms))
    with pytest.raises(EvaluationError, match=f"arms.json: the entry {key} .*k_lat: 0.01 -> 0.004"):
        evaluate(out=tmp_path, policies=["lane-keep"], **ARGS)


BAD_LINES = {
    "empty object": b"{}",
    "null": b"null",
    "a list": b"[1, 2]",
    "bad JSON": b'{"scenario": oops}',
    "missing status": b'{"scenario": "emergency-brake", "policy": "zero", "seed": 9}',
    "ok without metrics": b'{"scenario": "emergency-brake", "policy": "zero", "seed": 9, "status": "ok"}',
    "a string seed": b'{"scenario": "emergency-brake", "policy": "zero", "seed": "9", "status": "error"}',
    "binary": bytes(range(128, 256)),
}


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Two arms, two seeds, traced: what evaluate, compare, aggregate and plot read."""
    out = tmp_path_factory.mktemp("records") / "base"
    evaluate(out=out, policies=["lane-keep", "zero"], **ARGS)
    return out


@pytest.mark.parametrize("line", BAD_LINES.values(), ids=BAD_LINES.keys())
def test_a_line_that_is_not_a_record_is_reported_and_skipped_by_every_reader(folder, tmp_path, capsys, line):
    out = tmp_path / "out"
    shutil.copytree(folder, out)
    good = (out / EPISODES_FILE).read_bytes()
    n = good.count(b"\n") + 1  # the bad line's number
    # and a last line cut by an interruption, skipped silently as before
    (out / EPISODES_FILE).write_bytes(good + line + b"\n" + b'{"scenario": "emergency-brake", "pol')
    assert [r["seed"] for r in read_records(out)] == [r["seed"] for r in read_records(folder)]
    warned = capsys.readouterr().err
    assert "skipped 1 line(s)" in warned and f"line {n} (" in warned
    assert ev_command.main(["--policy", "lane-keep", "zero", *CLI, "--out", str(out)]) == 0  # resumed: nothing reran
    assert compare.main([str(out), "--policies", "lane-keep", "zero"]) == 0
    assert aggregate.main([str(out), "--runs", "lane-keep", "zero", "--name", "x"]) == 0
    assert plot_command.main([str(out)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    data = (out / EPISODES_FILE).read_bytes()
    assert data.startswith(good + line + b"\n") and data.count(b"\n") == n + 1  # appended to only, nothing lost
    assert len(read_records(out)) == len(read_records(folder))


def test_a_list_override_in_a_folder_holding_another_config_is_refused_not_a_traceback():
    """``--set KEY=[...]`` made the arm unhashable: the conflict check crashed with a TypeError (review finding)."""
    (arm,) = resolve_arms(["emergency-brake"], ["enkts"], {"enkts": {"problem.sigma_ref": [2.0, 0.05, 1.0]}})
    other = {**ev._base_record(ev.Job(arm, 5)), "status": "ok", "config_hash": "0" * 16}
    with pytest.raises(EvaluationError, match="another config"):
        ev.check_conflicts([arm], [(1, other)])


def test_episode_bytes_reads_the_records_as_bytes_and_refuses_a_folder_in_their_place(tmp_path):
    assert episode_bytes(tmp_path) == b""  # nothing yet
    (tmp_path / EPISODES_FILE).write_bytes(b'{"a": 1}\n{"cut')
    assert episode_bytes(tmp_path) == b'{"a": 1}\n{"cut'  # as they are, a cut last line included
    other = tmp_path / "other"
    (other / EPISODES_FILE).mkdir(parents=True)
    with pytest.raises(EvaluationError, match="is not a regular file"):
        episode_bytes(other)


@pytest.mark.parametrize("change", ["records", "arms"])
def test_unchanged_lock_refuses_a_change_planned_on_a_stale_reading_and_holds_the_lock(tmp_path, change):
    (tmp_path / EPISODES_FILE).write_bytes(b"line 1\n")
    arms = {"abc": {"policy": "idm", "config": {}}}
    write_arms(tmp_path, arms)
    data = episode_bytes(tmp_path)
    with unchanged_lock(tmp_path, data, arms):  # nothing changed: the block runs under the lock
        with pytest.raises(EvaluationError, match="in use by another bimp run"):
            with folder_lock(tmp_path):
                pass
    if change == "records":
        (tmp_path / EPISODES_FILE).write_bytes(data + b"line 2\n")
    else:
        write_arms(tmp_path, {**arms, "def": {"policy": "idm", "config": {"a": 1}}})
    ran = []
    with pytest.raises(EvaluationError, match="changed while it was read"):
        with unchanged_lock(tmp_path, data, arms):
            ran.append(True)
    assert not ran
    with folder_lock(tmp_path):  # released after the refusal
        pass


def test_episode_bytes_names_a_file_it_cannot_read(tmp_path, monkeypatch):
    (tmp_path / EPISODES_FILE).write_bytes(b"x\n")

    def denied(path, flags):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(records.os, "open", denied)  # chmod would not stop root
    with pytest.raises(EvaluationError, match=f"cannot read {tmp_path / EPISODES_FILE}: Permission denied"):
        episode_bytes(tmp_path)


def test_an_appender_follows_its_file_where_another_program_replaced_it(tmp_path):
    """A `git stash` of a results folder during a run replaced episodes.jsonl, and the run's records went on into the
    replaced file, which nobody reads: 820 of them were lost so. The next write now goes to the new file."""
    path = tmp_path / "episodes.jsonl"
    path.write_text("a\n")
    sink = ev.Appender(path)
    try:
        assert sink.write("b\n") is False
        (tmp_path / "other").write_text("a\n")
        (tmp_path / "other").replace(path)  # as git writes a checked-out file: a new one under the name
        assert sink.write("c\n") is True and sink.write("d\n") is False
        assert path.read_text() == "a\nc\nd\n"  # the new file's own line kept, the run's after it
        path.unlink()
        assert sink.write("e\n") is True
    finally:
        sink.close()
    assert path.read_text() == "e\n"
