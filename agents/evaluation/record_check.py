"""What a record of ``episodes.jsonl`` and an entry of ``arms.json`` must be for a reader to take it: every field a
reader uses by its type, finiteness and range, its names printable, its nesting and its line bounded
(``docs/evaluation.md``). A folder is input from anyone (``docs/security.md``): whatever fails is skipped by every
reader with one warning (:mod:`bimp.agents.evaluation.records`), never a traceback.
"""

from __future__ import annotations

import json
import math
import re

from bimp.agents.evaluation.metrics import BINARY, METRICS, SCORE_METRICS
from bimp.agents.files import MAX_DEPTH, shown, too_deep

# What every reader relies on; a JSON line without them is not a record (and never a traceback).
REQUIRED = {"scenario": str, "policy": str, "seed": int, "status": str}
OUTCOMES = ("success_rate", "collision_rate", "offroad_rate")  # what every reader takes from an ok record's metrics
# Bounds on what a reader takes in: a shared folder is input from anyone (docs/security.md). The largest record bimp
# writes is a long per-step trace (about 0.1 MB over 300 steps); the deepest is 4 levels (trace, constraints, step).
MAX_LINE_BYTES = 16 << 20
MAX_MAGNITUDE = 1e9  # no metric comes near it; 1e308 would average to inf
# The metrics each reader takes as they are: an episode's outcome is 0 or 1, a share of steps or a score in [0, 1].
_UNIT = {"input_violation_rate", "rate_violation_rate", *SCORE_METRICS} - set(BINARY)
_NON_NEGATIVE = {"min_ttc_s", "rms_lateral_error_m", "rms_speed_error_mps", "max_abs_jerk", "plan_time_ms_p50",
                 "plan_time_ms_p95"}
_JSON_TYPES = {dict: "an object", list: "an array", str: "a string", int: "a number", float: "a number",
               bool: "a bool", type(None): "null"}


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _metric_problem(name: str, value: object) -> str | None:
    """Why ``value`` cannot be the metric ``name`` (None when it can; null is a metric that does not apply)."""
    if value is None:
        return None
    # The size first: an integer past float's range makes math.isfinite raise.
    if not _is_number(value) or abs(value) > MAX_MAGNITUDE or not math.isfinite(value):
        return f"metrics.{name} is {shown(value)}, not a finite number"
    if name in BINARY and value not in (0, 1):
        return f"metrics.{name} is {value!r}, not 0 or 1"
    if name in _UNIT and not 0 <= value <= 1:
        return f"metrics.{name} is {value!r}, not in [0, 1]"
    if name in _NON_NEGATIVE and value < 0:
        return f"metrics.{name} is {value!r}, below 0"
    return None


# Optional fields a reader uses, by their types: (type, None allowed).
_OPTIONAL = {"label": (str, False), "config_hash": (str, False), "config": (dict, False), "steps": (int, False),
             "overrides": (dict, False),
             "truncated": (bool, False), "git_commit": (str, True), "git_dirty": (bool, False), "machine": (str, True),
             "policy_info": (dict, True), "metrics": (dict, True)}


def _typed(value: object, kind: type, nullable: bool) -> bool:
    if value is None:
        return nullable
    return isinstance(value, kind) and (kind is bool or not isinstance(value, bool))  # JSON's true is no count


_COMMIT = re.compile(r"[0-9a-f]{7,40}")
MAX_NAME = 200  # characters of a scenario, policy or label name
MAX_MACHINE = 1000  # characters of a record's machine line (bimp verify prints it)


def _name_problem(key: str, name: str) -> str | None:
    """Why ``name`` cannot be a record's ``key`` (scenario, policy, label): names become file names and lines of
    output, so no control character (a newline would forge a line, an escape rewrite the terminal), no ``/``."""
    if len(name) > MAX_NAME or not name.isprintable() or "/" in name:
        return f"a record whose {key} is {shown(name)}, not a printable name without '/' of at most {MAX_NAME} chars"
    return None


