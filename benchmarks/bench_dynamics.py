"""Time one call of the dynamics models at the planner's batch sizes: numpy versus torch, so a planner can pick.

    .venv/bin/python benchmarks/bench_dynamics.py [--weights PATH] [--repeats 200] [--sizes 50 2000]

numpy's BLAS runs on one thread unless ``OPENBLAS_NUM_THREADS`` is set: the design's timing targets are for one
CPU thread, and on a busy machine a threaded BLAS waits for its workers (measured here: a 2000 x 128 x 128 float32
product took 12 ms with 2 threads against 1.3 ms with one).

Prints the median wall time of ``predict(x (N, 4), u (N, 2))`` over ``repeats`` calls (after a warm-up) for the
learned model's numpy path, its torch path on float32 and float64 tensors with torch's default thread count and
with one thread, and the exact bicycle model, plus the ratio torch / numpy. A script, not a test: timings depend
on the machine and its load, so compare numbers from one run only.
"""

from __future__ import annotations

import os

# Before numpy is imported, or OpenBLAS has started its threads already.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bimp.planners.dynamics import BicycleModel, load_model  # noqa: E402


def median_time(fn, repeats: int) -> float:
    """Median seconds of ``fn()`` over ``repeats`` calls after 10 warm-up calls."""
    for _ in range(10):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def batch(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Plausible planner rows: ``x (n, 4)`` near 25 m/s, ``u (n, 2)`` inside the planning bounds."""
    x = np.column_stack([rng.uniform(0, 300, n), rng.uniform(-4, 4, n), rng.normal(0, 0.1, n),
                         rng.uniform(0, 30, n)])
    u = np.column_stack([rng.uniform(-7, 3, n), rng.uniform(-0.05, 0.05, n)])
    return x, u


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", default=None, help="checkpoint (default: the shipped planners/weights/mlp.pt)")
    p.add_argument("--repeats", type=int, default=200)
    p.add_argument("--sizes", type=int, nargs="+", default=[50, 2000])
    args = p.parse_args(argv)

    model, bicycle = load_model(args.weights), BicycleModel()
    rng = np.random.default_rng(0)
    default_threads = torch.get_num_threads()
    print(f"{platform.processor() or platform.machine()}, numpy {np.__version__}, torch {torch.__version__}, "
          f"torch threads {default_threads}, OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs, median of {args.repeats} calls")
    print(f"{'N':>6} {'path':<28} {'time [us]':>10} {'vs numpy':>9}")
    for n in args.sizes:
        x, u = batch(rng, n)
        t_np = median_time(lambda: model.predict(x, u), args.repeats)
        rows = [("MLP numpy", t_np)]
        with torch.no_grad():
            for threads in (default_threads, 1):
                torch.set_num_threads(threads)
                for dtype in (torch.float32, torch.float64):
                    xt, ut = torch.as_tensor(x, dtype=dtype), torch.as_tensor(u, dtype=dtype)
                    t = median_time(lambda: model.predict_torch(xt, ut), args.repeats)
                    rows.append((f"MLP torch, {str(dtype)[6:]} x, {threads} thr", t))
            torch.set_num_threads(default_threads)
        rows.append(("bicycle numpy", median_time(lambda: bicycle.predict(x, u), args.repeats)))
        for name, t in rows:
            print(f"{n:>6} {name:<28} {t * 1e6:>10.1f} {t / t_np:>8.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
