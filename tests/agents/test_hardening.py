"""Files bimp reads are data: a results folder, a record, ``arms.json`` or a config file never makes bimp run code,
and a bad record, a device behind a symlink or a full disk is one line, never a traceback (docs/security.md)."""

from __future__ import annotations

import errno
import importlib
import json
import math
import os
import time

import gymnasium as gym
import pytest

from bimp import envs
from bimp.agents import files, rl
from bimp.agents.cli import EvaluationError, command_module, main
from bimp.agents.evaluation import migrate, record_check, records
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.metrics import METRICS, summarize
from bimp.agents.evaluation.records import (
    ARMS_FILE,
    EPISODES_FILE,
    folder_lock,
    latest_records,
    numbered_records,
    read_arms,
    read_records,
)
from bimp.agents.files import write_atomic
from bimp.agents.registry import make_policy

TOY = "tests.agents.toys:AlwaysBrake"
SCENARIO = "emergency-brake"
NESTED = b'{"a":' * 1000 + b"1" + b"}" * 1000  # 7 kB: past what json's parser (and any recursive walk) takes


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A real folder: two arms (lane keeping, the toy brake) on two seeds each, its records and arms.json."""
    out = tmp_path_factory.mktemp("made")
    evaluate(out=out, policies=["lane-keep", TOY], labels={TOY: "brake"}, scenarios=[SCENARIO], episodes=2, seed=5,
             workers=1, traces=0, progress=False)
    return {name: (out / name).read_bytes() for name in (EPISODES_FILE, ARMS_FILE)}


@pytest.fixture
def folder(made, tmp_path):
    """A fresh copy of ``made`` to attack."""
    out = tmp_path / "folder"
    out.mkdir()
    for name, data in made.items():
        (out / name).write_bytes(data)
    return out


def append(folder, line: bytes) -> None:
    with open(folder / EPISODES_FILE, "ab") as f:
        f.write(line + b"\n")


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


# --- 1. no code named by a results folder ------------------------------------------------------------------
def payload(marker) -> dict:
    """What the probe wrote: pydoc.pipepager(env, cmd=...) runs ``cmd`` in a shell."""
    return {"config": {"cmd": f"touch {marker}"}, "scenario": {}}


def test_migrate_never_imports_a_policy_a_record_names(folder, tmp_path, capsys):
    marker = tmp_path / "MARKER"
    record = {**json.loads((folder / EPISODES_FILE).read_bytes().splitlines()[0]), "policy": "pydoc:pipepager",
              "label": "evil", "config": payload(marker)}
    (folder / EPISODES_FILE).write_text(json.dumps(record) + "\n")
    assert main(["migrate", str(folder), "--dry-run"]) == 1
    out = capsys.readouterr().out
    assert not marker.exists()
    assert "'evil' (pydoc:pipepager)" in out and "--trust-policy pydoc:pipepager" in out


def test_migrate_never_imports_a_policy_arms_json_names(folder, tmp_path, capsys):
    marker = tmp_path / "MARKER"
    record = {**json.loads((folder / EPISODES_FILE).read_bytes().splitlines()[0]), "policy": "pydoc:pipepager",
              "config_hash": "0123456789abcdef"}
    (folder / EPISODES_FILE).write_text(json.dumps(record) + "\n")
    (folder / ARMS_FILE).write_text(json.dumps({"0123456789abcdef": {"policy": "pydoc:pipepager",
                                                                     "config": payload(marker)}}))
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert main(["migrate", str(folder)]) == 1
    assert not marker.exists()
    assert "not in the policy table" in capsys.readouterr().out
    assert {p.name: p.read_bytes() for p in folder.iterdir() if p.name != ".lock"} == before


def test_a_policy_the_user_names_on_the_command_line_is_theirs_to_run(folder, tmp_path):
    """The switch is what makes the difference: named by the user, the same folder's policy is built (and runs)."""
    marker = tmp_path / "MARKER"
    record = {**json.loads((folder / EPISODES_FILE).read_bytes().splitlines()[0]), "policy": "pydoc:pipepager",
              "config": payload(marker)}
    (folder / EPISODES_FILE).write_text(json.dumps(record) + "\n")
    report = migrate.migrate_folder(folder, dry_run=True, trusted=["pydoc:pipepager"])
    for _ in range(100):  # the payload's shell runs beside us: pipepager raised before waiting for it
        if marker.exists():
            break
        time.sleep(0.05)
    assert marker.exists(), report.line()


