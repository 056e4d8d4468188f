"""``bimp evaluate``: policies x scenarios x seeds, safety metrics, written episode by episode.

    bimp evaluate --scenario overtaking emergency-brake --policy enkts enks --episodes 50 --seed 0 \\
                  --workers 2 --out runs/eval

Episode ``i`` of every policy uses seed ``seed + i`` for both the env and the policy, so policies face the
same scenario instances. ``OUT/episodes.jsonl`` gets one line per finished episode, flushed at once; a
rerun with the same arguments skips the episodes already there, so an interrupted run resumes without
repeating or losing any. An episode that raises is recorded with its error and the run goes on.
``OUT/summary.{json,csv,md}`` are rewritten at the end from all the lines in the folder, so a later run
that adds a policy on the same seeds extends the same table.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import multiprocessing as mp
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from agents.metrics import METRICS, episode_metrics, summarize

EPISODES_FILE = "episodes.jsonl"


@dataclass(frozen=True)
class Job:
    """One episode to run. ``overrides``: keyword overrides for ``make_policy``; ``trace``: keep the
    per-step trace in the record (for figures)."""

    scenario: str
    policy: str
    seed: int
    trace: bool = False
    overrides: tuple = field(default_factory=tuple)

    @property
    def key(self) -> tuple[str, str, int]:
        return self.scenario, self.policy, self.seed


def run_episode(job: Job) -> dict:
    """Run one episode and return its record: identifiers, ``status`` ("ok" / "error"), ``metrics``, and
    the ``trace`` if asked for. Never raises for an error inside the episode."""
    import gymnasium as gym

    import envs
    from agents.registry import make_policy

    record = {"scenario": job.scenario, "policy": job.policy, "seed": job.seed}
    try:
        env = gym.make(envs.env_id(job.scenario))
        policy = make_policy(job.policy, env, **dict(job.overrides))
        obs, _ = env.reset(seed=job.seed)
        policy.reset(job.seed)
        trace: dict[str, list] = {k: [] for k in (
            "x", "y", "heading", "speed", "input", "ov_xy", "ov_distance", "edge_distance", "ttc",
            "lateral_error", "speed_error", "reference_speed", "collision", "offroad", "constraints", "plan_ms",
            "s")}
        terminated = truncated = False
        while not (terminated or truncated):
            start = time.perf_counter()
            action = policy.act(obs)
            trace["plan_ms"].append(1e3 * (time.perf_counter() - start))
            obs, _, terminated, truncated, info = env.step(action)
            ego, _, ovs, ref = env.unwrapped.scene.split_obs(obs)
            for name, value in zip(("x", "y", "heading", "speed"), ego):
                trace[name].append(float(value))
            trace["ov_xy"].append(ovs[:, 1:3].tolist())
            trace["reference_speed"].append(float(ref[0]))
            for name in ("input", "ov_distance", "edge_distance", "ttc", "lateral_error", "speed_error",
                         "collision", "offroad", "constraints", "s"):
                trace[name].append(info[name])
        record.update(status="ok", steps=len(trace["plan_ms"]), truncated=bool(truncated),
                      metrics=episode_metrics(trace, env.unwrapped.scene.dt, truncated=bool(truncated)))
        if job.trace:
            scene = env.unwrapped.scene
            record.update(trace=_finite(trace), road=dataclasses.asdict(scene.road),
                          bounds=dataclasses.asdict(scene.bounds))
        env.close()
    except Exception as err:  # recorded, never fatal: one broken episode must not end a long run
        record.update(status="error", error=f"{type(err).__name__}: {err}", traceback=traceback.format_exc())
    return record


def _finite(value):
    """JSON has no inf: infinities become None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def read_records(out: Path) -> list[dict]:
    """All complete episode records in ``out/episodes.jsonl`` (a line cut by an interruption is skipped)."""
    path = Path(out) / EPISODES_FILE
    records = []
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return records


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)  # workers are the parallelism; oversubscribed threads only slow them down


