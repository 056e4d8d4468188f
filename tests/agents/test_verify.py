"""``bimp verify``: a folder's arms rerun on a sample of seeds at the current code, every metric but timings compared;
a difference named by arm, seed and metric; an arm it cannot rerun refused before anything runs; and the arms found
the same read as the current code's by the leaderboard and compare."""

from __future__ import annotations

import json

import pytest

from bimp.agents.cli import main
from bimp.agents.evaluation import leaderboard, verification, verify
from bimp.agents.evaluation.compare import label_records
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.metrics import code_version
from bimp.agents.evaluation.records import ARMS_FILE, EPISODES_FILE
from bimp.agents.evaluation.verification import VERIFIED_FILE, as_current, read_verified
from bimp.agents.evaluation.verify import _groups, _spread, differences, verify_folder

SCENARIO = "emergency-brake"
OLD = "0" * 40  # a commit the records claim, of code the current code equals (monkeypatched below)


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    out = tmp_path_factory.mktemp("made")
    evaluate(out=out, policies=["lane-keep", "zero"], scenarios=[SCENARIO], episodes=3, seed=11, workers=1,
             progress=False)
    return {name: (out / name).read_bytes() for name in (EPISODES_FILE, ARMS_FILE)}


@pytest.fixture
def folder(made, tmp_path):
    for name, data in made.items():
        (tmp_path / name).write_bytes(data)
    return tmp_path


def rewrite(folder, change) -> None:
    lines = [json.loads(line) for line in (folder / EPISODES_FILE).read_bytes().splitlines()]
    for r in lines:
        change(r)
    (folder / EPISODES_FILE).write_text("".join(json.dumps(r) + "\n" for r in lines))


def test_an_unchanged_folder_is_found_the_same_and_says_so_in_verified_json(folder, capsys):
    assert main(["verify", str(folder), "--sample", "2"]) == 0
    out = capsys.readouterr().out
    assert out.count(": same") == 2 and "seeds [11, 13]" in out
    verified = read_verified(folder)
    assert {v["outcome"] for v in verified.values()} == {"same"} and len(verified) == 2
    assert all(v["seeds"] == [11, 13] for v in verified.values())


def test_a_changed_metric_is_named_by_arm_seed_and_metric(folder, capsys):
    def change(r):
        if r["policy"] == "zero" and r["seed"] == 13:
            r["metrics"]["min_distance_m"] += 0.5

    rewrite(folder, change)
    assert main(["verify", str(folder), "--sample", "2"]) == 1
    out = capsys.readouterr().out
    assert "'zero' (zero) on emergency-brake" in out and "DRIFT: seed 13: metrics.min_distance_m" in out
    assert "2 arm(s): 1 same, 1 drift, 0 different" in out
    assert read_verified(folder)[f"{SCENARIO}|zero|" + json.loads(
        (folder / EPISODES_FILE).read_bytes().splitlines()[-1])["config_hash"]]["outcome"] == "drift"


def test_a_changed_outcome_is_different_not_drift(folder, capsys):
    def change(r):
        if r["policy"] == "zero" and r["seed"] == 11:
            r["metrics"]["success_rate"] = 1.0 - r["metrics"]["success_rate"]

    rewrite(folder, change)
    assert main(["verify", str(folder), "--sample", "2"]) == 1
    assert "DIFFERENT: seed 11: metrics.success_rate" in capsys.readouterr().out


def test_timings_are_not_compared_and_a_status_is():
    old = {"seed": 1, "status": "ok", "steps": 10, "metrics": {"plan_time_ms_p50": 1.0, "score": 0.5}}
    assert differences(old, {**old, "metrics": {"plan_time_ms_p50": 9.0, "score": 0.5}}) == []
    assert differences(old, {**old, "steps": 11}) == ["seed 1: steps 10 -> 11"]


def test_arms_it_cannot_rerun_are_named_and_nothing_runs_or_is_written(folder, capsys):
    arms = json.loads((folder / ARMS_FILE).read_text())
    key = next(k for k, v in arms.items() if v["policy"] == "lane-keep")
    arms[key]["overrides"] = {"no_such_key": 1}
    (folder / ARMS_FILE).write_text(json.dumps(arms))
    rewrite(folder, lambda r: r.update(policy="pydoc:pipepager") if r["policy"] == "zero" else None)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert main(["verify", str(folder)]) == 2
    err = capsys.readouterr().err
    assert "2 arm(s) cannot be rerun" in err and "no_such_key" in err and "--trust-policy pydoc:pipepager" in err
    assert {p.name: p.read_bytes() for p in folder.iterdir() if p.name != ".lock"} == before


