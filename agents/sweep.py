"""``bimp sweep``: sample efficiency, success and violation rates against the ensemble size N.

    bimp sweep --scenario overtaking emergency-brake --policy enkts enks --n 10 20 50 100 200 \\
               --episodes 10 --out runs/sweep

Each N is an ordinary (resumable) evaluation in ``OUT/N<n>``; ``OUT/sweep.json`` and ``OUT/sweep.png``
collect them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from agents.evaluate import evaluate

RATES = ("success_rate", "collision_rate", "offroad_rate", "input_violation_rate", "rate_violation_rate")


def sweep(scenarios: list[str], policies: list[str], sizes: list[int], episodes: int, seed: int = 0,
          workers: int = 1, out: str | Path = "runs/sweep", progress: bool = True) -> dict:
    """``{str(N): summary}`` for every ensemble size, written to ``out/sweep.json``."""
    out = Path(out)
    results = {}
    for n in sizes:
        overrides = {p: {"n_particles": n} for p in policies}
        results[str(n)] = evaluate(scenarios, policies, episodes, seed, workers, out / f"N{n}", traces=0,
                                   overrides=overrides, progress=progress)
    (out / "sweep.json").write_text(json.dumps(results, indent=2))
    return results


def plot_sweep(results: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from agents.plots import policy_color

    sizes = sorted(int(n) for n in results)
    entries = next(iter(results.values())).values()
    scenarios = sorted({e["scenario"] for e in entries})
    policies = sorted({e["policy"] for e in entries})
    fig, axes = plt.subplots(len(scenarios), len(RATES), figsize=(3.2 * len(RATES), 2.8 * len(scenarios)),
                             squeeze=False)
    for i, scenario in enumerate(scenarios):
        for j, rate in enumerate(RATES):
            ax = axes[i, j]
            for policy in policies:
                ys = [results[str(n)][f"{policy}/{scenario}"][rate]["mean"] for n in sizes]
                ax.plot(sizes, ys, "o-", color=policy_color(policy), label=policy)
            ax.set_xscale("log")
            ax.set_xlabel("particles N")
            ax.set_title(f"{scenario}: {rate}", fontsize=8)
            ax.set_ylim(-0.05, 1.05)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp sweep", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", nargs="+", default=["overtaking", "emergency-brake"])
    parser.add_argument("--policy", nargs="+", default=["enkts", "enks"])
    parser.add_argument("--n", nargs="+", type=int, default=[10, 20, 50, 100, 200])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default="runs/sweep")
    args = parser.parse_args(argv)
    results = sweep(args.scenario, args.policy, args.n, args.episodes, args.seed, args.workers, args.out)
    print(plot_sweep(results, Path(args.out) / "sweep.png"))
    for n, summary in results.items():
        for key, e in summary.items():
            print(f"N={n:>4} {key:<28} " + " ".join(f"{r}={e[r]['mean']:.2f}" for r in RATES))
    return 0