def test_a_folder_cannot_switch_on_trust_model_for_migrate():
    config = {"config": {"algo": "ppo", "model_sha256": next(iter(migrate.shipped_models())), "trust_model": True}}
    with pytest.raises(migrate.MigrationError, match="trust_model"):
        migrate.rebuild("ppo", "overtaking", config)


# --- 2. no trust switch from a config file -----------------------------------------------------------------
@pytest.mark.parametrize("text", ["policy: ppo\nconfig: {model: evil.zip, trust_model: true}\n",
                                  "trust_model: true\n", "model: evil.zip\nnested: {deeper: {trust_model: false}}\n"])
def test_a_config_file_that_sets_trust_model_is_refused_naming_file_and_key(tmp_path, text):
    path = tmp_path / "t.yaml"
    path.write_text(text)
    env = gym.make(envs.env_id("overtaking"))
    with pytest.raises(ValueError, match=f"{path} sets .*trust_model, a trust switch"):
        make_policy("ppo", env, config=str(path))


def test_evaluate_refuses_a_set_config_file_with_trust_model_in_one_line(tmp_path, capsys):
    path = tmp_path / "t.yaml"
    path.write_text("policy: ppo\nconfig: {model: evil.zip, trust_model: true}\n")
    code = main(["evaluate", "--scenario", "overtaking", "--policy", "ppo", "--set", f"ppo.config={path}",
                 "--dry-run", "--out", str(tmp_path / "out")])
    err = one_line_error(capsys)
    assert code == 2 and "trust_model" in err and len(err.strip().splitlines()) == 1


# --- 3-4. bad records are skipped by every reader, with one warning naming line and field ---------------------
BAD_VALUES = ["yes", {}, [1], math.nan, math.inf, 1e308, 2.0, -1, 0.5, True, None, "many", 10**30, 10**400,
              "a\nb", "a/b", "\x1b[2J", "x" * 300]
FIELDS = ["seed", "steps", "status", "scenario", "policy", "label", "config_hash", "truncated", "git_commit",
          "git_dirty", "machine", "policy_info", "overrides", "seeding", "config", "config.config", "config.files",
          *[f"metrics.{name}" for name in METRICS]]


def variant(record: dict, field: str, value: object) -> dict:
    out = json.loads(json.dumps(record))
    head, _, name = field.partition(".")
    if name and not isinstance(out.get(head), dict):
        out[head] = {}
    (out[head] if name else out).__setitem__(name or head, value)
    return out


def sane(summary: dict) -> bool:
    """Every statistic of ``summary`` finite, every rate's mean in [0, 1]."""
    for entry in summary.values():
        for name in METRICS:
            stat = entry[name]
            values = [v for v in stat.values() if isinstance(v, float)]
            if not all(math.isfinite(v) for v in values):
                return False
            if name.endswith("_rate") and stat.get("mean") is not None and not 0 <= stat["mean"] <= 1:
                return False
    return True


