"""Records taken out of an evaluation folder, so that it can be rerun under the same labels after a config or a
scenario's ranges changed (the ``bimp drop`` command: :mod:`bimp.agents.commands.drop`).

DIR comes first (``--scenario`` and ``--label`` take every name after them). A record goes when its scenario is one
of ``--scenario`` and its label one of ``--label`` (either may be left out: then every scenario, or every label; not
both). ``bimp evaluate`` only ever appends, and refuses to add a label's episodes made with another config beside
its old ones: this is the one command that removes, and it prints what it removed, per scenario and label. In a
committed folder git keeps what went. A name that matches no record in the folder is refused, listing the folder's
names: a typo removes nothing.

Lines that are not records are kept as they are, and so is the file's final newline. ``arms.json`` loses the entries
that only the removed records named; an entry no record named before is kept (a run interrupted before its first
episode leaves one). The folder is locked for the change (as a run locks it; a dry run only reads), the records are
replaced in one step and then ``arms.json``, so a reader in between finds every config it looks up. The summary
files, where there are any, keep the rows they had but the dropped ones, recomputed from the records left (a summary
is of the last request, not always the whole folder). Exit status 0, or 2 on a bad request (then nothing is
written).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.metrics import summarize
from bimp.agents.evaluation.records import (
    EPISODES_FILE,
    episode_bytes,
    latest_records,
    numbered_records,
    read_arms,
    record_label,
    unchanged_lock,
    write_arms,
    write_summary,
)
from bimp.agents.files import read_json, write_atomic


def drop(out: str | Path, scenarios: list[str] | None = None, labels: list[str] | None = None,
         dry_run: bool = False) -> Counter:
    """Remove ``out``'s records of ``scenarios`` x ``labels`` (None: every one) and the ``arms.json`` entries only
    they named; the counts removed per ``(scenario, label)``. :class:`EvaluationError` for a folder without records
    or whose ``arms.json`` cannot be read, neither filter given, or a name that matches no record (the folder's names
    listed); then nothing is written."""
    out = Path(out)
    if not scenarios and not labels:
        raise EvaluationError("name what to drop: --scenario, --label or both (dropping everything is rm)")
    path = out / EPISODES_FILE
    if not path.is_file():
        raise EvaluationError(f"{out} is not an evaluation folder (no {EPISODES_FILE})")
    data = episode_bytes(out)
    records, arms = numbered_records(out, data), read_arms(out)
    check_names([r for _, r in records], scenarios, labels, str(out))
    gone = dict(matching(records, scenarios, labels))
    counts = Counter((r["scenario"], record_label(r)) for r in gone.values())
    if dry_run or not gone:
        return counts
    # Everything computed before the first write: what cannot be computed leaves the folder as it was.
    kept = [r for n, r in records if n not in gone]
    named_only_by_gone = {r.get("config_hash") for r in gone.values()} - {r.get("config_hash") for r in kept}
    summary = _summary(out, kept)
    try:
        with unchanged_lock(out, data, arms):
            lines = data.split(b"\n")  # line n is lines[n - 1], as numbered_records counts them; a final b"" stays
            write_atomic(path, b"\n".join(line for n, line in enumerate(lines, start=1) if n not in gone))
            if arms:
                write_arms(out, {key: entry for key, entry in arms.items() if key not in named_only_by_gone})
            if summary is not None:
                write_summary(summary, out)
    except OSError as err:
        raise EvaluationError(f"cannot write into {out}: {err}") from None
    return counts


def check_names(records: list[dict], scenarios: list[str] | None, labels: list[str] | None, where: str) -> None:
    """:class:`EvaluationError` for a name of ``scenarios`` or ``labels`` that no record of ``records`` has, listing
    the names ``where`` holds."""
    for flag, wanted, have in (("--scenario", scenarios, {r["scenario"] for r in records}),
                               ("--label", labels, {record_label(r) for r in records})):
        unknown = sorted(set(wanted or ()) - have)
        if unknown:
            raise EvaluationError(f"{flag} {' '.join(unknown)}: no record in {where} (it holds: "
                                  f"{', '.join(sorted(have))})")


def matching(records: list[tuple[int, dict]], scenarios: list[str] | None,
             labels: list[str] | None) -> list[tuple[int, dict]]:
    """The ``(line number, record)`` of ``records`` whose scenario is one of ``scenarios`` and label one of ``labels``
    (None: any)."""
    return [(number, r) for number, r in records
            if (not scenarios or r["scenario"] in scenarios) and (not labels or record_label(r) in labels)]


def _summary(out: Path, kept: list[dict]) -> dict | None:
    """The summary's rows that still have records, recomputed from ``kept`` (the rows of dropped arms go); None
    where the folder has no summary bimp can read (evaluate writes a fresh one on its next run)."""
    try:
        rows = read_json(out / "summary.json")
    except (FileNotFoundError, EvaluationError):
        return None
    if not isinstance(rows, dict):
        return None
    return {row: entry for row, entry in summarize(latest_records(kept)).items() if row in rows}
