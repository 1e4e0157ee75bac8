"""Statistics of per-episode results: Student-t confidence intervals, Welch's t-test, and
comparisons of two planners paired by world (`paired_by_world`), the test the evaluation
tables report: every planner runs the same worlds and trials."""

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


def world_means(x, worlds: int) -> np.ndarray:
    """(W,) per-world means of per-episode results (E,) stored world-major (episode e on
    world e // trials, as sweeps store them)."""
    x = np.asarray(x, np.float64)
    if worlds < 1 or len(x) % worlds:
        raise ValueError(f"{len(x)} episodes do not split into {worlds} worlds")
    return x.reshape(worlds, -1).mean(axis=1)


def paired_by_world(a, b, worlds: int, level: float = 0.95) -> dict:
    """Planner A against planner B on the same worlds and trials (per-episode results (E,)
    each, world-major): the W per-world mean differences A - B, their mean with a
    Student-t confidence interval, the paired t-test over them (scipy.stats.ttest_rel),
    the Wilcoxon signed-rank test (zero differences dropped; p = 1 when all are zero) and
    Cohen's d_z (mean difference / their standard deviation). The worlds, not the
    episodes, are the independent samples: trials on one world share its layout."""
    from scipy import stats  # noqa: PLC0415

    if len(a) != len(b):
        raise ValueError(f"paired comparison of {len(a)} and {len(b)} episodes; allowed: "
                         "the same worlds and trials for both")
    diff = world_means(a, worlds) - world_means(b, worlds)
    mean, std, half = mean_ci(diff, level)
    if worlds < 2 or std == 0:
        p = 1.0 if mean == 0 else (0.0 if worlds > 1 else float("nan"))
        t = 0.0 if mean == 0 else math.copysign(math.inf, mean)
    else:
        t, p = (float(v) for v in stats.ttest_rel(world_means(a, worlds),
                                                  world_means(b, worlds)))
    nonzero = diff[diff != 0]
    wilcoxon = float(stats.wilcoxon(nonzero).pvalue) if len(nonzero) else 1.0
    return {"worlds": worlds, "diff": mean, "ci": [mean - half, mean + half], "t": t,
            "df": worlds - 1, "p": p, "p_wilcoxon": wilcoxon,
            "dz": mean / std if std > 0 else (0.0 if mean == 0 else math.copysign(
                math.inf, mean))}
