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

Default columns
- Factors: those of ``m``, ``mu``, ``d`` present in the table.
- Metrics: ``R``, ``T``, ``S`` first (those present), then every other numeric, non-boolean
  column that is not a factor, not a bookkeeping column (``rep``, ``seed``, ``success``,
  ``run``, ``run_id``, ``id``, ``index``, ``Unnamed: ...``) and not a flag (a column whose
  name starts with ``flag`` or whose values are all 0/1 integers).
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from wbc_jax.errors import InputError

DEFAULT_FACTORS = ("m", "mu", "d")
PREFERRED_METRICS = ("R", "T", "S")
BOOKKEEPING = frozenset({"rep", "seed", "success", "run", "run_id", "id", "index", "first_contact_s"})
SS_NAMES = {1: "I", 2: "II", 3: "III"}
PERFECT_FIT_RTOL = 1e-10  # R's summary.lm rule: residual SS < 1e-10 x model SS
ZERO_SD_RTOL = 1e-10  # a cell SD below this x max|y| counts as zero variance
ESTIMABLE_TOL = 1e-8  # L is estimable if its part outside the row space of X is below this
CONF = 0.95  # confidence level of EMM and pairwise intervals

_TRUE = frozenset({"true", "t", "yes", "y", "1", "1.0"})
_FALSE = frozenset({"false", "f", "no", "n", "0", "0.0"})


# --------------------------------------------------------------------------- columns


def infer_factors(df: pd.DataFrame, factors: Sequence[str] | None = None) -> list[str]:
    """Factor columns: the given names (checked) or those of m, mu, d present."""
    if factors is None:
        found = [f for f in DEFAULT_FACTORS if f in df.columns]
        if not found:
            raise InputError("no factor columns: none of m, mu, d in the table (name them with --factors)")
        return found
    return _check_names(df, factors, "factor")


def infer_metrics(df: pd.DataFrame, factors: Sequence[str], metrics: Sequence[str] | None = None) -> list[str]:
    """Metric columns: the given names (checked) or the default rule of the module docstring."""
    if metrics is not None:
        names = _check_names(df, metrics, "metric")
        both = [m for m in names if m in factors]
        if both:
            raise InputError(f"column '{both[0]}' is given both as a factor and as a metric")
        return names
    first = [c for c in PREFERRED_METRICS if c in df.columns and c not in factors]
    rest = [c for c in df.columns if c not in first and _is_default_metric(df, c, factors)]
    if not first + rest:
        raise InputError("no metric columns found (name them with --metrics)")
    return first + rest


def _check_names(df: pd.DataFrame, names: Sequence[str], kind: str) -> list[str]:
    names = [str(n).strip() for n in names]
    if not names or "" in names:
        raise InputError(f"empty {kind} name in the {kind} list")
    dup = [n for n in names if names.count(n) > 1]
    if dup:
        raise InputError(f"{kind} '{dup[0]}' is named twice")
    for n in names:
        if n not in df.columns:
            raise InputError(f"{kind} column '{n}' is not in the table (columns: {', '.join(map(str, df.columns))})")
    return names


def _is_default_metric(df: pd.DataFrame, col, factors: Sequence[str]) -> bool:
    name = str(col)
    s = df[col]
    if col in factors or name.lower() in BOOKKEEPING or name.startswith("Unnamed:") or name.lower().startswith("flag"):
        return False
    if pd.api.types.is_bool_dtype(s) or not pd.api.types.is_numeric_dtype(s):
        return False
    if pd.api.types.is_integer_dtype(s) and set(s.dropna().unique()) <= {0, 1}:
        return False
    return True


def levels(s: pd.Series) -> list:
    """Sorted distinct non-missing values of a factor column (numeric order if possible)."""
    vals = list(pd.unique(s.dropna()))
    try:
        return sorted(vals)
    except TypeError:
        return sorted(vals, key=str)


# --------------------------------------------------------------------------- validation


def prepare(df: pd.DataFrame, factors: Sequence[str], metrics: Sequence[str]) -> pd.DataFrame:
    """Validate a results table and return a copy with a boolean ``success`` column.

    Raises:
        InputError: no rows; a missing column; a factor with empty values or one level; a
            non-numeric or non-finite metric; a ``success`` column that is not boolean.
    """
    if len(df) == 0:
        raise InputError("the results table has no rows")
    _check_names(df, factors, "factor")
    _check_names(df, metrics, "metric")
    out = df.copy()
    for f in factors:
        n_na = int(out[f].isna().sum())
        if n_na:
            raise InputError(f"factor '{f}' has {n_na} empty value(s)")
        lv = levels(out[f])
        if len(lv) < 2:
            raise InputError(f"factor '{f}' has only one level ({lv[0]!r}); a factor needs at least two")
    out["success"] = success_column(out)
    for m in metrics:
        s = out[m]
        if pd.api.types.is_bool_dtype(s):
            raise InputError(f"metric '{m}' is boolean, not numeric")
        if not pd.api.types.is_numeric_dtype(s):
            bad = s[pd.to_numeric(s, errors="coerce").isna() & s.notna()]
            example = f" (e.g. {bad.iloc[0]!r})" if len(bad) else ""
            raise InputError(f"metric '{m}' is not numeric{example}")
        n_inf = int(np.isinf(s.astype(float)).sum())
        if n_inf:
            raise InputError(f"metric '{m}' has {n_inf} infinite value(s)")
    return out