def test_fuzzed_record_fields_are_skipped_or_read_never_a_traceback(made, tmp_path, capsys):
    """Every field a reader uses, each set to every bad value: each line is either skipped (and named in the warning)
    or read, and what is read summarizes to finite statistics with rates in [0, 1]."""
    good = [json.loads(line) for line in made[EPISODES_FILE].splitlines()]
    lines = [json.dumps(variant(good[0], f, v)).encode() for f in FIELDS for v in BAD_VALUES]
    (tmp_path / EPISODES_FILE).write_bytes(made[EPISODES_FILE] + b"\n".join(lines) + b"\n")
    (tmp_path / ARMS_FILE).write_bytes(made[ARMS_FILE])
    kept = numbered_records(tmp_path)
    warning = capsys.readouterr().err
    assert warning.count("bimp: warning:") == 1 and "line 5 (" in warning
    for number, record in kept:
        summary = summarize(latest_records([record]))
        assert sane(summary), (number, record)
    assert len(kept) < len(good) + len(lines)  # something was refused: the check is not a pass-through
    for field, value in [("metrics.success_rate", "yes"), ("metrics.collision_rate", 0.5), ("seed", -1),
                         ("metrics.min_ttc_s", math.nan), ("metrics.score", 2.0), ("steps", "many"),
                         ("machine", "\x1b[2J"), ("machine", "a\nb")]:
        assert records.record_problem(variant(good[0], field, value)) is not None, (field, value)
        assert field.rpartition(".")[2] in records.record_problem(variant(good[0], field, value))


WRONG_TYPE = (b'{"scenario": "emergency-brake", "policy": "lane-keep", "label": "lane-keep", "seed": 9, '
              b'"status": "ok", "metrics": {"success_rate": "yes"}}')


@pytest.mark.parametrize("line", [NESTED, WRONG_TYPE])
def test_every_reader_skips_a_bad_line_and_the_folder_still_resumes(folder, tmp_path, capsys, line):
    append(folder, line)
    records._reported.clear()  # the warning is said once per process and folder: say it here
    codes = [main(argv) for argv in (["compare", str(folder), "--policies", "lane-keep", "brake"],
                                     ["aggregate", str(folder), "--runs", "lane-keep", "brake", "--name", "x"],
                                     ["leaderboard", str(folder)],
                                     ["merge", str(folder), "--into", str(tmp_path / "merged")],
                                     ["drop", str(folder), "--label", "brake", "--dry-run"],
                                     ["migrate", str(folder), "--dry-run"])]
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    assert codes == [0] * 5 + [1], codes  # migrate: the toy brake is a module:factory policy, not the bad line
    assert "--trust-policy tests.agents.toys:AlwaysBrake" in out
    assert err.count("bimp: warning:") == 1 and "skipped 1 line(s) that are not episode records: line 5" in err
    evaluate(out=folder, policies=["lane-keep"], scenarios=[SCENARIO], episodes=3, seed=5, workers=1, traces=0,
             progress=False)
    assert len(read_records(folder)) == 5  # resumed: the two done, one more


def test_drop_with_a_bad_record_in_the_folder_drops_and_rewrites_its_summary(folder):
    evaluate(out=folder, policies=["lane-keep", TOY], labels={TOY: "brake"}, scenarios=[SCENARIO], episodes=2,
             seed=5, workers=1, traces=0, progress=False)  # resumes, writes the summary
    append(folder, json.dumps(variant(json.loads(folder.joinpath(EPISODES_FILE).read_bytes().splitlines()[0]),
                                      "metrics.collision_rate", math.nan)).encode())
    assert main(["drop", str(folder), "--label", "brake"]) == 0
    assert set(json.loads((folder / "summary.json").read_text())) == {f"lane-keep/{SCENARIO}"}
    assert {r["label"] for r in read_records(folder)} == {"lane-keep"}


# --- 5. bounded reads ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("device", ["/dev/zero", "/dev/full"])
def test_a_records_file_linked_to_a_device_is_refused_not_read(folder, capsys, device):
    (folder / EPISODES_FILE).unlink()
    (folder / EPISODES_FILE).symlink_to(device)
    with pytest.raises(EvaluationError, match="not a regular file"):
        read_records(folder)
    assert main(["leaderboard", str(folder)]) == 2
    assert "not a regular file" in one_line_error(capsys)


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    os.mkfifo(tmp_path / EPISODES_FILE)
    with pytest.raises(EvaluationError, match="not a regular file"):
        read_records(tmp_path)


