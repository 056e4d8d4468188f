"""Learning curves and training cost of ``bimp train-rl`` runs, read from what each run folder holds: its Monitor
logs (``{i}.monitor.csv``: every finished episode's return, length and wall time) and ``config.json``.

    bimp curves results/training/*_cut-in-hard_s* --out docs/img/rl/cut-in-hard.png

draws one panel per algorithm and scenario (each training seed thin, their mean bold, the band from the lowest to
the highest seed) and prints per group the runs, their timesteps and the hours they trained.
"""

from __future__ import annotations

import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

from bimp.agents.errors import EvaluationError
from bimp.agents.files import read_json, read_json_or, write_figure

BIN = 5_000  # timesteps per point of a curve over seeds


def monitor_files(out: Path) -> list[Path]:
    """The Monitor logs of a run folder in the order they were written (``{i}.monitor.csv``)."""
    return sorted(out.glob("*.monitor.csv"), key=lambda p: int(p.name.split(".")[0]))


def _config(out: Path) -> dict:
    config = read_json_or(out / "config.json", None)
    if not isinstance(config, dict) or not {"algo", "scenario", "seed", "n_envs", "timesteps"} <= set(config):
        raise EvaluationError(f"{out} is not a `bimp train-rl` run folder (no config.json with algo, scenario, "
                              f"seed, n_envs and timesteps)")
    return config


def trained(out: Path) -> int | None:
    """The timesteps a run folder's last finished training reached (``train_time.json``, written last); None while
    it has never finished."""
    record = read_json_or(out / "train_time.json", None)
    return record.get("timesteps") if isinstance(record, dict) else None


def finished(out: Path) -> bool:
    """Whether a run folder's training is done for the timesteps its config asks (not while it is made longer)."""
    return (trained(out) or 0) >= _config(out)["timesteps"]


