"""The factorial linear model of one metric and its ANOVA table.

The model per metric is ``y ~ (A + B + C)**order`` with sum-to-zero contrasts (``C(x, Sum)``),
fitted by statsmodels ``ols`` on the successful runs that have a value of the metric; its ANOVA
table comes from ``anova_lm`` with type III sums of squares by default (equal to types I and II
when balanced). :func:`fit_anova` also judges whether the F tests can be trusted (near-perfect fit,
zero-variance cells, no residual degrees of freedom) and says why in ``AnovaFit.warnings``.
statsmodels is imported where used, so that checking a table stays fast.
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from wbc_jax.analysis.table import levels, plain, successful
from wbc_jax.errors import InputError

SS_NAMES = {1: "I", 2: "II", 3: "III"}
PERFECT_FIT_RTOL = 1e-10  # R's summary.lm rule: residual SS < 1e-10 x model SS
ZERO_SD_RTOL = 1e-10  # a cell SD below this x max|y| counts as zero variance


@dataclass
class AnovaFit:
    """A fitted factorial model of one metric and its ANOVA table.

    Attributes:
        metric: metric column.
        factors: factor columns, model order.
        levels: factor -> sorted levels present among the analysed runs.
        table: ANOVA rows: source, sum_sq, df, mean_sq, F, p, partial_eta_sq (last row Residual).
        result: statsmodels RegressionResults of the fit.
        ss_type: "I", "II" or "III".
        order: highest interaction order in the model.
        formula: the model in the table's column names.
        cells: per cell of the grid: n, mean, sd of the analysed runs.
        reliable: False when F tests are not trustworthy (near-perfect fit, zero-variance
            cells, no residual degrees of freedom).
        warnings: human-readable findings about this fit.
        unreliable_reasons: why ``reliable`` is False (empty when it is True).
    """

    metric: str
    factors: list[str]
    levels: dict
    table: pd.DataFrame
    result: object
    ss_type: str
    order: int
    formula: str
    cells: pd.DataFrame
    reliable: bool
    warnings: list[str] = field(default_factory=list)
    unreliable_reasons: list[str] = field(default_factory=list)
    _grid: tuple | None = None

    @property
    def n(self) -> int:
        return int(self.result.nobs)

    @property
    def mse(self) -> float:
        return float(self.result.scale)

    @property
    def df_resid(self) -> float:
        return float(self.result.df_resid)

    @property
    def degenerate(self) -> bool:
        """Residuals numerically zero: residual SS <= PERFECT_FIT_RTOL x total SS, or residual
        RMS <= ZERO_SD_RTOL x max|y| (rounding noise of a constant metric)."""
        y = np.asarray(self.result.model.endog, float)
        ssr = float(self.result.ssr)
        tss = float(np.sum((y - y.mean()) ** 2))
        return ssr <= PERFECT_FIT_RTOL * tss or np.sqrt(ssr / len(y)) <= ZERO_SD_RTOL * float(np.max(np.abs(y)))

    def significant(self, alpha: float) -> list[str]:
        """Effect sources with p < alpha (none when the F tests are unreliable)."""
        if not self.reliable:
            return []
        t = self.table[self.table["source"] != "Residual"]
        return [s for s, p in zip(t["source"], t["p"]) if np.isfinite(p) and p < alpha]


def coded_name(i: int) -> str:
    """Column name of factor ``i`` in the model's data frame (factor names may not be valid formula names)."""
    return f"_f{i}"


def model_terms(factors: Sequence[str], order: int = 2) -> list[tuple[str, ...]]:
    """Model terms: all main effects and interactions up to ``order``, as factor tuples."""
    return [c for k in range(1, min(order, len(factors)) + 1) for c in itertools.combinations(factors, k)]


