"""``bimp sweep`` (any config key) and ``bimp frontier`` (quality against compute): points evaluated into one
folder with evaluate's resume."""

import json

import pytest

from bimp.agents.cli import EvaluationError, main
from bimp.agents.evaluation.records import read_arms, read_records, record_config
from bimp.agents.evaluation.sweep import axis_points, param_points

EB = ["--scenario", "emergency-brake", "--episodes", "2", "--seed", "5"]


def test_a_param_sweep_runs_one_point_per_value_and_resumes(tmp_path, capsys):
    out = tmp_path / "sweep"
    assert main(["sweep", "--param", "lane-keep.k_speed=0.2,0.8", *EB, "--out", str(out)]) == 0
    rows = json.loads((out / "sweep.json").read_text())
    assert [(r["label"], r["value"], r["episodes"]) for r in rows] == [("lane-keep k_speed=0.2", 0.2, 2),
                                                                      ("lane-keep k_speed=0.8", 0.8, 2)]
    records, arms = read_records(out), read_arms(out)
    assert {record_config(r, arms)["config"]["k_speed"] for r in records} == {0.2, 0.8} and len(records) == 4
    assert (out / "sweep.png").stat().st_size > 0 and "| emergency-brake | lane-keep | k_speed | 0.2 |" in \
        (out / "sweep.md").read_text()
    summary = json.loads((out / "summary.json").read_text())  # the folder's summary holds every point
    assert sorted(summary) == ["lane-keep k_speed=0.2/emergency-brake", "lane-keep k_speed=0.8/emergency-brake"]
    main(["sweep", "--param", "lane-keep.k_speed=0.2,0.8", *EB, "--out", str(out)])
    assert len(read_records(out)) == 4  # resumed: nothing ran again


def test_a_nested_key_is_swept_whole_and_bad_params_are_named():
    import gymnasium as gym

    from bimp.agents.evaluation.tune import factory_kwargs
    from bimp.agents.registry import make_policy

    (point,) = param_points(["mppi.problem.barrier.edge_margin=0.5"])
    configured = factory_kwargs(make_policy("mppi", gym.make("bimp/Overtaking-v0")))["problem"]["barrier"]
    assert point.overrides["problem"]["barrier"] == {**configured, "edge_margin": 0.5}  # the rest as configured
    # The label drops "problem.": a folder swept before issue 25 moved the key keeps its rows' names.
    assert (point.label, point.param) == ("mppi barrier.edge_margin=0.5", "problem.barrier.edge_margin")
    for bad, match in ((["lane-keep.k_speed"], "POLICY.KEY=V1"), (["lane-keep.k_nope=1,2"], "k_nope"),
                       (["nope.k=1"], "unknown policy"),
                       (["lane-keep.k_lat=1", "lane-keep.k_head=1,2"], "different lengths")):
        with pytest.raises(EvaluationError, match=match):
            param_points(bad)


def test_several_params_of_a_policy_sweep_together_value_by_value():
    points = param_points(["lane-keep.k_lat=0.01,0.02", "lane-keep.k_head=0.1,0.2"])
    assert [(p.label, p.overrides) for p in points] == [
        ("lane-keep k_lat=0.01 k_head=0.1", {"k_lat": 0.01, "k_head": 0.1}),
        ("lane-keep k_lat=0.02 k_head=0.2", {"k_lat": 0.02, "k_head": 0.2})]


def test_the_frontier_table_has_one_row_per_policy_and_compute_value(tmp_path):
    out = tmp_path / "frontier"
    assert main(["frontier", "--policies", "mppi", "lane-keep", "--n", "2", "4", "--set", "mppi.problem.horizon=3",
                 *EB, "--out", str(out)]) == 0
    rows = json.loads((out / "frontier.json").read_text())
    assert sorted((r["policy"], r["value"]) for r in rows) == [("lane-keep", None), ("mppi", 2), ("mppi", 4)]
    assert all(r["plan_time_ms_p50"]["mean"] > 0 for r in rows)
    lines = [line for line in (out / "frontier.md").read_text().splitlines() if line.startswith("| emergency")]
    assert len(lines) == 3
    arms = read_arms(out)
    assert {record_config(r, arms)["config"]["problem"]["horizon"] for r in read_records(out)
            if r["policy"] == "mppi"} == {3}


