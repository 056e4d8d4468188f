"""bimp.agents.evaluation.bench: the report of a synthetic result (no timing here: benchmarks are never timed tests),
the argument checks, the highway scenario's recorded (observation, scene) pairs and (slow) one quick highway run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bimp.agents.commands import bench as bench_command
from bimp.agents.evaluation import bench


def synthetic_result() -> dict:
    rows = [{"planner": p, "n_particles": n, "horizon": 20, "repeats": 3, "median_ms": m * n / 50, "p95_ms": m}
            for n in (50, 500) for p, m in (("enkts", 1.0), ("enks", 0.9), ("mppi", 2.0))]
    h_rows = [{"planner": "enkts", "n_particles": 50, "horizon": h, "repeats": 3, "median_ms": h / 20,
               "p95_ms": h / 10} for h in (10, 20, 40)]
    nmpc = {"planner": "nmpc", "horizon": 20, "repeats": 3, "median_ms": 200.0, "p95_ms": 300.0,
            "solver_failures": 0, "ipopt_statuses": {"Solve_Succeeded": 4}}
    return {"scenario": "overtaking", "steps_before": 5, "horizon": 20, "repeats": 3, "float": "float32",
            "floor_ms": {"50": 0.5, "500": 5.0},
            "machine": {"load_average": [1.0, 1.0, 1.0], "cpus": 2}, "rows": rows, "nmpc": nmpc,
            "enkts_vs_horizon": h_rows,
            "ratios": {"enkts/mppi N=50": 0.5, "enkts/mppi N=500": 0.5, "nmpc/enkts N=50": 200.0}}


def test_device_report_lists_every_size():
    rows = [{"n_particles": n, "median_ms": 1.0, "p95_ms": 2.0, "first_call_ms": 900.0} for n in (50, 100_000)]
    text = bench.report_device({"device": "gpu: H100", "horizon": 20, "float": "float32", "repeats": 3, "rows": rows})
    assert "gpu: H100" in text and "N= 100000" in text and "first call 900 ms" in text


def test_report_lists_every_planner_and_ratio():
    text = bench.report(synthetic_result())
    assert "EnKTS/MPPI" in text and "0.50x" in text and "EnKTS/floor" in text and "2.0x" in text
    assert "float32" in text
    assert "NMPC/EnKTS(N=50) = 200x" in text and "Solve_Succeeded" in text
    assert "H=10" in text and "H=40" in text and "(2.00x)" in text and "k = 1.00 (H 10->20), 1.00 (H 20->40)" in text
    assert text.count("\n") >= 6


@pytest.mark.parametrize("argv", [["--repeats", "0"], ["--steps", "-1"], ["--bogus"], ["--scenario", "bogus-v0"],
                                  ["--device", "--scenario", "highway-v0"]])
def test_bad_arguments_exit(argv):
    with pytest.raises(SystemExit):
        bench_command.main(argv)


def synthetic_highway_result() -> dict:
    row = lambda p, m, **kw: {"planner": p, "n_particles": 50, "horizon": 20, "repeats": 3,  # noqa: E731
                              "median_ms": m, "p95_ms": 2 * m, "first_call_ms": 4000.0, **kw}
    base = row("enkts", 2.0, n_obstacles=8, road_points=160, road_spacing=1.0)
    k_sweep = [{**row("enkts", 2.0 * k / 8, n_obstacles=k, road_points=160, road_spacing=1.0), "ratio": k / 8}
               for k in (2, 8)]
    p_sweep = [{**row("enkts", 2.0 * p / 160, n_obstacles=8, road_points=p, road_spacing=160 / p), "ratio": p / 160}
               for p in (40, 160)]
    return {"scenario": "highway-v0", "steps_before": 5, "horizon": 20, "n_particles": 50, "n_obstacles": 8,
            "road_points": 160, "road_spacing": 1.0, "repeats": 3, "p_sweep_spacing": "road_spacing = 160 m / P",
            "machine": {"load_average": [4.0, 4.0, 4.0], "cpus": 2}, "floor_ms": {"50": 0.5},
            "rows": [base, row("enks", 1.5, n_obstacles=8, road_points=160, road_spacing=1.0)],
            "k_sweep": k_sweep, "p_sweep": p_sweep, "ratios": {"enkts/floor": 4.0, "enks/floor": 3.0},
            "target_ms": 5.0, "target_met": True, "note": "loaded"}


def test_highway_report_lists_point_and_sweeps():
    text = bench.report_highway(synthetic_highway_result())
    assert "bimp/highway-v0" in text and "K = 8 OVs, P = 160" in text and "4.0x floor" in text and "3.0x floor" in text
    assert "target EnKTS <= 5 ms: met" in text and "load average 4.00" in text and "note: loaded" in text
    assert "EnKTS vs K" in text and "0.25x" in text and "EnKTS vs P" in text and "4.00 m" in text


def test_highway_observations_pair_each_observation_with_its_scene():
    """The wrapped env republishes its scene (a road from at least 30 m behind the EV to at least 250 m ahead,
    kept while it serves) every step: each recorded observation comes with the scene that was current then, so the
    EV sits within that scene's road."""
    from bimp.envs.highway.lanes import AHEAD, BEHIND, SLACK

    pairs = bench.highway_observations("highway-fast-v0", 4, 2)
    assert len(pairs) == 4 and len({id(scene) for _, scene in pairs}) == 4
    for obs, scene in pairs:
        assert obs.shape == (scene.obs_dim,) and scene.n_obstacles == 2
        along = float(scene.road.project(np.asarray(obs[:2], float)).s)
        assert BEHIND - 1.0 < along - float(scene.road.s[0]) < BEHIND + SLACK + 1.0
        assert float(scene.road.s[-1]) - along > AHEAD - 1.0


