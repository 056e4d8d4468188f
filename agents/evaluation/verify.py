"""A sample of each arm's seeds rerun at the current code and every recorded metric but timings compared; what it
found goes into ``DIR/verified.json`` (the ``bimp verify`` command: :mod:`bimp.agents.commands.verify`).

Per arm (a scenario, a label and its config hash), the policy is rebuilt from the policy table with the overrides
the arm was run with (a ``module:factory`` policy only when named with ``--trust-policy``: a folder never names code
to run), and must resolve to the arm's config hash: else the arm cannot be rerun, and says why. ``--sample K`` seeds
of its results, evenly spread over them, are rerun in a fresh folder (``bimp evaluate``); at least one seed of every
code version its records hold; an arm that ran batched (``batch`` in its records: EnKTS and EnKS plan B episodes in
one call, which reproduces per seed only in the same batch) reruns the whole batch of each chosen seed, each batch
in one call with its seeds in the order they ran. An arm seeded otherwise than the current code seeds is refused.
Compared: ``status``, ``steps``, ``truncated`` and every metric but the plan times, to 1e-9. A difference prints the
arm, the seed and the metric. An arm is ``same`` (every value to 1e-9), ``drift`` (every episode outcome the same:
status, steps, the end and the 0/1 outcomes, such as success and collision, while a continuous metric moved:
floating-point drift, a closed loop amplifies it) or ``different`` (an outcome changed). Each record names the
machine it ran on (:func:`bimp.agents.evaluation.provenance.machine`: the CPU and the numerical packages); where an
arm drifts or differs and its records ran on another machine, the line says so: the same code moves there too, and
only a rerun on the recording's machine tells the code's changes from the machine's.

Exit status: 0 when every arm rerun is the same, 1 when one drifts or differs, 2 when an arm cannot be rerun (then
nothing runs and the folder is left as it was). ``compare``, ``aggregate`` and ``leaderboard`` then take the arms
found the same as made by the current code (:mod:`bimp.agents.evaluation.verification`).
"""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bimp.agents.errors import EvaluationError
from bimp.agents.evaluation.evaluate import evaluate, resolve_arms
from bimp.agents.evaluation.metrics import BINARY, record_label
from bimp.agents.evaluation.metrics import code_version as code_version_of
from bimp.agents.evaluation.provenance import code_version, config_diff, machine
from bimp.agents.evaluation.records import (
    EPISODES_FILE,
    episode_bytes,
    folder_lock,
    numbered_records,
    read_arms,
    read_records,
    record_config,
)
from bimp.agents.evaluation.verification import VERIFIED_FILE, arm_key, read_verified
from bimp.agents.files import write_atomic
from bimp.agents.registry import POLICIES
from bimp.agents.rollout import SEEDING
from bimp.configs import trust_switch

TIMINGS = ("plan_time_ms_p50", "plan_time_ms_p95")  # the machine's, not the code's
COMPARED = ("status", "steps", "truncated")
TOLERANCE = 1e-9


@dataclass
class ArmCheck:
    """One arm of a folder: what to rerun (``seeds``, ``batch``) or why it cannot be (``reason``), then what was
    found (``differences``)."""

    scenario: str
    label: str
    policy: str
    config_hash: str | None
    overrides: dict = field(default_factory=dict)
    groups: list[list[int]] = field(default_factory=list)  # the seeds of each call to rerun, as they ran
    versions: list[str] = field(default_factory=list)  # the code versions of the records the rerun checks
    machines: list[str] = field(default_factory=list)  # where those records ran ("unknown": before it was recorded)
    reason: str | None = None
    differences: list[str] | None = None
    outcomes_changed: bool = False

    @property
    def outcome(self) -> str:
        return "different" if self.outcomes_changed else "drift" if self.differences else "same"

    @property
    def seeds(self) -> list[int]:
        return sorted(s for group in self.groups for s in group)

    @property
    def batch(self) -> int:
        return max((len(g) for g in self.groups), default=1)

    @property
    def name(self) -> str:
        return f"{self.label!r} ({self.policy}) on {self.scenario}, hash {self.config_hash}"


