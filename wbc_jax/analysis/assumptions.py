"""Assumption tests of a fitted ANOVA model: normality of residuals and homogeneity of variance.

scipy and statsmodels are imported where used.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from wbc_jax.analysis.anova import ZERO_SD_RTOL, AnovaFit, coded_name


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
        run("Levene (mean)", equal, lambda: sps.levene(*groups, center="mean"), *_spread_check(groups, np.mean)),
        run("Brown-Forsythe (median)", equal, lambda: sps.levene(*groups, center="median"),
            *_spread_check(groups, np.median)),
    ]
    rows[0]["note"] = rows[0]["note"] or "p from the Lilliefors table, limited to [0.001, 0.2]"
    if len(r) > 5000 and rows[1]["ok"] is not None:
        rows[1]["note"] = "n > 5000: p is approximate"
    for row in rows:
        if row["ok"] is False:
            fit.warnings.append(f"{row['test']}: p = {row['p']:.3g} < {alpha:g}, {row['assumption']} rejected")
    return rows


def _spread_check(groups: list[np.ndarray], centre) -> tuple[bool, str]:
    """(can run, why not) for Levene's test of ``groups`` (the cells' values, 2+ runs each) about ``centre``.

    The test compares the cells' mean absolute deviation from their centre against how much those deviations vary
    within the cells. It cannot run when they do not vary within any cell (their RMS about the cell's mean
    deviation at most ``ZERO_SD_RTOL`` x max|y|), as in cells of 2 runs (both equally far from the centre) or of
    zero variance (identical values): the statistic is then a ratio of rounding errors.
    """
    if len(groups) < 2:
        return False, "fewer than 2 cells with 2+ runs"
    dev = [np.abs(g - centre(g)) for g in groups]
    spread = np.sqrt(sum(float(np.sum((z - z.mean()) ** 2)) for z in dev) / sum(len(g) for g in groups))
    scale = max(float(np.max(np.abs(g))) for g in groups)
    if spread > ZERO_SD_RTOL * scale:
        return True, ""
    zero = sum(float(np.std(g)) <= ZERO_SD_RTOL * scale for g in groups)
    two = sum(len(g) == 2 for g in groups)
    why = [f"{two} of {len(groups)} cells have 2 runs, which lie equally far from their centre" if two else "",
           f"{zero} of {len(groups)} cells have zero variance, their runs identical" if zero else ""]
    why = [w for w in why if w] or ["in every cell the runs lie equally far from the centre"]
    return False, "cannot be run: no cell's deviations from its centre vary: " + "; ".join(why)


def _cell_keys(fit: AnovaFit) -> list[np.ndarray]:
    ex = fit.result.model.data.frame
    return [ex[coded_name(i)].to_numpy() for i in range(len(fit.factors))]