@pytest.mark.slow
def test_highway_quick_run_has_both_sweeps():
    """A real (quick) highway run: the point, the K and P sweeps with finite times and their ratios (not a timed
    test: nothing is asserted about the times themselves)."""
    before = bench._threads()
    result = bench.run_highway("highway-fast-v0", repeats=2, quick=True, steps=0, progress=lambda _: None)
    json.dumps(result)
    assert [r["planner"] for r in result["rows"]] == ["enkts", "enks"]
    assert [r["n_obstacles"] for r in result["k_sweep"]] == list(bench.K_QUICK)
    assert [r["road_points"] for r in result["p_sweep"]] == list(bench.P_QUICK)
    for r in [*result["rows"], *result["k_sweep"], *result["p_sweep"]]:
        assert math.isfinite(r["median_ms"]) and math.isfinite(r["p95_ms"]) and r["median_ms"] > 0
    for r in [*result["k_sweep"], *result["p_sweep"]]:
        assert math.isfinite(r["ratio"]) and r["ratio"] > 0
        assert r["road_spacing"] * r["road_points"] == pytest.approx(bench.ROAD_WINDOW)
    point = [r for r in result["k_sweep"] if r["n_obstacles"] == 8]
    assert point[0]["ratio"] == 1.0 and point[0]["road_points"] == 160
    assert all(math.isfinite(v) for v in result["ratios"].values()) and isinstance(result["target_met"], bool)
    # Timed on one thread of each kind (bimp.agents.rollout.one_thread), and those restored afterwards.
    assert set(result["threads"].values()) == {1} and "torch" in result["threads"], result["threads"]
    after = bench._threads()
    assert {k: after[k] for k in before} == before  # restored (the run may load a library more)
    assert "EnKTS vs K" in bench.report_highway(result)


def test_env_bench_times_both_cores_on_the_same_steps_and_writes_json_and_markdown(tmp_path, capsys):
    from bimp.agents.evaluation import bench_env

    out = tmp_path / "env.json"
    assert bench_command.main(["--env", "highway-fast-v0", "emergency-brake", "plain:highway-v0", "--env-steps", "3",
                       "--quick", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result["scenarios"]) == {"highway-fast-v0", "emergency-brake", "plain:highway-v0"}
    for row in result["scenarios"].values():
        for core in bench_env.CORES:
            assert len(row[core]["round_s"]) == 1 and row[core]["steps_per_s"] > 0
        assert row["ratio"] == row["fast"]["steps_per_s"] / row["highway-env"]["steps_per_s"]
    # The adapter's share: timed under the adapter only (the paper's envs and a plain highway-env env have none).
    adapter = result["scenarios"]["highway-fast-v0"]["adapter_ms"]
    assert 0 < adapter < 1e3 / result["scenarios"]["highway-fast-v0"]["fast"]["steps_per_s"]
    assert result["scenarios"]["emergency-brake"]["adapter_ms"] is None
    assert result["scenarios"]["plain:highway-v0"]["adapter_ms"] is None
    assert result["adapter_ms_max"] == adapter
    assert "| highway-fast-v0 |" in out.with_suffix(".md").read_text()
    assert bench_command.main(["--env", "no-such-road"]) == 2
    assert "unknown scenario" in capsys.readouterr().err
