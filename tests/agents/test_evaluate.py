import csv
import json

from agents.evaluate import EPISODES_FILE, evaluate, read_records
from agents.metrics import METRICS
from agents.plots import plot_all

ARGS = dict(scenarios=["emergency-brake"], policies=["lane-keep"], episodes=3, seed=5, workers=1,
            traces=1, progress=False)


def test_summary_files_carry_every_named_key(tmp_path):
    summary = evaluate(out=tmp_path, **ARGS)
    entry = json.loads((tmp_path / "summary.json").read_text())["lane-keep/emergency-brake"]
    assert entry == summary["lane-keep/emergency-brake"]
    assert entry["episodes"] == 3 and all(k in entry for k in METRICS)
    header = next(csv.reader(open(tmp_path / "summary.csv")))
    assert all(f"{k}_mean" in header and f"{k}_std" in header for k in METRICS)
    md = (tmp_path / "summary.md").read_text()
    assert all(k in md for k in METRICS) and "lane-keep" in md
    # the lane keeper is blind to the braking OVs: the metrics must say so
    assert entry["collision_rate"]["mean"] == 1.0 and entry["success_rate"]["mean"] == 0.0
    assert len(plot_all(tmp_path)) == 3


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
    seeds = [r["seed"] for r in read_records(part)]
    assert sorted(seeds) == [5, 6, 7]  # nothing repeated, nothing lost


def test_an_episode_that_raises_is_recorded_and_the_run_goes_on(tmp_path):
    summary = evaluate(out=tmp_path, **{**ARGS, "episodes": 1, "policies": ["lane-keep", "enkts"]},
                       overrides={"enkts": {"n_particle": 10}})  # a typo: the policy cannot be built
    records = {r["policy"]: r for r in read_records(tmp_path)}
    assert records["enkts"]["status"] == "error" and "n_particle" in records["enkts"]["error"]
    assert records["lane-keep"]["status"] == "ok"
    assert summary["enkts/emergency-brake"]["errors"] == 1