def test_an_optional_record_reads_as_its_default_only_where_there_is_no_file(tmp_path):
    from bimp.agents.files import read_json_or

    assert read_json_or(tmp_path / "none.json", [0]) == [0]
    (tmp_path / "a.json").write_text("[1, 2]\n")
    assert read_json_or(tmp_path / "a.json", None) == [1, 2]
    (tmp_path / "bad.json").write_text("[1,")
    with pytest.raises(EvaluationError, match="bad.json is not JSON"):  # a broken record is never its default
        read_json_or(tmp_path / "bad.json", [])


def test_a_file_or_a_line_over_its_limit_is_refused_naming_the_limit(folder, monkeypatch, capsys):
    monkeypatch.setattr(record_check, "MAX_LINE_BYTES", 100)
    assert read_records(folder) == []
    assert "over 100 bytes, the limit per line" in capsys.readouterr().err
    monkeypatch.setattr(files, "MAX_FILE_BYTES", 100)
    with pytest.raises(EvaluationError, match="limit of 100 bytes per file"):
        records.episode_bytes(folder)


def test_a_deeply_nested_arms_json_is_one_line(folder, capsys):
    (folder / ARMS_FILE).write_bytes(NESTED)
    with pytest.raises(EvaluationError, match="arms.json is not JSON"):
        read_arms(folder)
    deep: object = 1
    for _ in range(files.MAX_DEPTH + 1):
        deep = [deep]
    (folder / ARMS_FILE).write_text(json.dumps({"a": deep}))
    with pytest.raises(EvaluationError, match="nested deeper"):
        read_arms(folder)


# --- 6. atomic writes, a full disk ---------------------------------------------------------------------------
def test_a_full_disk_leaves_the_old_file_no_temporary_and_one_line(folder, monkeypatch):
    before = (folder / ARMS_FILE).read_bytes()

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(records.os, "fsync", full)
    with pytest.raises(EvaluationError, match=r"cannot write .*arms.json: No space left on device \(ENOSPC\)"):
        write_atomic(folder / ARMS_FILE, "{}")
    assert (folder / ARMS_FILE).read_bytes() == before
    assert not [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]


def test_a_full_disk_under_a_command_is_one_line_and_exit_2(folder, monkeypatch, capsys):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    monkeypatch.setattr(records.os, "fsync", full)
    assert main(["drop", str(folder), "--label", "brake"]) == 2
    assert "No space left on device" in one_line_error(capsys)
    assert {p.name: p.read_bytes() for p in folder.iterdir() if p.name != ".lock"} == before


def test_an_os_error_escaping_a_command_is_one_line(monkeypatch, capsys):
    def boom(argv):
        raise OSError(errno.EIO, "Input/output error", "some/file")

    monkeypatch.setattr(importlib.import_module(command_module("compare")), "main", boom)  # the module cli runs
    assert main(["compare", "x", "--policies", "a", "b"]) == 2
    assert one_line_error(capsys).strip() == "bimp compare: error: some/file: Input/output error"


# --- 7. small ones -------------------------------------------------------------------------------------------
def test_migrate_refuses_a_locked_folder_in_one_line(folder, capsys):
    record = {**json.loads((folder / EPISODES_FILE).read_bytes().splitlines()[0])}
    record["metrics"]["score"] = 0.5  # a missed goal's score: something to rewrite
    record["truncated"], record["metrics"]["success_rate"] = True, 0.0
    record["metrics"]["collision_rate"] = record["metrics"]["offroad_rate"] = 0.0
    (folder / EPISODES_FILE).write_text(json.dumps(record) + "\n")
    with folder_lock(folder):
        assert main(["migrate", str(folder)]) == 1
    out = capsys.readouterr().out
    assert "is in use by another bimp run" in out and "Traceback" not in out


# --- what a review found: trust switches anywhere, planted symlinks, config internals ---------------------------
def evil_zip(tmp_path, marker):
    """A shipped PPO model with a pickle that creates ``marker`` when SB3's own load unpickles it."""
    from tests.agents.test_model_files import _evil_data, _rewrite

    shipped = sorted(rl.MODEL_DIR.glob("ppo_overtaking_*.zip"))[0]
    return _rewrite(shipped, tmp_path / "evil.zip", data=_evil_data(shipped, marker))


