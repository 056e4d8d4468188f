"""What produced an episode: the policy's fully resolved config, its hash, and the code version.

Every episode record carries these so a result can never be attributed to the wrong configuration:
resume in :mod:`bimp.agents.evaluation.evaluate` matches on ``(scenario, label, config_hash, seed)``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

from bimp.agents.evaluation.records import finite
from bimp.agents.registry import load, policy_spec
from bimp.configs import neutral_values

REPO_ROOT = Path(__file__).resolve().parents[2]  # the checkout: agents/evaluation/provenance.py


def resolved_config(policy) -> dict:
    """The policy's complete configuration as plain JSON-able data, ``{"config": ...}``: its ``config``, a
    dataclass (a planner's holds its ``problem``) or a dict, and ``"files"``: the files it loaded that its config
    names only by name or path, by content, keyed by that config key (a planner's ``{"problem.dynamics": sha256}``
    of its weights: new weights at the same path are another config, the same weights elsewhere the same), when it
    has any; and ``"road"``: what the env's road changes in it (a planner's ``{"sigma_du": ..., "track_course": true}``
    on a road whose steering bound is not the paper's: :func:`bimp.planners.problem.road_changes`), when it changes
    anything. ``TypeError`` for a policy that exposes no config: its results could
    not be attributed."""
    config = getattr(policy, "config", None)
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = dataclasses.asdict(config)
    if not isinstance(config, dict):
        raise TypeError(f"{type(policy).__name__} exposes no `config` (a dataclass or dict): "
                        "evaluation cannot record what produced its episodes")
    files, road = getattr(policy, "files", None), getattr(policy, "road", None)
    resolved = {"config": config, **({"files": dict(files)} if files else {}), **({"road": dict(road)} if road else {})}
    return json.loads(json.dumps(resolved, default=str))  # tuples -> lists, paths -> str: as recorded


def plain(value: Any) -> Any:
    """``value`` as a record holds it: JSON data (tuples as lists, paths as strings), infinities and NaN as None
    (:func:`bimp.agents.evaluation.records.finite`: JSON has no inf)."""
    return finite(json.loads(json.dumps(value, default=str)))


@functools.lru_cache(maxsize=None)
def _neutral(policy_name: str, by_road: bool = False) -> str:
    # JSON text, so that the cache hands out no mutable dict.
    try:
        reference = policy_spec(policy_name).config_class
    except ValueError:  # not a policy: a hash of something else (a tuning study's space, say)
        return "{}"
    return "{}" if reference is None else json.dumps(plain(neutral_values(load(reference), by_road)))


def neutral_config(policy_name: str) -> dict:
    """``{field: neutral value}`` of the fields the policy's config class declares with
    :func:`bimp.configs.added_field` (nested configs nested), as a record holds them; ``{}`` when none."""
    return json.loads(_neutral(policy_name))


def without_neutral(value: dict, neutral: dict) -> dict:
    """``value`` without the fields at a neutral value (``neutral``: :func:`bimp.configs.neutral_values` with
    ``by_road``, a list of the values per field; nested mappings key by key)."""
    out = {}
    for key, item in value.items():
        mark = neutral.get(key, _NONE)
        if isinstance(mark, list) and item in mark:
            continue
        out[key] = without_neutral(item, mark) if isinstance(item, dict) and isinstance(mark, dict) else item
    return out


_NONE = object()  # no neutral value declared


def _without_key(value: Any, path: list[str]) -> Any:
    """``value`` (nested mappings) without the entry at the dotted ``path``."""
    if not isinstance(value, dict) or path[0] not in value:
        return value
    if len(path) == 1:
        return {k: v for k, v in value.items() if k != path[0]}
    return {**value, path[0]: _without_key(value[path[0]], path[1:])}


def config_hash(policy_name: str, config: dict) -> str:
    """16 hex digits of SHA-256 over the policy name and the config, canonical JSON as a record holds it
    (:func:`plain`: a record's own config hashes to its arm's), with every field of the policy's config
    (``config["config"]``) left out that is at its neutral value or at one of its ``by_road`` values
    (:func:`bimp.configs.added_field`: what those change on a road, the record's ``road`` holds), and every
    entry that names a file known by its content (``config["files"]``, keyed by the entry's dotted key) left out
    for that content: the same weights at two paths are one config, new weights at one path two.

    Leaving those out is what lets a config grow: a field added later, at the value that reproduces the behaviour
    from before it existed, leaves every hash unchanged, so old records keep resuming (``docs/evaluation.md``). Every
    other field is hashed, at its default or not: a field whose old behaviour no value reproduces changes the hash of
    every config, and the old records are refused instead of taken for the new behaviour's."""
    config = plain(config)
    neutral = json.loads(_neutral(policy_name, by_road=True))
    if neutral and isinstance(config.get("config"), dict):
        config = {**config, "config": without_neutral(config["config"], neutral)}
    for key in config.get("files") or {}:  # a file known by its content is hashed by it, not by its name or path
        config = {**config, "config": _without_key(config.get("config"), key.split("."))}
    blob = json.dumps({"policy": policy_name, "config": config}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def config_diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    """``key: old -> new`` for every leaf where two resolved configs differ (dotted keys)."""
    lines = []
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            lines += config_diff(va, vb, f"{prefix}{key}.")
        elif va != vb:
            lines.append(f"{prefix}{key}: {va!r} -> {vb!r}")
    return lines


# What makes a result: a change elsewhere (docs, the results folders a run writes into) does not make a run dirty.
CODE_PATHS = ("agents", "envs", "planners", "configs", "pyproject.toml")


def git_state(root: Path = REPO_ROOT) -> tuple[str | None, bool | None]:
    """``(commit, dirty)`` of the checkout at ``root``: dirty when a tracked file under ``CODE_PATHS`` differs
    from the commit; ``(None, None)`` when ``root`` is not the top of a git checkout (an installed wheel inside some
    other repository, a project's ``.venv`` say, must not record that repository's commit)."""
    try:
        run = functools.partial(subprocess.run, cwd=root, capture_output=True, text=True, timeout=10)
        top = run(["git", "rev-parse", "--show-toplevel"])
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != Path(root).resolve():
            return None, None
        head = run(["git", "rev-parse", "HEAD"])
        status = run(["git", "status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHS])
        return head.stdout.strip(), bool(status.stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return None, None


@functools.lru_cache(maxsize=1)
def code_version() -> dict:
    """``{"bimp_version", "git_commit", "git_dirty"}``; the git entries are None outside a git checkout."""
    try:
        version = metadata.version("bimp")
    except metadata.PackageNotFoundError:
        version = None
    commit, dirty = git_state()
    return {"bimp_version": version, "git_commit": commit, "git_dirty": dirty}


# The packages whose builds set an episode's floating point (XLA's, torch's and numpy's kernels) or its traffic.
MACHINE_PACKAGES = ("jax", "jaxlib", "numpy", "scipy", "torch", "highway-env", "gymnasium", "pytorch-mppi")


@functools.lru_cache(maxsize=1)
def machine() -> str:
    """The machine an episode ran on, as one line: the CPU's model, Python's and :data:`MACHINE_PACKAGES`'
    versions. A planner's closed loop amplifies float32 rounding, and the same code moves on another CPU or library
    build (MPPI on highway-v0, results seed 1000: 960 m on one machine, 850 m on another), so ``bimp verify`` names
    the machines beside a drift: a rerun on the recording's machine tells the code's changes from the machine's."""
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name")), cpu)
    except OSError:
        pass
    versions = []
    for name in MACHINE_PACKAGES:
        try:
            versions.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            pass
    return "; ".join([cpu, f"python {platform.python_version()}", *versions])


__all__ = ["CODE_PATHS", "code_version", "config_diff", "config_hash", "git_state", "machine", "neutral_config",
           "plain", "resolved_config", "without_neutral"]