def _spread(seeds: list[int], sample: int) -> list[int]:
    """``sample`` of ``seeds`` (sorted), evenly spread from the first to the last."""
    picks = np.unique(np.round(np.linspace(0, len(seeds) - 1, min(sample, len(seeds)))).astype(int))
    return [seeds[i] for i in picks]


def _groups(arm_records: list[dict]) -> list[list[dict]]:
    """The arm's records (in file order) in the groups they ran in: a batched call writes its ``batch`` records
    together (consecutive lines, one ``batch`` value and one ``wall_s``); an unbatched record is a group alone."""
    groups: list[list[dict]] = []
    for r in arm_records:
        size = int(r.get("batch") or 1)
        last = groups[-1] if groups else None
        if (last is not None and len(last) < size and int(last[0].get("batch") or 1) == size
                and last[0].get("wall_s") == r.get("wall_s")):
            last.append(r)
        else:
            groups.append([r])
    return groups


def plan(folder: str | Path, sample: int, trusted: Iterable[str] = ()) -> list[ArmCheck]:
    """Every arm of ``folder`` with the seeds to rerun, or the reason it cannot be rerun."""
    folder = Path(folder)
    data = episode_bytes(folder)
    numbered, arms_json = numbered_records(folder, data), read_arms(folder)
    by_arm: dict[tuple, list[dict]] = {}
    for _, r in numbered:
        if r["status"] == "ok":
            by_arm.setdefault((r["scenario"], record_label(r), r.get("config_hash")), []).append(r)
    checks = []
    for (scenario, label, key), rs in by_arm.items():
        first = rs[0]
        entry = arms_json.get(key, {})
        overrides = first.get("overrides", entry.get("overrides", {})) or {}
        check = ArmCheck(scenario, label, first["policy"], key, overrides)
        checks.append(check)
        if key is None:
            check.reason = "made before config hashes: `bimp migrate` it first"
        elif check.policy not in POLICIES and check.policy not in trusted:
            check.reason = (f"its policy is not in the policy table and a folder never names code to run; if you "
                            f"trust it, name it: --trust-policy {check.policy}")
        elif trust_switch(overrides) is not None:
            check.reason = f"its overrides set {trust_switch(overrides)}, which no file may switch on"
        if check.reason:
            continue
        try:
            (arm,) = resolve_arms([scenario], [check.policy], {check.policy: overrides}, {check.policy: label})
        except EvaluationError as err:
            check.reason = f"the current code cannot build it: {err}"
            continue
        if arm.config_hash != key:
            diff = config_diff(record_config(first, arms_json) or {}, arm.resolved)
            check.reason = ("the current code resolves it to another config (" + "; ".join(diff[:3]) + "): rerun "
                            "the arm instead")
            continue
        if first.get("seeding", entry.get("seeding", SEEDING)) not in (SEEDING, None):
            check.reason = "its episodes were seeded otherwise than the current code seeds them: rerun the arm"
            continue
        latest = {r["seed"]: r for r in rs}  # the last ok record per seed, as every reader takes it
        chosen = set(_spread(sorted(latest), sample))
        by_version: dict[str, list[int]] = {}
        for seed, r in sorted(latest.items()):
            by_version.setdefault(code_version_of(r), []).append(seed)
        chosen |= {seeds[0] for seeds in by_version.values()}  # every code version the arm holds, checked
        picked = []
        for group in _groups(rs):  # the group each chosen seed's latest record ran in, in file order
            if any(latest.get(r["seed"]) is r and r["seed"] in chosen for r in group) and group not in picked:
                picked.append(group)
        check.groups = [[r["seed"] for r in group] for group in picked]
        check.versions = sorted({code_version_of(r) for group in picked for r in group})
        check.machines = sorted({r.get("machine") or "unknown" for group in picked for r in group})
    return checks


OUTCOME_FIELDS = (*COMPARED, *(f"metrics.{name}" for name in BINARY))  # what an episode's outcome is


