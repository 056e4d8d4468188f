"""``bimp plot DIR``: figures like the paper's from the traced episodes of an evaluation folder.

Per scenario, comparing the policies on the first traced seed they share:
- ``trajectories_<scenario>.png``: the EV paths on the road with the OVs (paper Fig. 1 and 3);
- ``controls_<scenario>.png``: acceleration, steering and their per-step changes with the bounds (Fig. 2, 4);
- ``safety_<scenario>.png``: distance to each OV and to the road edge with the safety margins, and the
  speed against the reference speed (Fig. 5).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: files only
import gymnasium as gym  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bimp import envs  # noqa: E402
from bimp.agents.cli import EvaluationError, check_out_dir  # noqa: E402
from bimp.agents.records import read_records, record_label  # noqa: E402
from bimp.agents.registry import make_policy, policy_color, policy_label  # noqa: E402
from bimp.agents.rollout import rollout  # noqa: E402
from bimp.envs.road import RoadGeometry  # noqa: E402
from bimp.envs.scene import Bounds  # noqa: E402

OV_COLORS = ("tab:cyan", "tab:olive", "tab:gray")  # kept apart from every policy's colour (the policy table's)


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


def plot_trajectories(scenario: str, runs: dict[str, dict], out: Path) -> Path:
    fig, axes = plt.subplots(len(runs), 1, figsize=(11, 2.6 * len(runs)), squeeze=False)
    for ax, (policy, rec) in zip(axes[:, 0], runs.items()):
        t = rec["trace"]
        road = RoadGeometry(**rec["road"])
        x, y = np.array(t["x"]), np.array(t["y"])
        _road(ax, road, s_max=float(np.max(x)) + 80.0)
        ov = np.array(t["ov_xy"], dtype=float)  # (T, K, 2)
        for k in range(ov.shape[1]):
            color = OV_COLORS[k % len(OV_COLORS)]
            ax.plot(ov[:, k, 0], ov[:, k, 1], ":", color=color, label=f"OV{k + 1}")
            ax.plot(*ov[-1, k], "s", color=color)
        if t.get("reference") and t.get("s"):  # the reference lane the behaviour layer named, along the EV's path
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
    b = Bounds(**{k: tuple(v) if isinstance(v, list) else v for k, v in next(iter(runs.values()))["bounds"].items()})
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
    k_ovs = len(first["trace"]["ov_distance"][0])
    fig, axes = plt.subplots(1, k_ovs + 2, figsize=(4 * (k_ovs + 2), 3.4))
    for policy, rec in runs.items():
        t, c = rec["trace"], policy_color(policy)
        d = np.array(t["ov_distance"], dtype=float)
        for k in range(k_ovs):
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
    fig.savefig(path, dpi=110)
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
    there is something to draw. :class:`bimp.agents.cli.EvaluationError` for a folder or ``out`` that cannot be
    read or written."""
    folder = Path(folder)
    flag = "--out" if out is not None else "the figures folder"
    out = check_out_dir(folder / "figures" if out is None else out, create=False, flag=flag)
    traced = traced_episodes(read_records(folder))
    if not traced:
        return []
    check_out_dir(out, flag=flag)
    written = []
    for scenario, runs in traced.items():
        written += [plot_trajectories(scenario, runs, out), plot_controls(scenario, runs, out),
                    plot_safety(scenario, runs, out)]
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp plot", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", help="an evaluation folder (holding episodes.jsonl)")
    parser.add_argument("--out", default=None, help="where to write the PNGs (default FOLDER/figures)")
    args = parser.parse_args(argv)
    try:
        written = plot_all(args.folder, args.out)
    except EvaluationError as err:
        print(f"bimp plot: error: {err}", file=sys.stderr)
        return 2
    if not written:
        print(f"no traced episodes in {args.folder} (bimp evaluate keeps no per-step trace unless asked): run "
              "`bimp evaluate --traces 1 ...` into it first")
        return 1
    for path in written:
        print(path)
    return 0
