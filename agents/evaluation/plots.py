"""Figures like the paper's from the traced episodes of an evaluation folder (:func:`plot_all`; the command
``bimp plot DIR``: :mod:`bimp.agents.commands.plot`).

Per scenario, comparing the policies on the first traced seed they share:
- ``trajectories_<scenario>.png``: the EV paths on the road with the OVs (paper Fig. 1 and 3);
- ``controls_<scenario>.png``: acceleration, steering and their per-step changes with the bounds (Fig. 2, 4);
- ``safety_<scenario>.png``: distance to each OV and to the road edge with the safety margins, and the
  speed against the reference speed (Fig. 5).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: files only
import gymnasium as gym  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bimp import envs  # noqa: E402
from bimp.agents.errors import check_out_dir  # noqa: E402
from bimp.agents.evaluation.records import EPISODES_FILE, numbered_records, record_label  # noqa: E402
from bimp.agents.files import write_figure
from bimp.agents.registry import make_policy, policy_color, policy_label  # noqa: E402
from bimp.agents.rollout import rollout  # noqa: E402
from bimp.envs.road import RoadGeometry, Route  # noqa: E402
from bimp.envs.scene import Bounds  # noqa: E402

OV_COLORS = ("tab:cyan", "tab:olive", "tab:gray")  # kept apart from every policy's colour (the policy table's)
# A shared folder is input from anyone: every value drawn must be a finite number matplotlib can place (1e308 has
# no room for the axis margins). No road or trace bimp writes comes near it.
MAX_MAGNITUDE = 1e9
# What the figures read of a record's trace, as shapes: T the steps, None a length that is the same in every row.
TRACE_SHAPES = {"x": ("T",), "y": ("T",), "speed": ("T",), "reference_speed": ("T",), "edge_distance": ("T",),
                "input": ("T", 2), "ov_xy": ("T", None, 2), "ov_distance": ("T", None)}
BOUNDS_KEYS = ("accel", "steer", "accel_rate", "steer_rate", "d_min", "edge_margin")
ROAD_KEYS = tuple(f.name for f in dataclasses.fields(RoadGeometry))


def _number(value: object) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= MAX_MAGNITUDE
            and math.isfinite(value))  # the size first: an integer past float's range makes isfinite raise


def _shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 30 else text[:27] + "..."


def _array_problem(value: object, shape: tuple) -> str | None:
    """Why ``value`` is not nested lists of finite numbers of ``shape`` (an int a length, None any length the same
    for every row), as ``"[3][1] is 'a', not a number"``; None when it is."""
    if not shape:
        return None if _number(value) else f" is {_shown(value)}, not a finite number"
    if not isinstance(value, list):
        return f" is {_shown(value)}, not a list"
    if shape[0] is not None and len(value) != shape[0]:
        return f" has {len(value)} entries, not {shape[0]}"
    inner = shape[1:]
    if inner and inner[0] is None and value and isinstance(value[0], list):
        inner = (len(value[0]), *inner[1:])  # the first row fixes the length every row must have
    for i, item in enumerate(value):
        problem = _array_problem(item, inner)
        if problem is not None:
            return f"[{i}]{problem}"
    return None


def trace_problem(record: dict) -> str | None:
    """Why the figures cannot draw the traced ``record`` (None when they can), naming the field: everything
    :func:`plot_trajectories`, :func:`plot_controls` and :func:`plot_safety` read of it, with the shape they read it
    as. Checked here once, so a malformed record is skipped by name instead of failing a figure halfway."""
    t = record["trace"]
    if not isinstance(t, dict):
        return f"trace is {_shown(t)}, not an object"
    missing = [k for k in TRACE_SHAPES if k not in t]
    if missing:
        return f"trace lacks {', '.join(missing)}"
    steps = len(t["x"]) if isinstance(t["x"], list) else 0
    if not steps:
        return "trace.x is not a list of at least one step"
    for name, shape in TRACE_SHAPES.items():
        problem = _array_problem(t[name], tuple(steps if d == "T" else d for d in shape))
        if problem is not None:
            return f"trace.{name}{problem}"
    if "road" in record:
        if _reference_lane(t):
            for name, shape in (("s", (steps,)), ("reference", (steps, None))):
                problem = _array_problem(t[name], shape)
                if problem is not None:
                    return f"trace.{name}{problem}"
            if len(t["reference"][0]) < 3:
                return "trace.reference[0] has no lane offset (entry 2)"
        road = record["road"]
        if not isinstance(road, dict) or set(road) - set(ROAD_KEYS) or not all(map(_number, road.values())):
            return f"road is {_shown(road)}, not an object of finite numbers among {', '.join(ROAD_KEYS)}"
        try:
            RoadGeometry(**road)
        except ValueError as err:
            return f"road: {err}"
    elif "route" in record:
        route = record["route"]
        if not isinstance(route, dict):
            return f"route is {_shown(route)}, not an object"
        points = len(route["xy"]) if isinstance(route.get("xy"), list) else 0
        if points < 2:
            return "route.xy is not a list of at least two points"
        for name, shape in (("xy", (points, 2)), ("left", (points,)), ("right", (points,))):
            problem = _array_problem(route.get(name), shape)
            if problem is not None:
                return f"route.{name}{problem}"
        try:
            _route(route)
        except ValueError as err:
            return f"route: {err}"
    else:
        return "a traced record with neither road nor route"
    bounds = record.get("bounds")
    if not isinstance(bounds, dict):
        return f"bounds is {_shown(bounds)}, not an object"
    for name in BOUNDS_KEYS:
        problem = _array_problem(bounds.get(name), (2,) if name == "accel" else ())
        if problem is not None:
            return f"bounds.{name}{problem}"
    return None


def _reference_lane(trace: dict) -> bool:
    """Whether the trajectories figure draws the reference lane: where the trace has one, on a closed-form road."""
    return bool(trace.get("reference") and trace.get("s"))


def _route(route: dict) -> Route:
    return Route.from_points(np.array(route["xy"], dtype=float), np.array(route["left"], dtype=float),
                             np.array(route["right"], dtype=float))


def _bounds(record: dict) -> Bounds:
    return Bounds(**{k: tuple(record["bounds"][k]) if k == "accel" else record["bounds"][k] for k in BOUNDS_KEYS})


def drawable_records(folder: Path) -> list[dict]:
    """The records of ``folder`` with every ok record whose trace the figures cannot draw (:func:`trace_problem`)
    left out, each with one warning on stderr naming its line, scenario, label, seed and the field at fault."""
    kept = []
    for line, r in numbered_records(folder):
        problem = trace_problem(r) if r["status"] == "ok" and "trace" in r else None
        if problem is None:
            kept.append(r)
            continue
        label = record_label(r) + (f" (policy {r['policy']})" if record_label(r) != r["policy"] else "")
        print(f"bimp plot: warning: {folder / EPISODES_FILE} line {line}: skipped the trace of {r['scenario']}, "
              f"{label}, seed {r['seed']}: {problem}", file=sys.stderr)
    return kept


def traced_episodes(records: list[dict]) -> dict[str, dict[str, dict]]:
    """``{scenario: {policy: record}}``, for each scenario the lowest seed traced for every policy there."""
    by_scenario: dict[str, dict[int, dict[str, dict]]] = {}
    for r in records:
        if r.get("status") == "ok" and "trace" in r:
            by_scenario.setdefault(r["scenario"], {}).setdefault(r["seed"], {})[record_label(r)] = r
    chosen = {}
    for scenario, seeds in by_scenario.items():
        policies = set().union(*seeds.values())
        common = [s for s in sorted(seeds) if set(seeds[s]) == policies]
        seed = common[0] if common else min(seeds)
        chosen[scenario] = dict(sorted(seeds[seed].items()))
    return chosen


def _road(ax, road: RoadGeometry, s_max: float) -> None:
    s = np.linspace(0.0, min(road.length, s_max), 400)
    for lat, style in ((-road.half_width, "k-"), (road.half_width, "k-"), (0.0, "k--")):
        xy = road.position(s, np.full_like(s, lat))
        ax.plot(xy[:, 0], xy[:, 1], style, lw=1.0 if style == "k-" else 0.6)


def _route_edges(ax, route: Route) -> None:
    for lat, style in ((route.left, "k-"), (route.right, "k-"), (np.zeros_like(route.s), "k--")):
        xy = route.position(route.s, lat)
        ax.plot(xy[:, 0], xy[:, 1], style, lw=1.0 if style == "k-" else 0.6)


def plot_trajectories(scenario: str, runs: dict[str, dict], out: Path) -> Path:
    fig, axes = plt.subplots(len(runs), 1, figsize=(11, 2.6 * len(runs)), squeeze=False)
    for ax, (policy, rec) in zip(axes[:, 0], runs.items()):
        t = rec["trace"]
        x, y = np.array(t["x"], dtype=float), np.array(t["y"], dtype=float)
        if "road" in rec:
            road = RoadGeometry(**rec["road"])
            _road(ax, road, s_max=float(np.max(x)) + 80.0)
        else:  # a highway-env road: the EV's route at the episode's last step, all the record keeps of it
            _route_edges(ax, _route(rec["route"]))
        ov = np.array(t["ov_xy"], dtype=float).reshape(len(x), -1, 2)  # (T, K, 2), K = 0 too
        for k in range(ov.shape[1]):
            color = OV_COLORS[k % len(OV_COLORS)]
            ax.plot(ov[:, k, 0], ov[:, k, 1], ":", color=color, label=f"OV{k + 1}")
            ax.plot(*ov[-1, k], "s", color=color)
        # The reference lane the behaviour layer named, along the EV's path. Only on a closed-form road: a route's
        # trace measures s and the lane on the route of each step, not on the last one the record keeps.
        if "road" in rec and _reference_lane(t):
            lane = np.array([ref[2] for ref in t["reference"]], dtype=float)
            ref_xy = road.position(np.array(t["s"], dtype=float), lane)
            ax.plot(ref_xy[:, 0], ref_xy[:, 1], "--", color=policy_color(policy), lw=0.8, alpha=0.6,
                    label="reference lane")
        ax.plot(x, y, color=policy_color(policy), lw=2, label=f"EV ({policy_label(policy)})")
        ax.plot(x[-1], y[-1], "s", color=policy_color(policy))
        outcome = "collision" if rec["metrics"]["collision_rate"] else (
            "off road" if rec["metrics"]["offroad_rate"] else "safe")
        ax.set_title(f"{scenario}, {policy}, seed {rec['seed']}: {outcome}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.invert_yaxis()  # highway-env draws +y downwards: keep the rendered orientation
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(loc="upper right", fontsize=7)
    return _save(fig, out / f"trajectories_{scenario}.png")


def plot_controls(scenario: str, runs: dict[str, dict], out: Path) -> Path:
    b = _bounds(next(iter(runs.values())))
    fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True)
    panels = [("acceleration [m/s²]", b.accel), ("steering [rad]", (-b.steer, b.steer)),
              ("Δ acceleration [m/s² per step]", (-b.accel_rate, b.accel_rate)),
              ("Δ steering [rad per step]", (-b.steer_rate, b.steer_rate))]
    for policy, rec in runs.items():
        u = np.array(rec["trace"]["input"], dtype=float)
        du = np.diff(np.vstack([np.zeros((1, 2)), u]), axis=0)
        for ax, series in zip(axes.flat, (u[:, 0], u[:, 1], du[:, 0], du[:, 1])):
            ax.plot(series, color=policy_color(policy), label=policy_label(policy))
    for ax, (label, (lo, hi)) in zip(axes.flat, panels):
        ax.axhline(lo, color="k", lw=0.8)
        ax.axhline(hi, color="k", lw=0.8)
        ax.set_ylabel(label)
    for ax in axes[1]:
        ax.set_xlabel("time step")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{scenario}: control profiles with their bounds")
    return _save(fig, out / f"controls_{scenario}.png")


def plot_safety(scenario: str, runs: dict[str, dict], out: Path) -> Path:
    first = next(iter(runs.values()))
    d_min = first["bounds"]["d_min"]
    # Each record's own OVs: records of one scenario made by different code may track different numbers of them.
    k_ovs = max(len(rec["trace"]["ov_distance"][0]) for rec in runs.values())
    fig, axes = plt.subplots(1, k_ovs + 2, figsize=(4 * (k_ovs + 2), 3.4))
    for policy, rec in runs.items():
        t, c = rec["trace"], policy_color(policy)
        d = np.array(t["ov_distance"], dtype=float).reshape(len(t["x"]), -1)
        for k in range(d.shape[1]):
            axes[k].plot(d[:, k], color=c, label=policy_label(policy))
        axes[k_ovs].plot(t["edge_distance"], color=c, label=policy_label(policy))
        axes[k_ovs + 1].plot(t["speed"], color=c, label=policy_label(policy))
    axes[k_ovs + 1].plot(first["trace"]["reference_speed"], "k--", label="reference")
    for k in range(k_ovs):
        axes[k].axhline(d_min, color="k", lw=0.8)
        axes[k].set_ylabel(f"distance to OV{k + 1} [m]")
    axes[k_ovs].axhline(first["bounds"]["edge_margin"], color="k", lw=0.8)
    axes[k_ovs].set_ylabel("distance to road edge [m]")
    axes[k_ovs + 1].set_ylabel("speed [m/s]")
    for ax in axes:
        ax.set_xlabel("time step")
        ax.legend(fontsize=7)
    fig.suptitle(f"{scenario}: safety margins and reference-speed tracking")
    return _save(fig, out / f"safety_{scenario}.png")


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    write_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def render_episode(scenario: str, policy: str, seed: int, path: str | Path, every: int = 30) -> Path:
    """Run one episode with highway-env's renderer and save a strip of frames (every ``every`` steps and
    the last one) as one PNG: what the simulator shows, next to the plotted trajectories."""
    env = gym.make(envs.env_id(scenario), render_mode="rgb_array")
    frames: list[tuple[int, np.ndarray]] = []

    def keep(env, obs, info) -> None:
        step = env.unwrapped.steps
        done = info.get("collision") or info.get("offroad") or env.unwrapped.steps >= env.spec.max_episode_steps
        if step % every == 0 or done:
            frames.append((step, env.render()))

    rollout(env, make_policy(policy, env), seed, on_step=keep)
    env.close()
    fig, axes = plt.subplots(len(frames), 1, figsize=(8, 2.4 * len(frames)))
    for ax, (step, frame) in zip(np.atleast_1d(axes), frames):
        ax.imshow(frame)
        ax.set_axis_off()
        ax.set_title(f"{scenario}, {policy}, seed {seed}: step {step}", fontsize=8)
    return _save(fig, Path(path))


def plot_all(folder: str | Path, out: str | Path | None = None) -> list[Path]:
    """Draw every figure for the evaluation in ``folder`` into ``out`` (default ``folder/figures``), made only when
    there is something to draw. :class:`bimp.agents.errors.EvaluationError` for a folder or ``out`` that cannot be
    read or written. A record whose trace cannot be drawn is skipped with a warning (:func:`drawable_records`)."""
    folder = Path(folder)
    flag = "--out" if out is not None else "the figures folder"
    out = check_out_dir(folder / "figures" if out is None else out, create=False, flag=flag)
    traced = traced_episodes(drawable_records(folder))
    if not traced:
        return []
    check_out_dir(out, flag=flag)
    written = []
    for scenario, runs in traced.items():
        written += [plot_trajectories(scenario, runs, out), plot_controls(scenario, runs, out),
                    plot_safety(scenario, runs, out)]
    return written
