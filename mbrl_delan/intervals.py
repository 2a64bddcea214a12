"""Interval estimates and tests for the records: a mean over seeds (Student t), a rate of
falls (Wilson score) and a paired comparison of falls (exact McNemar)."""

from __future__ import annotations

import math
import statistics

from scipy import stats

CONFIDENCE = 0.95


def mean_ci(values: list[float], level: float = CONFIDENCE) -> tuple[float | None, float | None]:
    """Mean and confidence-interval half-width over seeds (Student t).

    half-width = t_{(1 + level) / 2, n - 1} * s / sqrt(n), with s the sample std (ddof 1).
    Returns (None, None) without values and (mean, None) for a single value.
    """
    if not values:
        return None, None
    mean = statistics.fmean(values)
    if len(values) < 2:
        return mean, None
    t = float(stats.t.ppf((1.0 + level) / 2.0, len(values) - 1))
    return mean, t * statistics.stdev(values) / math.sqrt(len(values))


def wilson_interval(k: int, n: int, level: float = CONFIDENCE) -> tuple[float, float]:
    """The Wilson score interval of a rate k / n (n >= 1): the falls' 95% interval."""
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=level, method="wilson")
    return float(ci.low), float(ci.high)


def mcnemar_exact(b: int, c: int) -> float:
    """The exact McNemar test's two-sided p-value on the discordant pairs: b episodes where
    only the model fell, c where only the oracle fell (binomial, 1/2 each); 1 without any."""
    return 1.0 if b + c == 0 else float(stats.binomtest(min(b, c), b + c, 0.5).pvalue)
