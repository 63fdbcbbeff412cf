"""The results table of a campaign: column inference, validation and descriptive statistics.

The input is a tidy results table, one row per run: factor columns (``m``, ``mu``, ``d`` in the
transport campaign; any others by name), a boolean ``success`` and numeric metric columns
(``R``, ``T``, ``S``, ...). Runs with ``success == False`` are excluded from every mean (they are
counted as failures in :func:`design_table`).

Default columns
- Factors: those of ``m``, ``mu``, ``d`` present in the table.
- Metrics: ``R``, ``T``, ``S`` first (those present), then every other numeric, non-boolean
  column that is not a factor, not a bookkeeping column (``rep``, ``seed``, ``success``,
  ``run``, ``run_id``, ``id``, ``index``, ``Unnamed: ...``) and not a flag (a column whose
  name starts with ``flag`` or whose values are all 0/1 integers).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from wbc_jax.errors import InputError

DEFAULT_FACTORS = ("m", "mu", "d")
PREFERRED_METRICS = ("R", "T", "S")
BOOKKEEPING = frozenset({"rep", "seed", "success", "run", "run_id", "id", "index", "first_contact_s"})

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


def plain(value) -> str:
    """A value as a one-line message shows it: numbers as written (``0.2``, not ``np.float64(0.2)``), strings
    quoted (``'abc'``)."""
    if isinstance(value, np.generic):
        value = value.item()
    return repr(value) if isinstance(value, str) else str(value)


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
            raise InputError(f"factor '{f}' has only one level ({plain(lv[0])}); a factor needs at least two")
    out["success"] = success_column(out)
    for m in metrics:
        s = out[m]
        if pd.api.types.is_bool_dtype(s):
            raise InputError(f"metric '{m}' is boolean, not numeric")
        if not pd.api.types.is_numeric_dtype(s):
            bad = s[pd.to_numeric(s, errors="coerce").isna() & s.notna()]
            example = f" (e.g. {plain(bad.iloc[0])})" if len(bad) else ""
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
        raise InputError(f"column 'success' is not boolean (e.g. {plain(s[bad.index[0]])})")
    return low.isin(_TRUE)


def successful(df: pd.DataFrame) -> pd.DataFrame:
    """The rows with ``success`` True (see :func:`success_column`)."""
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


def cell_means(df: pd.DataFrame, factors: Sequence[str], metrics: Sequence[str],
               successful_only: bool = True) -> pd.DataFrame:
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
    d = successful(df) if successful_only else df
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
    d = successful(df)
    rows = []
    for m in metrics:
        for f in factors:
            agg = d.groupby(f)[m].agg(["mean", "std", "count"])
            for lv in levels(df[f]):
                mean, sd, n = agg.loc[lv] if lv in agg.index else (np.nan, np.nan, 0)
                rows.append({"metric": m, "factor": f, "level": lv, "mean": mean, "sd": sd, "n": int(n)})
    return pd.DataFrame(rows, columns=["metric", "factor", "level", "mean", "sd", "n"])
