"""The short table of ``bimp demo`` (:mod:`bimp.agents.commands.demo`: a few episodes of the default scenarios with
EnKTS and EnKS, then this table, the figures and one MP4 per policy and scenario): :func:`short_table`, the metrics a
terminal shows whole, with their intervals. The full table (every metric, the failed seeds) is the run folder's
``summary.md``."""

from __future__ import annotations

from bimp.agents.evaluation.records import format_stat

# The columns a terminal shows whole: (header, summary key). Every other metric is in summary.md.
SHORT_COLUMNS = (
    ("success", "success_rate"),
    ("collision", "collision_rate"),
    ("off road", "offroad_rate"),
    ("progress [m]", "progress_m"),
    ("plan time p50 [ms]", "plan_time_ms_p50"),
)


def short_table(summary: dict) -> str:
    """One row per scenario and policy of a summary (``bimp.agents.evaluation.metrics.summarize``): episodes, then
    success, collision, off road (Wilson 95% intervals), progress and median plan time per step (bootstrap 95%
    intervals), as Markdown."""
    head = ["scenario", "policy", "episodes"] + [name for name, _ in SHORT_COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for e in sorted(summary.values(), key=lambda e: (e["scenario"], e["policy"])):
        cells = [e["scenario"], e["policy"], str(e["episodes"])] + [format_stat(e.get(key)) for _, key in SHORT_COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
