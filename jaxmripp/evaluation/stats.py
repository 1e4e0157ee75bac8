"""Statistics of per-episode results: Welch's t-test and Student-t confidence intervals."""

from __future__ import annotations

import math

import numpy as np


def welch_ttest(a, b) -> tuple[float, float, float]:
    """Welch's unequal-variance t-test: (t, degrees of freedom, two-sided p-value).

    Matches scipy.stats.ttest_ind(a, b, equal_var=False). Two constant samples give
    t = +-inf and p = 0 when their means differ, t = 0 and p = 1 when they do not.
    """
    from scipy import special  # noqa: PLC0415

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    diff = a.mean() - b.mean()
    se2 = va + vb
    if se2 == 0:
        return (0.0, float("nan"), 1.0) if diff == 0 else (math.copysign(math.inf, diff),
                                                           float("nan"), 0.0)
    t = diff / math.sqrt(se2)
    df = se2 ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    p = float(special.betainc(df / 2, 0.5, df / (df + t * t)))  # = 2 P(T_df > |t|)
    return float(t), float(df), p


def mean_ci(x, level: float = 0.95) -> tuple[float, float, float]:
    """(mean, std, half-width of the Student-t confidence interval of the mean)."""
    from scipy import stats  # noqa: PLC0415

    x = np.asarray(x, np.float64)
    if len(x) < 2:
        return float(x.mean()), 0.0, float("nan")
    std = float(x.std(ddof=1))
    half = float(stats.t.ppf(0.5 + level / 2, len(x) - 1) * std / math.sqrt(len(x)))
    return float(x.mean()), std, half
