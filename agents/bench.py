"""``bimp bench``: plan-step time of EnKTS, EnKS, MPPI and NMPC side by side, in one run (targets: README "Benchmark").

    bimp bench [--repeats 30] [--quick] [--out bench.json]
    bimp bench --device [--out bench_device.json]     # EnKTS on JAX's default device, N up to 10^5

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

One thread everywhere: ``torch.set_num_threads(1)`` and ``OPENBLAS_NUM_THREADS=1`` (also OMP / MKL). BLAS reads the
latter only when numpy loads, and ``bimp`` has loaded numpy before this module (the ``agents`` package imports
gymnasium), so unless the variable is already 1 the benchmark reruns itself in a fresh interpreter with it set.
On a shared machine the numbers move with the load: compare ratios from one run, not times across runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym

from bimp import envs
from bimp.agents.cli import EvaluationError, check_out_dir
from bimp.agents.registry import POLICIES, make_policy
from bimp.agents.rollout import rollout
from bimp.planners.dynamics import load_model

THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
SCENARIO = "overtaking"
N_VALUES, N_QUICK = (50, 500, 2000), (50, 500)
N_LARGE = 10_000  # EnKTS and EnKS only: MPPI and the floor take seconds there
N_DEVICE = (50, 2000, 10_000, 100_000)
H_DEFAULT, H_VALUES = 20, (10, 20, 40)


def sampled() -> list[str]:
    """The planners timed at every N: those whose compute is the particle count (``n_particles`` is the frontier
    axis of their :class:`~bimp.agents.registry.PolicySpec`), in the table's order."""
    return [name for name, spec in POLICIES.items() if spec.frontier_axis == "n_particles"]


def _single_threaded() -> bool:
    return all(os.environ.get(v) == "1" for v in THREAD_VARS)


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


def floor_ms(n: int, repeats: int, horizon: int = H_DEFAULT) -> float:
    """Median [ms] of ``horizon`` forward passes of the shipped MLP on ``n`` rows, float32, plain numpy."""
    import numpy as np

    model = load_model()
    rng = np.random.default_rng(0)
    x = np.column_stack([np.zeros((n, 3)), rng.uniform(0, 30, n)])
    u = np.column_stack([rng.uniform(-7, 3, n), rng.uniform(-0.05, 0.05, n)])
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        for _ in range(horizon):
            model.change(x, u)
        times.append(1e3 * (time.perf_counter() - start))
    return float(np.median(times[1:]))


def run(repeats: int, quick: bool, steps: int, progress=print) -> dict:
    """Time everything; returns the JSON-ready result (rows and ratios)."""
    import torch

    torch.set_num_threads(1)
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
        "threads": {"torch": torch.get_num_threads(), **{v: os.environ.get(v) for v in THREAD_VARS}},
        "machine": {"python": platform.python_version(), "processor": platform.machine(), "cpus": os.cpu_count(),
                    "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None},
        "float": "float32", "floor_ms": {str(n): f for n, f in floors.items()},
        "rows": rows, "nmpc": nmpc, "enkts_vs_horizon": h_rows, "ratios": ratios,
    }


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


def report_device(result: dict) -> str:
    lines = [f"EnKTS on {result['device']}, H = {result['horizon']}, {result['float']}, median (p95) of "
             f"{result['repeats']} calls:"]
    for r in result["rows"]:
        lines.append(f"  N={r['n_particles']:>7}: {r['median_ms']:9.2f} ({r['p95_ms']:.2f}) ms, "
                     f"first call {r['first_call_ms']:.0f} ms")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per planner (default 30, quick 5)")
    parser.add_argument("--quick", action="store_true", help="N in {50, 500} and 5 repeats")
    parser.add_argument("--steps", type=int, default=5, help="EnKTS-driven env steps before the timed ones")
    parser.add_argument("--device", action="store_true", help="EnKTS alone on JAX's default device, N up to 10^5")
    parser.add_argument("--out", type=Path, default=None, help="also write the result as JSON here")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    repeats = args.repeats if args.repeats is not None else (5 if args.quick else 30)
    if repeats < 1 or args.steps < 0:
        parser.error("--repeats must be >= 1 and --steps >= 0")
    if args.out is not None:  # before minutes of timing, not after
        try:
            if args.out.is_dir() or not args.out.name:
                raise EvaluationError(f"--out {args.out} is a folder: name the JSON file to write")
            check_out_dir(args.out.parent, create=False)
        except EvaluationError as err:
            print(f"bimp bench: error: {err}", file=sys.stderr)
            return 2
    if not _single_threaded():
        env = {**os.environ, **{v: "1" for v in THREAD_VARS}}
        forwarded = list(sys.argv[1:] if argv is None else argv)
        return subprocess.run([sys.executable, "-m", "bimp.agents.bench", *forwarded], env=env).returncode
    print(f"timing {'quick ' if args.quick else ''}benchmark ({repeats} repeats per planner)...", flush=True)
    if args.device:
        result = run_device(repeats, args.steps, progress=lambda s: print(s, flush=True))
        text = report_device(result)
    else:
        result = run(repeats, args.quick, args.steps, progress=lambda s: print(s, flush=True))
        text = report(result)
    print()
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
