"""``bimp bench``: plan-step time of EnKTS, EnKS, MPPI and NMPC side by side, in one run (targets: README "Benchmark").

    bimp bench [--repeats 30] [--quick] [--out bench.json]
    bimp bench --device [--out bench_device.json]     # EnKTS on JAX's default device, N up to 10^5
    bimp bench --env [SCENARIO ...] [--out results/bench/env.json]   # env steps/s: fast traffic vs highway-env's

Every planner plans on the same observations: the overtaking env after ``reset(seed=0)``, driven by EnKTS (shared
tuning, seed 0) for ``--steps`` steps and then ``--repeats`` more, recorded once. Each planner is built, reset, and
called untimed on the observation at ``--steps`` (NMPC compiles its solver there), then timed on the next
``--repeats`` observations in order. A sequence rather than one observation repeated, because a warm start is
the shifted previous plan: on a frozen state that guess is wrong by one step at every call, and NMPC then
runs into its CPU-time cap at every call (on seed 0 even a cold solve needs 20-100 IPOPT iterations), so the
"time" would be the cap. On the recorded sequence each planner runs as in closed loop; the state is the same
for all of them. Reported: median and 95th percentile [ms] for EnKTS, EnKS and MPPI at N in {50, 500, 2000}
(EnKTS and EnKS also at 10^4) with H = 20, NMPC once (it has no N) with its IPOPT statuses; the *floor* at each N
(20 forward passes of the 2x128 MLP on N rows, float32, plain numpy: the model work every plan must do); the ratios
EnKTS/floor and EnKTS/MPPI per N and NMPC/EnKTS at N = 50; EnKTS at N = 50 for H in {10, 20, 40} (how a plan grows
with H); and the first call of each JAX planner shape (compile + one plan). ``--quick``: N in {50, 500} and 5
repeats. EnKTS and EnKS compute in float32 (``bimp.planners.core``).

One thread everywhere: ``run``, ``run_highway`` and ``run_device`` run under :func:`bimp.agents.rollout.one_thread`
(one BLAS / OpenMP thread through ``threadpoolctl``, one torch thread), as every episode does, and the JSON says
what it found there.
On a shared machine the numbers move with the load: compare ratios from one run, not times across runs.

``--scenario ID`` (a wrapped highway-env id, e.g. ``highway-v0``; default ``overtaking``, the above) times EnKTS and
EnKS on the general road instead: ``gym.make("bimp/ID", n_obstacles=K)`` from episode seed 0, driven by highway-env's
IDM/MOBIL (the ``idm`` policy), its first observations recorded together with the scene that was current at each
(the wrapped env republishes its scene, the road ahead of the EV, every step); each planner plans on a stand-in env
whose scene is set to the recorded one before each call, so it sees what it would have seen in closed loop.
Reported: EnKTS and EnKS at N = 50, H = 20, K = 8 OV slots, P = 160 road points every 1 m (``problem.road_points``,
``problem.road_spacing``) with the floor at N = 50 and their ratios to it (target: EnKTS <= 5 ms); EnKTS for K in
{2, 4, 8, 16} at P = 160 (observations recorded anew for each K: the same IDM episode, K slots) and for P in
{40, 80, 160, 320, 640} at K = 8, the window's length held at 160 m (spacing 160 m / P: the same road ahead at a
finer or coarser resolution), each with its ratio to the K = 8, P = 160 point of the same run. All of them (the
floor too) are timed interleaved (:func:`time_interleaved`): each compiled first, then in rounds of one call each on
the same recorded step, so a load that comes and goes falls on all alike. ``--quick``: K in
{2, 8}, P in {40, 160}, 5 repeats. ``--note TEXT`` is stored in the JSON (e.g. what else loaded the machine).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import gymnasium as gym

from bimp import envs
from bimp.agents.evaluation import bench_env
from bimp.agents.registry import POLICIES, make_policy
from bimp.agents.rollout import one_thread, rollout
from bimp.planners.dynamics import load_model

SCENARIO = "overtaking"
N_VALUES, N_QUICK = (50, 500, 2000), (50, 500)
N_LARGE = 10_000  # EnKTS and EnKS only: MPPI and the floor take seconds there
N_DEVICE = (50, 2000, 10_000, 100_000)
H_DEFAULT, H_VALUES = 20, (10, 20, 40)
# --scenario ID (a wrapped highway-env env): the point and the sweeps around it
HIGHWAY_N, HIGHWAY_K, HIGHWAY_P = 50, 8, 160
K_VALUES, K_QUICK = (2, 4, 8, 16), (2, 8)
P_VALUES, P_QUICK = (40, 80, 160, 320, 640), (40, 160)
ROAD_WINDOW = 160.0  # m: the P sweep's window length, road_spacing = ROAD_WINDOW / P (1 m at the default P = 160)
TARGET_MS = 5.0  # issue 26 item 6: EnKTS median plan step at the point above


def sampled() -> list[str]:
    """The planners timed at every N: those whose compute is the particle count (``n_particles`` is the frontier
    axis of their :class:`~bimp.agents.registry.PolicySpec`), in the table's order."""
    return [name for name, spec in POLICIES.items() if spec.frontier_axis == "n_particles"]