def evaluate(scenarios: list[str], policies: list[str], episodes: int, seed: int = 0, workers: int = 1,
             out: str | Path = "runs/eval", traces: int = 2, overrides: dict | None = None,
             progress: bool = True) -> dict:
    """Run the missing episodes, append them to ``out/episodes.jsonl``, write and return the summary.

    ``traces``: how many episodes per policy and scenario keep their per-step trace (figures use them);
    ``overrides``: ``make_policy`` keyword overrides for every policy that is named in it, e.g.
    ``{"enkts": {"n_particles": 100}}``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    done = {(r["scenario"], r["policy"], r["seed"]) for r in read_records(out)}
    jobs = [Job(s, p, seed + i, trace=i < traces, overrides=tuple(sorted((overrides or {}).get(p, {}).items())))
            for s in scenarios for p in policies for i in range(episodes)]
    todo = [j for j in jobs if j.key not in done]
    path = out / EPISODES_FILE
    if path.exists() and path.stat().st_size and not path.read_bytes().endswith(b"\n"):
        with open(path, "a") as sink:  # end the line an interruption cut, or the next record joins it
            sink.write("\n")
    with open(path, "a") as sink, tqdm(total=len(jobs), initial=len(jobs) - len(todo),
                                                       desc="episodes", disable=not progress) as bar:
        def write(record: dict) -> None:
            sink.write(json.dumps(_finite(record)) + "\n")
            sink.flush()
            os.fsync(sink.fileno())
            bar.update()
            if record["status"] == "error":
                bar.write(f"episode {record['policy']}/{record['scenario']}/{record['seed']} failed: "
                          f"{record['error']}")

        if workers > 1 and len(todo) > 1:
            # Spawned workers import numpy afresh: one BLAS thread each, or they fight over the cores.
            for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
                os.environ.setdefault(var, "1")
            with mp.get_context("spawn").Pool(workers, initializer=_init_worker) as pool:
                for record in pool.imap_unordered(run_episode, todo):
                    write(record)
        else:
            for job in todo:
                write(run_episode(job))
    # The summary covers the whole folder, so policies added by later runs (on the same seeds) join the table.
    summary = summarize(read_records(out))
    write_summary(summary, out)
    return summary


def write_summary(summary: dict, out: Path) -> None:
    """``summary.json`` (every statistic), ``summary.csv`` (mean and std columns), ``summary.md`` (a table)."""
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    columns = ["policy", "scenario", "episodes", "errors"]
    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns + [f"{m}_{s}" for m in METRICS for s in ("mean", "std")])
        for e in summary.values():
            w.writerow([e[c] for c in columns] + [e[m][s] for m in METRICS for s in ("mean", "std")])
    (out / "summary.md").write_text(markdown_table(summary))


def _fmt(stat: dict) -> str:
    if stat["mean"] is None:
        return "-"
    digits = 3 if abs(stat["mean"]) < 10 else 1
    return f"{stat['mean']:.{digits}f} ± {stat['std']:.{digits}f}"


def markdown_table(summary: dict) -> str:
    """Scenario-by-policy rows, every metric as ``mean ± std`` over episodes."""
    head = ["scenario", "policy", "episodes"] + list(METRICS)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for e in sorted(summary.values(), key=lambda e: (e["scenario"], e["policy"])):
        cells = [e["scenario"], e["policy"], str(e["episodes"])] + [_fmt(e[m]) for m in METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _parse_overrides(pairs: list[str]) -> dict:
    """``policy.key=value`` (YAML value) -> ``{policy: {key: value}}``."""
    import yaml

    result: dict[str, dict] = {}
    for pair in pairs:
        name, _, value = pair.partition("=")
        policy, _, key = name.partition(".")
        if not key or not _:
            raise SystemExit(f"--set expects POLICY.KEY=VALUE, got {pair!r}")
        result.setdefault(policy, {})[key] = yaml.safe_load(value)
    return result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", nargs="+", default=["overtaking", "emergency-brake"])
    parser.add_argument("--policy", nargs="+", default=["enkts", "enks"])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=max(1, min(2, os.cpu_count() or 1)))
    parser.add_argument("--traces", type=int, default=2, help="episodes per policy/scenario that keep traces")
    parser.add_argument("--set", dest="overrides", nargs="*", default=[], metavar="POLICY.KEY=VALUE",
                        help="config override for one policy, e.g. enkts.n_particles=100")
    parser.add_argument("--out", default="runs/eval")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp evaluate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    args = parser.parse_args(argv)
    from agents.registry import POLICIES

    unknown = sorted(set(args.policy) - set(POLICIES))
    if unknown:
        parser.error(f"unknown policy {unknown}; choose from {sorted(POLICIES)}")
    summary = evaluate(args.scenario, args.policy, args.episodes, args.seed, args.workers, args.out,
                       args.traces, _parse_overrides(args.overrides))
    print(markdown_table(summary))
    print(f"wrote {Path(args.out) / EPISODES_FILE} and summary.{{json,csv,md}}")
    return 0


__all__ = ["Job", "evaluate", "read_records", "run_episode"]