def fit_anova(df: pd.DataFrame, factors: Sequence[str], metric: str, ss_type: int = 3, order: int = 2) -> AnovaFit:
    """Fit ``metric ~ (factors)**order`` with sum-to-zero contrasts; ANOVA of the given SS type.

    Only successful runs with a value of ``metric`` enter. Partial eta squared is
    SS_effect / (SS_effect + SS_residual).

    Raises:
        InputError: no analysable runs, or a factor left with one level among them.
    """
    import statsmodels.formula.api as smf
    from statsmodels.stats.anova import anova_lm

    if ss_type not in SS_NAMES:
        raise InputError(f"SS type must be 1, 2 or 3, not {plain(ss_type)}")
    factors = list(factors)
    d = successful(df)
    n_nan = int(d[metric].isna().sum())
    d = d[d[metric].notna()]
    if len(d) == 0:
        raise InputError(f"metric '{metric}' has no values among successful runs")
    x = pd.DataFrame({"_y": d[metric].astype(float).to_numpy()})
    lv = {}
    for i, f in enumerate(factors):
        lv[f] = levels(d[f])
        if len(lv[f]) < 2:
            raise InputError(f"factor '{f}' has only one level among successful runs with '{metric}' values")
        x[coded_name(i)] = pd.Categorical(d[f].to_numpy(), categories=lv[f])
    code = {f: coded_name(i) for i, f in enumerate(factors)}
    terms = model_terms(factors, order)
    rhs = " + ".join(":".join(f"C({code[f]}, Sum)" for f in t) for t in terms)
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")  # rank deficiency and perfect fits are reported by _check_fit
        res = smf.ols(f"_y ~ {rhs}", x).fit()
        aov = anova_lm(res, typ=ss_type)
    aov = aov.drop(index="Intercept", errors="ignore")
    name = {f"C({code[f]}, Sum)": f for f in factors}
    ssr = float(res.ssr)
    table = pd.DataFrame(
        {
            "source": [":".join(name.get(p, p) for p in s.split(":")) for s in aov.index],
            "sum_sq": aov["sum_sq"].to_numpy(float),
            "df": aov["df"].to_numpy(float),
        }
    )
    with np.errstate(all="ignore"):
        table["mean_sq"] = table["sum_sq"] / table["df"]
        table["F"] = aov["F"].to_numpy(float)
        table["p"] = aov["PR(>F)"].to_numpy(float)
        table["partial_eta_sq"] = table["sum_sq"] / (table["sum_sq"] + ssr)
    table.loc[table["source"] == "Residual", ["F", "p", "partial_eta_sq"]] = np.nan

    cells = x.groupby([code[f] for f in factors], observed=False)["_y"].agg(["count", "mean", "std"])
    cells.index.names = factors
    cells = cells.rename(columns={"count": "n", "std": "sd"}).reset_index()
    fit = AnovaFit(
        metric=metric,
        factors=factors,
        levels=lv,
        table=table,
        result=res,
        ss_type=SS_NAMES[ss_type],
        order=min(order, len(factors)),
        formula=f"{metric} ~ " + " + ".join(":".join(t) for t in terms),
        cells=cells,
        reliable=True,
    )
    _check_fit(fit, n_nan)
    return fit


def _check_fit(fit: AnovaFit, n_nan: int) -> None:
    """Fill ``fit.warnings`` and ``fit.reliable`` (never raises)."""
    res, w = fit.result, fit.warnings
    if n_nan:
        w.append(f"{n_nan} successful run(s) have no {fit.metric} value and are left out of its model")
    n = fit.cells["n"]
    if (n == 0).any():
        w.append(f"{int((n == 0).sum())} of {len(n)} cells have no analysable runs")
    if n.nunique() > 1:
        w.append(f"unbalanced design: {int(n.min())} to {int(n.max())} runs per cell; "
                 f"type {fit.ss_type} SS reported (types I, II and III differ)")
    if res.model.rank < res.model.exog.shape[1]:
        w.append(f"rank-deficient model ({res.model.rank} of {res.model.exog.shape[1]} parameters estimable, "
                 "empty cells): type III tests of terms involving the empty cells are not well defined, "
                 "and EMMs of empty cells are not estimable")
    unreliable = []
    if res.df_resid <= 0:
        unreliable.append("no residual degrees of freedom")
    y = res.model.endog
    scale = float(np.max(np.abs(y))) if len(y) else 0.0
    mss, ssr = float(res.ess), float(res.ssr)
    if np.ptp(y) == 0:
        unreliable.append(f"{fit.metric} is constant over the analysed runs")
    elif ssr < PERFECT_FIT_RTOL * mss:
        unreliable.append(f"near-perfect fit: residual SS {ssr:.3g} < {PERFECT_FIT_RTOL:g} x model SS {mss:.3g}")
    zero = (n >= 2) & (fit.cells["sd"].fillna(np.inf) <= ZERO_SD_RTOL * scale)
    if zero.any():
        unreliable.append(f"{int(zero.sum())} of {int((n >= 2).sum())} cells have zero within-cell variance")
    if unreliable:
        fit.reliable = False
        fit.unreliable_reasons = unreliable
        w.append("F tests are unreliable (" + "; ".join(unreliable) + "): F and p are not evidence of effects")
