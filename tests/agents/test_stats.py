import numpy as np
import pytest

from bimp.agents.evaluation.stats import bootstrap_mean_ci, mcnemar_exact, paired_bootstrap, rate_summary, wilson


@pytest.mark.parametrize("k, n, low, high", [
    (0, 10, 0.0, 0.2775),      # upper = z^2 / (n + z^2)
    (5, 10, 0.2366, 0.7634),
    (10, 10, 0.7225, 1.0),
    (1, 50, 0.00354, 0.1050),
])
def test_wilson_against_known_values(k, n, low, high):
    lo, hi = wilson(k, n)
    assert lo == pytest.approx(low, abs=1e-4) and hi == pytest.approx(high, abs=1e-4)


def test_wilson_by_hand():
    k, n, z = 7, 20, 1.959963984540054
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    assert wilson(k, n) == pytest.approx((centre - half, centre + half), abs=1e-9)


def test_rate_summary_counts():
    r = rate_summary([1, 0, 1, 1])
    assert (r["k"], r["n"], r["mean"]) == (3, 4, 0.75) and r["ci_low"] < 0.75 < r["ci_high"]
    assert rate_summary([])["mean"] is None


def test_mcnemar_exact_by_hand():
    # discordant pairs: A only on 5 seeds, B only on 1: p = 2 * P(X <= 1), X ~ Bin(6, 1/2) = 2 * 7/64
    a = [1] * 5 + [0] + [1] * 4 + [0] * 3
    b = [0] * 5 + [1] + [1] * 4 + [0] * 3
    m = mcnemar_exact(a, b)
    assert (m["only_a"], m["only_b"]) == (5, 1)
    assert m["p_value"] == pytest.approx(14 / 64)
    assert mcnemar_exact([1, 0], [1, 0])["p_value"] == 1.0
    with pytest.raises(ValueError, match="same length"):
        mcnemar_exact([1], [1, 0])


def test_bootstrap_covers_the_mean_and_is_reproducible():
    x = np.random.default_rng(3).normal(2.0, 1.0, 200)
    lo, hi = bootstrap_mean_ci(x)
    assert lo < x.mean() < hi and hi - lo < 0.5  # about 2 * 1.96 / sqrt(200) = 0.28
    assert bootstrap_mean_ci(x) == (lo, hi)
    assert bootstrap_mean_ci([3.0, 3.0, 3.0]) == (3.0, 3.0)


def test_paired_bootstrap_sees_a_shift_unpaired_intervals_hide():
    rng = np.random.default_rng(0)
    base = rng.normal(0, 5, 60)  # large seed-to-seed spread
    d = paired_bootstrap(base + 0.5 + rng.normal(0, 0.1, 60), base)
    assert d["mean_diff"] == pytest.approx(0.5, abs=0.05) and d["ci_low"] > 0.4 and d["ci_high"] < 0.6