def differences(old: dict, new: dict) -> list[str]:
    """What differs between two records of one seed: ``status``, ``steps``, ``truncated`` and every metric but
    the timings (to :data:`TOLERANCE`), each ``"seed S: FIELD old -> new"``."""
    # What the old record holds: a field added since is not a difference.
    out = [f"seed {old['seed']}: {k} {old.get(k)!r} -> {new.get(k)!r}" for k in COMPARED
           if k in old and old.get(k) != new.get(k)]
    a, b = old.get("metrics") or {}, new.get("metrics") or {}
    for name in sorted(set(a) - set(TIMINGS)):
        x, y = a.get(name), b.get(name)
        same = (x is None and y is None) or (x is not None and y is not None
                                             and math.isclose(x, y, rel_tol=TOLERANCE, abs_tol=TOLERANCE))
        if not same:
            out.append(f"seed {old['seed']}: metrics.{name} {x!r} -> {y!r}")
    return out


def rerun(folder: Path, check: ArmCheck, workers: int, progress: bool) -> list[str]:
    """The differences between ``check``'s seeds as recorded in ``folder`` and as the current code runs them."""
    recorded = {r["seed"]: r for r in read_records(folder) if r["status"] == "ok"
                and (r["scenario"], record_label(r), r.get("config_hash"))
                == (check.scenario, check.label, check.config_hash)}
    with tempfile.TemporaryDirectory(prefix="bimp-verify-") as scratch:
        for group in check.groups:  # each batch as it ran: its seeds, in its order, in one call
            evaluate([check.scenario], [check.policy], seeds=group, out=scratch, workers=workers,
                     overrides={check.policy: check.overrides}, labels={check.policy: check.label},
                     batch=len(group), progress=progress)
        fresh = {r["seed"]: r for r in read_records(scratch)}
    found = []
    for seed in check.seeds:
        found += differences(recorded[seed], fresh[seed]) if seed in fresh else [f"seed {seed}: status (no record)"]
    return found


def outcome_changed(found: list[str]) -> bool:
    """Whether one of ``found`` (:func:`differences`) is an episode's outcome, not a continuous metric."""
    return any(d.split(": ", 1)[1].split(" ", 1)[0] in OUTCOME_FIELDS for d in found)


def verify_folder(folder: str | Path, sample: int = 2, workers: int = 1, trusted: Iterable[str] = (),
                  dry_run: bool = False, progress: bool = True) -> list[ArmCheck]:
    """Verify ``folder`` (the module doc); the arms with what was found. :class:`EvaluationError`, with nothing
    run or written, when an arm cannot be rerun (every such arm named)."""
    folder = Path(folder)
    if not (folder / EPISODES_FILE).is_file():
        raise EvaluationError(f"{folder} is not an evaluation folder (no {EPISODES_FILE})")
    checks = plan(folder, sample, trusted)
    refused = [c for c in checks if c.reason]
    if refused:
        raise EvaluationError(f"{folder}: {len(refused)} arm(s) cannot be rerun: "
                              + "; ".join(f"{c.name}: {c.reason}" for c in refused))
    if dry_run:
        return checks
    version = code_version()
    with folder_lock(folder, hint="wait for it to end"):  # held throughout: no run adds records meanwhile
        for check in checks:
            check.differences = rerun(folder, check, workers, progress)
            check.outcomes_changed = outcome_changed(check.differences)
            verified = read_verified(folder)  # each arm kept as soon as it is known
            verified[arm_key(check.scenario, check.label, check.config_hash)] = {
                "policy": check.policy, "commit": version["git_commit"] or "", "dirty": bool(version["git_dirty"]),
                "seeds": check.seeds, "groups": check.groups, "versions": check.versions,
                "machines": check.machines, "machine": machine(),
                "outcome": check.outcome, "differences": check.differences}
            write_atomic(folder / VERIFIED_FILE, _dumps(verified))
    return checks


def _dumps(verified: dict) -> str:
    return json.dumps(verified, indent=1, sort_keys=True) + "\n"


__all__ = ["ArmCheck", "differences", "plan", "verify_folder"]
