"""Policies x scenarios x seeds, safety metrics with intervals, written episode by episode (:func:`evaluate`;
the command ``bimp evaluate``: :mod:`bimp.agents.commands.evaluate`).

Every policy, scenario and override is validated before the first episode runs: a bad one exits with status
2 and writes nothing. Each row of the table is an *arm*: a policy under one fully resolved config, named by its
label (the policy name unless ``--label`` says otherwise). ``OUT/arms.json`` holds each arm's resolved config once,
keyed by its hash (written before the arm's first record); ``OUT/episodes.jsonl`` gets one compact record per
finished episode, fsynced at once, carrying the config's hash, the scenario's drawn parameters, the seeds and the
code version (``docs/evaluation.md``); per-step traces only with ``--traces K`` (figures). A rerun skips the
episodes already recorded for the same ``(scenario, label, config_hash, seed)``; records made with another config
under the same label make it refuse (give ``--label``), never reuse them, and so does a record whose config (its
own, or its ``arms.json`` entry) does not hash to its ``config_hash`` (naming its line, or the entry's hash).
``--dry-run`` resolves and checks the request exactly so, then lists per arm the episodes done and to run, and
writes nothing. A line that is not a record is reported and skipped, never a traceback. An
episode that raises is recorded with its traceback, shown in the ``errors`` column and retried by the next run.
A worker process that dies is detected and its episode retried alone, then recorded as an error if it dies
again; the run never hangs. One run at a time per folder (a lock). ``OUT/summary.{json,csv,md}`` cover the
episodes this command asked for (``--all``: the folder).
Episodes run on a local process pool (``--workers``) or, with ``--backend ray [--address ADDR]``, on a Ray
cluster (:mod:`bimp.agents.evaluation.backends`, ``docs/scaling.md``); this process writes the records either way.
The folder itself (records, lock, summary files) is :mod:`bimp.agents.evaluation.records`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shlex
import time
import traceback
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
from tqdm import tqdm

from bimp import envs
from bimp.agents.errors import EvaluationError, check_out_dir
from bimp.agents.evaluation.backends import BackendError, check_backend, run_groups, start_backend
from bimp.agents.evaluation.metrics import episode_metrics, summarize
from bimp.agents.evaluation.provenance import code_version, config_diff, config_hash, machine, resolved_config
from bimp.agents.evaluation.records import (
    ARMS_FILE,
    EPISODES_FILE,
    finite,
    folder_lock,
    latest_records,
    numbered_records,
    read_arms,
    read_records,
    record_config,
    record_key,
    record_label,
    write_arms,
    write_summary,
)
from bimp.agents.registry import POLICIES, is_policy_name, make_policy, policy_spec
from bimp.agents.rollout import SEEDING, rollout, rollout_batch, with_video

VIDEO_DIR = "videos"


@dataclass(frozen=True)
class ArmSpec:
    """One row of the table: policy ``policy`` under ``overrides`` on ``scenario``, shown as ``label``;
    ``config`` is the policy's fully resolved config and ``config_hash`` its hash; ``artifacts``: the files the
    policy loaded, by name (its ``artifacts``; shown in ``arms.json``, not hashed: the config names them by content)."""

    scenario: str
    label: str
    policy: str
    overrides: str  # canonical JSON, as config: a list value (--set KEY=[1, 2]) must not make the arm unhashable
    config: str  # canonical JSON: frozen and hashable
    config_hash: str
    artifacts: str = "{}"  # canonical JSON

    @property
    def resolved(self) -> dict:
        return json.loads(self.config)

    @property
    def given(self) -> dict:
        """The overrides, as given to ``make_policy``."""
        return json.loads(self.overrides)

    def entry(self) -> dict:
        """The arm's entry in ``arms.json`` (infinities as null, as JSON holds them)."""
        return finite({"policy": self.policy, "config": self.resolved, "artifacts": json.loads(self.artifacts),
                       "overrides": self.given, "seeding": SEEDING})


@dataclass(frozen=True)
class Job:
    """One episode to run: ``arm`` on episode ``seed``; ``trace``: keep the per-step trace (figures);
    ``video_dir``: record an MP4 there; ``version``: the code version to stamp on the record; ``inline``: the
    arm's fields a record repeats because they differ from its ``arms.json`` entry (overrides, seeding)."""

    arm: ArmSpec
    seed: int
    trace: bool = False
    video_dir: str | None = None
    version: tuple = ()
    inline: tuple = ()

    @property
    def key(self) -> tuple[str, str, str, int]:
        return self.arm.scenario, self.arm.label, self.arm.config_hash, self.seed


