import csv
import json
import signal
from contextlib import contextmanager

import numpy as np
import pytest

from bimp.agents.cli import EvaluationError
from bimp.agents.commands import evaluate as ev
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.metrics import METRICS
from bimp.agents.evaluation.plots import plot_all
from bimp.agents.evaluation.records import EPISODES_FILE, folder_lock, read_arms, read_records, record_config

ARGS = dict(scenarios=["emergency-brake"], policies=["lane-keep"], episodes=3, seed=5, workers=1,
            traces=1, progress=False)
FAULTY = "tests.agents.faulty:Faulty"
SMALL_ENKTS = {"n_particles": 10, "problem.horizon": 5}


@contextmanager
def deadline(seconds):
    """Fail instead of hanging the suite."""
    def expire(*_):
        raise TimeoutError(f"still running after {seconds} s")
    old = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_summary_files_carry_every_named_key_with_intervals(tmp_path):
    summary = evaluate(out=tmp_path, **ARGS)
    entry = json.loads((tmp_path / "summary.json").read_text())["lane-keep/emergency-brake"]
    assert entry == summary["lane-keep/emergency-brake"]
    assert entry["episodes"] == 3 and all(k in entry for k in METRICS)
    header = next(csv.reader(open(tmp_path / "summary.csv")))
    assert all(f"{k}_{s}" in header for k in METRICS for s in ("mean", "ci_low", "ci_high"))
    assert "errors" in header and "error_seeds" in header
    md = (tmp_path / "summary.md").read_text()
    assert all(k in md for k in METRICS) and "lane-keep" in md and "errors" in md
    # the lane keeper is blind to the braking OVs: the metrics must say so, with the failing seeds
    assert entry["collision_rate"]["mean"] == 1.0 and entry["success_rate"]["mean"] == 0.0
    assert entry["collision_rate"]["ci_low"] == pytest.approx(0.4385, abs=1e-3)  # Wilson, 3 of 3
    assert entry["failed_seeds"]["collision"] == [5, 6, 7]
    assert len(plot_all(tmp_path)) == 3


def test_records_carry_provenance(tmp_path):
    evaluate(out=tmp_path, **{k: v for k, v in {**ARGS, "episodes": 1}.items() if k != "traces"})
    (r,) = read_records(tmp_path)
    arm = read_arms(tmp_path)[r["config_hash"]]  # the arm's config, once, beside the records
    assert not {"config", "overrides", "seeding"} & set(r)  # a compact record names it by hash
    assert arm["config"]["config"] == {"k_lat": 0.004, "k_head": 0.15, "k_speed": 0.8}
    assert arm["config"]["scenario"]["brake_decel"] == [5.0, 7.0]  # the scenario's ranges are part of the config
    assert arm["policy"] == "lane-keep" and arm["overrides"] == {} and arm["artifacts"] == {}
    assert len(r["config_hash"]) == 16 and r["label"] == "lane-keep" and r["policy"] == "lane-keep"
    assert set(r["scenario_params"]) >= {"ev_speed", "ov1_gap", "brake_decel"}
    assert r["env_seed"] != r["policy_seed"] and "SeedSequence" in arm["seeding"]
    assert "trace" not in r  # traces only when asked for (--traces)
    assert r["bimp_version"] and "git_commit" in r and "git_dirty" in r


def test_interrupted_run_resumes_to_the_same_summary(tmp_path):
    full = evaluate(out=tmp_path / "full", **ARGS)
    part = tmp_path / "part"
    evaluate(out=part, **{**ARGS, "episodes": 2})  # the "interrupted" run: two episodes landed
    with open(part / EPISODES_FILE, "a") as f:
        f.write('{"scenario": "emergency-brake", "policy": "lane-k')  # a line cut by the interruption
    resumed = evaluate(out=part, **ARGS)
    timing = {"plan_time_ms_p50", "plan_time_ms_p95"}  # wall-clock: the only thing allowed to differ
    strip = lambda s: {k: {m: v for m, v in e.items() if m not in timing} for k, e in s.items()}  # noqa: E731
    assert strip(resumed) == strip(full)
    assert sorted(r["seed"] for r in read_records(part)) == [5, 6, 7]  # nothing repeated, nothing lost