def _threads() -> dict:
    """The thread counts the timing ran on: torch's and each loaded BLAS / OpenMP library's (threadpoolctl)."""
    import torch
    from threadpoolctl import threadpool_info

    # Keyed by file: numpy and scipy each load their own OpenBLAS.
    return {"torch": torch.get_num_threads(),
            **{Path(pool["filepath"]).name: pool["num_threads"] for pool in threadpool_info()}}


def observations(count: int):
    """The shared observations: the overtaking env from episode seed 0 driven by EnKTS (shared tuning), the first
    ``count`` observations it acted on. Returns ``(env, [obs, ...])``; the env stays open because the planners read
    its scene (the road is fixed within an episode)."""
    env = gym.make(envs.env_id(SCENARIO))
    recorded: list = []
    rollout(env, make_policy("enkts", env), 0, max_steps=count, observations=recorded)
    if len(recorded) < count:
        raise RuntimeError(f"the EnKTS driver ended the episode after {len(recorded)} steps; use fewer")
    return env, recorded


class _Replay:
    """A stand-in env for a planner on recorded (observation, scene) pairs: ``unwrapped.scene`` is whatever the
    benchmark set last, the recorded scene of the observation about to be planned on."""

    def __init__(self, scene):
        self.scene = scene

    @property
    def unwrapped(self):
        return self


def highway_observations(scenario: str, count: int, n_obstacles: int) -> list[tuple]:
    """The first ``count`` observations of ``bimp/<scenario>`` with ``n_obstacles`` OV slots, episode seed 0,
    driven by highway-env's IDM/MOBIL (``idm``), each with the scene that was current when it was observed:
    ``[(obs, scene), ...]``."""
    env = gym.make(f"bimp/{scenario}", n_obstacles=n_obstacles)
    pairs: list = []
    episode = rollout(env, make_policy("idm", env), 0, max_steps=count,
                      on_step=lambda e, obs, _: pairs.append((obs, e.unwrapped.scene)))
    env.close()
    if episode.steps < count:
        raise RuntimeError(f"the IDM driver's episode on {scenario} ended after {episode.steps} steps; use fewer")
    return pairs[:count]  # on_step also saw the observation after the last step, which nothing acted on


def time_policy(name: str, env, sequence: list, repeats: int, horizon: int = H_DEFAULT, **overrides) -> dict:
    """Median and 95th percentile [ms] of ``act`` on ``sequence[1:repeats + 1]`` after an untimed call on
    ``sequence[0]``, planning ``horizon`` steps ahead (the problem's horizon, the same key for every planner)."""
    import jax
    import numpy as np

    jax.clear_caches()  # the first call of a JAX planner then includes its compile, whatever ran before
    policy = make_policy(name, env, problem={"horizon": horizon}, **overrides)
    policy.reset(0)
    start = time.perf_counter()
    policy.act(sequence[0])  # JAX planners compile here
    first = 1e3 * (time.perf_counter() - start)
    times = np.empty(repeats)
    for i in range(repeats):
        obs = sequence[i + 1]
        start = time.perf_counter()
        policy.act(obs)
        times[i] = 1e3 * (time.perf_counter() - start)
    row = {"planner": name, **overrides, "horizon": horizon, "repeats": repeats, "median_ms": float(np.median(times)),
           "p95_ms": float(np.percentile(times, 95)), "first_call_ms": first}
    if hasattr(policy, "failures"):  # NMPC: how the timed solves ended
        row["solver_failures"] = int(policy.failures)
        row["ipopt_statuses"] = dict(policy.statuses)
    return row


