"""Evaluation folders' records copied into one, so that runs made apart (on two machines, in two worktrees, a family
rerun into a folder of its own) are read, resumed and ranked as one folder (the ``bimp merge`` command:
:mod:`bimp.agents.commands.merge`).

SRC come first (``--scenario`` and ``--label`` take every name after them). A record is copied when its scenario is
one of ``--scenario`` and its label one of ``--label`` (either left out: every one), as its line, byte for byte, with
its config's ``arms.json`` entry. What a merge will not do is mix two arms under one name: a label whose records on a
scenario were made with another config in DIR (or in an earlier SRC) is refused, naming it, and so is an ``arms.json``
entry that does not hash to its key (an edited config would vouch for records it did not make); then nothing is
written. So is a record without a config hash (older code: ``bimp migrate`` it first), and an entry DIR already
holds under the same hash but with another seeding or overrides (a record leaves those to its entry). An episode DIR
already holds (the same scenario, label, config and seed) is skipped, unless DIR holds it failed and the source has
its result: a second merge copies nothing. Records made by different code stay what they are: their
``git_commit`` goes with them, and ``bimp leaderboard`` says when a row mixes versions.

DIR is created if needed and locked for the change (as a run locks it; the sources are only read); its
``arms.json`` is written first, as a run writes a config before its first record, then its records in one step,
then its summary files, for the whole folder. A merge cut between ``arms.json`` and the records is mended by running
it again (the summary is rewritten by the next run that writes there). Exit status 0, or 2 on a bad request (then
nothing is written).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.drop import check_names, matching
from bimp.agents.evaluation.metrics import summarize
from bimp.agents.evaluation.provenance import config_hash
from bimp.agents.evaluation.records import (
    EPISODES_FILE,
    episode_bytes,
    latest_records,
    numbered_records,
    read_arms,
    read_records,
    record_key,
    record_label,
    unchanged_lock,
    write_arms,
    write_summary,
)
from bimp.agents.files import write_atomic


def merge(sources: list[str | Path], into: str | Path, scenarios: list[str] | None = None,
          labels: list[str] | None = None, dry_run: bool = False) -> tuple[Counter, Counter, list[str]]:
    """Copy the records of ``scenarios`` x ``labels`` (None: every one) from each of ``sources`` into ``into``, with
    their ``arms.json`` entries; ``(copied, skipped, added)``: counts per ``(scenario, label)``, skipped being the
    episodes ``into`` already held or an earlier source gave, and the config hashes added to ``arms.json``.
    :class:`EvaluationError`, with nothing written, for a source that is not an evaluation folder or is ``into``, a
    name no source has, a label that would hold two configs on a scenario, a record without a config hash, or a
    config that is not the one its hash names."""
    into = Path(into)
    if not sources:
        raise EvaluationError("name at least one folder to copy from")
    if into.exists() and not into.is_dir():
        raise EvaluationError(f"{into} is not a folder")
    target = into / EPISODES_FILE
    data = episode_bytes(into)
    held, held_arms = numbered_records(into, data), read_arms(into)
    if any(r.get("config_hash") is None for _, r in held):
        raise EvaluationError(f"{into} holds records without a config hash (older code): bimp migrate {into} first")
    read = [_read_source(Path(source), into) for source in sources]
    check_names([r for _, _, records, _ in read for _, r in records], scenarios, labels,
                " or ".join(map(str, sources)))
    arms, rows = dict(held_arms), {}
    for _, r in held:
        rows.setdefault((r["scenario"], record_label(r)), r.get("config_hash"))
    done = {record_key(r) for _, r in held if r["status"] == "ok"}
    present = {record_key(r) for _, r in held}
    lines, copied, skipped, checked = [], Counter(), Counter(), set()
    for source, source_lines, records, source_arms in read:
        for number, r in matching(records, scenarios, labels):
            key, row = record_key(r), (r["scenario"], record_label(r))
            if key[2] is None:  # made before config hashes: its config cannot be told from another's
                raise EvaluationError(f"{source} line {number}: a record without a config hash (older code): "
                                      f"bimp migrate {source} first")
            if rows.setdefault(row, key[2]) != key[2]:
                raise EvaluationError(
                    f"{source} line {number}: {row[1]!r} on {row[0]} holds config {rows[row]} where it is merged "
                    f"and {key[2]} here: two arms under one name. Copy it under another label (rerun it with "
                    f"--label), or take the other out first (bimp drop)")
            skip = key in done or (r["status"] != "ok" and key in present)
            if "config" in r:
                _check_hash(f"{source} line {number}", r["policy"], r["config"], key[2])
            elif (source, key[2]) not in checked and (not skip or key[2] not in held_arms):
                # a skipped record's entry only where DIR lacks it: that mends a merge cut before arms.json, and
                # every source naming the hash is compared with the first
                arms[key[2]] = _entry(source, source_arms, key[2], arms.get(key[2]))
                checked.add((source, key[2]))
            if skip:
                skipped[row] += 1
                continue
            lines.append(source_lines[number - 1])
            copied[row] += 1
            present.add(key)
            if r["status"] == "ok":
                done.add(key)
    added = sorted(set(arms) - set(held_arms))
    if dry_run or (not lines and not added):
        return copied, skipped, added
    try:
        into.mkdir(parents=True, exist_ok=True)
        with unchanged_lock(into, data, held_arms):
            write_arms(into, arms)  # first, as evaluate does: every record written names a config that is there
            if lines:
                head = data if not data or data.endswith(b"\n") else data + b"\n"  # a cut last line stays apart
                write_atomic(target, head + b"\n".join(lines) + b"\n")
            write_summary(summarize(latest_records(read_records(into))), into)
    except OSError as err:
        raise EvaluationError(f"cannot write into {into}: {err}") from None
    return copied, skipped, added


def _read_source(source: Path, into: Path) -> tuple[Path, list[bytes], list[tuple[int, dict]], dict[str, dict]]:
    """``(source, its lines, its numbered records, its arms)``, the records parsed from the lines read (a run
    appending meanwhile cannot shift a number)."""
    path = source / EPISODES_FILE
    if not path.is_file():
        raise EvaluationError(f"{source} is not an evaluation folder (no {EPISODES_FILE})")
    if source.resolve() == into.resolve():
        raise EvaluationError(f"{source} is the folder merged into")
    data = episode_bytes(source)
    return source, data.split(b"\n"), numbered_records(source, data), read_arms(source)


def _check_hash(where: str, policy: str, config: dict, key: str) -> None:
    if config_hash(policy, config) != key:
        raise EvaluationError(f"{where}: its config does not hash to {key}: it is not that config")


def _entry(source: Path, source_arms: dict[str, dict], key: str, held: dict | None) -> dict:
    """The ``arms.json`` entry of ``key`` to copy from ``source``: refused when it is missing or does not hash to
    ``key``. Where the target ``held`` one already, that one stays, and must agree on what a record leaves to its
    entry (the seeding and the overrides: evaluate writes into a record only where they differ); the configs may
    differ only as the hash allows (a field at its neutral value, weights at another path)."""
    entry = source_arms.get(key)
    if entry is None:
        raise EvaluationError(f"{source}: a record names config {key}, which its arms.json does not hold")
    _check_hash(f"{source}: the arms.json entry {key}", entry["policy"], entry["config"], key)
    if held is None:
        return entry
    _check_hash(f"the merged folder's arms.json entry {key}", held["policy"], held["config"], key)
    differ = [k for k in ("policy", "seeding", "overrides") if held.get(k) != entry.get(k)]
    if differ:
        raise EvaluationError(f"{source}: the arms.json entry {key} differs from the merged folder's in its "
                              f"{', '.join(differ)}: its records would be read with the other's")
    return held