def test_a_rerun_with_other_overrides_refuses_and_a_label_adds_a_row(tmp_path):
    args = {**ARGS, "policies": ["enkts"], "episodes": 1}
    evaluate(out=tmp_path, overrides={"enkts": SMALL_ENKTS}, **args)
    before = (tmp_path / EPISODES_FILE).read_text()
    with pytest.raises(EvaluationError, match=r"(?s)n_particles: 10 -> 12.*--label"):
        evaluate(out=tmp_path, overrides={"enkts": {**SMALL_ENKTS, "n_particles": 12}}, **args)
    assert (tmp_path / EPISODES_FILE).read_text() == before  # nothing recorded, nothing lost
    summary = evaluate(out=tmp_path, overrides={"enkts": {**SMALL_ENKTS, "n_particles": 12}},
                       labels={"enkts": "enkts-n12"}, **args)
    assert set(summary) == {"enkts-n12/emergency-brake"}  # this request's rows only
    assert set(evaluate(out=tmp_path, overrides={"enkts": SMALL_ENKTS}, all_records=True, **args)) == {
        "enkts/emergency-brake", "enkts-n12/emergency-brake"}
    records, arms = read_records(tmp_path), read_arms(tmp_path)
    assert len(records) == 2 and {record_config(r, arms)["config"]["n_particles"] for r in records} == {10, 12}