def time_interleaved(entries: list[dict], repeats: int, progress=print) -> list[dict]:
    """Time several planners side by side on recorded (observation, scene) pairs, interleaved: each entry
    ``{"name", "pairs", "problem", "overrides", "row"}`` (``pairs``: ``[(obs, scene), ...]``, ``problem``: problem
    keys besides the horizon, ``row``: fields for its row) is built and called once on ``pairs[0]`` after
    ``jax.clear_caches()`` (its first call: compile + one plan), then every planner is reset and warmed anew (the
    cache cleared for the later ones), and the timed calls go in rounds: round ``i`` calls each planner once on its
    ``pairs[i + 1]``, the scene it sees set to that pair's (the order rotated each round). A load that comes and goes
    on a shared machine then falls on every planner alike, and ratios within a run hold. ``None`` as an entry's
    name times the floor (:func:`floor_ms`'s 20 MLP passes, on ``HIGHWAY_N`` rows) in the same rounds. Returns one
    row per entry."""
    import jax
    import numpy as np

    floor = floor_passes(HIGHWAY_N)
    calls, firsts = [], []
    for entry in entries:
        if entry["name"] is None:
            calls.append(lambda _: floor())
            firsts.append(None)
            continue
        pairs, env = entry["pairs"], _Replay(entry["pairs"][0][1])
        jax.clear_caches()  # the first call then includes its compile, whatever ran before
        policy = make_policy(entry["name"], env, problem={"horizon": H_DEFAULT, **entry["problem"]},
                             **entry["overrides"])
        policy.reset(0)
        start = time.perf_counter()
        policy.act(pairs[0][0])
        firsts.append(1e3 * (time.perf_counter() - start))
        progress(f"  built {entry['name']} {entry['row']} (first call {firsts[-1]:.0f} ms)")

        def call(i: int, policy=policy, env=env, pairs=pairs) -> None:
            obs, env.scene = pairs[i]
            policy.act(obs)

        calls.append((policy, env, pairs, call))
    for c in calls:  # every planner from its start again, compiled anew (untimed) after the last cache clear
        if isinstance(c, tuple):
            policy, env, pairs, _ = c
            policy.reset(0)
            env.scene = pairs[0][1]
            policy.act(pairs[0][0])
    calls = [c[3] if isinstance(c, tuple) else c for c in calls]
    times = np.empty((len(calls), repeats))
    for i in range(repeats):
        for j in np.roll(np.arange(len(calls)), -i):
            start = time.perf_counter()
            calls[j](i + 1)
            times[j, i] = 1e3 * (time.perf_counter() - start)
    return [{"planner": e["name"] or "floor", **e["row"], "horizon": H_DEFAULT, "repeats": repeats,
             "median_ms": float(np.median(t)), "p95_ms": float(np.percentile(t, 95)),
             **({"first_call_ms": f} if f is not None else {})} for e, t, f in zip(entries, times, firsts)]


def floor_passes(n: int, horizon: int = H_DEFAULT):
    """The floor's work as a call: ``horizon`` forward passes of the shipped MLP on ``n`` fixed rows (states at
    0-30 m/s, inputs inside the planning bounds), float32, plain numpy."""
    import numpy as np

    model = load_model()
    rng = np.random.default_rng(0)
    x = np.column_stack([np.zeros((n, 3)), rng.uniform(0, 30, n)])
    u = np.column_stack([rng.uniform(-7, 3, n), rng.uniform(-0.05, 0.05, n)])

    def passes() -> None:
        for _ in range(horizon):
            model.change(x, u)

    return passes


def floor_ms(n: int, repeats: int, horizon: int = H_DEFAULT) -> float:
    """Median [ms] of :func:`floor_passes` (``horizon`` passes on ``n`` rows) over ``repeats`` calls after one."""
    import numpy as np

    passes = floor_passes(n, horizon)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        passes()
        times.append(1e3 * (time.perf_counter() - start))
    return float(np.median(times[1:]))


