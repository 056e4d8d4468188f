"""bimp.agents.bench: the report of a synthetic result (no timing here: benchmarks are never timed tests) and the
argument checks."""

from __future__ import annotations

import pytest

from bimp.agents import bench


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


@pytest.mark.parametrize("argv", [["--repeats", "0"], ["--steps", "-1"], ["--bogus"]])
def test_bad_arguments_exit(argv):
    with pytest.raises(SystemExit):
        bench.main(argv)