def success_column(df: pd.DataFrame) -> pd.Series:
    """``success`` as booleans (all True if the column is absent).

    Accepts bool, 0/1 numbers and the strings true/false/yes/no/t/f/y/n/1/0 (any case).
    """
    if "success" not in df.columns:
        return pd.Series(True, index=df.index)
    s = df["success"]
    if pd.api.types.is_bool_dtype(s) and not s.isna().any():
        return s.astype(bool)
    if s.isna().any():
        raise InputError(f"column 'success' has {int(s.isna().sum())} empty value(s)")
    if pd.api.types.is_numeric_dtype(s) and set(s.unique()) <= {0, 1}:
        return s.astype(bool)
    low = s.astype(str).str.strip().str.lower()
    bad = low[~low.isin(_TRUE | _FALSE)]
    if len(bad):
        raise InputError(f"column 'success' is not boolean (e.g. {s[bad.index[0]]!r})")
    return low.isin(_TRUE)


def _successful(df: pd.DataFrame) -> pd.DataFrame:
    return df[success_column(df).to_numpy()]


# --------------------------------------------------------------------------- descriptives


def design_table(df: pd.DataFrame, factors: Sequence[str]) -> pd.DataFrame:
    """Runs, successes and failures per cell of the full factorial grid (empty cells included)."""
    factors = list(factors)
    grid = pd.MultiIndex.from_product([levels(df[f]) for f in factors], names=factors)
    ok = success_column(df).astype(int)
    g = ok.groupby([df[f] for f in factors], sort=False)
    runs = g.size().reindex(grid, fill_value=0)
    succ = g.sum().reindex(grid, fill_value=0)
    out = pd.DataFrame({"runs": runs.astype(int), "successes": succ.astype(int)})
    out["failures"] = out["runs"] - out["successes"]
    return out.reset_index()


def cell_means(df: pd.DataFrame, factors: Sequence[str], metrics: Sequence[str], successful_only: bool = True) -> pd.DataFrame:
    """Mean, SD (ddof 1) and n of each metric per cell, long format.

    Args:
        df: results table, one row per run.
        factors: factor columns defining the cells.
        metrics: metric columns.
        successful_only: drop runs with ``success == False`` first (if the column exists).

    Returns:
        One row per (cell, metric): the factor columns, ``metric``, ``mean``, ``sd``, ``n``.
        Every cell of the grid of the table's factor levels appears; cells without values
        have n = 0 and NaN mean.
    """
    factors = list(factors)
    grid = pd.MultiIndex.from_product([levels(df[f]) for f in factors], names=factors)
    d = _successful(df) if successful_only else df
    parts = []
    for m in metrics:
        agg = d.groupby(factors, sort=False)[m].agg(["mean", "std", "count"]).reindex(grid)
        agg = agg.rename(columns={"std": "sd", "count": "n"}).reset_index()
        agg["n"] = agg["n"].fillna(0).astype(int)
        agg.insert(len(factors), "metric", m)
        parts.append(agg)
    return pd.concat(parts, ignore_index=True)


def level_means(df: pd.DataFrame, factors: Sequence[str], metrics: Sequence[str]) -> pd.DataFrame:
    """Mean, SD and n of each metric per level of each factor (successful runs), long format."""
    d = _successful(df)
    rows = []
    for m in metrics:
        for f in factors:
            agg = d.groupby(f)[m].agg(["mean", "std", "count"])
            for lv in levels(df[f]):
                mean, sd, n = agg.loc[lv] if lv in agg.index else (np.nan, np.nan, 0)
                rows.append({"metric": m, "factor": f, "level": lv, "mean": mean, "sd": sd, "n": int(n)})
    return pd.DataFrame(rows, columns=["metric", "factor", "level", "mean", "sd", "n"])


# --------------------------------------------------------------------------- ANOVA


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


def _code(i: int) -> str:
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
        raise InputError(f"SS type must be 1, 2 or 3, not {ss_type!r}")
    factors = list(factors)
    d = _successful(df)
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
        x[_code(i)] = pd.Categorical(d[f].to_numpy(), categories=lv[f])
    code = {f: _code(i) for i, f in enumerate(factors)}
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


# --------------------------------------------------------------------------- assumptions


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
    return [ex[_code(i)].to_numpy() for i in range(len(fit.factors))]


# --------------------------------------------------------------------------- EMMs


def _grid(fit: AnovaFit) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """Full factorial grid of levels, its design matrix and the row-space projector of X."""
    if fit._grid is None:
        from statsmodels.formula._manager import FormulaManager

        g = pd.DataFrame(list(itertools.product(*(fit.levels[f] for f in fit.factors))), columns=fit.factors)
        coded = pd.DataFrame({_code(i): pd.Categorical(g[f], categories=fit.levels[f]) for i, f in enumerate(fit.factors)})
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


# --------------------------------------------------------------------------- everything


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
        raise InputError(f"SS type must be 1, 2 or 3, not {ss_type!r}")
    if not (isinstance(order, int) and order >= 1):
        raise InputError(f"model order must be an integer >= 1, not {order!r}")
    factors, metrics = list(factors), list(metrics)
    design = design_table(df, factors)
    n_failed = int(design["failures"].sum())
    notes = []
    if n_failed:
        notes.append(f"{n_failed} of {len(df)} runs failed (success = False) and are excluded from the analysis")
    if (design["runs"] == 0).any():
        notes.append(f"{int((design['runs'] == 0).sum())} of {len(design)} cells have no runs at all")
    if (design["runs"] > 0).any() and ((design["successes"] == 0) & (design["runs"] > 0)).any():
        notes.append(f"{int(((design['successes'] == 0) & (design['runs'] > 0)).sum())} cells have runs but no successful run")
    if _successful(df).empty:
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