@one_thread()
def run(repeats: int, quick: bool, steps: int, progress=print) -> dict:
    """Time everything; returns the JSON-ready result (rows and ratios)."""
    env, recorded = observations(steps + repeats + 1)
    obs = recorded[steps:]
    n_values = N_QUICK if quick else N_VALUES
    rows = []
    for n in n_values:
        for name in sampled():
            rows.append(time_policy(name, env, obs, repeats, n_particles=n, horizon=H_DEFAULT))
            progress(f"  {name:<6} N={n:<5} {rows[-1]['median_ms']:9.2f} ms")
    floors = {n: floor_ms(n, repeats) for n in n_values}
    for n in n_values:
        progress(f"  floor  N={n:<5} {floors[n]:9.2f} ms  (20 MLP passes, numpy float32)")
    if not quick:
        for name in ("enkts", "enks"):
            rows.append(time_policy(name, env, obs, repeats, n_particles=N_LARGE, horizon=H_DEFAULT))
            progress(f"  {name:<6} N={N_LARGE:<5} {rows[-1]['median_ms']:9.2f} ms")
    nmpc = time_policy("nmpc", env, obs, repeats, horizon=H_DEFAULT)
    progress(f"  nmpc   any N  {nmpc['median_ms']:9.2f} ms")
    h_rows = [r for r in rows if r["planner"] == "enkts" and r["n_particles"] == 50 and r["horizon"] == H_DEFAULT]
    for h in H_VALUES:
        if h != H_DEFAULT:
            h_rows.append(time_policy("enkts", env, obs, repeats, n_particles=50, horizon=h))
            progress(f"  enkts  N=50    H={h:<3} {h_rows[-1]['median_ms']:9.2f} ms")
    h_rows.sort(key=lambda r: r["horizon"])
    env.close()

    median = {(r["planner"], r["n_particles"]): r["median_ms"] for r in rows}
    ratios = {f"enkts/mppi N={n}": median["enkts", n] / median["mppi", n] for n in n_values}
    ratios.update({f"enkts/floor N={n}": median["enkts", n] / floors[n] for n in n_values})
    ratios["nmpc/enkts N=50"] = nmpc["median_ms"] / median["enkts", 50]
    return {
        "scenario": SCENARIO, "env_seed": 0, "steps_before": steps, "horizon": H_DEFAULT, "repeats": repeats,
        "threads": _threads(),
        "machine": bench_env.machine(),
        "float": "float32", "floor_ms": {str(n): f for n, f in floors.items()},
        "rows": rows, "nmpc": nmpc, "enkts_vs_horizon": h_rows, "ratios": ratios,
    }


@one_thread()
def run_highway(scenario: str, repeats: int, quick: bool, steps: int, progress=print) -> dict:
    """EnKTS and EnKS on a wrapped highway-env env's recorded observations (module docstring): the point
    (N = 50, H = 20, K = 8, P = 160), the floor, the K and P sweeps; returns the JSON-ready result."""
    k_values, p_values = (K_QUICK, P_QUICK) if quick else (K_VALUES, P_VALUES)
    count = steps + repeats + 1
    recorded = {k: highway_observations(scenario, count, k)[steps:] for k in sorted({*k_values, HIGHWAY_K})}
    point = [(HIGHWAY_K, HIGHWAY_P), *((k, HIGHWAY_P) for k in k_values if k != HIGHWAY_K),
             *((HIGHWAY_K, p) for p in p_values if p != HIGHWAY_P)]  # the point first, then the sweeps' others
    entries = [{"name": None, "pairs": None, "problem": {}, "overrides": {}, "row": {"n_particles": HIGHWAY_N}}]
    for name, (k, p) in [("enkts", point[0]), ("enks", point[0]), *(("enkts", kp) for kp in point[1:])]:
        entries.append({"name": name, "pairs": recorded[k], "problem": {"road_points": p,
                                                                         "road_spacing": ROAD_WINDOW / p},
                        "overrides": {"n_particles": HIGHWAY_N},
                        "row": {"n_particles": HIGHWAY_N, "n_obstacles": k, "road_points": p,
                                "road_spacing": ROAD_WINDOW / p}})
    timed = time_interleaved(entries, repeats, progress)
    floor_row, rows = timed[0], timed[1:3]
    floor, base = floor_row["median_ms"], rows[0]
    by_kp = {(r["n_obstacles"], r["road_points"]): r for r in [rows[0], *timed[3:]]}
    k_sweep = [{**by_kp[k, HIGHWAY_P], "ratio": by_kp[k, HIGHWAY_P]["median_ms"] / base["median_ms"]}
               for k in k_values]
    p_sweep = [{**by_kp[HIGHWAY_K, p], "ratio": by_kp[HIGHWAY_K, p]["median_ms"] / base["median_ms"]}
               for p in p_values]
    for r in [*rows, floor_row]:
        progress(f"  {r['planner']:<6} {r['median_ms']:9.2f} ms (p95 {r['p95_ms']:.2f})")
    median = {r["planner"]: r["median_ms"] for r in rows}
    return {
        "scenario": scenario, "driver": "idm", "env_seed": 0, "steps_before": steps, "horizon": H_DEFAULT,
        "n_particles": HIGHWAY_N, "n_obstacles": HIGHWAY_K, "road_points": HIGHWAY_P,
        "road_spacing": ROAD_WINDOW / HIGHWAY_P, "repeats": repeats, "quick": quick,
        "p_sweep_spacing": f"road_spacing = {ROAD_WINDOW:g} m / P: the window's length held, resolution varied",
        "threads": _threads(),
        "machine": bench_env.machine(), "float": "float32", "timing": "interleaved",
        "floor_ms": {str(HIGHWAY_N): floor}, "floor_p95_ms": floor_row["p95_ms"], "rows": rows,
        "k_sweep": k_sweep, "p_sweep": p_sweep,
        "ratios": {"enkts/floor": median["enkts"] / floor, "enks/floor": median["enks"] / floor,
                   "enkts/enks": median["enkts"] / median["enks"]},
        "target_ms": TARGET_MS, "target_met": median["enkts"] <= TARGET_MS,
    }


