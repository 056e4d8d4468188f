"""``bimp compare``: two arms on the same episode seeds, paired.

    bimp compare runs/eval --policies enkts enks
    bimp compare runs/a runs/b --policies enkts enkts       # A from the first folder, B from the second

For every scenario both arms ran, on the seeds where both have a result: the exact McNemar test of each episode
outcome (success, collision, off-road) with the seeds where the two disagree, and a paired bootstrap 95% interval
of the mean per-seed difference A - B of every continuous metric. Pairing removes the scenario-to-scenario
variation that unpaired intervals carry, so it detects differences the summary's intervals cannot.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bimp.agents.metrics import BINARY, METRICS
from bimp.agents.records import latest_records, read_records, record_label
from bimp.agents.stats import mcnemar_exact, paired_bootstrap


def label_results(folder: Path, label: str) -> dict[tuple[str, int], dict]:
    """``{(scenario, seed): metrics}`` of the successful episodes of ``label`` in ``folder``."""
    rows = [r for r in latest_records(read_records(folder))
            if record_label(r) == label and r["status"] == "ok"]
    for scenario in {r["scenario"] for r in rows}:  # one config per scenario (the scenario's ranges are in it)
        hashes = {r.get("config_hash") for r in rows if r["scenario"] == scenario}
        if len(hashes) > 1:
            raise ValueError(f"{folder} holds {label!r} on {scenario} under {len(hashes)} configs; give each its "
                             "own --label")
    return {(r["scenario"], r["seed"]): r["metrics"] for r in rows}


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


def report(result: dict, label_a: str, label_b: str) -> str:
    lines = []
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp compare", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", metavar="DIR", help="one folder, or two (A from the first)")
    parser.add_argument("--policies", nargs=2, required=True, metavar=("A", "B"), help="the two labels")
    parser.add_argument("--json", default=None, help="also write the comparison to this JSON file")
    args = parser.parse_args(argv)
    if len(args.folders) > 2:
        parser.error("give one or two folders")
    folder_a, folder_b = Path(args.folders[0]), Path(args.folders[-1])
    label_a, label_b = args.policies
    if folder_a == folder_b and label_a == label_b:
        parser.error("comparing an arm with itself: name two labels, or two folders")
    try:
        a, b = label_results(folder_a, label_a), label_results(folder_b, label_b)
    except ValueError as err:
        print(f"bimp compare: error: {err}", file=sys.stderr)
        return 2
    for label, folder, got in ((label_a, folder_a, a), (label_b, folder_b, b)):
        if not got:
            print(f"bimp compare: error: no results of {label!r} in {folder}", file=sys.stderr)
            return 2
    result = compare(a, b)
    print(report(result, label_a, label_b))
    if args.json:
        try:
            Path(args.json).write_text(json.dumps(result, indent=2))
        except OSError as err:
            print(f"bimp compare: error: cannot write --json {args.json}: {err.strerror or err}", file=sys.stderr)
            return 2
    return 0 if result else 1


__all__ = ["compare", "label_results", "report"]
