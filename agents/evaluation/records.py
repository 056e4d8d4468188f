"""An evaluation folder: its episode records (``episodes.jsonl``), its lock, and its summary files.

Every command that reads or writes a folder goes through here: ``bimp evaluate`` appends records under the lock and
writes the summary; ``compare``, ``aggregate``, ``plot``, ``sweep`` and ``tune`` read the records. A line that is not
a record is reported once with its number and skipped, never a traceback (``docs/evaluation.md``).

An arm's resolved config is written once, in ``arms.json`` beside the records (:func:`read_arms`,
:func:`write_arms`), keyed by its ``config_hash``; a record names it by that hash (:func:`record_config`). Records
written before ``arms.json`` existed carry their config inline and are read as they are.
"""

from __future__ import annotations

import csv
import fcntl
import io
import json
import math
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.metrics import BINARY, METRICS, record_label
from bimp.agents.evaluation.record_check import (
    MAX_LINE_BYTES,
    OUTCOMES,
    REQUIRED,
    config_problem,
    entry_problem,
    parse_record,
    record_problem,
)
from bimp.agents.files import os_reason, read_bounded, read_json, write_atomic

EPISODES_FILE = "episodes.jsonl"
ARMS_FILE = "arms.json"
LOCK_FILE = ".lock"


def record_key(record: dict) -> tuple[str, str, str | None, int]:
    """``(scenario, label, config_hash, seed)`` of a record."""
    return record["scenario"], record_label(record), record.get("config_hash"), record["seed"]


# --- reading records ---------------------------------------------------------------------------------------
_reported: set[tuple[str, tuple[int, ...]]] = set()  # said once per process: evaluate reads a folder three times


def numbered_records(out: str | Path, data: bytes | None = None) -> list[tuple[int, dict]]:
    """``(line number, record)`` of every record in ``out/episodes.jsonl``, in file order. A line that is not a
    record (not JSON, not an object, lacking a key every reader needs: :func:`record_problem`) is skipped and
    reported on stderr with its number; the last line, when no newline ends it, may be a record cut by an
    interruption: kept when it parses as a whole record, else skipped silently. :class:`EvaluationError` when the
    file cannot be read. ``data``: the file's bytes as the caller read them (who then copies or rewrites lines by
    these numbers: a run appending in between must not shift them)."""
    path = Path(out) / EPISODES_FILE
    try:
        data = read_bounded(path) if data is None else data
    except FileNotFoundError:
        return []
    lines = data.split(b"\n")
    cut = lines.pop()  # b"" after a final newline, else the line an interruption cut
    records, skipped = [], []
    for number, line in enumerate(lines + [cut], start=1):
        if not line.strip():
            continue
        value, problem = parse_record(line)
        if problem is None:
            records.append((number, value))
        elif number <= len(lines):
            skipped.append(f"line {number} ({problem})")
    warn_skipped(path, skipped)
    return records


def warn_skipped(path: Path, skipped: list[str]) -> None:
    """One warning on stderr naming the lines of ``path`` that are not records and why (``skipped``: ``"line N
    (why)"`` each), once per process and content."""
    if skipped and (str(path), tuple(skipped)) not in _reported:
        _reported.add((str(path), tuple(skipped)))
        shown = "; ".join(skipped[:5]) + ("; ..." if len(skipped) > 5 else "")
        print(f"bimp: warning: {path}: skipped {len(skipped)} line(s) that are not episode records: {shown}",
              file=sys.stderr)


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


# --- arms.json: each arm's config, once ---------------------------------------------------------------------
def read_arms(out: str | Path) -> dict[str, dict]:
    """``{config_hash: {"policy", "config", "artifacts", "overrides", "seeding"}}`` of ``out/arms.json`` (``{}``
    where there is none). :class:`EvaluationError` naming the file when it cannot be read or is not such a map: a
    folder whose configs cannot be read cannot be resumed."""
    path = Path(out) / ARMS_FILE
    try:
        arms = read_json(path)
    except FileNotFoundError:
        return {}
    bad = ["(the file)"] if not isinstance(arms, dict) else [key for key, entry in arms.items()
                                                             if entry_problem(entry)]
    if bad:
        raise EvaluationError(f"{path}: not a map of config hash to {{policy, config, ...}}; bad entries: {bad[:5]}")
    return arms


def write_arms(out: str | Path, arms: dict[str, dict]) -> None:
    """``out/arms.json`` replaced atomically (a temporary file, then ``os.replace``): a reader or an interruption
    sees the old map or the new one, never half of one."""
    write_atomic(Path(out) / ARMS_FILE, json.dumps(finite(arms), indent=1, sort_keys=True) + "\n")