# --- resolving and validating a request ----------------------------------------------------------------
def resolve_arms(scenarios: list[str], policies: list[str], overrides: dict | None = None,
                 labels: dict | None = None) -> list[ArmSpec]:
    """Validate the whole request and build one :class:`ArmSpec` per scenario and policy, by constructing each
    policy once on its scenario's env (so every override is checked exactly as an episode would apply it).
    Raises :class:`EvaluationError` naming the first problem."""
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
                built = make_policy(policy, env, **given)
                config = arm_config(built, env)
            except (ValueError, TypeError, OSError, ImportError, AttributeError) as err:  # OSError: a model path
                raise EvaluationError(f"policy {policy!r} on {scenario} with overrides {given}: {err}") from None
            artifacts = json.dumps(getattr(built, "artifacts", {}), sort_keys=True, default=str)
            arms.append(ArmSpec(scenario, labels.get(policy, policy), policy, json.dumps(given, sort_keys=True),
                            json.dumps(config, sort_keys=True), config_hash(policy, config), artifacts))
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


def check_conflicts(arms: list[ArmSpec], records: list[tuple[int, dict]], out: str | Path = ".",
                    entries: dict[str, dict] | None = None) -> None:
    """Refuse (:class:`EvaluationError`) when ``records`` (``(line number, record)`` of ``out``'s records) hold
    episodes of an arm's ``(scenario, label)`` made with another config, or a *foreign* record: one carrying the
    arm's ``config_hash`` whose config (its own, or its entry in ``entries``, ``out/arms.json`` by default) does not
    hash to it, or that has none. Such a record was not made by this arm (edited, or copied in from another config)
    and resume must not count its episode as done."""
    entries = read_arms(out) if entries is None else entries
    by_row = {(arm.scenario, arm.label): arm for arm in arms}
    checked = set()  # ids of the configs found to hash to their arm's key: each is hashed once, not per record
    for arm in arms:  # the arm's own entry must be its config: an edited arms.json would vouch for every record
        entry = entries.get(arm.config_hash)
        if entry is not None and config_hash(entry["policy"], entry["config"]) == arm.config_hash:
            checked.add(id(entry["config"]))
        elif entry is not None:
            diff = config_diff(entry["config"], finite(arm.resolved)) or [f"policy: {entry['policy']!r}"]
            raise EvaluationError(
                f"{Path(out) / ARMS_FILE}: the entry {arm.config_hash} ({arm.label!r} on {arm.scenario}) does not "
                f"hash to its key ({'; '.join(diff[:4])}): it is not that config; choose another --out")
    others: dict[ArmSpec, list[dict]] = {}
    for number, r in records:
        arm = by_row.get((r["scenario"], record_label(r)))
        if arm is None:
            continue
        config = record_config(r, entries)
        verified = id(config) in checked and r["policy"] == arm.policy  # its arm's entry, hashed above
        if r.get("config_hash") != arm.config_hash:
            others.setdefault(arm, []).append(r)
        elif config is None or (not verified and config_hash(r["policy"], config) != arm.config_hash):
            # A hash without the config it names proves nothing: such a record is foreign too.
            diff = (config_diff(config, finite(arm.resolved)) if config is not None
                    else [f"its hash is not in {ARMS_FILE} and it carries no config"]) \
                or [f"policy: {r['policy']!r} -> {arm.policy!r}"]
            raise EvaluationError(
                f"{Path(out) / EPISODES_FILE} line {number}: a record of {arm.label!r} on {arm.scenario} carries "
                f"config hash {arm.config_hash}, but its config hashes otherwise ({'; '.join(diff[:4])}): it was "
                "not made with that config; choose another --out (a run never rewrites a folder's records)")
    for arm, rs in others.items():
        old = rs[-1]
        diff = config_diff(record_config(old, entries) or {}, arm.resolved) or ["(the old records carry no config)"]
        raise EvaluationError(
            f"the folder already holds {len(rs)} episode(s) of {arm.label!r} on {arm.scenario} made with "
            f"another config (hash {old.get('config_hash')} here, {arm.config_hash} now):\n  "
            + "\n  ".join(diff[:12])
            + "\ngive --label NAME to add this config as a new row, choose another --out, or take the old records "
            f"out first: bimp drop {shlex.join([str(out), '--scenario', arm.scenario, '--label', arm.label])}")


# --- running one episode -------------------------------------------------------------------------------
def _base_record(job: Job) -> dict:
    arm = job.arm
    # The config, overrides and seeding are the arm's entry in arms.json: a record names it by hash, and repeats only
    # what differs from it (job.inline).
    return {"scenario": arm.scenario, "label": arm.label, "policy": arm.policy, "seed": job.seed,
            "config_hash": arm.config_hash, **dict(job.inline), **dict(job.version),
            "machine": machine()}  # where the episode runs (a worker, a Ray node), not where it was asked for


