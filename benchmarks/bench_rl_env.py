"""What an RL training step's env costs on each suite family, under bimp's fast traffic core and highway-env's own.

    .venv/bin/python benchmarks/bench_rl_env.py [--steps 200]

Per family at ``hard`` (paper-noisy: both of its scenarios): the env as RL trains on it (``PlanningWrapper`` over
``gym.make(ID)``), driven by uniform random actions from a fixed generator (as an untrained policy acts), ``--steps``
steps under each core, the two interleaved in rounds of 50 steps. Reported: env steps per CPU second (process time,
so a load that shares the machine counts less than in wall time) under each core, their ratio, and the CPU hours of
the env alone for six runs of 150k steps (PPO and SAC x 3 training seeds, docs/suite.md) under the fast core. A
script, not a test: compare the numbers of one run only.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one thread, as every episode runs

import argparse  # noqa: E402
import time  # noqa: E402

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

from bimp import envs  # noqa: E402
from bimp.envs.wrappers import PlanningWrapper  # noqa: E402

FAMILIES = ["two-way-overtake-hard", "erratic-traffic-hard", "cut-in-hard", "stalled-vehicle-hard",
            "dense-highway-hard", "lane-drop-hard", "overtaking-noisy-hard", "emergency-brake-noisy-hard"]
RUN_STEPS = 6 * 150_000  # PPO and SAC, three training seeds each, 150k steps


def _drive(env: gym.Env, rng: np.random.Generator, steps: int, episode: list[int]) -> float:
    spent = 0.0
    for _ in range(steps):
        action = rng.uniform(-1.0, 1.0, 2).astype(np.float32)
        start = time.process_time()
        _, _, terminated, truncated, _ = env.step(action)
        spent += time.process_time() - start
        if terminated or truncated:
            episode[0] += 1
            env.reset(seed=episode[0])
    return spent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=200, help="steps per core and family")
    args = parser.parse_args()
    print("| family | env steps per CPU second, fast | highway-env's | ratio | six runs' env, CPU hours (fast) |")
    print("|---|---|---|---|---|")
    total = 0.0
    for name in FAMILIES:
        made = {fast: PlanningWrapper(gym.make(envs.env_id(name), fast_traffic=fast)) for fast in (True, False)}
        spent = {True: 0.0, False: 0.0}
        rngs = {fast: np.random.default_rng(0) for fast in made}
        episodes = {fast: [0] for fast in made}
        for env in made.values():
            env.reset(seed=0)
        for k in range(0, args.steps, 50):
            for fast in ((True, False) if k % 100 == 0 else (False, True)):
                spent[fast] += _drive(made[fast], rngs[fast], min(50, args.steps - k), episodes[fast])
        rate = {fast: args.steps / spent[fast] for fast in made}
        hours = RUN_STEPS / rate[True] / 3600
        total += hours
        print(f"| {name} | {rate[True]:.0f} | {rate[False]:.0f} | {rate[True] / rate[False]:.2f} | {hours:.1f} |",
              flush=True)
    print(f"\nsix highway families and paper-noisy: {total:.1f} CPU hours of env steps under the fast core")


if __name__ == "__main__":
    main()
