"""Intervals and paired tests for evaluation results, on scipy.stats.

- A rate over episodes (success, collision, off-road: one 0/1 outcome per episode) gets the Wilson score
  interval, which keeps its coverage at 0 or n successes where mean ± std of a 0/1 outcome says nothing.
- A continuous per-episode metric gets a bootstrap interval of its mean (BCa; percentile where BCa is
  undefined, e.g. all values equal), from a generator seeded here so a summary is reproducible.
- Runs of a learning algorithm (training seeds): the mean over tasks of the mean score over runs, with the
  stratified bootstrap interval of Agarwal et al. (2021): runs resampled within each task.
- Two policies on the same seeds: the exact McNemar test on the discordant pairs of a 0/1 outcome, and a paired
  bootstrap interval of the mean per-seed difference of a continuous metric.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
N_RESAMPLES = 2000
BOOTSTRAP_SEED = 20261123  # fixed: the same records always give the same summary


def wilson(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval ``(low, high)`` of a proportion ``successes / n``; ``(0, 1)`` for ``n = 0``."""
    if n == 0:
        return 0.0, 1.0
    ci = stats.binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def rate_summary(outcomes: list[bool | float], confidence: float = CONFIDENCE) -> dict:
    """``{mean, ci_low, ci_high, k, n}`` of 0/1 outcomes (Wilson interval); ``mean`` is None when ``n = 0``."""
    n, k = len(outcomes), int(round(sum(float(o) for o in outcomes)))
    low, high = wilson(k, n, confidence)
    return {"mean": k / n if n else None, "ci_low": low if n else None, "ci_high": high if n else None,
            "k": k, "n": n}


def bootstrap_mean_ci(values, confidence: float = CONFIDENCE, seed: int = BOOTSTRAP_SEED) -> tuple[float, float]:
    """Bootstrap interval ``(low, high)`` of the mean of ``values`` (BCa, percentile where BCa is undefined)."""
    x = np.asarray(values, dtype=float)
    if x.size == 0:
        return math.nan, math.nan
    if x.size == 1 or np.all(x == x[0]):
        return float(x[0]), float(x[0])  # no spread to resample
    for method in ("BCa", "percentile"):
        res = stats.bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=N_RESAMPLES,
                              method=method, rng=np.random.default_rng(seed))
        low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
        if math.isfinite(low) and math.isfinite(high):
            return low, high
    return float(x.min()), float(x.max())


def mean_summary(values, confidence: float = CONFIDENCE) -> dict:
    """``{mean, ci_low, ci_high, std, min, max, n}`` of a continuous metric; None entries when empty."""
    x = np.asarray([v for v in values if v is not None], dtype=float)
    if x.size == 0:
        return {"mean": None, "ci_low": None, "ci_high": None, "std": None, "min": None, "max": None, "n": 0}
    low, high = bootstrap_mean_ci(x, confidence)
    return {"mean": float(x.mean()), "ci_low": low, "ci_high": high, "std": float(x.std()),
            "min": float(x.min()), "max": float(x.max()), "n": int(x.size)}


def mcnemar_exact(a: list[bool], b: list[bool]) -> dict:
    """Exact McNemar test of paired 0/1 outcomes: ``b01`` = a true and b false, ``b10`` = a false and b
    true; two-sided p-value of the binomial test of ``b01`` among the ``b01 + b10`` discordant pairs at 1/2."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape:
        raise ValueError(f"paired outcomes must have the same length, got {a.shape} and {b.shape}")
    only_a, only_b = int(np.sum(a & ~b)), int(np.sum(~a & b))
    p = stats.binomtest(only_a, only_a + only_b, 0.5).pvalue if only_a + only_b else 1.0
    return {"only_a": only_a, "only_b": only_b, "p_value": float(p)}


def paired_bootstrap(a, b, confidence: float = CONFIDENCE) -> dict:
    """Mean per-pair difference ``a - b`` with its bootstrap interval (pairs resampled together)."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    low, high = bootstrap_mean_ci(d, confidence)
    return {"mean_diff": float(d.mean()) if d.size else None, "ci_low": low, "ci_high": high, "n": int(d.size)}


def stratified_bootstrap(scores: list, confidence: float = CONFIDENCE, n_resamples: int = 10_000,
                         seed: int = BOOTSTRAP_SEED) -> dict:
    """Mean over tasks of the per-task mean over runs, with its percentile interval under resampling the runs
    of each task with replacement (stratified by task; Agarwal et al. 2021, rliable's ``StratifiedBootstrap``).

    ``scores``: one 1-D sequence per task, a score per run (e.g. one training seed's success rate on a
    scenario). Returns ``{mean, ci_low, ci_high, runs}``. With few runs the interval is wide by construction:
    with 3 runs of one task it is their range (all three draws alike has probability 1/27 > 2.5%)."""
    tasks = [np.asarray(s, dtype=float) for s in scores]
    if not tasks or any(t.ndim != 1 or t.size == 0 for t in tasks):
        raise ValueError("scores must be one non-empty 1-D sequence of run scores per task")
    rng = np.random.default_rng(seed)
    # (n_resamples,) per task: the mean of a resample of its runs; then the mean over tasks
    resampled = np.mean([t[rng.integers(0, t.size, (n_resamples, t.size))].mean(axis=1) for t in tasks], axis=0)
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(resampled, [alpha, 1.0 - alpha])
    return {"mean": float(np.mean([t.mean() for t in tasks])), "ci_low": float(low), "ci_high": float(high),
            "runs": [int(t.size) for t in tasks]}


__all__ = ["bootstrap_mean_ci", "mcnemar_exact", "mean_summary", "paired_bootstrap", "rate_summary",
           "stratified_bootstrap", "wilson"]
