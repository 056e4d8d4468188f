"""``bimp train-dynamics``: train the MLP vehicle model on the env's own vehicle, save its weights and print its
accuracy on held-out data (:mod:`bimp.planners.dynamics_train`)."""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from bimp.planners.dynamics import save_model
from bimp.planners.dynamics_train import DataConfig, TrainConfig, accuracy_report, generate_data, train

DEFAULT_OUT = Path("runs") / "dynamics" / "mlp.pt"


def parser() -> argparse.ArgumentParser:
    """The command line of ``bimp train-dynamics``."""
    p = argparse.ArgumentParser(prog="bimp train-dynamics", description="Train the MLP vehicle model on the env's "
                                "own vehicle, save its weights and print its accuracy on held-out data.")
    p.add_argument("--seed", type=int, default=0, help="seed of the data, the training and the report")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT,
                   help=f"where to write the weights (default: {DEFAULT_OUT}; the shipped model is replaced only "
                   f"when named: --out planners/weights/mlp.pt). A planner config uses them with `dynamics: PATH`")
    p.add_argument("--steps", type=int, default=TrainConfig.steps, help="Adam steps")
    p.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    p.add_argument("--episodes", type=int, default=10, help="held-out runs per scenario in the report")
    p.add_argument("--steer-limit", type=float, default=DataConfig.steer_limit,
                   help="the model's steering envelope [rad] either way (default: the paper's actuator, "
                   f"{DataConfig.steer_limit}; the shipped wide model: 0.8, the widest actuator of a highway-env road)")
    return p


def main(argv: list[str] | None = None) -> int:
    """``bimp train-dynamics ARGS``: ``argv`` the arguments (default: the command line's)."""
    args = parser().parse_args(argv)
    config = TrainConfig(seed=args.seed, steps=args.steps, batch_size=args.batch_size)
    data_config = DataConfig(steer_limit=args.steer_limit)
    train_seq, report_seq = np.random.SeedSequence(args.seed).spawn(2)

    t0 = time.perf_counter()
    x, u, y = generate_data(np.random.default_rng(train_seq), data_config)
    print(f"training data: {len(x)} transitions of the env's vehicle ({time.perf_counter() - t0:.1f} s)")
    t1 = time.perf_counter()
    model, losses = train(x, u, y, config, log_every=max(config.steps // 10, 1),
                          steer_range=(-data_config.steer_limit, data_config.steer_limit))
    print(f"trained {config.steps} steps in {time.perf_counter() - t1:.0f} s; final loss "
          f"{losses[-min(100, len(losses)):].mean():.3e}")
    path = save_model(model, args.out, extra={"train": asdict(config), "data": asdict(data_config)})
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} kB)\n")
    print(accuracy_report(model, np.random.default_rng(report_seq), episodes=args.episodes))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")
    print(f"weights: {path} (use them in a planner config with `dynamics: {path}`)")
    return 0