def test_a_batched_arm_is_read_in_the_groups_it_ran_in():
    """Consecutive records of one batched call share its size and wall time; a rerun seed's record stands alone."""
    records = ([{"seed": s, "batch": 3, "wall_s": 1.0} for s in (5, 7, 6)]
               + [{"seed": s, "batch": 2, "wall_s": 2.0} for s in (8, 9)]
               + [{"seed": s, "batch": 2, "wall_s": 3.0} for s in (10, 11)] + [{"seed": 6}])
    assert [[r["seed"] for r in g] for g in _groups(records)] == [[5, 7, 6], [8, 9], [10, 11], [6]]
    assert _spread(list(range(100)), 3) == [0, 50, 99] and _spread([7], 3) == [7]


def test_the_rerun_takes_each_chosen_seeds_latest_group_and_every_code_version(folder):
    def change(r):
        r.update(batch=3, wall_s=1.0 if r["seed"] < 14 else 2.0)
        if r["policy"] == "zero" and r["seed"] == 13:
            r.update(git_commit=OLD, git_dirty=False)

    rewrite(folder, change)
    checks = {c.label: c for c in verify.plan(folder, sample=1)}
    assert checks["lane-keep"].groups == [[11, 12, 13]] and checks["lane-keep"].batch == 3
    assert checks["zero"].versions == sorted({OLD, code_version(json.loads(
        (folder / EPISODES_FILE).read_bytes().splitlines()[0]))})


def test_verified_arms_are_the_current_codes_to_the_readers(folder, monkeypatch):
    rewrite(folder, lambda r: r.update(git_commit=OLD, git_dirty=False) if r["policy"] == "zero" else None)
    arms = leaderboard.load_arms([folder])
    assert any(m.kind == "code" for m in leaderboard.find_mixing(arms))  # two code versions: mixed
    now = json.loads((folder / EPISODES_FILE).read_bytes().splitlines()[0])["git_commit"]
    monkeypatch.setattr(verification, "current_commit", lambda: now)
    monkeypatch.setattr(verification, "same_code", lambda a, b: True)
    monkeypatch.setattr(verify, "code_version", lambda: {"git_commit": now, "git_dirty": False})
    verify_folder(folder, sample=1, progress=False)
    versions = {code_version(r) for r in as_current(folder, [json.loads(x) for x in
                                                              (folder / EPISODES_FILE).read_bytes().splitlines()])}
    assert versions == {now}
    assert not any(m.kind == "code" for m in leaderboard.find_mixing(leaderboard.load_arms([folder])))
    assert {code_version(r) for r in label_records(folder, "zero").values()} == {now}
    verified = read_verified(folder)
    for kind, change in (("other code", {"commit": OLD}), ("uncommitted code", {"dirty": True}),
                         ("other versions", {"versions": [now]})):
        (folder / VERIFIED_FILE).write_text(json.dumps({k: {**v, **change} for k, v in verified.items()}))
        monkeypatch.setattr(verification, "same_code", lambda a, b: a == b)
        assert any(m.kind == "code" for m in leaderboard.find_mixing(leaderboard.load_arms([folder]))), kind


def test_a_drift_names_the_machine_the_records_ran_on_where_it_is_not_this_one(folder, capsys):
    from bimp.agents.evaluation.provenance import machine

    def change(r):
        r["machine"] = "another CPU; jax 0.0"
        if r["policy"] == "zero" and r["seed"] == 13:
            r["metrics"]["min_distance_m"] += 0.5

    rewrite(folder, change)
    assert main(["verify", str(folder), "--sample", "2"]) == 1
    lines = capsys.readouterr().out.splitlines()
    drift = next(line for line in lines if "DRIFT" in line)
    assert f"[records ran on: another CPU; jax 0.0] [this machine: {machine()}]" in drift
    assert not any("records ran on" in line for line in lines if ": same" in line)  # no note where nothing moved
    entry = next(v for v in read_verified(folder).values() if v["policy"] == "zero")
    assert entry["machines"] == ["another CPU; jax 0.0"] and entry["machine"] == machine()


def test_records_name_the_machine_they_ran_on(made):
    from bimp.agents.evaluation.provenance import machine

    records = [json.loads(line) for line in made[EPISODES_FILE].splitlines()]
    assert {r["machine"] for r in records} == {machine()}
    assert "python" in machine() and "jax" in machine() and "numpy" in machine()


def test_a_drift_on_records_that_name_no_machine_says_so(folder, capsys):
    def change(r):
        r.pop("machine", None)
        if r["policy"] == "zero" and r["seed"] == 13:
            r["metrics"]["min_distance_m"] += 0.5

    rewrite(folder, change)
    assert main(["verify", str(folder), "--sample", "2"]) == 1
    drift = next(line for line in capsys.readouterr().out.splitlines() if "DRIFT" in line)
    assert "[records ran on an unrecorded machine" in drift and "this machine" not in drift