def test_axis_points_label_each_value_and_keep_a_policy_without_an_axis_whole():
    points = axis_points(["enkts", "ppo"], {"enkts": ("n_particles", [10, 20])}, {"enkts": {"problem.horizon": 5}})
    assert [(p.label, p.overrides) for p in points] == [
        ("enkts N=10", {"problem.horizon": 5, "n_particles": 10}),
        ("enkts N=20", {"problem.horizon": 5, "n_particles": 20}),
        ("ppo", {})]


def test_repeated_param_and_set_flags_add_up_instead_of_replacing_each_other(tmp_path):
    # argparse's plain `nargs="*"` keeps only the last of repeated flags: a sweep of two policies, each its own
    # --param, silently ran only the second.
    out = tmp_path / "two"
    assert main(["sweep", "--param", "lane-keep.k_lat=0.01,0.02", "--param", "mppi.n_particles=2,3",
                 "--set", "mppi.problem.horizon=3", "--set", "lane-keep.k_head=0.1", *EB, "--episodes", "1",
                 "--out", str(out)]) == 0
    records, arms = read_records(out), read_arms(out)
    assert {r["label"] for r in records} == {"lane-keep k_lat=0.01", "lane-keep k_lat=0.02", "mppi n_particles=2",
                                             "mppi n_particles=3"}
    assert all('"horizon": 3' in json.dumps(record_config(r, arms)) for r in records if r["policy"] == "mppi")
    assert all('"k_head": 0.1' in json.dumps(record_config(r, arms)) for r in records if r["policy"] == "lane-keep")


@pytest.mark.parametrize("command, match", [
    (["sweep", "--param", "lane-keep.k_nope=1,2"], "k_nope"),
    (["sweep", "--param", "bogus"], "POLICY.KEY=V1"),
    (["frontier", "--policies", "nope"], "unknown policy"),
    (["frontier", "--policies", "lane-keep", "--set", "mppi.problem.horizon=3"], "no point evaluates"),
    (["frontier", "--policies", "lane-keep", "--episodes", "0"], "--episodes"),
])
def test_a_bad_request_exits_2_naming_it_and_writes_nothing(tmp_path, capsys, command, match):
    out = tmp_path / "out"
    assert main([*command, "--scenario", "emergency-brake", "--out", str(out)]) == 2
    assert match in capsys.readouterr().err
    assert not out.exists()


def test_every_point_is_checked_before_the_first_runs(tmp_path, capsys):
    out = tmp_path / "frontier"
    # N = 4 is fine, N = 1 is not: no episode of N = 4 may run before the refusal.
    assert main(["frontier", "--policies", "mppi", "--n", "4", "1", "--set", "mppi.problem.horizon=3", *EB,
                 "--out", str(out)]) == 2
    assert "n_particles" in capsys.readouterr().err and read_records(out) == []
    assert main(["sweep", "--param", "lane-keep.k_speed=0.2", *EB, "--out", str(out)]) == 0
    # k_speed=0.2 under another k_lat is the folder's label with another config: refused before k_speed=0.3 runs
    assert main(["sweep", "--param", "lane-keep.k_speed=0.3,0.2", "--set", "lane-keep.k_lat=0.5", *EB,
                 "--out", str(out)]) == 2
    assert "another config" in capsys.readouterr().err
    assert len(read_records(out)) == 2


def test_a_dry_run_of_a_sweep_lists_each_point_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "sweep"
    argv = ["sweep", "--param", "lane-keep.k_lat=0.01,0.02", *EB, "--episodes", "1", "--out", str(out)]
    assert main([*argv, "--dry-run"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == "dry run: 2 episode(s) would run"
    assert not out.exists()
    assert main(argv) == 0
    before = sorted((p, p.stat().st_mtime_ns) for p in out.rglob("*"))
    assert main([*argv, "--dry-run"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == "dry run: 0 episode(s) would run"
    assert sorted((p, p.stat().st_mtime_ns) for p in out.rglob("*")) == before
