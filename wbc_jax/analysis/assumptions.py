"""Assumption tests of a fitted ANOVA model: normality of residuals and homogeneity of variance.

scipy and statsmodels are imported where used.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from wbc_jax.analysis.anova import AnovaFit, coded_name


def assumption_tests(fit: AnovaFit, alpha: float = 0.05) -> list[dict]:
    """Normality of residuals (Lilliefors KS, Shapiro-Wilk) and equal variances (Levene, Brown-Forsythe).

    Returns:
        One dict per test: test, assumption, statistic, p, ok (p >= alpha, or None if the
        test could not run), note. A failed test also appends a warning to ``fit.warnings``.
    """
    from scipy import stats as sps
    from statsmodels.stats.diagnostic import lilliefors

    r = np.asarray(fit.result.resid, float)
    y = np.asarray(fit.result.model.endog, float)
    degenerate = fit.degenerate
    groups = [g.to_numpy(float) for _, g in pd.Series(y).groupby(_cell_keys(fit)) if len(g) >= 2]

    def run(name, assumption, fn, ok_to_run, why):
        row = {"test": name, "assumption": assumption, "statistic": np.nan, "p": np.nan, "ok": None, "note": ""}
        if not ok_to_run:
            row["note"] = why
            return row
        try:
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore")
                stat, p = fn()
        except (ValueError, ZeroDivisionError, np.linalg.LinAlgError) as e:
            row["note"] = f"not computable: {e}"
            return row
        row["statistic"], row["p"] = float(stat), float(p)
        if np.isfinite(p):
            row["ok"] = bool(p >= alpha)
        else:
            row["note"] = "not computable"
        return row

    normal = "normality of residuals"
    equal = "homogeneity of variance"
    zero_why = "residuals are numerically zero"
    rows = [
        run("Lilliefors KS", normal, lambda: lilliefors(r, dist="norm", pvalmethod="table"),
            len(r) >= 5 and not degenerate, zero_why if degenerate else "fewer than 5 residuals"),
        run("Shapiro-Wilk", normal, lambda: sps.shapiro(r), len(r) >= 3 and not degenerate,
            zero_why if degenerate else "fewer than 3 residuals"),
        run("Levene (mean)", equal, lambda: sps.levene(*groups, center="mean"), len(groups) >= 2,
            "fewer than 2 cells with 2+ runs"),
        run("Brown-Forsythe (median)", equal, lambda: sps.levene(*groups, center="median"), len(groups) >= 2,
            "fewer than 2 cells with 2+ runs"),
    ]
    rows[0]["note"] = rows[0]["note"] or "p from the Lilliefors table, limited to [0.001, 0.2]"
    if len(r) > 5000 and rows[1]["ok"] is not None:
        rows[1]["note"] = "n > 5000: p is approximate"
    for row in rows:
        if row["ok"] is False:
            fit.warnings.append(f"{row['test']}: p = {row['p']:.3g} < {alpha:g}, {row['assumption']} rejected")
    return rows


def _cell_keys(fit: AnovaFit) -> list[np.ndarray]:
    ex = fit.result.model.data.frame
    return [ex[coded_name(i)].to_numpy() for i in range(len(fit.factors))]
