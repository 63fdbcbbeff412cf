"""Statistics of a factorial campaign: design, descriptives, ANOVA, assumptions, EMMs.

Pure functions on pandas DataFrames that return DataFrames and dicts: no files, no plots
(``wbc_jax.analysis.report`` does those). scipy and statsmodels are imported where used, so that
checking a table (and the CLI's error path) stays fast. The input is a tidy results table, one row per run:
factor columns (``m``, ``mu``, ``d`` in the transport campaign; any others by name), a
boolean ``success`` and numeric metric columns (``R``, ``T``, ``S``, ...).

Conventions
- Runs with ``success == False`` are excluded from every model and mean (they are counted
  as failures in :func:`design_table`); a missing (NaN) metric value drops that run from
  that metric only.
- The linear model per metric is ``y ~ (A + B + C)**order`` with sum-to-zero contrasts
  (``C(x, Sum)``), fitted by statsmodels ``ols``; its ANOVA table comes from ``anova_lm``
  with type III sums of squares by default (equal to types I and II when balanced).
- Estimated marginal means (EMMs) weight every level of the other factors equally over
  the full factorial grid, as R's ``emmeans`` and SPSS's ``EMMEANS`` do; their standard
  errors use the pooled model MSE and the model's residual degrees of freedom.

Default factor and metric columns: see :mod:`wbc_jax.analysis.table`.

The pieces live in one module each; this module runs them all (:func:`analyze`) and re-exports
their public names for callers (``wbc_jax.analysis.report``, the tests):

- :mod:`wbc_jax.analysis.table`: column inference, validation, design table, cell and level means;
- :mod:`wbc_jax.analysis.anova`: the factorial model and its ANOVA table (:class:`AnovaFit`);
- :mod:`wbc_jax.analysis.assumptions`: normality and equal-variance tests of a fit;
- :mod:`wbc_jax.analysis.emm`: EMMs, simple main effects, Bonferroni pairwise comparisons.
"""

from __future__ import annotations

from collections.abc import Sequence

import pandas as pd

from wbc_jax.analysis.anova import PERFECT_FIT_RTOL, SS_NAMES, ZERO_SD_RTOL, AnovaFit, fit_anova, model_terms
from wbc_jax.analysis.assumptions import assumption_tests
from wbc_jax.analysis.emm import CONF, ESTIMABLE_TOL, emmeans, simple_effects
from wbc_jax.analysis.table import (
    BOOKKEEPING,
    DEFAULT_FACTORS,
    PREFERRED_METRICS,
    cell_means,
    design_table,
    infer_factors,
    infer_metrics,
    level_means,
    levels,
    plain,
    prepare,
    success_column,
    successful,
)
from wbc_jax.errors import InputError

__all__ = [
    "AnovaFit", "BOOKKEEPING", "CONF", "DEFAULT_FACTORS", "ESTIMABLE_TOL", "PERFECT_FIT_RTOL", "PREFERRED_METRICS",
    "SS_NAMES", "ZERO_SD_RTOL", "analyze", "assumption_tests", "cell_means", "design_table", "emmeans", "fit_anova",
    "infer_factors", "infer_metrics", "level_means", "levels", "model_terms", "plain", "prepare", "simple_effects",
    "success_column", "successful",
]


def analyze(df: pd.DataFrame, factors: Sequence[str], metrics: Sequence[str], alpha: float = 0.05,
            ss_type: int = 3, order: int = 2) -> dict:
    """All statistics of a report: design, descriptives, and per metric ANOVA, assumptions, EMMs.

    Args:
        df: a table checked by :func:`prepare`.
        factors, metrics: column names.
        alpha: significance level of the F tests and assumption tests.
        ss_type: 1, 2 or 3 (default III).
        order: highest interaction order in the model (default 2: main effects + two-way).

    Returns:
        dict: ``design``, ``cell_means``, ``level_means`` (DataFrames), ``warnings`` (list
        of str, table-wide), ``n_runs``, ``n_failed``, and ``metrics``: metric -> dict with
        ``fit`` (AnovaFit), ``anova`` (DataFrame), ``assumptions`` (list of dict),
        ``significant`` (list of sources), ``emms`` (interaction source -> DataFrame of
        two-way EMMs), ``simple_effects`` (list of :func:`simple_effects` dicts, both
        directions of each significant two-way interaction) and ``warnings``.
    """
    if not 0 < alpha < 1:
        raise InputError(f"alpha must be between 0 and 1, not {alpha}")
    if ss_type not in SS_NAMES:
        raise InputError(f"SS type must be 1, 2 or 3, not {plain(ss_type)}")
    if not (isinstance(order, int) and order >= 1):
        raise InputError(f"model order must be an integer >= 1, not {plain(order)}")
    factors, metrics = list(factors), list(metrics)
    design = design_table(df, factors)
    n_failed = int(design["failures"].sum())
    notes = []
    if n_failed:
        notes.append(f"{n_failed} of {len(df)} runs failed (success = False) and are excluded from the analysis")
    if (design["runs"] == 0).any():
        notes.append(f"{int((design['runs'] == 0).sum())} of {len(design)} cells have no runs at all")
    no_success = (design["successes"] == 0) & (design["runs"] > 0)
    if no_success.any():
        notes.append(f"{int(no_success.sum())} cells have runs but no successful run")
    if successful(df).empty:
        raise InputError("no successful runs (success is False in every row)")
    out = {"design": design, "cell_means": cell_means(df, factors, metrics),
           "level_means": level_means(df, factors, metrics), "warnings": notes,
           "n_runs": len(df), "n_failed": n_failed, "metrics": {}}
    for m in metrics:
        fit = fit_anova(df, factors, m, ss_type=ss_type, order=order)
        assumptions = assumption_tests(fit, alpha)
        sig = fit.significant(alpha)
        pairs = [t for t in model_terms(factors, 2) if len(t) == 2]
        emms = {":".join(t): emmeans(fit, t) for t in pairs}
        simple = [simple_effects(fit, e, b) for s in sig if s.count(":") == 1
                  for e, b in (s.split(":"), s.split(":")[::-1])]
        out["metrics"][m] = {"fit": fit, "anova": fit.table, "assumptions": assumptions, "significant": sig,
                             "emms": emms, "simple_effects": simple, "warnings": fit.warnings}
    return out
