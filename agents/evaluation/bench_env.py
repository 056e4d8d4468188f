"""``bimp bench --env``: env steps per second of every registered scenario, bimp's fast traffic core beside
highway-env's own, timed in the same run.

    bimp bench --env                                  # every scenario: the paper's, highway-env's ids, the families
    bimp bench --env highway-v0 cut-in-hard --env-steps 100 --out results/bench/env.json

Per scenario, two envs: ``gym.make(ID)`` (the fast core, :mod:`bimp.envs.traffic`) and ``gym.make(ID,
fast_traffic=False)`` (highway-env's own ``Road``). They drive the same episodes (episode seeds 0, 1, ...; the EV
holds the zero action: no acceleration, wheels straight, so its traffic decides), in rounds of ``--env-steps`` steps
each, the two interleaved round by round and the first of a round alternating, so that a load that comes and goes
falls on both alike. Last, ``plain:highway-v0``: highway-env's own ``gym.make("highway-v0")`` at its default config
(its discrete actions, IDLE every step; 15 simulation steps a step) through :func:`bimp.envs.accelerate` beside the
same env as highway-env has it. Only ``env.step`` is timed (a reset is not). One thread (:func:`one_thread`), as
every episode runs. Reported: steps per second of each and their ratio (fast / highway-env's), and on the envs
behind the highway-env adapter the adapter's share of a fast step in ms (the step's time less the time in
highway-env's own ``step`` under it: the scene, the observation, the safety ``info``); the JSON also keeps each
round's times. On a shared machine the times move with the load: read the ratios, measured side by side.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence

import gymnasium as gym
import numpy as np

from bimp import envs
from bimp.agents.rollout import one_thread
from bimp.envs.highway.adapter import HighwayAdapter

CORES = ("fast", "highway-env")


PLAIN = ("plain:highway-v0",)  # highway-env's own env at its default config, through accelerate


def scenario_names() -> list[str]:
    """Every registered scenario, in the table's order, then highway-env's own highway-v0 (:data:`PLAIN`)."""
    return [*envs.SCENARIOS, *PLAIN]


class _SimClock(gym.Wrapper):
    """Times highway-env's own ``step`` under the adapter (``seconds``), so the adapter's share is the rest."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.seconds = 0.0

    def step(self, action):
        start = time.perf_counter()
        try:
            return self.env.step(action)
        finally:
            self.seconds += time.perf_counter() - start


def _sim_clock(env: gym.Env) -> _SimClock | None:
    """A :class:`_SimClock` put under the highway-env adapter in ``env``'s wrappers (None where there is none)."""
    layer = env
    while isinstance(layer, gym.Wrapper):
        if isinstance(layer, HighwayAdapter):
            layer.env = _SimClock(layer.env)
            return layer.env
        layer = layer.env
    return None


def _drive(env: gym.Env, seed: int, steps: int) -> tuple[float, int]:
    """``(seconds in env.step, steps)`` of ``steps`` steps from ``reset(seed=seed)`` (a new episode, seed + 1000,
    where one ends)."""
    env.reset(seed=seed)
    # The zero action; highway-env's discrete actions: IDLE (1), keep lane and speed.
    action = np.zeros(env.action_space.shape, dtype=env.action_space.dtype) if env.action_space.shape else 1
    spent, episode = 0.0, seed
    for _ in range(steps):
        start = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        spent += time.perf_counter() - start
        if terminated or truncated:
            episode += 1000
            env.reset(seed=episode)
    return spent, steps


def time_scenario(scenario: str, steps: int, rounds: int) -> dict:
    """Both cores on ``scenario`` (the module doc): ``{"fast": {...}, "highway-env": {...}, "ratio"}`` with each
    core's ``steps_per_s``, ``seconds`` and per-round ``round_s``. ``scenario`` ``"plain:ID"``: highway-env's own
    env of ``ID`` at its default config (its actions, 15 simulation steps a step), through :func:`accelerate`."""
    if scenario.startswith("plain:"):
        plain = scenario.removeprefix("plain:")
        made = {"fast": envs.accelerate(gym.make(plain)), "highway-env": gym.make(plain)}
    else:
        made = {"fast": gym.make(envs.env_id(scenario)),
                "highway-env": gym.make(envs.env_id(scenario), fast_traffic=False)}
    return _time(made, steps, rounds)


