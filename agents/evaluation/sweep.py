"""Policies evaluated along one axis of their configs: the points of a sweep or a frontier, run (:func:`run_points`),
tabled and drawn (the commands ``bimp sweep`` and ``bimp frontier``: :mod:`bimp.agents.commands.sweep`,
:mod:`bimp.agents.commands.frontier`).

A sweep is a list of *points* (a policy under one set of overrides, shown as a label such as ``enkts N=50``), each
an ordinary evaluation (:func:`bimp.agents.evaluation.evaluate.evaluate`) into the one folder ``OUT``: the same resume,
lock and provenance, one ``episodes.jsonl``, and the same ``--backend ray [--address ADDR]`` (``docs/scaling.md``).
Every point is checked (its config, and against the folder's records) before the first episode runs: a bad request exits
with status 2 and names the point, never after hours of the others. ``--param POLICY.KEY=V1,V2,...`` sweeps any config
key (``KEY`` as in ``bimp tune``'s search spaces: ``barrier.edge_margin``, ``sigma_du[1]``; values read as YAML);
several ``--param`` sweep together, value by value (the i-th values of a policy's params form one point; the x axis
shows the first). ``--n`` sweeps ``n_particles`` of every ``--policy``.

The frontier puts quality against compute: each policy along its compute axis (its spec's ``frontier_axis``: the
particles N of EnKTS, EnKS and MPPI, the iteration cap of NMPC; one point for a policy without one, such as PPO),
success (Wilson interval) and bound violations against the plan time per step (the per-episode median, averaged over
episodes). Episodes run one at a time (no ``--batch``): a batched plan's time is not one plan's. Run it on held-out
seeds and an otherwise idle machine, with ``--workers 1`` (the default) so that no two episodes share a core.

Writes ``OUT/sweep.json`` (the points with their summaries), ``OUT/sweep.md`` (one row per point and scenario)
and ``OUT/sweep.png`` (or ``frontier.json``, ``frontier.md``, ``frontier.png``). ``--dry-run``: every point checked as
for a run, then one line per arm (episodes done, to run) and ``dry run: N episode(s) would run``; nothing written.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import matplotlib
import yaml

from bimp import envs
from bimp.agents.errors import EvaluationError, check_out_dir
from bimp.agents.evaluation.evaluate import DryRun, check_conflicts, evaluate, resolve_arms
from bimp.agents.evaluation.records import format_stat, numbered_records, write_summary
from bimp.agents.evaluation.tune_space import TuneError, factory_kwargs, overrides_for
from bimp.agents.files import write_atomic, write_figure
from bimp.agents.registry import make_policy, policy_color, policy_label

RATES = ("success_rate", "collision_rate", "offroad_rate", "input_violation_rate", "rate_violation_rate")


@dataclass(frozen=True)
class Point:
    """One policy under ``overrides``, the sweep's ``value`` of ``param`` (None: the policy's own config)."""

    label: str
    policy: str
    overrides: dict
    param: str | None = None
    value: object = None


def param_points(params: list[str], base: dict | None = None) -> list[Point]:
    """Points of ``--param POLICY.KEY=V1,V2,...`` (several params: swept together, value by value).
    ``base``: ``{policy: overrides}`` under every point. :class:`EvaluationError` naming a malformed param."""
    parsed = []
    for item in params:
        name, eq, values = item.partition("=")
        policy, dot, key = name.partition(".")
        if not (eq and dot and policy and key and values):
            raise EvaluationError(f"--param expects POLICY.KEY=V1,V2,..., got {item!r}")
        try:
            parsed.append((policy, key, [yaml.safe_load(v) for v in values.split(",")]))
        except yaml.YAMLError as err:
            raise EvaluationError(f"--param {item!r}: a value is not valid YAML ({err})") from None
    if len({len(values) for _, _, values in parsed}) > 1:
        raise EvaluationError(f"--param lists of different lengths cannot sweep together: {params}")
    base = base or {}
    defaults = {policy: _factory_kwargs(policy, base.get(policy, {})) for policy, _, _ in parsed}
    points = []
    for i in range(len(parsed[0][2]) if parsed else 0):
        for policy in dict.fromkeys(p for p, _, _ in parsed):  # one point per policy and value index
            params_i = {key: values[i] for p, key, values in parsed if p == policy}
            try:
                overrides = {**base.get(policy, {}), **overrides_for(defaults[policy], params_i)}
            except TuneError as err:
                raise EvaluationError(f"--param {policy}: {err}") from None
            # The label names a problem key without its "problem." (as before issue 25 moved them): the rows of a
            # folder swept before keep their names, and the shorter one reads the same for every planner.
            label = f"{policy} " + " ".join(f"{k.removeprefix('problem.')}={v}" for k, v in params_i.items())
            points.append(Point(label, policy, overrides, "+".join(params_i), next(iter(params_i.values()))))
    return points


def _factory_kwargs(policy: str, overrides: dict) -> dict:
    """The policy's complete keyword arguments under ``overrides`` (built once on the first default scenario's env)."""
    try:
        return factory_kwargs(make_policy(policy, gym.make(envs.env_id(envs.default_scenarios()[0])), **overrides))
    except (TuneError, ValueError, TypeError, OSError) as err:
        raise EvaluationError(f"policy {policy!r}: {err}") from None


def axis_points(policies: list[str], axis: dict[str, tuple[str, list]], base: dict | None = None) -> list[Point]:
    """Each policy along ``axis[policy] = (key, values)``, or one point if it has none there."""
    base = base or {}
    points = []
    for policy in policies:
        if policy not in axis:
            points.append(Point(policy, policy, dict(base.get(policy, {}))))
            continue
        key, values = axis[policy]
        short = {"n_particles": "N", "max_iter": "iters"}.get(key, key)
        points += [Point(f"{policy} {short}={v}", policy, {**base.get(policy, {}), key: v}, key, v) for v in values]
    return points


def run_points(points: list[Point], scenarios: list[str], episodes: int, seed: int, out: str | Path, *,
               workers: int = 1, batch: int = 1, progress: bool = True, backend: str = "local",
               address: str | None = None, ray_cpus: int | None = None, dry_run: bool = False) -> list[dict] | DryRun:
    """Evaluate every point into ``out``; ``[{label, policy, param, value, scenario, **summary entry}]``.
    ``backend``, ``address``, ``ray_cpus``: where the episodes run, as for
    :func:`bimp.agents.evaluation.evaluate.evaluate`. ``dry_run``: the same checks, then the
    :class:`bimp.agents.evaluation.evaluate.DryRun` of all the points; nothing written."""
    labels = [p.label for p in points]
    if not points or len(set(labels)) != len(labels):
        raise EvaluationError(f"the points need distinct labels, got {labels}")
    if episodes < 1 or seed < 0 or workers < 1:
        raise EvaluationError(f"--episodes and --workers must be >= 1 and --seed >= 0, got {episodes}, {workers} "
                              f"and {seed}")
    # Every point checked, and against the folder, before the first runs: a bad last point must not cost the others'
    # hours first.
    out = check_out_dir(out, create=False)
    arms = [arm for p in points
            for arm in resolve_arms(scenarios, [p.policy], {p.policy: p.overrides}, {p.policy: p.label})]
    check_conflicts(arms, numbered_records(out), out)
    if dry_run:
        plans = [evaluate(scenarios, [p.policy], episodes, seed, workers, out, overrides={p.policy: p.overrides},
                          labels={p.policy: p.label}, batch=batch, dry_run=True) for p in points]
        return DryRun([e for plan in plans for e in plan.to_run], sum(plan.done for plan in plans),
                      [a for plan in plans for a in plan.arms])
    rows, combined = [], {}
    for p in points:
        summary = evaluate(scenarios, [p.policy], episodes, seed, workers, out, traces=0, progress=progress,
                           overrides={p.policy: p.overrides}, labels={p.policy: p.label}, batch=batch,
                           backend=backend, address=address, ray_cpus=ray_cpus)
        combined.update(summary)
        rows += [{**entry, "label": p.label, "policy": p.policy, "param": p.param, "value": p.value}
                 for entry in summary.values()]
    write_summary(combined, out)  # each evaluation wrote its own point's; the folder's files hold them all
    return rows


def table(rows: list[dict]) -> str:
    """One row per point and scenario: the rates with their intervals and the plan time."""
    head = ["scenario", "policy", "param", "value", "episodes", *RATES, "plan_time_ms_p50"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in sorted(rows, key=lambda r: (r["scenario"], r["policy"], _order(r["value"]))):
        cells = [r["scenario"], r["policy"], r["param"] or "-", "-" if r["value"] is None else str(r["value"]),
                 str(r["episodes"])] + [format_stat(r[m]) for m in (*RATES, "plan_time_ms_p50")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\nIntervals: 95%, Wilson for the rates per episode, bootstrap for the plan time.\n"


def _order(value):
    return (0, value) if isinstance(value, (int, float)) else (1, str(value))


def plot(rows: list[dict], path: Path, frontier: bool) -> Path:
    """Per scenario: success (with its interval) and the bound-violation rate, against the swept value (a sweep)
    or the plan time (the frontier), one line per policy."""
    matplotlib.use("Agg")  # headless: files only
    import matplotlib.pyplot as plt  # heavy (and it must follow the backend's choice): only when a figure is drawn

    scenarios = sorted({r["scenario"] for r in rows})
    fig, axes = plt.subplots(len(scenarios), 2, figsize=(10, 3.2 * len(scenarios)), squeeze=False)
    for i, scenario in enumerate(scenarios):
        for policy in sorted({r["policy"] for r in rows}):
            rs = sorted((r for r in rows if r["scenario"] == scenario and r["policy"] == policy),
                        key=lambda r: _order(r["value"]))
            if not rs:
                continue
            xs = [r["plan_time_ms_p50"]["mean"] if frontier else r["value"] for r in rs]
            if not frontier and not all(isinstance(x, (int, float)) for x in xs):
                xs = list(range(len(rs)))
            s = [r["success_rate"] for r in rs]
            err = [[x["mean"] - x["ci_low"] for x in s], [x["ci_high"] - x["mean"] for x in s]]
            style = dict(color=policy_color(policy), label=policy_label(policy), marker="o", capsize=3)
            axes[i, 0].errorbar(xs, [x["mean"] for x in s], yerr=err, **style)
            violation = [(r["input_violation_rate"]["mean"] + r["rate_violation_rate"]["mean"]) / 2 for r in rs]
            axes[i, 1].plot(xs, violation, **{k: v for k, v in style.items() if k != "capsize"})
            if frontier or len(rs) > 1:
                for x, r in zip(xs, rs):
                    if r["value"] is not None:
                        axes[i, 0].annotate(str(r["value"]), (x, r["success_rate"]["mean"]), fontsize=6)
        numeric = [x for r in rows for x in [r["plan_time_ms_p50"]["mean"] if frontier else r["value"]]
                   if isinstance(x, (int, float)) and x > 0]
        for j, name in enumerate(("success rate", "steps over an input or rate bound")):
            ax = axes[i, j]
            if numeric and max(numeric) / min(numeric) >= 10:
                ax.set_xscale("log")
            ax.set_xlabel("plan time per step [ms]" if frontier else (rows[0]["param"] or "point"))
            ax.set_title(f"{scenario}: {name}", fontsize=9)
        axes[i, 0].set_ylim(-0.05, 1.05)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    write_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def write(rows: list[dict], out: Path, name: str) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / f"{name}.json", json.dumps(rows, indent=2, default=str))
    write_atomic(out / f"{name}.md", table(rows))
    return [out / f"{name}.json", out / f"{name}.md", plot(rows, out / f"{name}.png", frontier=name == "frontier")]


__all__ = ["Point", "axis_points", "param_points", "run_points", "table"]
