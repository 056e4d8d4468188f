"""Evaluation folders written by older code, turned into ones the current code resumes (the ``bimp migrate`` command:
:mod:`bimp.agents.commands.migrate`).

Per arm (the records sharing one config), the old config is brought to today's (``docs/evaluation.md``):

- the config shape of issue 25: EnKTS/EnKS's problem keys move under ``config.problem``; MPPI/NMPC's ``tuning``
  becomes ``config.problem``, with ``horizon`` (when not null), NMPC's ``nu`` and ``bound_tightening`` (as
  ``problem.barrier.bound_margin``) moved into it; the ``--set`` overrides the same (``horizon`` ->
  ``problem.horizon``, ...). Fields added since, missing from an old config, take their neutral value
  (:func:`bimp.configs.added_field`: the value that reproduces the behaviour from before they existed, left out of
  the hash); a field declared without one (NMPC's ``slack_penalty``: the first wave's NMPC had hard constraints) is
  not filled, so such an arm no longer resolves to a current config and is left in place, reported;
- planners: their weights by content, ``files = {"problem.dynamics": sha256}`` (the shipped ``mlp.pt``, unchanged
  since before the first record: ``SHIPPED_WEIGHTS``); an arm that named another weights file is left in place;
- PPO/SAC: the absolute ``model_path`` is dropped (``model_sha256`` names the file), and the shipped file with that
  sha256 goes into the arm's ``artifacts`` as ``bimp:agents/models/NAME``;
- the hash recomputed with :func:`bimp.agents.evaluation.provenance.config_hash`, and the config moved into
  ``arms.json`` (records keep their labels, seeds, metrics (but a gated score, below) and code version; only ``config``,
  ``overrides`` and ``seeding`` go, to the arm's entry).

Per record, whatever its arm (migrated or left in place): the score's goal gate (``docs/suite.md``). A record that ran
to its time limit without its goal (:func:`bimp.agents.evaluation.metrics.record_missed_goal`) and was scored before the
gate existed gets the score 0, its parts as they were: exact, since the gate multiplies what was recorded.

Each migrated arm is checked, not assumed: its policy is rebuilt from the migrated config on its scenario's env, and
its resolved config must be the migrated one (what a resume will compare). A folder where an arm fails (or a record
carries no config at all) is reported naming the arm and left as it is; nothing is half written: the new files are
written beside the old and renamed over them. MPPI arms made before commit ``MPPI_SEEDING`` (its seeding changed
there, its config did not) are not results of the current code: they are left in place, inline, and reported. A
second migration changes nothing. ``--drop-traces``: the migrated records lose their per-step traces (for folders no
figure is drawn from: a trace is most of a record). Exit status 0 when every folder is migrated (or was already), 1
when one is left as it was, 2 for a DIR that is not an evaluation folder.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import re
import subprocess
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import yaml

from bimp import envs
from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.metrics import record_label, record_missed_goal
from bimp.agents.evaluation.provenance import (
    REPO_ROOT,
    config_diff,
    config_hash,
    neutral_config,
    plain,
    resolved_config,
)
from bimp.agents.evaluation.records import (
    EPISODES_FILE,
    episode_bytes,
    finite,
    folder_lock,
    parse_record,
    read_arms,
    record_config,
    warn_skipped,
    write_arms,
)
from bimp.agents.evaluation.verification import VERIFIED_FILE, arm_key, read_verified
from bimp.agents.files import write_atomic
from bimp.agents.registry import POLICIES, load, make_policy, policy_spec
from bimp.configs import file_sha256, is_old_tuned, read_yaml, renamed_key, trust_switch, tuned_files, tuning_path
from bimp.planners.problem import RENAMED, ProblemConfig

# sha256 of planners/weights/mlp.pt as committed at ad50d20 and never changed since (git log): every planner record
# that names "mlp" was made with it.
SHIPPED_WEIGHTS = "81870b0390f5823b577ee618768fc82a51a2f4a32bd8e1518234d80306c54e52"
MPPI_SEEDING = "667c57c"  # MPPI's generator seeding changed here; its config hash did not
MODEL_DIR = REPO_ROOT / "agents" / "models"
PROBLEM_KEYS = tuple(f.name for f in dataclasses.fields(ProblemConfig))
MOVED = ("config", "overrides", "seeding")  # what a record hands to its arm's entry in arms.json
# A record's per-step trace (--traces): only figures read it. "route": the drawn road where an env has no closed form
# (issue 26), written in place of "road".
TRACE_FIELDS = ("trace", "road", "route", "bounds")


class NotReproduced(ValueError):
    """An arm the current code does not reproduce (it resolves to another config): not migrated, left in place."""


class MigrationError(ValueError):
    """An arm whose records cannot be migrated exactly (the message says why)."""



# --- one config ----------------------------------------------------------------------------------------------
def new_shape(policy: str, config: dict) -> dict:
    """An old record's config (``{"config", "tuning"?, "scenario"}``) in today's shape (the module doc); a config
    already in it comes back equal."""
    config = copy.deepcopy(config)
    own = config.get("config")
    if not isinstance(own, dict):
        raise MigrationError("the config has no 'config' part")
    if "tuning" in config:  # MPPI, NMPC: the separate problem becomes config.problem
        problem = config.pop("tuning")
        horizon = own.pop("horizon", None)
        if horizon is not None:  # null meant the problem's own
            problem["horizon"] = horizon
        if "nu" in own:
            problem["nu"] = own.pop("nu")
        if "bound_tightening" in own:
            problem.setdefault("barrier", {})["bound_margin"] = own.pop("bound_tightening")
        own["problem"] = problem
    elif "problem" not in own and "horizon" in own:  # EnKTS, EnKS: the problem's keys at the top
        own["problem"] = {key: own.pop(key) for key in PROBLEM_KEYS if key in own}
    if "model_sha256" in own:  # PPO, SAC: the file is its sha256; where it lay is no part of the config
        own.pop("model_path", None)
    own = renamed(own)
    config["config"] = _with_neutral(own, neutral_config(policy))
    dynamics = own.get("problem", {}).get("dynamics") if isinstance(own.get("problem"), dict) else None
    if dynamics is not None and "files" not in config:  # a planner: its weights by content (issue 28)
        if dynamics == "mlp":
            # The shipped weights have not changed since they were first committed (ad50d20), before any record.
            config["files"] = {"problem.dynamics": SHIPPED_WEIGHTS}
        elif dynamics != "bicycle":
            raise NotReproduced(f"its weights {dynamics!r} cannot be told by content now")
    stray = sorted(set(config) - {"config", "files", "road", "scenario"})
    if stray:
        raise MigrationError(f"the config holds {stray}, which no current config has")
    return config


def renamed(config: dict) -> dict:
    """``config`` (a planner's factory kwargs, nested) with each setting :data:`RENAMED` names under its new name."""
    config = copy.deepcopy(config)
    for old, new in RENAMED.items():
        *where, key = old.split(".")
        node = functools.reduce(lambda d, k: d.get(k) if isinstance(d, dict) else None, where, config)
        if isinstance(node, dict) and key in node:
            value = node.pop(key)
            *there, name = new.split(".")
            functools.reduce(lambda d, k: d.setdefault(k, {}), there, config)[name] = value
    return config


def _with_neutral(value: dict, neutral: dict) -> dict:
    """``value`` with the fields it lacks that were added since with a neutral value, at that value."""
    out = dict(value)
    for key, mark in neutral.items():
        if key not in out:
            out[key] = copy.deepcopy(mark)
        elif isinstance(out[key], dict) and isinstance(mark, dict):
            out[key] = _with_neutral(out[key], mark)
    return out


def new_overrides(old_config: dict, overrides: dict) -> dict:
    """The ``--set`` overrides of an arm, renamed as :func:`new_shape` moves the keys they set."""
    tuning, flat = "tuning" in old_config, "horizon" in old_config.get("config", {}) and "tuning" not in old_config
    out = {}
    for key, value in overrides.items():
        head = re.split(r"[.\[]", key, maxsplit=1)[0]
        if tuning and key == "horizon":
            if value is None:  # the problem's own horizon: nothing to set
                continue
            key = "problem.horizon"
        elif tuning and key == "nu":
            key = "problem.nu"
        elif tuning and key == "bound_tightening":
            key = "problem.barrier.bound_margin"
        elif flat and head in PROBLEM_KEYS:
            key = f"problem.{key}"
        out[renamed_key(key, RENAMED) or key] = value
    return out


@functools.lru_cache(maxsize=None)
def shipped_models() -> dict[str, str]:
    """``{sha256: file name}`` of the models under ``agents/models/``."""
    return {file_sha256(path): path.name for path in sorted(MODEL_DIR.glob("*.zip"))}


@functools.lru_cache(maxsize=None)
def _env(scenario: str) -> gym.Env:
    return gym.make(envs.env_id(scenario))


def rebuild(policy: str, scenario: str, config: dict, given: str | None = None) -> tuple[dict, str | None]:
    """``(artifacts, note)`` of ``policy`` rebuilt on ``scenario`` from the migrated ``config``;
    :class:`MigrationError` unless its resolved config is ``config``'s (what a resume compares). A model is the
    shipped file with the config's sha256; where none ships (a model since replaced, a user's own file: ``given``, the
    old ``model_path``), the policy is rebuilt on a shipped model of the same algorithm and must resolve to the same
    fields but the sha256: the config names the file by content, so it stays exact, and ``note`` says so."""
    own, note = config["config"], None
    switch = trust_switch(config)
    if switch is not None:  # a trust switch comes from the command line or the call, never from a file
        raise MigrationError(f"its config sets {switch}, which no file may switch on (docs/security.md)")
    if policy in ("ppo", "sac") and not isinstance(own.get("model_sha256"), str):
        raise MigrationError("its model is not named by content (no model_sha256): a path in a folder is not loaded")
    kwargs = _infinities(own, _default_config(policy))  # a record holds infinities as null
    if "model_sha256" in own:
        name = shipped_models().get(own["model_sha256"])
        if name is None:
            same = sorted(n for n in shipped_models().values() if n.startswith(f"{own.get('algo')}_{scenario}_"))
            name = same[0] if same else None
            if name is None:
                raise MigrationError(f"no shipped {own.get('algo')} model to check its config against")
            note = (f"its model (sha256 {own['model_sha256'][:12]}...) is no shipped file: config checked on "
                    f"{name}; artifacts name the file it was made with")
        kwargs = {"model": str(MODEL_DIR / name)}
    try:
        built = make_policy(policy, _env(scenario), **kwargs)
        resolved = plain(resolved_config(built))
    except (ValueError, TypeError, OSError, ImportError, AttributeError) as err:
        raise MigrationError(f"the current code cannot build it: {type(err).__name__}: {err}") from None
    artifacts = getattr(built, "artifacts", {})
    if note is not None:
        resolved["config"]["model_sha256"] = own["model_sha256"]
        # Only the name: an absolute path would tie the folder to the machine it was made on.
        artifacts = {"model": Path(given).name if given and Path(given).is_absolute() else given}
    expected = plain({"config": own, **{k: config[k] for k in ("files", "road") if k in config}})
    if resolved != expected:
        raise NotReproduced("rebuilt, it resolves otherwise: " + "; ".join(config_diff(expected, resolved)[:4]))
    return artifacts, note


def _default_config(policy: str) -> object:
    """The policy's config class at its defaults (None when its spec names none)."""
    reference = policy_spec(policy).config_class
    return None if reference is None else load(reference)()


def _infinities(value: object, default: object) -> object:
    """``value`` with each null where ``default`` (the config class's instance, walked alongside) holds a float
    turned into ``inf``: JSON has no inf, so a record wrote ``nu: inf`` as ``null``."""
    if isinstance(value, dict):
        def child(key: str) -> object:
            return default.get(key) if isinstance(default, dict) else getattr(default, key, None)
        return {key: _infinities(item, child(key)) for key, item in value.items()}
    return math.inf if value is None and isinstance(default, float) else value


# --- one config file -----------------------------------------------------------------------------------------
def migrate_config_file(path: str | Path, dry_run: bool = False) -> str:
    """Bring the YAML config ``path`` to today's shape: a tuned config in the old envelope (``policy``, ``tuning``
    and ``config`` around the config, :func:`bimp.configs.is_old_tuned`) split into the config alone and its tuning
    beside it (:func:`bimp.configs.tuned_files`), and each renamed setting (:data:`RENAMED`) under its new name. The
    values are kept as they were, so a policy loads the same config from the file. A plain file that needs a rename
    is written again without its comments. Returns a line saying what changed; ``MigrationError`` for a file that is
    not a YAML mapping."""
    path = Path(path)
    try:
        doc = read_yaml(path)
    except ValueError as err:
        raise MigrationError(str(err)) from None
    if not isinstance(doc, dict):
        raise MigrationError(f"{path}: not a config (a YAML mapping)")
    old = is_old_tuned(doc)
    config = doc["config"] if old else doc
    new = renamed(config)
    if not old and new == config:
        return f"{path}: nothing to change"
    what = ("split: the config alone, its tuning in " + tuning_path(path).name) if old else "settings renamed"
    if not dry_run:
        files = tuned_files(path, new, doc["policy"], doc.get("tuning")) if old else \
            {path: yaml.safe_dump(new, sort_keys=False, default_flow_style=None, width=110)}
        for file, text in files.items():
            write_atomic(file, text)
    return f"{path}: {'would be ' if dry_run else ''}{what}"


# --- one folder ----------------------------------------------------------------------------------------------
@dataclass
class FolderReport:
    """What :func:`migrate_folder` did (or would do) to one folder. ``problem``: why it was left as it was."""

    folder: Path
    records: int = 0
    changed: int = 0
    gated: int = 0  # scores the goal gate zeroed
    arms: int = 0
    left: list[str] = field(default_factory=list)  # arms left in place (inline, old hash), and why
    notes: list[str] = field(default_factory=list)  # arms migrated with something to know
    problem: str | None = None
    bytes_before: int = 0
    bytes_after: int = 0

    def line(self) -> str:
        if self.problem:
            return f"{self.folder}: not migrated: {self.problem}"
        what = f"{self.changed} of {self.records} record(s) rewritten" if self.changed else "nothing to change"
        what += f" ({self.gated} score(s) zeroed by the goal gate)" if self.gated else ""
        left = "".join(f"\n  left in place: {reason}" for reason in self.left)
        left += "".join(f"\n  note: {note}" for note in self.notes)
        return (f"{self.folder}: {what}; {self.arms} arm(s) in arms.json; {self.bytes_before / 1e6:.2f} MB -> "
                f"{self.bytes_after / 1e6:.2f} MB{left}")


@functools.lru_cache(maxsize=None)
def made_after_mppi_seeding(commit: str | None) -> bool:
    """Whether ``commit`` holds MPPI's current seeding (None, or a commit this checkout lacks: not proven)."""
    if not commit:
        return False
    run = subprocess.run(["git", "merge-base", "--is-ancestor", MPPI_SEEDING, commit], cwd=REPO_ROOT,
                         capture_output=True)
    return run.returncode == 0


def migrate_folder(folder: str | Path, dry_run: bool = False, drop_traces: bool = False,
                   trusted: Iterable[str] = ()) -> FolderReport:
    """Migrate ``folder`` (the module doc); with ``dry_run`` only report; ``drop_traces``: the migrated records lose
    their per-step traces too (a folder no figure is drawn from). Never raises for a folder that cannot be
    migrated: the report's ``problem`` says why, and the folder is untouched.

    A folder is data: an arm is rebuilt only from the policy table, never from a ``module:factory`` name a record or
    ``arms.json`` gives (that would import and call whatever the file names), unless the caller names that policy in
    ``trusted`` (``--trust-policy``); nor does a config in the folder switch on ``trust_model``."""
    folder = Path(folder)
    path = folder / EPISODES_FILE
    report = FolderReport(folder)
    try:
        data = episode_bytes(folder)
        old_entries = read_arms(folder)
    except EvaluationError as err:
        report.problem = str(err)
        return report
    report.bytes_before = report.bytes_after = len(data) + _size(folder / "arms.json")
    lines = data.split(b"\n")
    if lines[-1] == b"":
        lines.pop()
    parsed: list[dict | None] = []
    skipped = []
    for number, line in enumerate(lines, start=1):  # a line that is not a record is kept as it is, named
        value, problem = parse_record(line) if line.strip() else (None, None)
        parsed.append(value)
        if problem is not None:
            skipped.append(f"line {number} ({problem})")
    warn_skipped(path, skipped)
    report.records = sum(r is not None for r in parsed)
    gated = [n for n, r in enumerate(parsed, start=1) if r is not None and _gate_goal(r)]
    report.gated = len(gated)

    # The arms: records sharing a policy and an old config (inline, or their arms.json entry).
    arms: dict[tuple[str, str], list[int]] = {}
    for number, r in enumerate(parsed, start=1):
        if r is None:
            continue
        config = record_config(r, old_entries)
        if config is None:
            report.problem = (f"line {number} ({record_label(r)} on {r['scenario']}) carries no config "
                              "(made before records carried one): nothing to migrate it from")
            return report
        arms.setdefault((r["policy"], json.dumps(config, sort_keys=True)), []).append(number)

    new_lines, entries, referenced = list(lines), {}, set()
    rehashed: dict[tuple[str, str | None], str] = {}  # (scenario, old hash) -> new hash
    for (policy, old_json), numbers in arms.items():
        first = parsed[numbers[0] - 1]
        name = f"{record_label(first)!r} ({policy}) on {first['scenario']}, hash {first.get('config_hash')}"
        if policy not in POLICIES and policy not in trusted:
            report.problem = (f"arm {name}: its policy is not in the policy table, and a folder never names code for "
                              f"bimp to import; if you trust it, name it yourself: --trust-policy {policy}")
            return report
        if policy == "mppi" and not all(made_after_mppi_seeding(parsed[n - 1].get("git_commit")) for n in numbers):
            report.left.append(f"{name}: {len(numbers)} record(s) made before {MPPI_SEEDING} (MPPI's seeding "
                               "changed there): rerun them")
            referenced.add(first.get("config_hash"))
            continue
        old = json.loads(old_json)
        source = old_entries.get(first.get("config_hash"), {})  # the arm's entry, if already migrated
        try:
            given = (old.get("config") or {}).get("model_path") or source.get("artifacts", {}).get("model")
            config = new_shape(policy, old)
            artifacts, note = rebuild(policy, first["scenario"], config, given)
        except NotReproduced as err:  # made by code that is gone: history, kept as it was
            report.left.append(f"{name}: {len(numbers)} record(s) the current code does not reproduce ({err})")
            referenced.add(first.get("config_hash"))
            continue
        except MigrationError as err:
            report.problem = f"arm {name}: {err}"
            return report
        except (KeyError, TypeError, AttributeError, ValueError) as err:  # a config of no shape bimp ever wrote
            report.problem = f"arm {name}: its config cannot be read ({type(err).__name__}: {err})"
            return report
        key = config_hash(policy, config)  # the current hash, whatever it leaves out: never copied
        rehashed[(first["scenario"], first.get("config_hash"))] = key
        if note:
            report.notes.append(f"{name}: {note}")
        for number in numbers:
            r = parsed[number - 1]
            overrides = new_overrides(old, r.get("overrides", source.get("overrides", {})))
            seeding = r.get("seeding", source.get("seeding"))
            entry = entries.setdefault(key, finite({"policy": policy, "config": config, "artifacts": artifacts,
                                                    "overrides": overrides, "seeding": seeding}))
            record = {k: v for k, v in r.items() if k not in MOVED and not (drop_traces and k in TRACE_FIELDS)}
            record["config_hash"] = key
            # A record repeats what differs from its arm's entry (another label's spelling of the same config).
            record.update({k: v for k, v in (("overrides", overrides), ("seeding", seeding)) if entry[k] != v})
            new_lines[number - 1] = json.dumps(finite(record)).encode()
    for number in gated:  # a record of an arm left in place keeps its config, not its old score
        if new_lines[number - 1] == lines[number - 1]:
            new_lines[number - 1] = json.dumps(finite(parsed[number - 1])).encode()
    final = {**{k: v for k, v in old_entries.items() if k in referenced}, **entries}
    new_data = b"".join(line + b"\n" for line in new_lines)
    report.arms = len(final)
    report.changed = sum(a != b for a, b in zip(lines, new_lines))
    report.bytes_after = len(new_data) + len(_arms_text(final))
    if dry_run or (new_data == data and final == old_entries):
        return report
    try:
        verified = read_verified(folder)
        carried = _rehashed_verified(verified, rehashed)
        with folder_lock(folder, hint="wait for it to end"):
            if episode_bytes(folder) != data:
                report.problem = "the folder changed while it was migrated (a run writing into it?): try again"
                return report
            # arms.json first, the old entries kept: a reader between the two renames finds every hash it looks up.
            write_arms(folder, {**old_entries, **final})
            write_atomic(path, new_data)
            write_arms(folder, final)
            if carried != verified:
                write_atomic(folder / VERIFIED_FILE, json.dumps(carried, indent=1, sort_keys=True) + "\n")
    except EvaluationError as err:  # locked by a run, or a write refused (a full disk): one line, not a traceback
        report.problem = str(err)
    return report


def _rehashed_verified(verified: dict, rehashed: dict) -> dict:
    """``verified`` (a folder's ``verified.json``) with each arm's key under its new config hash: a verification
    is of the config's content, which a migration keeps (it checks the migrated config resolves the same)."""
    out = {}
    for key, value in verified.items():
        scenario, label, old = key.split("|", 2)
        new = rehashed.get((scenario, old))
        out[arm_key(scenario, label, new) if new else key] = value
    return out


def _gate_goal(record: dict) -> bool:
    """Zero the score of ``record`` (in place) where it missed its goal and was scored before the goal gate;
    whether it changed."""
    metrics = record.get("metrics") or {}
    if not record_missed_goal(record) or metrics.get("score") in (None, 0.0):
        return False
    metrics["score"] = 0.0
    return True


def _arms_text(entries: dict) -> str:
    return json.dumps(finite(entries), indent=1, sort_keys=True) + "\n" if entries else ""


def _size(path: Path) -> int:
    return path.stat().st_size if path.exists() else 0


__all__ = ["FolderReport", "MigrationError", "migrate_folder", "new_overrides", "new_shape", "rebuild"]