def _time(made: dict, steps: int, rounds: int) -> dict:
    spent = {core: [] for core in CORES}
    clock = _sim_clock(made["fast"])
    for r in range(rounds):
        for core in (CORES if r % 2 == 0 else CORES[::-1]):
            seconds, _ = _drive(made[core], r, steps)
            spent[core].append(seconds)
    for env in made.values():
        env.close()
    out = {core: {"steps_per_s": steps * rounds / sum(spent[core]), "seconds": sum(spent[core]),
                  "round_s": spent[core]} for core in CORES}
    out["ratio"] = out["fast"]["steps_per_s"] / out["highway-env"]["steps_per_s"]
    out["adapter_ms"] = None if clock is None else 1e3 * (sum(spent["fast"]) - clock.seconds) / (steps * rounds)
    return out


def run_env(scenarios: Sequence[str] | None = None, steps: int = 50, rounds: int = 3,
            progress: Callable[[str], None] = lambda s: None) -> dict:
    """:func:`time_scenario` of every scenario of ``scenarios`` (default :func:`scenario_names`), one thread."""
    names = list(scenarios) if scenarios else scenario_names()
    for name in names:
        if name not in PLAIN:
            envs.scenario_spec(name)  # an unknown name refused before minutes of timing
    results = {}
    with one_thread() as threads:
        for name in names:
            results[name] = time_scenario(name, steps, rounds)
            progress(f"{name}: {results[name]['fast']['steps_per_s']:.0f} steps/s fast, "
                     f"{results[name]['highway-env']['steps_per_s']:.0f} highway-env's, "
                     f"x{results[name]['ratio']:.2f}")
    ratios = np.array([r["ratio"] for r in results.values()])
    adapter = [r["adapter_ms"] for r in results.values() if r["adapter_ms"] is not None]
    return {"adapter_ms_max": max(adapter) if adapter else None,
            "steps": steps, "rounds": rounds, "threads": threads, "machine": machine(), "scenarios": results,
            "ratio_median": float(np.median(ratios)), "ratio_min": float(ratios.min()),
            "ratio_max": float(ratios.max())}


def machine() -> dict:
    """What a benchmark ran on: Python, the processor, the CPUs and the load when it ended (``bimp bench`` too)."""
    return {"python": platform.python_version(), "processor": platform.machine(), "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}


def report_env(result: dict) -> str:
    """The result as a markdown table, a row per scenario, then the ratios' median and range."""
    lines = ["| scenario | steps/s, fast | steps/s, highway-env's | ratio | adapter ms/step |", "|---|---|---|---|---|"]
    for name, r in result["scenarios"].items():
        adapter = "-" if r.get("adapter_ms") is None else f"{r['adapter_ms']:.2f}"
        lines.append(f"| {name} | {r['fast']['steps_per_s']:.0f} | {r['highway-env']['steps_per_s']:.0f} | "
                     f"{r['ratio']:.2f} | {adapter} |")
    lines.append("")
    lines.append(f"Env steps per second, one thread ({result['steps']} steps x {result['rounds']} rounds per core and "
                 f"scenario, interleaved); ratio: fast / highway-env's, median {result['ratio_median']:.2f} "
                 f"(range {result['ratio_min']:.2f}-{result['ratio_max']:.2f}); adapter: the fast step's time outside "
                 f"highway-env's own step" + (f", at most {result['adapter_ms_max']:.2f} ms."
                                              if result.get("adapter_ms_max") is not None else "."))
    return "\n".join(lines) + "\n"


__all__ = ["CORES", "machine", "report_env", "run_env", "scenario_names", "time_scenario"]