@one_thread()
def run_device(repeats: int, steps: int, sizes=N_DEVICE, progress=print) -> dict:
    """EnKTS on JAX's default device (a GPU when JAX sees one) at large N: median plan time and first call."""
    import jax

    env, recorded = observations(steps + repeats + 1)
    obs = recorded[steps:]
    rows = []
    for n in sizes:
        rows.append(time_policy("enkts", env, obs, repeats, n_particles=n, horizon=H_DEFAULT))
        progress(f"  enkts  N={n:<7} {rows[-1]['median_ms']:9.2f} ms (first call {rows[-1]['first_call_ms']:.0f} ms)")
    env.close()
    device = jax.devices()[0]
    return {"device": f"{device.platform}: {device.device_kind}", "horizon": H_DEFAULT, "repeats": repeats,
            "float": "float32", "rows": rows}


def report(result: dict) -> str:
    """The side-by-side table as text."""
    fmt = lambda r: f"{r['median_ms']:8.2f} ({r['p95_ms']:7.2f})"  # noqa: E731
    by = {(r["planner"], r["n_particles"]): r for r in result["rows"]}
    n_values = sorted({r["n_particles"] for r in result["rows"]})
    load = result["machine"]["load_average"]
    lines = [
        f"plan-step time [ms], median (p95) of {result['repeats']} calls, one thread; {result['scenario']} env, "
        f"seed 0, EnKTS-driven steps {result['steps_before'] + 1}..{result['steps_before'] + result['repeats']}; "
        f"H = {result['horizon']}"
        + (f"; load average {load[0]:.2f} on {result['machine']['cpus']} CPUs" if load else ""),
        f"{'N':>6} {'EnKTS':>18} {'EnKS':>18} {'MPPI':>18} {'floor':>8} {'EnKTS/floor':>11} {'EnKTS/MPPI':>11}"
        f" {'EnKTS 1st call':>14}",
    ]
    for n in n_values:
        mppi = fmt(by["mppi", n]) if ("mppi", n) in by else f"{'-':>18}"
        floor = result["floor_ms"].get(str(n))
        ratio = result["ratios"].get(f"enkts/mppi N={n}")
        lines.append(f"{n:>6} {fmt(by['enkts', n])} {fmt(by['enks', n])} {mppi} "
                     + (f"{floor:8.2f} {by['enkts', n]['median_ms'] / floor:>10.1f}x " if floor
                        else f"{'-':>8} {'-':>11} ")
                     + (f"{ratio:>10.2f}x" if ratio else f"{'-':>11}")
                     + f" {by['enkts', n].get('first_call_ms', float('nan')):>11.0f} ms")
    nmpc = result["nmpc"]
    lines.append(f"NMPC (CasADi + IPOPT, same MLP; no N): {fmt(nmpc)}   NMPC/EnKTS(N=50) = "
                 f"{result['ratios']['nmpc/enkts N=50']:.0f}x")
    lines.append(f"  IPOPT over the {nmpc['repeats'] + 1} solves: {nmpc['ipopt_statuses']}, "
                 f"fallbacks {nmpc['solver_failures']}")
    h_rows = result["enkts_vs_horizon"]
    base = next(r for r in h_rows if r["horizon"] == result["horizon"])["median_ms"]
    slopes = [math.log(b["median_ms"] / a["median_ms"]) / math.log(b["horizon"] / a["horizon"])
              for a, b in zip(h_rows, h_rows[1:])]
    lines.append("EnKTS at N = 50 vs H: " + ", ".join(
        f"H={r['horizon']}: {fmt(r).strip()} ({r['median_ms'] / base:.2f}x)" for r in h_rows)
        + "; time ~ H^k with k = " + ", ".join(
            f"{k:.2f} (H {a['horizon']}->{b['horizon']})" for k, a, b in zip(slopes, h_rows, h_rows[1:])))
    lines.append("  (per horizon step O(N) model and measurement work, and an update over the full-width control "
                 "history"
                 " (N x (6 + 2H)): linear in H, quadratic once the update dominates)")
    lines.append(f"float type: {result.get('float', 'float64')}; floor: 20 MLP forward passes on N rows, numpy float32")
    return "\n".join(lines)


