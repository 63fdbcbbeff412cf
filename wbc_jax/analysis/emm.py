"""Estimated marginal means (EMMs), simple main effects and pairwise comparisons of a fitted model.

EMMs weight every level of the other factors equally over the full factorial grid, as R's
``emmeans`` and SPSS's ``EMMEANS`` do; their standard errors use the pooled model MSE and the
model's residual degrees of freedom. An EMM of an empty cell that the model cannot estimate is NaN.
scipy and statsmodels are imported where used.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import pandas as pd

from wbc_jax.analysis.anova import AnovaFit, coded_name

ESTIMABLE_TOL = 1e-8  # L is estimable if its part outside the row space of X is below this
CONF = 0.95  # confidence level of EMM and pairwise intervals


def _grid(fit: AnovaFit) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """Full factorial grid of levels, its design matrix and the row-space projector of X."""
    if fit._grid is None:
        from statsmodels.formula._manager import FormulaManager

        g = pd.DataFrame(list(itertools.product(*(fit.levels[f] for f in fit.factors))), columns=fit.factors)
        coded = pd.DataFrame({coded_name(i): pd.Categorical(g[f], categories=fit.levels[f])
                              for i, f in enumerate(fit.factors)})
        spec = fit.result.model.data.model_spec
        X = np.asarray(FormulaManager().get_matrices(spec, coded, pandas=False, prediction=True), float)
        ex = np.asarray(fit.result.model.exog, float)
        fit._grid = (g, X, np.linalg.pinv(ex) @ ex)
    return fit._grid


def _emm_rows(fit: AnovaFit, by: Sequence[str]) -> tuple[pd.DataFrame, np.ndarray]:
    """Level combinations of ``by`` and the matrix L whose rows give their EMMs as L @ beta."""
    g, X, _ = _grid(fit)
    keys = pd.DataFrame(list(itertools.product(*(fit.levels[f] for f in by))), columns=list(by))
    L = np.empty((len(keys), X.shape[1]))
    for i, k in enumerate(keys.itertuples(index=False)):
        mask = np.logical_and.reduce([g[f].to_numpy() == v for f, v in zip(by, k)])
        L[i] = X[mask].mean(axis=0)
    return keys, L


def _estimate(fit: AnovaFit, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimates L beta and their covariance L V L' (NaN for non-estimable rows)."""
    _, _, P = _grid(fit)
    beta = np.asarray(fit.result.params, float)
    V = np.asarray(fit.result.cov_params(), float)
    est = L @ beta
    cov = L @ V @ L.T
    bad = np.linalg.norm(L - L @ P, axis=1) > ESTIMABLE_TOL * np.maximum(np.linalg.norm(L, axis=1), 1.0)
    est[bad] = np.nan
    cov[bad, :] = np.nan
    cov[:, bad] = np.nan
    return est, cov


def emmeans(fit: AnovaFit, by: Sequence[str], conf: float = CONF) -> pd.DataFrame:
    """EMMs of the level combinations of ``by`` (equal weights over the other factors).

    Returns:
        Columns: the ``by`` factors, emm, se, df, ci_low, ci_high (unadjusted ``conf`` CI).
    """
    from scipy import stats as sps

    keys, L = _emm_rows(fit, by)
    est, cov = _estimate(fit, L)
    se = np.sqrt(np.diag(cov))
    tcrit = sps.t.ppf(0.5 + conf / 2, fit.df_resid) if fit.df_resid > 0 else np.nan
    out = keys.copy()
    out["emm"], out["se"], out["df"] = est, se, fit.df_resid
    out["ci_low"], out["ci_high"] = est - tcrit * se, est + tcrit * se
    return out


def simple_effects(fit: AnovaFit, effect: str, by: str, conf: float = CONF) -> dict:
    """Simple main effects of ``effect`` at each level of ``by``, with Bonferroni pairwise EMM comparisons.

    The F test per level of ``by`` is the joint Wald F of the k-1 EMM contrasts of
    ``effect`` at that level (numerator df k-1, denominator the model's residual df, pooled
    MSE), as SPSS's EMMEANS ... COMPARE and emmeans' joint tests print. Pairwise
    differences form one Bonferroni family of k(k-1)/2 per level of ``by``; their CIs are
    Bonferroni-adjusted (family-wise ``conf``).

    Returns:
        dict with ``effect``, ``by``, ``method`` (text), ``tests`` (by level, F, df1, df2,
        p, partial_eta_sq) and ``pairs`` (by level, level_a, level_b, diff, se, t, df,
        ci_low, ci_high, p_unadj, p_bonf) DataFrames.
    """
    from scipy import stats as sps

    keys, L = _emm_rows(fit, [by, effect])
    est, cov = _estimate(fit, L)
    beta = np.asarray(fit.result.params, float)
    V = np.asarray(fit.result.cov_params(), float)
    df2, mse, ssr = fit.df_resid, fit.mse, float(fit.result.ssr)
    lv_e = fit.levels[effect]
    k = len(lv_e)
    n_pairs = k * (k - 1) // 2
    tcrit = sps.t.ppf(1 - (1 - conf) / (2 * n_pairs), df2) if df2 > 0 else np.nan
    tests, pairs = [], []
    for b in fit.levels[by]:
        idx = np.flatnonzero(keys[by].to_numpy() == b)
        C = L[idx[1:]] - L[idx[0]]
        F, q, p = np.nan, np.nan, np.nan
        if np.all(np.isfinite(est[idx])) and df2 > 0:
            CVC = C @ V @ C.T
            q = int(np.linalg.matrix_rank(CVC))
            cb = C @ beta
            with np.errstate(all="ignore"):
                F = float(cb @ np.linalg.pinv(CVC) @ cb / q) if q else np.nan
            p = float(sps.f.sf(F, q, df2)) if q else np.nan
        ss = F * q * mse if np.isfinite(F) else np.nan
        tests.append({by: b, "F": F, "df1": q, "df2": df2, "p": p, "partial_eta_sq": ss / (ss + ssr)})
        for i, j in itertools.combinations(range(k), 2):
            a, c = idx[i], idx[j]
            diff = est[a] - est[c]
            se = float(np.sqrt(cov[a, a] + cov[c, c] - 2 * cov[a, c]))
            with np.errstate(all="ignore"):
                t = diff / se
            p_un = float(2 * sps.t.sf(abs(t), df2)) if df2 > 0 else np.nan
            pairs.append({by: b, "level_a": lv_e[i], "level_b": lv_e[j], "diff": diff, "se": se, "t": t, "df": df2,
                          "ci_low": diff - tcrit * se, "ci_high": diff + tcrit * se,
                          "p_unadj": p_un, "p_bonf": min(1.0, p_un * n_pairs) if np.isfinite(p_un) else np.nan})
    method = (f"EMMs of {effect} at each level of {by} (equal weights over the other factors); "
              f"simple-effect F on ({k - 1}, {df2:g}) df with the pooled model MSE {mse:.4g}; pairwise "
              f"differences Bonferroni-adjusted within each level of {by} (family of {n_pairs}), "
              f"{conf:.0%} family-wise CIs")
    return {"effect": effect, "by": by, "method": method, "tests": pd.DataFrame(tests), "pairs": pd.DataFrame(pairs)}