def record_config(record: dict, arms: dict[str, dict]) -> dict | None:
    """The resolved config a record was made with: its own (records from before ``arms.json``), else its arm's entry
    in ``arms`` by ``config_hash``; None when neither holds one."""
    if isinstance(record.get("config"), dict):
        return record["config"]
    entry = arms.get(record.get("config_hash"))
    return entry["config"] if entry is not None else None


# --- the lock ----------------------------------------------------------------------------------------------
@contextmanager
def folder_lock(out: Path, hint: str = "wait for it to end or choose another --out") -> Iterator[None]:
    """Hold ``out/.lock`` for the run; a second run into the same folder refuses at once, saying ``hint``. The lock
    is an ``flock``, so the kernel releases it when the holder dies: no stale locks."""
    try:  # NOFOLLOW: a .lock planted as a symlink must not truncate what it points to
        handle = os.fdopen(os.open(out / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NOCTTY, 0o666), "r+")
    except OSError as err:
        raise EvaluationError(f"cannot lock {out / LOCK_FILE}: {os_reason(err)}") from None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "another process"
        handle.close()
        raise EvaluationError(f"{out} is in use by another bimp run ({holder}); {hint}") from None
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        handle.flush()
        yield
    finally:
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


def episode_bytes(out: str | Path) -> bytes:
    """The bytes of ``out/episodes.jsonl`` (none yet: ``b""``), for a command that rewrites or copies its lines by
    number; :class:`EvaluationError` when it is not a file or cannot be read."""
    try:
        return read_bounded(Path(out) / EPISODES_FILE)
    except FileNotFoundError:
        return b""


@contextmanager
def unchanged_lock(out: Path, data: bytes, arms: dict[str, dict]) -> Iterator[None]:
    """Hold ``out``'s lock for a change planned on its records read as ``data`` and its ``arms``:
    :class:`EvaluationError` when either changed since (a run wrote in between), so nothing is written from a stale
    reading."""
    with folder_lock(out, hint="wait for it to end"):
        if episode_bytes(out) != data or read_arms(out) != arms:
            raise EvaluationError(f"{out} changed while it was read (a run writing into it?): try again")
        yield


# --- writing records and summaries ------------------------------------------------------------------------
def finite(value: Any) -> Any:
    """JSON has no inf: infinities and NaN become None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    return value


STATS = ("mean", "ci_low", "ci_high")  # the columns of every metric in summary.csv


def write_summary(summary: dict, out: Path) -> None:
    """``summary.json`` (every statistic), ``summary.csv`` (mean and interval columns), ``summary.md``, each written
    atomically (:func:`write_atomic`)."""
    write_atomic(out / "summary.json", json.dumps(finite(summary), indent=2))
    columns = ["policy", "scenario", "episodes", "errors"]
    with io.StringIO(newline="") as f:
        w = csv.writer(f)
        w.writerow(columns + ["error_seeds", "failed_seeds"] + [f"{m}_{s}" for m in METRICS for s in STATS]
                   + ["fallback_seeds", "fallback_steps"])
        for e in summary.values():
            w.writerow([e[c] for c in columns] + [" ".join(map(str, e["error_seeds"])),
                                                  " ".join(map(str, e["failed_seeds"]["success"]))]
                       + [e[m][s] for m in METRICS for s in STATS]
                       + [" ".join(map(str, e["fallback_seeds"])), e["fallback_steps"]])
        write_atomic(out / "summary.csv", f.getvalue())
    write_atomic(out / "summary.md", markdown_table(summary))


def format_stat(stat: dict | None) -> str:
    """``mean [low, high]`` of a summary statistic, 3 digits below 10, else 1; ``-`` where there is no value."""
    if not stat or stat.get("mean") is None:
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
        lines.append("| " + " | ".join(cells + [format_stat(e[m]) for m in METRICS]) + " |")
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


__all__ = ["ARMS_FILE", "EPISODES_FILE", "LOCK_FILE", "MAX_LINE_BYTES", "OUTCOMES", "REQUIRED", "config_problem",
           "episode_bytes", "finite", "folder_lock", "format_stat", "latest_records", "markdown_table",
           "numbered_records", "parse_record", "read_arms", "read_records", "record_config", "record_key",
           "record_label", "record_problem", "unchanged_lock", "warn_skipped", "write_arms", "write_summary"]
