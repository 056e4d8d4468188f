"""Two arms on the same episode seeds, paired (the ``bimp compare`` command: :mod:`bimp.agents.commands.compare`).

For every scenario both arms ran, on the seeds where both have a result: the exact McNemar test of each episode
outcome (success, collision, off-road) with the seeds where the two disagree, and a paired bootstrap 95% interval
of the mean per-seed difference A - B of every continuous metric. Pairing removes the scenario-to-scenario
variation that unpaired intervals carry, so it detects differences the summary's intervals cannot. Where the paired
records come from more than one code version (two folders made by different commits, an arm resumed after a code
change), a note first names them: a difference may then be the code's.
"""

from __future__ import annotations

from pathlib import Path

from bimp.agents.evaluation.metrics import BINARY, METRICS, code_version
from bimp.agents.evaluation.records import latest_records, read_records, record_label
from bimp.agents.evaluation.stats import mcnemar_exact, paired_bootstrap
from bimp.agents.evaluation.verification import as_current


def label_records(folder: Path, label: str) -> dict[tuple[str, int], dict]:
    """``{(scenario, seed): record}`` of the successful episodes of ``label`` in ``folder`` (an arm ``bimp verify``
    found the same at the current code: as made by it, :func:`bimp.agents.evaluation.verification.as_current`)."""
    rows = [r for r in as_current(folder, latest_records(read_records(folder)))
            if record_label(r) == label and r["status"] == "ok"]
    for scenario in {r["scenario"] for r in rows}:  # one config per scenario (the scenario's ranges are in it)
        hashes = {r.get("config_hash") for r in rows if r["scenario"] == scenario}
        if len(hashes) > 1:
            raise ValueError(f"{folder} holds {label!r} on {scenario} under {len(hashes)} configs; give each its "
                             "own --label")
    return {(r["scenario"], r["seed"]): r for r in rows}


def label_results(folder: Path, label: str) -> dict[tuple[str, int], dict]:
    """``{(scenario, seed): metrics}`` of the successful episodes of ``label`` in ``folder``."""
    return {key: r["metrics"] for key, r in label_records(folder, label).items()}


def paired_code_versions(result: dict, a: dict, b: dict) -> dict[str, dict[str, int]]:
    """``{"A": {version: episodes}, "B": ...}``: the code versions (:func:`code_version`) of the records ``result``
    paired, ``a`` and ``b`` the arms' ``{(scenario, seed): record}``."""
    versions: dict[str, dict[str, int]] = {"A": {}, "B": {}}
    for scenario, entry in result.items():
        for seed in entry["seeds"]:
            for arm, records in (("A", a), ("B", b)):
                version = code_version(records[scenario, seed])
                versions[arm][version] = versions[arm].get(version, 0) + 1
    return versions


def code_version_note(versions: dict[str, dict[str, int]], label_a: str, label_b: str) -> str | None:
    """One line saying the compared records come from more than one code version, naming them per arm (None when
    they come from one): a difference may then be the code's, not the arms'."""
    every = set(versions["A"]) | set(versions["B"])
    if len(every) < 2:
        return None
    arms = "; ".join(f"{arm} ({label}) " + ", ".join(f"{_short(v)} ({n} episode{'s' if n != 1 else ''})"
                                                  for v, n in sorted(counts.items()))
                     for (arm, counts), label in zip(versions.items(), (label_a, label_b)))
    return f"note: the paired records come from {len(every)} code versions: {arms}; a difference may be the code's"


def _short(version: str) -> str:
    return version[:7] + version[40:] if len(version) >= 40 else version  # a commit's 7 digits, +dirty kept


def compare(a: dict, b: dict) -> dict[str, dict]:
    """Paired comparison per scenario of two ``{(scenario, seed): metrics}`` maps (see the module doc)."""
    out = {}
    for scenario in sorted({s for s, _ in a} & {s for s, _ in b}):
        seeds = sorted(seed for s, seed in a if s == scenario and (s, seed) in b)
        if not seeds:
            continue
        ma, mb = [a[scenario, s] for s in seeds], [b[scenario, s] for s in seeds]
        entry: dict = {"pairs": len(seeds), "seeds": seeds}
        for name in METRICS:
            if name in BINARY:
                both = [(s, bool(m[name]), bool(n[name])) for s, m, n in zip(seeds, ma, mb)
                        if m.get(name) is not None and n.get(name) is not None]  # overtake: overtaking only
                if not both:
                    entry[name] = None
                    continue
                xa, xb = [p for _, p, _ in both], [q for _, _, q in both]
                entry[name] = {"a": sum(xa) / len(xa), "b": sum(xb) / len(xb), **mcnemar_exact(xa, xb),
                               "disagree": [s for s, p, q in both if p != q]}
            else:
                both = [(m[name], n[name]) for m, n in zip(ma, mb)  # older records may lack a newer metric
                        if m.get(name) is not None and n.get(name) is not None]
                entry[name] = paired_bootstrap([p for p, _ in both], [q for _, q in both])
        out[scenario] = entry
    return out


def report(result: dict, label_a: str, label_b: str, note: str | None = None) -> str:
    """The comparison as markdown, ``note`` (:func:`code_version_note`) first where there is one."""
    lines = [note, ""] if note and result else []
    for scenario, e in result.items():
        lines.append(f"## {scenario}: {label_a} (A) vs {label_b} (B), {e['pairs']} paired seeds\n")
        lines.append("| outcome | A | B | only A | only B | McNemar exact p | seeds where they disagree |")
        lines.append("|---|---|---|---|---|---|---|")
        for name in BINARY:
            m = e[name]
            if m is None:
                continue
            shown = ", ".join(map(str, m["disagree"][:12])) + (", ..." if len(m["disagree"]) > 12 else "")
            lines.append(f"| {name} | {m['a']:.3f} | {m['b']:.3f} | {m['only_a']} | {m['only_b']} | "
                         f"{m['p_value']:.3g} | {shown or '-'} |")
        lines.append("\n| metric | mean A - B | 95% paired bootstrap | pairs |")
        lines.append("|---|---|---|---|")
        for name in METRICS:
            if name in BINARY:
                continue
            m = e.get(name)
            if m is None or m["mean_diff"] is None:
                lines.append(f"| {name} | - | - | 0 |")
            else:
                lines.append(f"| {name} | {m['mean_diff']:+.3f} | [{m['ci_low']:+.3f}, {m['ci_high']:+.3f}] | "
                             f"{m['n']} |")
        lines.append("")
    return "\n".join(lines) if lines else "no scenario where both arms have results on the same seeds\n"


__all__ = ["code_version_note", "compare", "label_records", "label_results", "paired_code_versions",
           "report"]