@pytest.mark.parametrize("route", ["record", "arms.json"])
def test_migrate_never_switches_on_trust_model_a_folder_sets(folder, tmp_path, capsys, route):
    marker = tmp_path / "MARKER"
    config = {"config": {"model": str(evil_zip(tmp_path, marker)), "trust_model": True}, "scenario": "overtaking"}
    record = {**json.loads((folder / EPISODES_FILE).read_bytes().splitlines()[0]), "policy": "ppo",
              "scenario": "overtaking", "config_hash": "0123456789abcdef"}
    if route == "record":
        record["config"] = config
    else:
        (folder / ARMS_FILE).write_text(json.dumps({"0123456789abcdef": {"policy": "ppo", "config": config}}))
    (folder / EPISODES_FILE).write_text(json.dumps(record) + "\n")
    assert main(["migrate", str(folder), "--dry-run"]) == 1
    assert not marker.exists()
    assert "trust_model, which no file may switch on" in capsys.readouterr().out


@pytest.mark.parametrize("name", [".arms.json.tmp", ".episodes.jsonl.tmp", ".summary.json.tmp", ".lock"])
def test_a_symlink_planted_in_a_folder_is_never_written_through(folder, tmp_path, capsys, name):
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    (folder / name).symlink_to(victim)
    evaluate(out=folder, policies=["lane-keep", TOY], labels={TOY: "brake"}, scenarios=[SCENARIO], episodes=2,
             seed=5, workers=1, traces=0, progress=False) if name != ".lock" else None
    main(["drop", str(folder), "--label", "brake"])
    assert victim.read_text() == "precious\n"
    assert "Traceback" not in capsys.readouterr().err


def test_a_rewritten_file_keeps_its_permissions(folder):
    os.chmod(folder / ARMS_FILE, 0o664)
    write_atomic(folder / ARMS_FILE, "{}")
    assert (folder / ARMS_FILE).stat().st_mode & 0o777 == 0o664


@pytest.mark.parametrize("config", [{"config": [1]}, {"config": {"algo": "ppo", "model_sha256": [1]}},
                                    {"config": {}, "files": 5}, {"config": {}, "files": [1]}])
def test_migrate_and_merge_skip_or_refuse_a_config_of_no_shape_in_one_line(folder, tmp_path, capsys, config):
    record = {**json.loads((folder / EPISODES_FILE).read_bytes().splitlines()[0]), "config": config}
    (folder / EPISODES_FILE).write_text(json.dumps(record) + "\n")
    codes = [main(["migrate", str(folder), "--dry-run"]), main(["merge", str(folder), "--into", str(tmp_path / "m")])]
    out, err = capsys.readouterr()
    assert "Traceback" not in err and codes[0] in (0, 1) and codes[1] in (0, 2), (codes, out, err)


def test_every_reader_names_the_bad_line_itself(folder, tmp_path, capsys):
    append(folder, NESTED)
    for argv in (["compare", str(folder), "--policies", "lane-keep", "brake"], ["leaderboard", str(folder)],
                 ["merge", str(folder), "--into", str(tmp_path / "merged")],
                 ["drop", str(folder), "--label", "brake", "--dry-run"], ["migrate", str(folder), "--dry-run"]):
        records._reported.clear()
        main(argv)
        assert "skipped 1 line(s) that are not episode records: line 5" in capsys.readouterr().err, argv


def test_a_yaml_cycle_or_a_billion_laughs_is_read_at_once(tmp_path):
    from bimp.configs import read_yaml

    (tmp_path / "cycle.yaml").write_text("a: &a [*a]\n")
    assert isinstance(read_yaml(tmp_path / "cycle.yaml"), dict)
    laughs = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + k)}: &{chr(98 + k)} [{', '.join(['*' + chr(97 + k)] * 9)}]\n" for k in range(9))
    (tmp_path / "laughs.yaml").write_text(laughs)
    start = time.perf_counter()
    read_yaml(tmp_path / "laughs.yaml")
    assert time.perf_counter() - start < 5.0  # each shared node walked once, not 9**10 times
