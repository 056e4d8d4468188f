"""``bimp merge SRC [SRC ...] --into DIR``: copy evaluation folders' records into one, so that runs made apart (on two
machines, in two worktrees, a family rerun into a folder of its own) are read, resumed and ranked as one folder.

    bimp merge runs/a runs/b --into runs/all --dry-run                   # what would be copied; writes nothing
    bimp merge results/suite-more --into results/suite --label idm lane-keep --scenario dense-highway-hard

SRC come first (``--scenario`` and ``--label`` take every name after them). A record is copied when its scenario is
one of ``--scenario`` and its label one of ``--label`` (either left out: every one), as its line, byte for byte, with
its config's ``arms.json`` entry. What a merge will not do is mix two arms under one name: a label whose records on a
scenario were made with another config in DIR (or in an earlier SRC) is refused, naming it, and so is an ``arms.json``
entry that does not hash to its key (an edited config would vouch for records it did not make); then nothing is
written. A record whose episode DIR already holds (the same scenario, label, config and seed, with a result) is
skipped: a second merge copies nothing. Records made by different code stay what they are: their ``git_commit``
goes with them, and ``bimp leaderboard`` says when a row mixes versions.

DIR is created if needed and locked for the change (as a run locks it; the sources are only read); its records are
replaced in one step and then ``arms.json``, and its summary files are rewritten for the whole folder. Exit status 0,
or 2 on a bad request (then nothing is written).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

from bimp.agents.cli import EvaluationError
from bimp.agents.drop import matching
from bimp.agents.metrics import summarize
from bimp.agents.provenance import config_diff, config_hash
from bimp.agents.records import (
    EPISODES_FILE,
    folder_lock,
    latest_records,
    numbered_records,
    read_arms,
    read_records,
    record_key,
    record_label,
    write_arms,
    write_atomic,
    write_summary,
)


def merge(sources: list[str | Path], into: str | Path, scenarios: list[str] | None = None,
          labels: list[str] | None = None, dry_run: bool = False) -> tuple[Counter, Counter]:
    """Copy the records of ``scenarios`` x ``labels`` (None: every one) from each of ``sources`` into ``into``, with
    their ``arms.json`` entries; ``(copied, skipped)`` counts per ``(scenario, label)``, skipped being the episodes
    ``into`` already held. :class:`EvaluationError`, with nothing written, for a source that is not an evaluation
    folder or is ``into``, a name no source has, a label that would hold two configs on a scenario, or a config that
    is not the one its hash names."""
    into = Path(into)
    if not sources:
        raise EvaluationError("name at least one folder to copy from")
    target = into / EPISODES_FILE
    data = target.read_bytes() if target.is_file() else b""
    held, held_arms = numbered_records(into), read_arms(into)
    arms = dict(held_arms)
    rows = _row_configs(r for _, r in held)
    done = {record_key(r) for _, r in held if r["status"] == "ok"}
    present = {record_key(r) for _, r in held}
    lines, copied, skipped = [], Counter(), Counter()
    for source in map(Path, sources):
        if not (source / EPISODES_FILE).is_file():
            raise EvaluationError(f"{source} is not an evaluation folder (no {EPISODES_FILE})")
        if source.resolve() == into.resolve():
            raise EvaluationError(f"{source} is the folder merged into")
        source_lines = (source / EPISODES_FILE).read_bytes().split(b"\n")
        source_arms = read_arms(source)
        for number, r in matching(numbered_records(source), scenarios, labels, str(source)):
            key, row = record_key(r), (r["scenario"], record_label(r))
            if key in done or (r["status"] != "ok" and key in present):
                skipped[row] += 1
                continue
            if rows.setdefault(row, key[2]) != key[2]:
                raise EvaluationError(
                    f"{source} line {number}: {row[1]!r} on {row[0]} holds config {rows[row]} where it is merged "
                    f"and {key[2]} here: two arms under one name. Copy it under another label (rerun it with "
                    f"--label), or take the other out first (bimp drop)")
            if key[2] is not None and "config" not in r:
                arms[key[2]] = _entry(source, source_arms, key[2], arms.get(key[2]))
            lines.append(source_lines[number - 1])
            copied[row] += 1
            present.add(key)
            if r["status"] == "ok":
                done.add(key)
    if dry_run or not lines:
        return copied, skipped
    into.mkdir(parents=True, exist_ok=True)
    with folder_lock(into, hint="wait for it to end"):
        now = target.read_bytes() if target.is_file() else b""
        if now != data or read_arms(into) != held_arms:
            raise EvaluationError(f"{into} changed while it was read (a run writing into it?): try again")
        head = data if not data or data.endswith(b"\n") else data + b"\n"  # a cut last line stays a line of its own
        write_atomic(target, head + b"\n".join(lines) + b"\n")
        write_arms(into, arms)
        write_summary(summarize(latest_records(read_records(into))), into)
    return copied, skipped


def _row_configs(records) -> dict[tuple[str, str], str | None]:
    """``{(scenario, label): config_hash}`` of ``records`` (the first one seen: evaluate never writes two)."""
    rows: dict[tuple[str, str], str | None] = {}
    for r in records:
        rows.setdefault((r["scenario"], record_label(r)), r.get("config_hash"))
    return rows


def _entry(source: Path, source_arms: dict[str, dict], key: str, held: dict | None) -> dict:
    """The ``arms.json`` entry of ``key`` to copy from ``source``: refused when it is missing, does not hash to
    ``key``, or differs in its config from the entry the target ``held`` already."""
    entry = source_arms.get(key)
    if entry is None:
        raise EvaluationError(f"{source}: a record names config {key}, which its arms.json does not hold")
    if config_hash(entry["policy"], entry["config"]) != key:
        raise EvaluationError(f"{source}: the arms.json entry {key} does not hash to its key: it is not that config")
    if held is not None and held["config"] != entry["config"]:
        raise EvaluationError(f"{source}: the arms.json entry {key} differs from the merged folder's "
                              f"({'; '.join(config_diff(held['config'], entry['config'])[:4])})")
    return held if held is not None else entry


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="bimp merge", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        usage="bimp merge SRC [SRC ...] --into DIR [--scenario S [S ...]] [--label L [L ...]] [--dry-run]")
    parser.add_argument("sources", nargs="+", metavar="SRC", help="evaluation folders to copy records from")
    parser.add_argument("--into", required=True, metavar="DIR", help="the folder they are copied into")
    parser.add_argument("--scenario", nargs="+", default=None, metavar="S", help="the scenarios whose records go")
    parser.add_argument("--label", nargs="+", default=None, metavar="L", help="the labels whose records go")
    parser.add_argument("--dry-run", action="store_true", help="print what would be copied; write nothing")
    args = parser.parse_args(argv)
    try:
        copied, skipped = merge(args.sources, args.into, args.scenario, args.label, dry_run=args.dry_run)
    except EvaluationError as err:
        print(f"bimp merge: error: {err}", file=sys.stderr)
        return 2
    verb = "would copy" if args.dry_run else "copied"
    for scenario, label in sorted(set(copied) | set(skipped)):
        print(f"{verb} {copied[scenario, label]:>5} record(s) of {label} on {scenario}"
              + (f" ({skipped[scenario, label]} already there)" if skipped[scenario, label] else ""))
    print(f"{args.into}: {verb} {sum(copied.values())} record(s), {sum(skipped.values())} already there")
    return 0