def run_group(group: tuple[Job, ...]) -> list[dict]:
    """Records of a group of episodes of one arm: one episode through :func:`bimp.agents.rollout.rollout` (with its
    video if asked for), several through one batched planner over one env each
    (:func:`bimp.agents.rollout.rollout_batch`). Never raises for an error inside an episode: the group's records come
    back as ``status: "error"`` with the traceback, and the next run retries each episode."""
    arm, batched = group[0].arm, len(group) > 1
    records = [_base_record(job) for job in group]
    start = time.perf_counter()
    try:
        envs_ = [gym.make(envs.env_id(arm.scenario), render_mode="rgb_array" if job.video_dir else None)
                 for job in group]
        if group[0].video_dir:  # only ever a group of one
            envs_[0] = with_video(envs_[0], group[0].video_dir, f"{arm.label}_{arm.scenario}_seed{group[0].seed}")
        policy = make_policy(arm.policy, envs_ if batched else envs_[0], **arm.given)
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
                # The closed-form road where there is one (the paper's: what plots redraw), else the last route.
                road = {"road": dataclasses.asdict(scene.geometry)} if scene.geometry is not None else \
                    {"route": {k: np.round(getattr(scene.road, k), 3).tolist() for k in ("xy", "left", "right")}}
                record.update(trace=episode.trace, bounds=dataclasses.asdict(scene.bounds), **road)
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
    # Made here, not in the worker that died: the machine it ran on is not known (a Ray node).
    return [{**_base_record(job), "machine": None, "status": "error", "traceback": None,
             "error": f"WorkerDied: {why}; a crash in native code or the out-of-memory killer are the usual causes"}
            for job in group]


# --- running many episodes ------------------------------------------------------------------------------
@dataclass(frozen=True)
class DryRun:
    """What a run would do (``evaluate(..., dry_run=True)``): ``to_run``, the ``(scenario, label, seed)`` of every
    episode it would run; ``done``, how many of the requested episodes the folder already holds; ``arms``, per arm
    ``(scenario, label, done, to run)``."""

    to_run: list[tuple[str, str, int]]
    done: int
    arms: list[tuple[str, str, int, int]]

    def lines(self) -> list[str]:
        """One line per arm, then ``dry run: N episode(s) would run``."""
        return ([f"{scenario}  {label}: {done} done, {todo} to run" for scenario, label, done, todo in self.arms]
                + [f"dry run: {len(self.to_run)} episode(s) would run"])