def episodes(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(timesteps, returns)`` of a run's finished episodes, each at the timestep it ended: all envs' logs
    ordered by wall time, their lengths summed (what the run had played when each ended)."""
    from stable_baselines3.common.monitor import load_results

    if not monitor_files(out):
        return np.zeros(0), np.zeros(0)
    df = load_results(str(out))  # episodes of all envs, ordered by wall time
    return np.cumsum(df["l"].to_numpy()).astype(float), df["r"].to_numpy().astype(float)


def last_episode_time(out: Path, n_envs: int, segment: int = -1) -> float:
    """Wall seconds from a segment's start (a run, or a resume: ``n_envs`` logs each) to its last logged episode."""
    logs = monitor_files(out)
    logs = logs[segment * n_envs:][:n_envs] if segment >= 0 else logs[-n_envs:]
    ends = [float(line.split(",")[2]) for log in logs for line in log.read_text().splitlines()[2:] if line.strip()]
    return max(ends, default=0.0)


def hours(out: Path) -> float:
    """Hours a run trained, every segment's summed: its process's CPU time (``cpu.json``, kept at each checkpoint
    and at the end; with the default ``vec_env: dummy`` a run steps its envs and learns in that one process), else
    its wall time, an upper bound where runs outnumbered the cores (``wall.json``: an interrupted segment up to its
    last logged episode or checkpoint, whichever came later; for a run older than that file ``train_time.json``'s
    where it trained in one go, else the Monitor logs, each segment up to its last finished episode)."""
    segments = _cpu_wall(out)
    if segments is not None:
        return sum(c if c > 0 else w for c, w in segments) / 3600  # a segment before cpu.json: its wall time
    done = read_json_or(out / "train_time.json", None)
    if isinstance(done, dict) and done.get("resumed_at") is None and isinstance(done.get("wall_s"), (int, float)):
        return done["wall_s"] / 3600  # trained in one go: its one segment's wall time
    n_envs = _config(out)["n_envs"]
    return sum(last_episode_time(out, n_envs, k) for k in range(len(monitor_files(out)) // n_envs)) / 3600


def seconds(out: Path, name: str) -> list[float] | None:
    """``wall.json`` or ``cpu.json``: seconds per segment; None where the run has no such file.
    :class:`EvaluationError` naming the file where it is not a list of seconds."""
    if not (out / name).is_file():
        return None
    values = read_json(out / name)
    if not (isinstance(values, list) and all(isinstance(v, (int, float)) for v in values)):
        raise EvaluationError(f"{out / name} is not a list of seconds: train into a new --out")
    return [float(v) for v in values]


def measured_cpu(out: Path) -> bool:
    """Whether :func:`hours` of this run is CPU time for every segment (``cpu.json``), not wall time for any."""
    segments = _cpu_wall(out)
    return bool(segments) and all(c > 0 for c, _ in segments)


def _cpu_wall(out: Path) -> list[tuple[float, float]] | None:
    """``(cpu, wall)`` seconds per segment (0 where a file does not reach that segment); None where the run has
    neither ``cpu.json`` nor ``wall.json``."""
    cpus, walls = seconds(out, "cpu.json"), seconds(out, "wall.json")
    if cpus is None and walls is None:
        return None
    cpus, walls = cpus or [], walls or []
    n = max(len(cpus), len(walls))
    return list(zip(per_segment(cpus, n), per_segment(walls, n), strict=True))


def per_segment(values: list[float], n_segments: int) -> list[float]:
    """Seconds per segment from ``values`` (``wall.json`` or ``cpu.json``), ``n_segments`` of them: cut there, and
    zeros for the segments the file does not reach (those run before it existed)."""
    return values[:n_segments] + [0.0] * (n_segments - len(values))


def plot_curve(out: Path, path: Path, title: str = "") -> None:
    """One run's episode return against timesteps, with a moving mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps, returns = episodes(out)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(steps, returns, ".", ms=2, alpha=0.3, label="episode")
    if len(returns) >= 2:
        w = max(1, min(50, len(returns) // 10))
        ax.plot(steps[w - 1:], np.convolve(returns, np.ones(w) / w, mode="valid"), label=f"mean of {w}")
    ax.set(xlabel="timesteps", ylabel="episode return", title=title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    write_figure(fig, path, dpi=120)
    plt.close(fig)


def binned(steps: np.ndarray, returns: np.ndarray, total: int) -> np.ndarray:
    """Mean episode return per :data:`BIN` timesteps, ``(ceil(total / BIN),)``; NaN where no episode ended."""
    n = -(-total // BIN)
    index = np.minimum((steps // BIN).astype(int), n - 1)
    sums, counts = np.bincount(index, returns, n), np.bincount(index, minlength=n)
    with np.errstate(invalid="ignore"):
        return sums / counts


CLIMB_WINDOW = 25_000  # timesteps compared at a curve's end
CLIMB_SHARE = 0.05  # of the gain since the first bin: more than this, and a curve still climbs


def climbing(curves: np.ndarray) -> bool:
    """Whether a learning curve over seeds (``(seeds, bins)`` of :func:`binned`) still climbs at its end: the mean
    over the seeds of their last ``CLIMB_WINDOW`` timesteps above that of the window before by more than
    ``CLIMB_SHARE`` of the gain since the first bin (noise at a plateau stays under it). The rule by which a run is
    made longer (docs/rl.md)."""
    k = CLIMB_WINDOW // BIN
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(curves, axis=0)
    if mean.size < 2 * k + 1 or np.isnan(mean[[0, -1]]).any():
        return False
    last, before = np.nanmean(mean[-k:]), np.nanmean(mean[-2 * k:-k])
    return bool(last - before > CLIMB_SHARE * abs(last - mean[0]))


def groups(runs: list[Path]) -> dict[tuple[str, str], list[tuple[int, Path]]]:
    """``{(algo, scenario): [(seed, run folder)]}``, seeds in order."""
    found: dict[tuple[str, str], list[tuple[int, Path]]] = defaultdict(list)
    for out in runs:
        config = _config(out)
        found[config["algo"], config["scenario"]].append((config["seed"], out))
    return {key: sorted(found[key]) for key in sorted(found)}


def plot_curves(runs: list[Path], path: Path) -> list[dict]:
    """One panel per algorithm and scenario of ``runs``: each seed's mean return per :data:`BIN` timesteps (thin),
    the mean over seeds (bold) and the band from the lowest to the highest seed. Returns a row per panel: runs,
    seeds, timesteps each (trained, or logged so far while training), hours (:func:`hours`), whether the mean still
    climbs (:func:`climbing`) and each seed's mean return over its last 10% of timesteps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    found = groups(runs)
    if not found:
        raise EvaluationError("no run folders given")
    fig, axes = plt.subplots(1, len(found), figsize=(5.5 * len(found), 3.8), squeeze=False)
    rows = []
    for ax, ((algo, scenario), seeds) in zip(axes[0], found.items(), strict=True):
        total = max(int(_config(out)["timesteps"]) for _, out in seeds)
        logged = [episodes(out) for _, out in seeds]  # read once: the curve and the rows below
        curves = np.array([binned(*run, total) for run in logged])
        x = (np.arange(curves.shape[1]) + 1) * BIN
        for (seed, _), curve in zip(seeds, curves, strict=True):
            ax.plot(x, curve, lw=0.8, alpha=0.6, label=f"seed {seed}")
        with warnings.catch_warnings():  # a bin no seed has reached yet stays empty
            warnings.simplefilter("ignore", RuntimeWarning)
            ax.fill_between(x, np.nanmin(curves, axis=0), np.nanmax(curves, axis=0), alpha=0.15)
            ax.plot(x, np.nanmean(curves, axis=0), lw=2.2, color="black", label="mean")
        ax.set(xlabel="timesteps", ylabel=f"mean episode return per {BIN:,}", title=f"{algo.upper()} {scenario}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        rows.append({"algo": algo, "scenario": scenario, "seeds": [seed for seed, _ in seeds],
                     "timesteps": [trained(out) or (int(s[-1]) if len(s) else 0)
                                   for (_, out), (s, _) in zip(seeds, logged, strict=True)],
                     "hours": round(sum(hours(out) for _, out in seeds), 3), "climbing": climbing(curves),
                     "final_return": [float(np.mean(r[s > 0.9 * total])) if np.any(s > 0.9 * total) else None
                                      for s, r in logged]})
    fig.tight_layout()
    write_figure(fig, path, dpi=110)
    plt.close(fig)
    return rows


__all__ = ["BIN", "CLIMB_SHARE", "CLIMB_WINDOW", "binned", "climbing", "episodes", "finished", "groups", "hours",
           "last_episode_time", "measured_cpu", "monitor_files", "plot_curve", "plot_curves", "seconds",
           "trained"]