def config_problem(config: object, where: str = "config") -> str | None:
    """Why ``config`` (a record's, or an ``arms.json`` entry's) is not one a reader can take: an object whose
    ``config`` part, where there is one, is an object, and whose ``files`` map names to sha256 strings."""
    if not isinstance(config, dict):
        return f"{where} is not an object"
    if "config" in config and not isinstance(config["config"], dict):
        return f"{where}.config is not an object"
    files = config.get("files", {})
    if not (isinstance(files, dict) and all(isinstance(v, str) for v in files.values())):
        return f"{where}.files is not a map of names to sha256 strings"
    return None


def record_problem(value: object) -> str | None:
    """Why a parsed JSON line is not an episode record (``None`` when it is one), naming the field: every field a
    reader uses is checked for its type, finiteness and range (docs/evaluation.md), so no reader meets a value it
    cannot take."""
    if not isinstance(value, dict):
        return f"{_JSON_TYPES.get(type(value), type(value).__name__)}, not a record"
    missing = [k for k in REQUIRED if k not in value]
    if missing:
        return f"a record without {', '.join(missing)}"
    wrong = [k for k, kind in REQUIRED.items() if not isinstance(value[k], kind) or isinstance(value[k], bool)]
    wrong += [k for k, (kind, nullable) in _OPTIONAL.items() if k in value and not _typed(value[k], kind, nullable)]
    if wrong:
        return f"a record whose {', '.join(wrong)} {'is' if len(wrong) == 1 else 'are'} of the wrong type"
    for key in ("scenario", "policy", "label"):
        problem = _name_problem(key, value[key]) if key in value else None
        if problem is not None:
            return problem
    machine = value.get("machine")
    if machine is not None and (len(machine) > MAX_MACHINE or not machine.isprintable()):
        return f"a record whose machine is {shown(machine)}, not a printable line of at most {MAX_MACHINE} chars"
    if value.get("git_commit") is not None and not _COMMIT.fullmatch(value["git_commit"]):
        return "a record whose git_commit is not a commit's hex digits"
    if "config" in value and config_problem(value["config"]) is not None:
        return f"a record whose {config_problem(value['config'])}"
    if value["seed"] < 0 or value.get("steps", 0) < 0:
        return f"a record whose {'seed' if value['seed'] < 0 else 'steps'} is below 0"
    if not isinstance((value.get("policy_info") or {}).get("fallback_steps", []), list):
        return "a record whose policy_info.fallback_steps is not a list"
    if too_deep(value):
        return f"a record nested deeper than {MAX_DEPTH} levels"
    metrics = value.get("metrics") or {}
    if value["status"] == "ok" and not all(k in metrics for k in OUTCOMES):
        return f"an ok record without metrics ({', '.join(OUTCOMES)})"
    for name in METRICS:
        problem = _metric_problem(name, metrics.get(name))
        if problem is not None:
            return f"a record whose {problem}"
    return None


def parse_record(line: bytes) -> tuple[dict | None, str | None]:
    """``(record, None)`` for a line that is an episode record, else ``(None, why not)``."""
    if len(line) > MAX_LINE_BYTES:
        return None, f"over {MAX_LINE_BYTES} bytes, the limit per line"
    try:
        value = json.loads(line)
    except ValueError:  # bad JSON or not UTF-8
        return None, "not JSON"
    except RecursionError:
        return None, f"nested deeper than {MAX_DEPTH} levels"
    problem = record_problem(value)
    return (value, None) if problem is None else (None, problem)


def entry_problem(entry: object) -> bool:
    """Whether an ``arms.json`` entry is not one a reader can take (its fields by their types, its config by
    :func:`config_problem`)."""
    return not (isinstance(entry, dict) and isinstance(entry.get("policy"), str)
                and _name_problem("policy", entry["policy"]) is None and config_problem(entry.get("config")) is None
                and all(isinstance(entry.get(k, {}), dict) for k in ("artifacts", "overrides")))


__all__ = ["MAX_DEPTH", "MAX_LINE_BYTES", "MAX_MAGNITUDE", "MAX_NAME", "OUTCOMES", "REQUIRED", "config_problem",
           "entry_problem", "parse_record", "record_problem", "shown", "too_deep"]
