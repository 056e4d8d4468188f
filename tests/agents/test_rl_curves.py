"""Learning curves and training hours read from run folders (``bimp curves``), on hand-written Monitor logs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bimp.agents import rl_curves
from bimp.agents.cli import main as bimp


def _run(folder, seed: int, segments: list[list[list[tuple[float, int, float]]]], algo: str = "ppo"):
    """A run folder of two envs: per segment, per env, its episodes ``(return, length, wall s)``."""
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"algo": algo, "scenario": "cut-in-hard", "seed": seed,
                                                    "n_envs": 2, "timesteps": 20_000}))
    i = 0
    for k, segment in enumerate(segments):
        for env in segment:
            rows = "".join(f"{r},{n},{t}\n" for r, n, t in env)
            (folder / f"{i}.monitor.csv").write_text(f'#{{"t_start": {1000.0 * (k + 1) + i}, "env_id": "x"}}\n'
                                                     f"r,l,t\n{rows}")
            i += 1
    return folder


def test_hours_sum_each_segments_last_episode_and_curves_bin_by_timesteps(tmp_path, capsys):
    one = _run(tmp_path / "s1", 1, [[[(1.0, 4000, 10.0), (3.0, 4000, 20.0)], [(2.0, 4000, 15.0)]],
                                    [[(5.0, 4000, 3600.0)], [(7.0, 4000, 1800.0)]]])  # resumed: a second segment
    two = _run(tmp_path / "s2", 2, [[[(10.0, 6000, 7200.0)], [(20.0, 6000, 7100.0)]]])
    assert rl_curves.hours(one) == pytest.approx((20.0 + 3600.0) / 3600)
    steps, returns = rl_curves.episodes(one)
    assert steps[-1] == 20_000 and sorted(returns) == [1.0, 2.0, 3.0, 5.0, 7.0]
    curve = rl_curves.binned(np.array([4000.0, 5000.0, 12_000.0]), np.array([1.0, 3.0, 6.0]), 20_000)
    np.testing.assert_array_equal(curve, [1.0, 3.0, 6.0, np.nan])  # 5,000 is the second bin's first step
    assert bimp(["curves", str(two), str(one), "--out", str(tmp_path / "c.png"), "--json"]) == 0
    [row] = json.loads(capsys.readouterr().out)
    assert row["seeds"] == [1, 2] and row["timesteps"] == [20_000, 12_000]
    assert row["hours"] == pytest.approx((20.0 + 3600.0 + 7200.0) / 3600, abs=1e-3)
    # the last 10% of 20,000 steps: the episode ending last by wall time (5.0); seed 2 never got there
    assert row["final_return"] == [5.0, None]
    assert (tmp_path / "c.png").stat().st_size > 1000


def test_curves_refuse_a_folder_that_is_not_a_run(tmp_path, capsys):
    (tmp_path / "x").mkdir()
    assert bimp(["curves", str(tmp_path / "x"), "--out", str(tmp_path / "c.png")]) == 2
    assert "not a `bimp train-rl` run folder" in capsys.readouterr().err


def test_the_training_table_sums_each_algorithms_hours(tmp_path):
    from bimp.agents.evaluation.report_rl import training_table

    _run(tmp_path / "ppo_1", 1, [[[(1.0, 4000, 1800.0)], [(2.0, 4000, 900.0)]]])
    _run(tmp_path / "ppo_2", 2, [[[(1.0, 5000, 3600.0)], [(2.0, 5000, 3000.0)]]])
    _run(tmp_path / "sac_1", 1, [[[(1.0, 1000, 360.0)], [(2.0, 1000, 360.0)]]], algo="sac")
    (tmp_path / "notes").mkdir()  # not a run: skipped
    for run in ("ppo_1", "ppo_2", "sac_1"):
        (tmp_path / run / "train_time.json").write_text('{"timesteps": 20000}')
    _run(tmp_path / "ppo_3", 3, [[[(1.0, 4000, 1800.0)], [(2.0, 4000, 900.0)]]])  # no train_time.json: training
    table, _ = training_table(tmp_path)
    assert table.endswith("Still training (not counted): ppo_3.")
    assert "| PPO | cut-in-hard | 1, 2 | 20,000, 20,000 | 1.50 | wall (at most) |" in table  # trained, not logged
    assert "| SAC | cut-in-hard | 1 | 20,000 | 0.10 | wall (at most) |" in table
    assert "| PPO | all | | | 1.50 | |" in table


def test_hours_come_from_wall_json_where_a_run_kept_it(tmp_path):
    from bimp.agents.errors import EvaluationError
    from bimp.agents.evaluation.report_rl import training_table

    run = _run(tmp_path / "r", 1, [[[(1.0, 4000, 10.0)], [(2.0, 4000, 15.0)]]])
    (run / "train_time.json").write_text('{"wall_s": 360.0, "timesteps": 8000, "resumed_at": null}')
    assert rl_curves.hours(run) == pytest.approx(0.1)  # trained in one go: its wall time, not the logs' 15 s
    (run / "wall.json").write_text("[1800.0, 900.0]")
    assert rl_curves.hours(run) == pytest.approx(0.75) and not rl_curves.measured_cpu(run)
    (run / "cpu.json").write_text("[900.0, 900.0]")  # the process's CPU time: wall counts the waiting for a core
    assert rl_curves.hours(run) == pytest.approx(0.5) and rl_curves.measured_cpu(run)
    (run / "cpu.json").write_text("[0.0, 900.0]")  # a first segment trained before cpu.json: its wall time
    assert rl_curves.hours(run) == pytest.approx(0.75) and not rl_curves.measured_cpu(run)
    with pytest.raises(EvaluationError, match="no training runs folder"):
        training_table(tmp_path / "nowhere")


def test_a_curve_climbs_while_its_last_window_gains_more_than_noise():
    flat = np.array([[10.0, 50, 90, 100, 101, 100, 99, 101, 100, 102, 100, 101]])  # a plateau from 20k on
    assert not rl_curves.climbing(flat)
    rising = np.array([[10.0, 30, 50, 70, 90, 110, 130, 150, 170, 190, 210, 230]])
    assert rl_curves.climbing(rising) and rl_curves.climbing(np.vstack([rising, rising + 5]))
    assert not rl_curves.climbing(rising[:, :6])  # too short to have two windows and a start
