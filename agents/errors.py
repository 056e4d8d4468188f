"""What both the ``bimp`` commands and the library raise and check: :class:`EvaluationError` and the checks of the
values a command or a call is given (overrides, labels, an output folder). No argparse here: the library imports
this module, never the CLI."""

from __future__ import annotations

import os
from pathlib import Path


class EvaluationError(ValueError):
    """A request that cannot be run as given (unknown name, bad override, a label's config conflict, an unusable
    folder): every command reports it in one line and exits with status 2, before anything is written."""


def parse_overrides(pairs: list[str]) -> dict:
    """``POLICY.KEY=VALUE`` (VALUE read as YAML) -> ``{policy: {key: value}}``; EvaluationError naming the pair."""
    import yaml  # heavy for `bimp --help`, which never parses a value

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