@pytest.mark.parametrize("argv, message", [
    (["--policy", "enkts", "--set", "enkts.bogus_key=3"], "bogus_key"),
    (["--policy", "enkts", "--set", "enkts.n_particles"], "POLICY.KEY=VALUE"),
    (["--policy", "enkts", "--set", "enkts.n_particles=1"], "n_particles"),
    (["--policy", "enkts", "--set", "mppi.n_particles=10"], "mppi"),
    (["--policy", "bogus"], "bogus"),
    (["--policy", "enkts", "--scenario", "bogus"], "bogus"),
    (["--policy", "enkts", "enks", "--label", "x"], "ambiguous"),
])
def test_a_bad_request_exits_non_zero_and_writes_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert ev.main([*argv, "--episodes", "1", "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_an_error_is_recorded_shown_and_retried_by_the_next_run(tmp_path):
    flag = tmp_path / "fixed"
    args = {**ARGS, "policies": ["lane-keep", FAULTY], "episodes": 2,
            "overrides": {FAULTY: {"flag": str(flag)}}}
    summary = evaluate(out=tmp_path / "out", **args)
    e = summary[f"{FAULTY}/emergency-brake"]
    assert e["episodes"] == 0 and e["errors"] == 2 and e["error_seeds"] == [5, 6]
    assert e["success_rate"]["mean"] is None  # an error is not a result
    assert "injected failure" in read_records(tmp_path / "out")[-1]["traceback"]
    assert "2 (5, 6)" in (tmp_path / "out" / "summary.md").read_text()
    flag.touch()  # the cause is fixed: the next run retries the errors, and only those
    summary = evaluate(out=tmp_path / "out", **args)
    e = summary[f"{FAULTY}/emergency-brake"]
    assert e["episodes"] == 2 and e["errors"] == 0
    assert len(read_records(tmp_path / "out")) == 6  # 2 lane-keep + 2 errors + 2 retries


def test_a_worker_that_dies_neither_hangs_nor_loses_its_episode(tmp_path):
    flag = tmp_path / "died-once"
    with deadline(240):
        summary = evaluate(out=tmp_path / "once", **{
            **ARGS, "workers": 2, "policies": [FAULTY], "episodes": 3,
            "overrides": {FAULTY: {"flag": str(flag), "mode": "die", "once": True}}})
    assert flag.exists()  # a worker did die
    e = summary[f"{FAULTY}/emergency-brake"]
    assert e["episodes"] == 3 and e["errors"] == 0  # retried, not lost


def test_a_worker_that_always_dies_is_recorded_and_the_rest_runs(tmp_path):
    with deadline(240):
        summary = evaluate(out=tmp_path, **{
            **ARGS, "workers": 2, "policies": ["lane-keep", FAULTY], "episodes": 2,
            "overrides": {FAULTY: {"flag": str(tmp_path / "never"), "mode": "die"}}})
    assert summary["lane-keep/emergency-brake"]["episodes"] == 2
    e = summary[f"{FAULTY}/emergency-brake"]
    assert e["errors"] == 2 and e["episodes"] == 0
    errors = [r["error"] for r in read_records(tmp_path) if r["status"] == "error"]
    assert len(errors) == 2 and all(err.startswith("WorkerDied") for err in errors)


def test_a_second_concurrent_run_into_one_folder_refuses(tmp_path):
    tmp_path.mkdir(exist_ok=True)
    with folder_lock(tmp_path):  # the first run holds the folder
        with pytest.raises(EvaluationError, match="in use by another bimp run"):
            evaluate(out=tmp_path, **ARGS)
    assert not (tmp_path / EPISODES_FILE).exists()
    evaluate(out=tmp_path, **{**ARGS, "episodes": 1})  # released: the next run goes ahead


def test_each_episode_is_counted_once(tmp_path):
    evaluate(out=tmp_path, **{**ARGS, "episodes": 2})
    records = read_records(tmp_path)
    with open(tmp_path / EPISODES_FILE, "a") as f:  # a duplicate, as two old unlocked runs would leave
        f.write(json.dumps(records[0]) + "\n")
    assert evaluate(out=tmp_path, **{**ARGS, "episodes": 2})["lane-keep/emergency-brake"]["episodes"] == 2


def test_explicit_seeds_and_video(tmp_path):
    import imageio_ffmpeg

    summary = evaluate(out=tmp_path, **{**ARGS, "episodes": 1, "traces": 0}, seeds=[13, 4], video=1)
    assert summary["lane-keep/emergency-brake"]["episodes"] == 2
    assert sorted(r["seed"] for r in read_records(tmp_path)) == [4, 13]
    (video,) = (tmp_path / "videos").glob("*.mp4")  # the first seed of the list only
    assert "seed13" in video.name and video.stat().st_size > 10_000
    frames = imageio_ffmpeg.read_frames(str(video))
    meta = next(frames)
    steps = next(r["steps"] for r in read_records(tmp_path) if r["seed"] == 13)
    assert meta["fps"] == 10.0  # real time at dt = 0.1 s
    assert sum(1 for _ in frames) == steps + 1  # the reset frame and one per step
    assert np.isclose(meta["duration"], (steps + 1) / 10.0, atol=0.15)


def test_batched_episodes_follow_the_single_ones(tmp_path):
    """One batched planner over three envs: the same seeds, streams and, step by step, the same inputs up to
    float32 rounding (vmap orders the sums differently). The closed loop amplifies rounding (the barrier gating and
    the innovation clipping are thresholds): here the inputs part after about 12 steps, so a batched run is the
    same experiment, not the same per-seed numbers."""
    args = {**ARGS, "policies": ["enks"], "episodes": 3, "traces": 3, "overrides": {"enks": {"n_particles": 16}}}
    evaluate(out=tmp_path / "one", **args)
    evaluate(out=tmp_path / "three", batch=3, **args)
    single = {r["seed"]: r for r in read_records(tmp_path / "one")}
    batched = {r["seed"]: r for r in read_records(tmp_path / "three")}
    assert sorted(batched) == sorted(single) == [5, 6, 7] and all(r["batch"] == 3 for r in batched.values())
    for seed, r in batched.items():
        assert (r["env_seed"], r["policy_seed"]) == (single[seed]["env_seed"], single[seed]["policy_seed"])
        assert r["scenario_params"] == single[seed]["scenario_params"]
        np.testing.assert_allclose(r["trace"]["input"][:8], single[seed]["trace"]["input"][:8], atol=1e-3)
    with pytest.raises(EvaluationError, match="lane-keep"):
        evaluate(out=tmp_path / "x", batch=2, **ARGS)


def test_a_changed_scenario_range_is_another_config(tmp_path, monkeypatch):
    import dataclasses

    from bimp.envs.scenarios import EmergencyBrakeEnv

    evaluate(out=tmp_path, **{**ARGS, "episodes": 1})
    params = dict(EmergencyBrakeEnv.PARAMS)
    params["brake_decel"] = dataclasses.replace(params["brake_decel"], default=(5.0, 6.0))
    monkeypatch.setattr(EmergencyBrakeEnv, "PARAMS", params)
    with pytest.raises(EvaluationError, match=r"scenario\.brake_decel: \[5\.0, 7\.0\] -> \[5\.0, 6\.0\]"):
        evaluate(out=tmp_path, **{**ARGS, "episodes": 1})


def test_a_changed_behaviour_rule_is_another_config(tmp_path, monkeypatch):
    import dataclasses

    from bimp.envs.scenarios import OvertakingEnv

    args = {**ARGS, "scenarios": ["overtaking"], "episodes": 1}
    evaluate(out=tmp_path, **args)
    rule = dataclasses.replace(OvertakingEnv.BEHAVIOUR, lane_change_s=3.0)
    monkeypatch.setattr(OvertakingEnv, "BEHAVIOUR", rule)
    with pytest.raises(EvaluationError, match=r"scenario\.behaviour\.lane_change_s: 2\.0 -> 3\.0"):
        evaluate(out=tmp_path, **args)


def test_compare_pairs_two_arms_across_both_scenarios(tmp_path, capsys):
    from bimp.agents.commands import compare

    args = {**ARGS, "scenarios": ["emergency-brake", "overtaking"], "policies": ["lane-keep", "zero"],
            "episodes": 2, "traces": 0}
    evaluate(out=tmp_path, **args)
    assert compare.main([str(tmp_path), "--policies", "lane-keep", "zero", "--json", str(tmp_path / "c.json")]) == 0
    text = capsys.readouterr().out
    assert "## emergency-brake: lane-keep (A) vs zero (B), 2 paired seeds" in text and "## overtaking" in text
    result = json.loads((tmp_path / "c.json").read_text())
    assert result["emergency-brake"]["seeds"] == [5, 6] and "p_value" in result["overtaking"]["success_rate"]
    assert result["emergency-brake"]["overtake_rate"] is None  # no OV1 to pass in the emergency brake
    assert "p_value" in result["overtaking"]["overtake_rate"]


# --- --dry-run and compact records (issue 28) ----------------------------------------------------------------------
def _tree(folder) -> dict:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def test_a_dry_run_lists_the_missing_seeds_and_writes_nothing(tmp_path, capsys):
    args = {k: v for k, v in ARGS.items() if k != "traces"}
    absent = tmp_path / "absent"
    plan = evaluate(out=absent, dry_run=True, **args)
    assert plan.done == 0 and plan.to_run == [("emergency-brake", "lane-keep", s) for s in (5, 6, 7)]
    assert not absent.exists()  # no mkdir, no lock
    evaluate(out=tmp_path, **{**args, "episodes": 2})
    before = _tree(tmp_path)
    plan = evaluate(out=tmp_path, dry_run=True, **{**args, "episodes": 4})
    assert plan.done == 2 and plan.to_run == [("emergency-brake", "lane-keep", 7), ("emergency-brake", "lane-keep", 8)]
    assert ev.main(["--policy", "lane-keep", "--scenario", "emergency-brake", "--episodes", "2", "--seed", "5",
                    "--out", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out == ["emergency-brake  lane-keep: 2 done, 0 to run", "dry run: 0 episode(s) would run"]
    assert _tree(tmp_path) == before  # no record, no arms.json, no summary, no lock touched
    # A refusal is the real run's: another config under the label exits 2 naming it, and still writes nothing.
    assert ev.main(["--policy", "lane-keep", "--set", "lane-keep.k_lat=0.01", "--scenario", "emergency-brake",
                    "--out", str(tmp_path), "--dry-run"]) == 2
    assert "k_lat" in capsys.readouterr().err and _tree(tmp_path) == before


def test_a_record_without_its_trace_still_summarizes_and_plot_says_there_is_none(tmp_path, capsys):
    from bimp.agents.commands import plot as plot_command

    summary = evaluate(out=tmp_path, **{**ARGS, "traces": 0})
    assert summary["lane-keep/emergency-brake"]["episodes"] == 3
    assert not any("trace" in r for r in read_records(tmp_path))
    assert plot_command.main([str(tmp_path)]) == 1
    assert "no traced episodes" in capsys.readouterr().out
