"""What ``bimp verify`` found, as the readers use it: an arm rerun on a sample of its seeds at some code and found the
same is taken as made by that code, and so by the current code when the two do not differ (``docs/evaluation.md``).

``verified.json`` in an evaluation folder maps ``"SCENARIO|LABEL|CONFIG_HASH"`` to ``{"commit", "seeds", "outcome",
"differences"}``, the outcome ``same``, ``drift`` or ``different`` (:func:`bimp.agents.evaluation.verify.verify_folder`
writes it; only ``same`` makes an arm the current code's). :func:`as_current` gives ``compare``,
``aggregate`` and ``leaderboard`` the records of the arms verified at code the current code equals with the current
commit as their version, so a folder made over many commits and verified since is one code version to them.
"""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.metrics import code_version, record_label
from bimp.agents.evaluation.provenance import CODE_PATHS, REPO_ROOT
from bimp.agents.evaluation.provenance import code_version as running_code
from bimp.agents.files import read_json

VERIFIED_FILE = "verified.json"


def arm_key(scenario: str, label: str, config_hash: str | None) -> str:
    return f"{scenario}|{label}|{config_hash}"


def read_verified(folder: str | Path) -> dict[str, dict]:
    """``folder/verified.json`` (``{}`` where there is none); :class:`EvaluationError` naming the file when it is
    not such a map."""
    path = Path(folder) / VERIFIED_FILE
    try:
        verified = read_json(path)
    except FileNotFoundError:
        return {}
    good = isinstance(verified, dict) and all(
        isinstance(v, dict) and isinstance(v.get("commit"), str) and v.get("outcome") in ("same", "drift", "different")
        for v in verified.values())
    if not good:
        raise EvaluationError(f"{path}: not a map of arms to what bimp verify found")
    return verified


@functools.lru_cache(maxsize=None)
def same_code(commit: str, other: str) -> bool:
    """Whether the code (``CODE_PATHS``) at ``commit`` is the code at ``other`` (False where git cannot tell)."""
    if commit == other:
        return True
    try:
        run = subprocess.run(["git", "diff", "--quiet", commit, other, "--", *CODE_PATHS], cwd=REPO_ROOT,
                             capture_output=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return False
    return run.returncode == 0


def current_commit() -> str | None:
    """The commit of the running code, None when it has uncommitted changes (nothing is verified against those)."""
    version = running_code()
    return version["git_commit"] if version["git_commit"] and not version["git_dirty"] else None


def as_current(folder: str | Path, records: list[dict]) -> list[dict]:
    """``records`` (of ``folder``) with the arms ``verified.json`` found the same at code the current code equals
    stamped with the current commit (``verified_from``: the commit they were made at): only the records of the code
versions the rerun checked, and only where the verifying checkout had no uncommitted changes; the rest as they
are."""
    verified, now = read_verified(folder), current_commit()
    if not verified or now is None:
        return records
    # Found the same, at committed code the current code equals: the records of the code versions it checked.
    current = {key: set(v.get("versions") or ()) for key, v in verified.items()
               if v["outcome"] == "same" and v.get("dirty") is False and same_code(v["commit"], now)}
    return [{**r, "git_commit": now, "git_dirty": False, "verified_from": r.get("git_commit")}
            if code_version(r) in current.get(arm_key(r["scenario"], record_label(r), r.get("config_hash")), ())
            else r for r in records]


__all__ = ["VERIFIED_FILE", "arm_key", "as_current", "current_commit", "read_verified", "same_code"]