def evaluate(scenarios: list[str], policies: list[str], episodes: int = 10, seed: int = 0, workers: int = 1,
             out: str | Path = "runs/eval", traces: int = 0, overrides: dict | None = None,
             progress: bool = True, *, seeds: list[int] | None = None, labels: dict | None = None,
             video: int = 0, all_records: bool = False, batch: int = 1, backend: str = "local",
             address: str | None = None, ray_cpus: int | None = None, dry_run: bool = False) -> dict | DryRun:
    """Run the missing episodes, append them to ``out/episodes.jsonl``, write and return the summary.

    Episodes: ``seeds`` if given, else ``seed, seed + 1, ..., seed + episodes - 1``. ``overrides``:
    ``{policy: {key: value}}`` for ``make_policy``; ``labels``: ``{policy: label}``; ``traces`` / ``video``:
    how many of the first seeds per arm keep their per-step trace / get an MP4 in ``out/videos``;
    ``all_records``: summarize the whole folder instead of this request; ``batch``: plan up to this many episodes
    of an arm in one batched call (policies whose spec says ``batched``; episodes with video run alone);
    ``backend``: where the episodes run (:mod:`bimp.agents.evaluation.backends`): ``"local"``, a pool of ``workers``
    processes, or ``"ray"``, the Ray cluster at ``address`` (default: a new local instance of ``ray_cpus`` CPUs). Raises
    :class:`EvaluationError` before anything is written when the request is invalid, conflicts with the folder's
    records, or names a backend that cannot run. ``dry_run``: check all that, then return a :class:`DryRun` (the
    episodes that would run) instead, writing nothing and starting no backend."""
    try:  # a dry run checks the request as a real run would, but connects to nothing
        (check_backend if dry_run else start_backend)(backend, address, ray_cpus)
    except BackendError as err:
        raise EvaluationError(str(err)) from None
    seeds = list(range(seed, seed + episodes)) if seeds is None else [int(s) for s in seeds]
    if not seeds or min(seeds) < 0 or len(set(seeds)) != len(seeds):
        raise EvaluationError(f"seeds must be distinct ints >= 0, at least one; got {seeds}")
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise EvaluationError(f"batch must be an int >= 1, got {batch!r}")
    arms = resolve_arms(scenarios, policies, overrides, labels)
    if batch > 1:
        single = sorted({arm.policy for arm in arms if not policy_spec(arm.policy).batched})
        if single:
            raise EvaluationError(f"--batch needs policies that plan batches; {single} do not")
    out = check_out_dir(out, create=False)
    numbered = numbered_records(out)
    check_conflicts(arms, numbered, out)  # before anything is written: a refusal leaves no trace
    if dry_run:
        done = {record_key(r) for _, r in numbered if r["status"] == "ok"}
        rows = [(arm, [s for s in seeds if (arm.scenario, arm.label, arm.config_hash, s) not in done]) for arm in arms]
        return DryRun([(arm.scenario, arm.label, s) for arm, todo in rows for s in todo],
                      len(arms) * len(seeds) - sum(len(todo) for _, todo in rows),
                      [(arm.scenario, arm.label, len(seeds) - len(todo), len(todo)) for arm, todo in rows])
    check_out_dir(out)
    with folder_lock(out):
        numbered = numbered_records(out)
        check_conflicts(arms, numbered, out)  # again under the lock: the folder may have changed meanwhile
        records = [r for _, r in numbered]
        version = tuple(code_version().items())
        video_dir = str(out / VIDEO_DIR)
        done = {record_key(r) for r in records if r["status"] == "ok"}
        entries = read_arms(out)
        new = {arm.config_hash: arm.entry() for arm in arms
               if arm.config_hash not in entries and _keys(arm, seeds) - done}
        if new:  # each new arm's config before its first record: a record never names a hash arms.json lacks
            entries = {**entries, **new}
            write_arms(out, entries)
        jobs = [Job(arm, s, trace=i < traces, video_dir=video_dir if i < video else None, version=version,
                    inline=_inline(arm, entries[arm.config_hash]) if arm.config_hash in entries else ())
                for arm in arms for i, s in enumerate(seeds)]
        todo = [j for j in jobs if j.key not in done]
        path = out / EPISODES_FILE
        if path.exists() and path.stat().st_size and not path.read_bytes().endswith(b"\n"):
            with open(path, "a") as sink:  # end the line an interruption cut, or the next record joins it
                sink.write("\n")
        with contextlib.closing(Appender(path)) as sink, tqdm(total=len(jobs), initial=len(jobs) - len(todo),
                                                             desc="episodes", disable=not progress) as bar:
            def write(record: dict) -> None:
                if sink.write(json.dumps(finite(record)) + "\n"):
                    bar.write(f"bimp: warning: {path} was replaced while this run appended to it (by another "
                              "program: git checkout or stash?); appending to the new file. The records written "
                              "before are only in the replaced one: the same command again redoes them.")
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


class Appender:
    """A file opened for appending that follows its path: where another program replaced the file meanwhile
    (``git checkout`` or ``git stash`` of a results folder during a run), the next write goes to the new file, not to
    the replaced one that nobody reads any more. Every line is flushed and fsynced."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.file = open(self.path, "a")

    def write(self, line: str) -> bool:
        """Append ``line``; whether the file had been replaced (and was reopened) first."""
        mine = os.fstat(self.file.fileno())
        try:
            now = os.stat(self.path)
            replaced = (now.st_ino, now.st_dev) != (mine.st_ino, mine.st_dev)
        except FileNotFoundError:
            replaced = True
        if replaced:
            self.file.close()
            self.file = open(self.path, "a")
        self.file.write(line)
        self.file.flush()
        os.fsync(self.file.fileno())
        return replaced

    def close(self) -> None:
        self.file.close()


def _keys(arm: ArmSpec, seeds: list[int]) -> set[tuple[str, str, str, int]]:
    return {(arm.scenario, arm.label, arm.config_hash, s) for s in seeds}


def _inline(arm: ArmSpec, entry: dict) -> tuple:
    """The fields of ``arm``'s records that differ from its ``arms.json`` entry (made by another label's
    spelling of the same config, or before the seeding changed): those a record must repeat."""
    mine = arm.entry()
    return tuple((key, mine[key]) for key in ("overrides", "seeding") if entry.get(key) != mine[key])


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


__all__ = ["ArmSpec", "DryRun", "EvaluationError", "Job", "evaluate", "latest_records", "read_records", "resolve_arms"]