def report_highway(result: dict) -> str:
    """The highway section as text: the point, then the K and P sweeps with their ratios to it."""
    fmt = lambda r: f"{r['median_ms']:8.2f} ({r['p95_ms']:7.2f})"  # noqa: E731
    load = result["machine"]["load_average"]
    floor = result["floor_ms"][str(result["n_particles"])]
    lines = [
        f"plan-step time [ms], median (p95) of {result['repeats']} calls, one thread; bimp/{result['scenario']}, "
        f"seed 0, IDM-driven steps {result['steps_before'] + 1}..{result['steps_before'] + result['repeats']}; "
        f"N = {result['n_particles']}, H = {result['horizon']}"
        + (f"; load average {load[0]:.2f} on {result['machine']['cpus']} CPUs" if load else ""),
        f"K = {result['n_obstacles']} OVs, P = {result['road_points']} road points every "
        f"{result['road_spacing']:g} m:",
    ]
    for r in result["rows"]:
        lines.append(f"  {r['planner']:<6} {fmt(r)}  {r['median_ms'] / floor:5.1f}x floor"
                     f"  (first call {r['first_call_ms']:.0f} ms)")
    enkts = result["rows"][0]["median_ms"]
    lines.append(f"  floor  {floor:8.2f}            (20 MLP passes on N rows, numpy float32)")
    lines.append(f"  target EnKTS <= {result['target_ms']:g} ms: {'met' if result['target_met'] else 'NOT met'} "
                 f"({enkts:.2f} ms, {result['ratios']['enkts/floor']:.1f}x floor)")
    lines.append(f"EnKTS vs K (P = {result['road_points']}):")
    lines.append(f"  {'K':>5} {'median (p95)':>18} {'vs K=' + str(result['n_obstacles']):>8}")
    for r in result["k_sweep"]:
        lines.append(f"  {r['n_obstacles']:>5} {fmt(r)} {r['ratio']:>7.2f}x")
    lines.append(f"EnKTS vs P (K = {result['n_obstacles']}; {result['p_sweep_spacing']}):")
    lines.append(f"  {'P':>5} {'spacing':>8} {'median (p95)':>18} {'vs P=' + str(result['road_points']):>8}")
    for r in result["p_sweep"]:
        lines.append(f"  {r['road_points']:>5} {r['road_spacing']:>6.2f} m {fmt(r)} {r['ratio']:>7.2f}x")
    if result.get("note"):
        lines.append(f"note: {result['note']}")
    return "\n".join(lines)


def report_device(result: dict) -> str:
    lines = [f"EnKTS on {result['device']}, H = {result['horizon']}, {result['float']}, median (p95) of "
             f"{result['repeats']} calls:"]
    for r in result["rows"]:
        lines.append(f"  N={r['n_particles']:>7}: {r['median_ms']:9.2f} ({r['p95_ms']:.2f}) ms, "
                     f"first call {r['first_call_ms']:.0f} ms")
    return "\n".join(lines)
