"""``bimp evaluate``: policies x scenarios x seeds, safety metrics with intervals, written episode by episode.

    bimp evaluate --scenario overtaking emergency-brake --policy enkts enks --episodes 50 --seed 1000 \\
                  --workers 2 --out runs/eval
    bimp evaluate --scenario emergency-brake --policy enkts --set enkts.n_particles=10 --label enkts-n10 ...
    bimp evaluate ... --seeds 4 10 13 --video 1

Every policy, scenario and override is validated before the first episode runs: a bad one exits with status
2 and writes nothing. Each row of the table is an *arm*: a policy under one fully resolved config, named by its
label (the policy name unless ``--label`` says otherwise). ``OUT/episodes.jsonl`` gets one record per
finished episode, fsynced at once, carrying the resolved config, its hash, the scenario's drawn parameters,
the seeds and the code version (``docs/evaluation.md``). A rerun skips the episodes already recorded for the
same ``(scenario, label, config_hash, seed)``; records made with another config under the same label make it
refuse (give ``--label``), never reuse them, and so does a record whose own config does not hash to its
``config_hash`` (naming its line). A line that is not a record is reported and skipped, never a traceback. An
episode that raises is recorded with its traceback, shown in the ``errors`` column and retried by the next run.
A worker process that dies is detected and its episode retried alone, then recorded as an error if it dies
again; the run never hangs. One run at a time per folder (a lock). ``OUT/summary.{json,csv,md}`` cover the
episodes this command asked for (``--all``: the folder).
Episodes run on a local process pool (``--workers``) or, with ``--backend ray [--address ADDR]``, on a Ray
cluster (:mod:`bimp.agents.backends`, ``docs/scaling.md``); this process writes the records either way.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import fcntl
import json
import math
import os
import sys
import time
import traceback
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bimp.agents.backends import BackendError, run_groups, start_backend
from bimp.agents.metrics import BINARY, METRICS, episode_metrics, summarize
from bimp.agents.provenance import code_version, config_diff, config_hash, resolved_config
from bimp.agents.rollout import SEEDING, rollout, rollout_batch
from bimp.agents.video import with_video

EPISODES_FILE = "episodes.jsonl"
LOCK_FILE = ".lock"
VIDEO_DIR = "videos"


class EvaluationError(ValueError):
    """A request that cannot be run as given (unknown name, bad override, a label's config conflict)."""


@dataclass(frozen=True)
class Arm:
    """One row of the table: policy ``policy`` under ``overrides`` on ``scenario``, shown as ``label``;
    ``config`` is the policy's fully resolved config and ``config_hash`` its hash."""

    scenario: str
    label: str
    policy: str
    overrides: tuple
    config: str  # canonical JSON: frozen and hashable
    config_hash: str

    @property
    def resolved(self) -> dict:
        return json.loads(self.config)


@dataclass(frozen=True)
class Job:
    """One episode to run: ``arm`` on episode ``seed``; ``trace``: keep the per-step trace (figures);
    ``video_dir``: record an MP4 there; ``version``: the code version to stamp on the record."""

    arm: Arm
    seed: int
    trace: bool = False
    video_dir: str | None = None
    version: tuple = ()

    @property
    def key(self) -> tuple[str, str, str, int]:
        return self.arm.scenario, self.arm.label, self.arm.config_hash, self.seed


def record_key(record: dict) -> tuple[str, str, str | None, int]:
    """``(scenario, label, config_hash, seed)`` of a record (records older than labels use the policy name)."""
    return record["scenario"], record.get("label", record["policy"]), record.get("config_hash"), record["seed"]


# --- resolving and validating a request ----------------------------------------------------------------
def resolve_arms(scenarios: list[str], policies: list[str], overrides: dict | None = None,
                 labels: dict | None = None) -> list[Arm]:
    """Validate the whole request and build one :class:`Arm` per scenario and policy, by constructing each
    policy once on its scenario's env (so every override is checked exactly as an episode would apply it).
    Raises :class:`EvaluationError` naming the first problem."""
    import gymnasium as gym

    from bimp import envs
    from bimp.agents.registry import POLICIES, is_policy_name, make_policy

    overrides, labels = overrides or {}, labels or {}
    if not scenarios or not policies:
        raise EvaluationError("give at least one scenario and one policy")
    for kind, names in (("scenario", scenarios), ("policy", policies)):
        if len(set(names)) != len(names):
            raise EvaluationError(f"a {kind} is named twice: {names}")
    unknown = [p for p in policies if not is_policy_name(p)]
    if unknown:
        raise EvaluationError(f"unknown policy {unknown}; choose from {sorted(POLICIES)} or give 'module:factory'")
    for name, mapping in (("--set", overrides), ("--label", labels)):
        stray = sorted(set(mapping) - set(policies))
        if stray:
            raise EvaluationError(f"{name} names {stray}, which is not among the policies {policies}")
    shown = [labels.get(p, p) for p in policies]
    if len(set(shown)) != len(shown):
        raise EvaluationError(f"two policies would share a label: {shown}")
    arms = []
    for scenario in scenarios:
        try:
            env = gym.make(envs.env_id(scenario))
        except ValueError as err:
            raise EvaluationError(str(err)) from None
        for policy in policies:
            given = overrides.get(policy, {})
            try:
                config = arm_config(make_policy(policy, env, **given), env)
            except (ValueError, TypeError, OSError, ImportError, AttributeError) as err:  # OSError: a model path
                raise EvaluationError(f"policy {policy!r} on {scenario} with overrides {given}: {err}") from None
            arms.append(Arm(scenario, labels.get(policy, policy), policy, tuple(sorted(given.items())),
                            json.dumps(config, sort_keys=True), config_hash(policy, config)))
        env.close()
    return arms


def arm_config(policy, env) -> dict:
    """What produces an arm's episodes: the policy's resolved config and the scenario's definition (its parameters'
    values, ranges and options, and its behaviour layer's rule; a changed range or rule must not resume onto the
    old episodes)."""
    base = env.unwrapped
    keys = sorted([*base.PARAMS, *base.OPTIONS])
    definition = {k: base.config[k] for k in keys}
    if base.BEHAVIOUR is not None:
        definition["behaviour"] = dataclasses.asdict(base.BEHAVIOUR)
    definition = json.loads(json.dumps(definition, default=float))
    return {**resolved_config(policy), "scenario": definition}


def check_conflicts(arms: list[Arm], records: list[tuple[int, dict]], out: str | Path = ".") -> None:
    """Refuse (:class:`EvaluationError`) when ``records`` (``(line number, record)`` of ``out``'s records) hold
    episodes of an arm's ``(scenario, label)`` made with another config, or a *foreign* record: one carrying the
    arm's ``config_hash`` whose own config does not hash to it. Such a record was not made by this arm (edited, or
    copied in from another config) and resume must not count its episode as done."""
    by_row = {(arm.scenario, arm.label): arm for arm in arms}
    written = {arm: config_hash(arm.policy, _finite(arm.resolved)) for arm in arms}  # infinities are null there
    others: dict[Arm, list[dict]] = {}
    for number, r in records:
        arm = by_row.get((r["scenario"], r.get("label", r["policy"])))
        if arm is None:
            continue
        if r.get("config_hash") != arm.config_hash:
            others.setdefault(arm, []).append(r)
        elif "config" in r and config_hash(r["policy"], r["config"]) != written[arm]:  # older records carry none
            diff = config_diff(r["config"], _finite(arm.resolved)) or [f"policy: {r['policy']!r} -> {arm.policy!r}"]
            raise EvaluationError(
                f"{Path(out) / EPISODES_FILE} line {number}: a record of {arm.label!r} on {arm.scenario} carries "
                f"config hash {arm.config_hash}, but its own config hashes otherwise ({'; '.join(diff[:4])}): it was "
                "not made with that config; choose another --out (the folder's records are never rewritten)")
    for arm, rs in others.items():
        old = rs[-1]
        diff = config_diff(old.get("config") or {}, arm.resolved) or ["(the old records carry no config)"]
        raise EvaluationError(
            f"the folder already holds {len(rs)} episode(s) of {arm.label!r} on {arm.scenario} made with "
            f"another config (hash {old.get('config_hash')} here, {arm.config_hash} now):\n  "
            + "\n  ".join(diff[:12])
            + "\ngive --label NAME to add this config as a new row, or choose another --out")


# --- running one episode -------------------------------------------------------------------------------
def _base_record(job: Job) -> dict:
    arm = job.arm
    return {"scenario": arm.scenario, "label": arm.label, "policy": arm.policy, "seed": job.seed,
            "config_hash": arm.config_hash, "config": arm.resolved, "overrides": dict(arm.overrides),
            "seeding": SEEDING, **dict(job.version)}


def run_episode(job: Job) -> dict:
    """Run one episode and return its record (see ``docs/evaluation.md``). Never raises for an error inside
    the episode: it comes back as ``status: "error"`` with the traceback."""
    return run_group((job,))[0]


def run_group(group: tuple[Job, ...]) -> list[dict]:
    """Records of a group of episodes of one arm: one episode through :func:`bimp.agents.rollout.rollout` (with its
    video if asked for), several through one batched planner over one env each
    (:func:`bimp.agents.rollout.rollout_batch`). Never raises for an error inside an episode: the group's records come
    back as ``status: "error"`` with the traceback, and the next run retries each episode."""
    import gymnasium as gym

    from bimp import envs
    from bimp.agents.registry import make_policy

    arm, batched = group[0].arm, len(group) > 1
    records = [_base_record(job) for job in group]
    start = time.perf_counter()
    try:
        envs_ = [gym.make(envs.env_id(arm.scenario), render_mode="rgb_array" if job.video_dir else None)
                 for job in group]
        if group[0].video_dir:  # only ever a group of one
            envs_[0] = with_video(envs_[0], group[0].video_dir, f"{arm.label}_{arm.scenario}_seed{group[0].seed}")
        policy = make_policy(arm.policy, envs_ if batched else envs_[0], **dict(arm.overrides))
        built = config_hash(arm.policy, arm_config(policy, envs_[0]))
        if built != arm.config_hash:
            raise RuntimeError(f"the policy resolved to config {built} in this process, {arm.config_hash} when "
                               "the run was checked: the config depends on something outside it")
        seeds = [job.seed for job in group]
        episodes = rollout_batch(envs_, policy, seeds) if batched else [rollout(envs_[0], policy, seeds[0])]
        for record, job, episode, env in zip(records, group, episodes, envs_):
            scene = env.unwrapped.scene
            record.update(env_seed=episode.env_seed, policy_seed=episode.policy_seed,
                          scenario_params=episode.params, status="ok", steps=episode.steps,
                          truncated=episode.truncated,
                          metrics=episode_metrics(episode.trace, scene.dt, truncated=episode.truncated))
            if batched:
                record["batch"] = len(group)
            if "policy_info" in episode.trace:
                record["policy_info"] = step_info_summary(episode.trace["policy_info"])
            if job.trace:
                record.update(trace=episode.trace, road=dataclasses.asdict(scene.road),
                              bounds=dataclasses.asdict(scene.bounds))
            env.close()
    except Exception as err:  # recorded, never fatal: one broken episode must not end a long run
        for record in records:
            record.update(status="error", error=f"{type(err).__name__}: {err}", traceback=traceback.format_exc())
    wall = round(time.perf_counter() - start, 3)
    for record in records:
        record["wall_s"] = wall
    return records


def step_info_summary(infos: list[dict]) -> dict:
    """A policy's per-step ``step_info`` in one record: for a flag, the steps where it was set (``fallback`` ->
    ``fallback_steps``: did a collision follow a solver fallback?); for a string, its counts; for a number, its
    mean and maximum."""
    summary: dict = {}
    for key in infos[0] if infos else ():
        values = [info.get(key) for info in infos]
        if all(isinstance(v, bool) for v in values):
            summary[f"{key}_steps"] = [i for i, v in enumerate(values) if v]
        elif all(isinstance(v, str) for v in values):
            summary[key] = dict(Counter(values))
        elif all(isinstance(v, (int, float)) for v in values):
            summary[key] = {"mean": float(np.mean(values)), "max": float(np.max(values))}
    return summary


def _crashed(group: tuple[Job, ...], why: str) -> list[dict]:
    """Error records of a group whose worker process died on every try (``why``: how the backend saw it)."""
    return [{**_base_record(job), "status": "error", "traceback": None,
             "error": f"WorkerDied: {why}; a crash in native code or the out-of-memory killer are the usual causes"}
            for job in group]


def _finite(value):
    """JSON has no inf: infinities and NaN become None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


# --- the folder: records, lock ---------------------------------------------------------------------------
# What every reader relies on; a JSON line without them is not a record (and never a traceback).
REQUIRED = {"scenario": str, "policy": str, "seed": int, "status": str}
OUTCOMES = ("success_rate", "collision_rate", "offroad_rate")  # what every reader takes from an ok record's metrics
_JSON_TYPES = {dict: "an object", list: "an array", str: "a string", int: "a number", float: "a number",
               bool: "a bool", type(None): "null"}


def record_problem(value: object) -> str | None:
    """Why a parsed JSON line is not an episode record (``None`` when it is one)."""
    if not isinstance(value, dict):
        return f"{_JSON_TYPES.get(type(value), type(value).__name__)}, not a record"
    missing = [k for k in REQUIRED if k not in value]
    if missing:
        return f"a record without {', '.join(missing)}"
    wrong = [k for k, kind in REQUIRED.items() if not isinstance(value[k], kind) or isinstance(value[k], bool)]
    wrong += [k for k in ("label", "config_hash") if not isinstance(value.get(k, ""), str)]
    wrong += [k for k in ("config",) if not isinstance(value.get(k, {}), dict)]
    if wrong:
        return f"a record whose {', '.join(wrong)} {'is' if len(wrong) == 1 else 'are'} of the wrong type"
    if value["status"] == "ok" and not (isinstance(value.get("metrics"), dict)
                                        and all(k in value["metrics"] for k in OUTCOMES)):
        return f"an ok record without metrics ({', '.join(OUTCOMES)})"
    return None


_reported: set[tuple[str, tuple[int, ...]]] = set()  # said once per process: evaluate reads a folder three times


def numbered_records(out: str | Path) -> list[tuple[int, dict]]:
    """``(line number, record)`` of every record in ``out/episodes.jsonl``, in file order. A line that is not a
    record (not JSON, not an object, lacking a key every reader needs: :func:`record_problem`) is skipped and
    reported on stderr with its number; the last line, when no newline ends it, is a record cut by an interruption
    and skipped silently. :class:`EvaluationError` when the file cannot be read."""
    path = Path(out) / EPISODES_FILE
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return []
    except OSError as err:
        raise EvaluationError(f"cannot read {path}: {err.strerror or err}") from None
    lines = data.split(b"\n")
    cut = lines.pop()  # b"" after a final newline, else the line an interruption cut
    records, skipped = [], []
    for number, line in enumerate(lines + [cut], start=1):
        if not line.strip():
            continue
        try:
            value = json.loads(line)
        except ValueError:  # bad JSON or not UTF-8
            value, problem = None, "not JSON"
        else:
            problem = record_problem(value)
        if problem is None:
            records.append((number, value))
        elif number <= len(lines):
            skipped.append(f"line {number} ({problem})")
    if skipped and (str(path), tuple(skipped)) not in _reported:
        _reported.add((str(path), tuple(skipped)))
        shown = "; ".join(skipped[:5]) + ("; ..." if len(skipped) > 5 else "")
        print(f"bimp: warning: {path}: skipped {len(skipped)} line(s) that are not episode records: {shown}",
              file=sys.stderr)
    return records


def read_records(out: str | Path) -> list[dict]:
    """Every record in ``out/episodes.jsonl``, in file order (:func:`numbered_records` without the numbers)."""
    return [record for _, record in numbered_records(out)]


def latest_records(records: list[dict]) -> list[dict]:
    """One record per ``(scenario, label, config_hash, seed)``: the last successful one, else the last error
    (an error that a later run retried successfully is no longer shown)."""
    chosen: dict[tuple, dict] = {}
    for r in records:
        key = record_key(r)
        if r["status"] == "ok" or chosen.get(key, {}).get("status") != "ok":
            chosen[key] = r
    return list(chosen.values())


def check_out_dir(out: str | Path, create: bool = True, flag: str = "--out") -> Path:
    """``out`` as a folder a command can write into (made, with its parents, when ``create``), or
    :class:`EvaluationError` in one line naming it (as ``flag``): empty (``--out ""`` would write into the current
    folder), an existing file, a path under a file, or a folder this user cannot write. ``create=False`` checks
    without writing anything, so a command can refuse before its first episode."""
    if not str(out).strip():
        raise EvaluationError(f"{flag} is empty: name the folder to write into")
    out = Path(out)
    existing = next(p for p in (out, *out.parents) if p.exists() or p == Path(p.anchor or "."))
    if not existing.is_dir():
        where = "is a file" if existing == out else f"lies under {existing}, a file"
        raise EvaluationError(f"{flag} {out} {where}, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise EvaluationError(f"{flag} {out}: {existing} is not writable")
    if create:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:  # what the checks above cannot see (a full disk, a race)
            raise EvaluationError(f"{flag} {out}: cannot create it ({err.strerror or err})") from None
    return out


@contextmanager
def folder_lock(out: Path):
    """Hold ``out/.lock`` for the run; a second run into the same folder refuses at once. The lock is an
    ``flock``, so the kernel releases it when the holder dies: no stale locks."""
    handle = open(out / LOCK_FILE, "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "another process"
        handle.close()
        raise EvaluationError(f"{out} is in use by another bimp run ({holder}); wait for it to end or choose "
                              "another --out") from None
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        handle.flush()
        yield
    finally:
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


# --- running many episodes ------------------------------------------------------------------------------
def evaluate(scenarios: list[str], policies: list[str], episodes: int = 10, seed: int = 0, workers: int = 1,
             out: str | Path = "runs/eval", traces: int = 2, overrides: dict | None = None,
             progress: bool = True, *, seeds: list[int] | None = None, labels: dict | None = None,
             video: int = 0, all_records: bool = False, batch: int = 1, backend: str = "local",
             address: str | None = None, ray_cpus: int | None = None) -> dict:
    """Run the missing episodes, append them to ``out/episodes.jsonl``, write and return the summary.

    Episodes: ``seeds`` if given, else ``seed, seed + 1, ..., seed + episodes - 1``. ``overrides``:
    ``{policy: {key: value}}`` for ``make_policy``; ``labels``: ``{policy: label}``; ``traces`` / ``video``:
    how many of the first seeds per arm keep their per-step trace / get an MP4 in ``out/videos``;
    ``all_records``: summarize the whole folder instead of this request; ``batch``: plan up to this many episodes
    of an arm in one batched call (policies with ``batched = True``; episodes with video run alone);
    ``backend``: where the episodes run (:mod:`bimp.agents.backends`): ``"local"``, a pool of ``workers`` processes,
    or ``"ray"``, the Ray cluster at ``address`` (default: a new local instance of ``ray_cpus`` CPUs). Raises
    :class:`EvaluationError` before anything is written when the request is invalid, conflicts with the folder's
    records, or names a backend that cannot run.
    """
    try:
        start_backend(backend, address, ray_cpus)
    except BackendError as err:
        raise EvaluationError(str(err)) from None
    seeds = list(range(seed, seed + episodes)) if seeds is None else [int(s) for s in seeds]
    if not seeds or min(seeds) < 0 or len(set(seeds)) != len(seeds):
        raise EvaluationError(f"seeds must be distinct ints >= 0, at least one; got {seeds}")
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise EvaluationError(f"batch must be an int >= 1, got {batch!r}")
    arms = resolve_arms(scenarios, policies, overrides, labels)
    if batch > 1:
        single = sorted({arm.policy for arm in arms if not _batched(arm.policy)})
        if single:
            raise EvaluationError(f"--batch needs policies that plan batches; {single} do not")
    out = check_out_dir(out, create=False)
    check_conflicts(arms, numbered_records(out), out)  # before anything is written: a refusal leaves no trace
    check_out_dir(out)
    with folder_lock(out):
        numbered = numbered_records(out)
        check_conflicts(arms, numbered, out)  # again under the lock: the folder may have changed meanwhile
        records = [r for _, r in numbered]
        version = tuple(code_version().items())
        video_dir = str(out / VIDEO_DIR)
        jobs = [Job(arm, s, trace=i < traces, video_dir=video_dir if i < video else None, version=version)
                for arm in arms for i, s in enumerate(seeds)]
        done = {record_key(r) for r in records if r["status"] == "ok"}
        todo = [j for j in jobs if j.key not in done]
        path = out / EPISODES_FILE
        if path.exists() and path.stat().st_size and not path.read_bytes().endswith(b"\n"):
            with open(path, "a") as sink:  # end the line an interruption cut, or the next record joins it
                sink.write("\n")
        with open(path, "a") as sink, tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="episodes",
                                           disable=not progress) as bar:
            def write(record: dict) -> None:
                sink.write(json.dumps(_finite(record)) + "\n")
                sink.flush()
                os.fsync(sink.fileno())
                bar.update()
                if record["status"] == "error":
                    bar.write(f"episode {record['label']}/{record['scenario']}/seed {record['seed']} failed: "
                              f"{record['error']}")

            run_groups(_groups(todo, batch), run_group, _crashed, write, backend=backend, workers=workers,
                       address=address, cpus=ray_cpus)
        wanted = {j.key for j in jobs}
        records = latest_records(read_records(out))
        summary = summarize(records if all_records else [r for r in records if record_key(r) in wanted])
        write_summary(summary, out)
    return summary


def _batched(policy: str) -> bool:
    from bimp.agents.registry import policy_class

    return bool(getattr(policy_class(policy), "batched", False))


def _groups(todo: list[Job], batch: int) -> list[tuple[Job, ...]]:
    """Consecutive episodes of one arm, up to ``batch`` each; an episode with video alone."""
    groups: list[tuple[Job, ...]] = []
    current: list[Job] = []
    for job in todo:
        if current and (len(current) == batch or job.arm != current[0].arm or job.video_dir):
            groups.append(tuple(current))
            current = []
        if job.video_dir:
            groups.append((job,))
        else:
            current.append(job)
    if current:
        groups.append(tuple(current))
    return groups


# --- the summary files ----------------------------------------------------------------------------------
STATS = ("mean", "ci_low", "ci_high")


def write_summary(summary: dict, out: Path) -> None:
    """``summary.json`` (every statistic), ``summary.csv`` (mean and interval columns), ``summary.md``."""
    (out / "summary.json").write_text(json.dumps(_finite(summary), indent=2))
    columns = ["policy", "scenario", "episodes", "errors"]
    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns + ["error_seeds", "failed_seeds"] + [f"{m}_{s}" for m in METRICS for s in STATS]
                   + ["fallback_seeds", "fallback_steps"])
        for e in summary.values():
            w.writerow([e[c] for c in columns] + [" ".join(map(str, e["error_seeds"])),
                                                  " ".join(map(str, e["failed_seeds"]["success"]))]
                       + [e[m][s] for m in METRICS for s in STATS]
                       + [" ".join(map(str, e["fallback_seeds"])), e["fallback_steps"]])
    (out / "summary.md").write_text(markdown_table(summary))


def _fmt(stat: dict) -> str:
    if stat["mean"] is None:
        return "-"
    digits = 3 if abs(stat["mean"]) < 10 else 1
    return f"{stat['mean']:.{digits}f} [{stat['ci_low']:.{digits}f}, {stat['ci_high']:.{digits}f}]"


def _seeds(seeds: list[int], most: int = 8) -> str:
    if not seeds:
        return "0"
    shown = ", ".join(map(str, seeds[:most])) + (", ..." if len(seeds) > most else "")
    return f"{len(seeds)} ({shown})"


def markdown_table(summary: dict) -> str:
    """Scenario-by-arm rows: every metric as ``mean [95% interval]`` (Wilson for the episode outcomes,
    bootstrap for the rest), the errors and the failed episodes with their seeds."""
    fallbacks = any(e.get("fallback_steps") for e in summary.values())  # a column only where a planner fell back
    head = ["scenario", "policy", "episodes", "errors", "failed"] + ["fallbacks"] * fallbacks + list(METRICS)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for e in sorted(summary.values(), key=lambda e: (e["scenario"], e["policy"])):
        cells = [e["scenario"], e["policy"], str(e["episodes"]), _seeds(e["error_seeds"]),
                 _seeds(e["failed_seeds"]["success"])]
        if fallbacks:
            cells.append(f"{_seeds(e['fallback_seeds'])}; {e['fallback_steps']} of {e['steps']} steps"
                         if e.get("fallback_steps") else "0")
        lines.append("| " + " | ".join(cells + [_fmt(e[m]) for m in METRICS]) + " |")
    notes = (f"\nIntervals: 95%, Wilson for {', '.join(BINARY)} (per episode), bootstrap of the mean for the "
             "rest. `errors`: episodes that raised (not results; retried by the next run). `failed`: episodes "
             "without success. Seeds in parentheses.\n")
    if fallbacks:
        notes += ("`fallbacks`: episodes where the planner found no usable plan on at least one step and fell back "
                  "(held or braked), and those steps out of all steps: what the outcomes of these rows rest on.\n")
    mixed = [f"{e['policy']}/{e['scenario']}" for e in summary.values() if len(e.get("code_versions", ())) > 1]
    if mixed:
        notes += (f"\n**Mixed code versions** in {', '.join(mixed)}: these rows hold records made by different "
                  "commits (a resumed run after a code change); rerun into a fresh folder to compare one version.\n")
    return "\n".join(lines) + "\n" + notes


# --- command line ---------------------------------------------------------------------------------------
def parse_overrides(pairs: list[str]) -> dict:
    """``POLICY.KEY=VALUE`` (VALUE read as YAML) -> ``{policy: {key: value}}``; EvaluationError naming the pair."""
    import yaml

    result: dict[str, dict] = {}
    for pair in pairs:
        name, eq, value = pair.partition("=")
        policy, dot, key = name.partition(".")
        if not (eq and dot and policy and key):
            raise EvaluationError(f"--set expects POLICY.KEY=VALUE, got {pair!r}")
        if key in result.get(policy, {}):
            raise EvaluationError(f"--set gives {policy}.{key} twice")
        try:
            result.setdefault(policy, {})[key] = yaml.safe_load(value)
        except yaml.YAMLError as err:
            raise EvaluationError(f"--set {pair!r}: the value is not valid YAML ({err})") from None
    return result


def parse_labels(items: list[str], policies: list[str]) -> dict:
    """``--label NAME`` (one policy) or ``POLICY=NAME`` per policy -> ``{policy: label}``."""
    labels = {}
    for item in items:
        policy, eq, name = item.rpartition("=")
        if not eq:
            if len(policies) != 1:
                raise EvaluationError(f"--label {item!r} is ambiguous with several policies: use POLICY=NAME")
            policy, name = policies[0], item
        if not name or "/" in name:
            raise EvaluationError(f"--label {item!r}: a label is a non-empty name without '/'")
        labels[policy] = name
    return labels


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", nargs="+", default=["overtaking", "emergency-brake"])
    parser.add_argument("--policy", nargs="+", default=["enkts", "enks"])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0, help="first episode seed (seeds by role: docs/evaluation.md)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="an explicit list of episode seeds")
    parser.add_argument("--workers", type=int, default=max(1, min(2, os.cpu_count() or 1)))
    parser.add_argument("--traces", type=int, default=2, help="episodes per arm that keep their per-step trace")
    parser.add_argument("--video", type=int, default=0, metavar="K", help="MP4 of the first K episodes per arm")
    # extend: a repeated flag adds to the earlier ones instead of silently replacing them
    parser.add_argument("--set", dest="overrides", nargs="*", action="extend", default=[],
                        metavar="POLICY.KEY=VALUE",
                        help="config override for one policy, e.g. enkts.n_particles=100")
    parser.add_argument("--label", nargs="*", action="extend", default=[], metavar="[POLICY=]NAME",
                        help="the row name of a policy's config (default: the policy name)")
    parser.add_argument("--batch", type=int, default=1, metavar="B",
                        help="plan B episodes of an arm in one batched call (enkts, enks)")
    parser.add_argument("--all", dest="all_records", action="store_true",
                        help="summarize every episode in the folder, not only this request's")
    parser.add_argument("--out", default="runs/eval")
    add_backend_arguments(parser)


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", default="local", help="where the episodes run: local (a process pool of "
                        "--workers) or ray (a Ray cluster: docs/scaling.md)")
    parser.add_argument("--address", default=None, help="with --backend ray: the cluster's head HOST:PORT, "
                        "ray://HOST:PORT or auto (default: a new local Ray instance)")
    parser.add_argument("--ray-cpus", type=int, default=None, metavar="N",
                        help="with --backend ray and no --address: CPUs of the new local instance (default: all)")


def backend_options(args: argparse.Namespace) -> dict:
    """The keyword arguments of :func:`evaluate` (and of what calls it) that :func:`add_backend_arguments` parsed."""
    return {"backend": args.backend, "address": args.address, "ray_cpus": args.ray_cpus}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp evaluate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        if args.episodes < 1 or args.workers < 1 or args.traces < 0 or args.video < 0:
            raise EvaluationError("--episodes and --workers must be >= 1, --traces and --video >= 0")
        summary = evaluate(args.scenario, args.policy, args.episodes, args.seed, args.workers, args.out,
                           args.traces, parse_overrides(args.overrides), seeds=args.seeds,
                           labels=parse_labels(args.label, args.policy), video=args.video,
                           all_records=args.all_records, batch=args.batch, **backend_options(args))
    except EvaluationError as err:
        print(f"bimp evaluate: error: {err}", file=sys.stderr)
        return 2
    print(markdown_table(summary))
    print(f"wrote {Path(args.out) / EPISODES_FILE} and summary.{{json,csv,md}}")
    return 0


__all__ = ["Arm", "EvaluationError", "Job", "evaluate", "latest_records", "read_records", "resolve_arms",
           "run_episode"]
