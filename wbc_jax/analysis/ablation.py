"""Controller ablations: each level of an ablation factor against its reference level, metric by metric.

An ablation factor is a column whose levels switch parts of the controller (:data:`REFERENCE`: ``variant``
against ``full``, ``observer`` 0 against 1; :mod:`wbc_jax.control.variants`). For each other level, pooled over
the other factors' levels and the repetitions (a balanced design gives every level the same mix of them):

- continuous metrics (:data:`METRICS`: max slip [mm] and R), on the successful runs: Welch's t test (unequal
  variances) and the Mann-Whitney U test (two-sided, no normality assumed);
- success (all runs): Fisher's exact test on the 2 x 2 table (level / reference x success / failure).

p values are two-sided; ``p_bonf`` multiplies by the number of levels compared with the same reference (one family
per factor, metric and test), capped at 1. A difference is reported where ``p_bonf < alpha``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from wbc_jax.analysis.table import levels, success_column

REFERENCE = {"variant": "full", "observer": 1}
METRICS = ("max_slip_mm", "R")
NAMES = {"max_slip_mm": "max slip [mm]", "R": "R", "success": "success"}
COLUMNS = ["factor", "level", "reference", "metric", "test", "n", "n_ref", "value", "value_ref", "statistic", "p",
           "detectable", "p_bonf", "differs"]


def ablation_factors(df: pd.DataFrame, factors) -> list[str]:
    """The factors of ``factors`` that are ablation factors with their reference level present."""
    return [f for f in factors if f in REFERENCE and _ref(df[f], REFERENCE[f]) is not None]


def _ref(col: pd.Series, ref):
    """The level of ``col`` equal to ``ref`` (1 also matches True / "1"), or None."""
    for lv in levels(col):
        if lv == ref or str(lv).strip().lower() == str(ref).lower():
            return lv
    return None


def _continuous(a: np.ndarray, b: np.ndarray, alpha: float) -> list[tuple[str, float, float, float, float, float]]:
    """(test, value, value_ref, statistic, p, detectable) of Welch's t (means; detectable: the smallest mean
    difference it finds with :data:`~wbc_jax.analysis.sensitivity.POWER` probability at level ``alpha``) and
    Mann-Whitney U (medians; detectable NaN); NaN where a sample is too small (t: 2 per group, U: 1) or constant in
    both groups (t)."""
    from scipy import stats as sps

    from wbc_jax.analysis.sensitivity import detectable_difference

    t = p = detect = np.nan
    if len(a) >= 2 and len(b) >= 2 and (np.ptp(a) > 0 or np.ptp(b) > 0):
        t, p = sps.ttest_ind(a, b, equal_var=False)
        detect = detectable_difference(float(np.std(a, ddof=1)), len(a), float(np.std(b, ddof=1)), len(b), alpha)
    u = pu = np.nan
    if len(a) and len(b):
        u, pu = sps.mannwhitneyu(a, b, alternative="two-sided")
    mean = lambda x: float(np.mean(x)) if len(x) else np.nan  # noqa: E731
    med = lambda x: float(np.median(x)) if len(x) else np.nan  # noqa: E731
    return [("Welch t (mean)", mean(a), mean(b), float(t), float(p), float(detect)),
            ("Mann-Whitney U (median)", med(a), med(b), float(u), float(pu), np.nan)]


def compare(df: pd.DataFrame, factors, alpha: float = 0.05) -> pd.DataFrame:
    """Every non-reference level of each ablation factor against the reference (module docstring).

    Args:
        df: results table (success as :func:`wbc_jax.analysis.table.success_column` reads it).
        factors: the table's factor columns.

    Returns:
        One row per (factor, level, metric, test), columns :data:`COLUMNS`: n and n_ref the runs compared
        (successful ones for a metric, all for success), value / value_ref the mean, median or success rate,
        statistic (t, U or the odds ratio), p, ``detectable`` (Welch rows: the smallest mean difference the test
        detects with 80 % probability at the Bonferroni-adjusted level, from the samples' sizes and SDs,
        :func:`wbc_jax.analysis.sensitivity.detectable_difference`; NaN elsewhere), p_bonf and ``differs``
        (p_bonf < alpha).
    """
    from scipy import stats as sps

    ok = success_column(df).to_numpy()
    rows = []
    for f in ablation_factors(df, factors):
        ref = _ref(df[f], REFERENCE[f])
        others = [lv for lv in levels(df[f]) if lv != ref]
        in_ref = (df[f] == ref).to_numpy()
        for lv in others:
            in_lv = (df[f] == lv).to_numpy()
            for m in [m for m in METRICS if m in df.columns]:
                y = pd.to_numeric(df[m], errors="coerce").to_numpy(float)
                a, b = y[in_lv & ok], y[in_ref & ok]
                a, b = a[np.isfinite(a)], b[np.isfinite(b)]
                for test, v, v_ref, stat, p, detect in _continuous(a, b, alpha / len(others)):
                    rows.append([f, lv, ref, m, test, len(a), len(b), v, v_ref, stat, p, detect])
            s, s_ref = int(ok[in_lv].sum()), int(ok[in_ref].sum())
            n, n_ref = int(in_lv.sum()), int(in_ref.sum())
            odds, p = sps.fisher_exact([[s, n - s], [s_ref, n_ref - s_ref]])
            rows.append([f, lv, ref, "success", "Fisher exact (rate)", n, n_ref, s / n, s_ref / n_ref, float(odds),
                         float(p), np.nan])
    out = pd.DataFrame(rows, columns=COLUMNS[:-2])
    k = out.groupby(["factor", "metric", "test"])["level"].transform("size") if len(out) else 0
    out["p_bonf"] = np.minimum(out["p"] * k, 1.0)
    out["differs"] = out["p_bonf"] < alpha
    return out


def _rate_intervals(row) -> str:
    """The 95 % Clopper-Pearson intervals of a success row's two rates (:func:`wbc_jax.analysis.success.interval`),
    e.g. "95 % intervals 96.0-100 % vs 96.0-100 %": what no failure in n runs rules out."""
    from wbc_jax.analysis.success import CONFIDENCE, interval

    n = np.array([row.n, row.n_ref])
    low, high = interval(np.rint(np.array([row.value, row.value_ref]) * n), n)
    return (f"{CONFIDENCE * 100:g} % intervals " + " vs ".join(f"{100 * a:.1f}-{100 * b:.1f} %"
                                                                for a, b in zip(low, high)))


def answers(t: pd.DataFrame, alpha: float) -> list[str]:
    """One sentence per (factor, level): does it change max slip, R and success, with the tests named (where Welch's
    test finds no change, the difference it would have found; for success, both rates' 95 % intervals)."""
    from wbc_jax.analysis.sensitivity import POWER

    out = []
    for (f, lv), g in t.groupby(["factor", "level"], sort=False):
        parts = []
        for m, gm in g.groupby("metric", sort=False):
            tests = "; ".join(f"{r.test}: {r.value:.4g} vs {r.value_ref:.4g}, p = {r.p_bonf:.3g}" if np.isfinite(r.p)
                              else f"{r.test}: not testable (n = {r.n} vs {r.n_ref})" for r in gm.itertuples())
            verdict = "changes" if gm["differs"].any() else "no significant change in"
            found = gm["detectable"].dropna()
            if not gm["differs"].any() and len(found):
                tests += (f"; a mean difference of {found.iloc[0]:.3g} or more would be found with "
                          f"{POWER * 100:g} % probability")
            if m == "success":
                tests += "; " + _rate_intervals(gm.iloc[0])
            parts.append(f"{verdict} {NAMES.get(m, m)} ({tests})")
        ref = g["reference"].iloc[0]
        out.append(f"{f} = {lv} against {f} = {ref}: " + "; ".join(parts)
                   + f" (Bonferroni-adjusted p, alpha = {alpha:g}).")
    return out
