"""Success rates of a campaign per factor level and per pair of factors (all runs, failed ones included).

Where the controller stops succeeding (e.g. push magnitude x speed in ``sweeps/robustness.toml``) is read from
these tables: the share of runs with ``success`` True, pooled over the other factors' levels and the
repetitions. Pure functions on the results table; the report (:mod:`wbc_jax.analysis.report`) renders them and
:func:`wbc_jax.analysis.figures.success_grid` plots them.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats as sps

from wbc_jax.analysis.table import levels, success_column

CONFIDENCE = 0.95  # of the success rates' intervals


def interval(successes, runs, confidence: float = CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """Clopper-Pearson (exact binomial) interval of the success rate, elementwise: (low, high), NaN without runs;
    ``successes == runs`` gives ((1 - confidence) / 2) ** (1 / runs) as the low end (a null result's bound)."""
    k, n = np.asarray(successes, dtype=float), np.asarray(runs, dtype=float)
    tail = (1.0 - confidence) / 2.0
    with np.errstate(invalid="ignore", divide="ignore"):
        low = np.where(k > 0, sps.beta.ppf(tail, k, n - k + 1), 0.0)
        high = np.where(k < n, sps.beta.isf(tail, k + 1, n - k), 1.0)
    none = n <= 0
    return np.where(none, np.nan, low), np.where(none, np.nan, high)


def _rates(df: pd.DataFrame, by: Sequence[str]) -> pd.DataFrame:
    """Runs, successes, rate and its :func:`interval` (``ci_low``, ``ci_high``) per combination of the ``by``
    columns' levels (the full grid)."""
    by = list(by)
    grid = pd.MultiIndex.from_product([levels(df[f]) for f in by], names=by)
    g = success_column(df).astype(int).groupby([df[f] for f in by])
    out = pd.DataFrame({"runs": g.size().reindex(grid, fill_value=0).astype(int),
                        "successes": g.sum().reindex(grid, fill_value=0).astype(int)}).reset_index()
    out["rate"] = out["successes"] / out["runs"].where(out["runs"] > 0)
    out["ci_low"], out["ci_high"] = interval(out["successes"], out["runs"])
    return out


def by_level(df: pd.DataFrame, factors: Sequence[str]) -> pd.DataFrame:
    """Long table: factor, level, runs, successes, rate, ci_low, ci_high (NaN without runs) for every level of
    every factor."""
    parts = [_rates(df, [f]).rename(columns={f: "level"}).assign(factor=f) for f in factors]
    return pd.concat(parts, ignore_index=True)[["factor", "level", "runs", "successes", "rate", "ci_low", "ci_high"]]


def pairs(factors: Sequence[str]) -> list[tuple[str, str]]:
    """Every pair of factors, in the factors' order."""
    return list(itertools.combinations(factors, 2))


def by_pair(df: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Long table: a, b, runs, successes, rate, ci_low, ci_high for every combination of the two factors' levels."""
    return _rates(df, [a, b])


def wide(t: pd.DataFrame, a: str, b: str, fmt=str) -> pd.DataFrame:
    """:func:`by_pair` as rows = levels of ``a``, columns = levels of ``b``, cells ``successes/runs (rate %)``;
    ``fmt`` formats the level labels."""
    cell = [f"{s}/{n} ({100 * r:.0f} %)" if n else "" for s, n, r in zip(t["successes"], t["runs"], t["rate"])]
    out = t.assign(cell=cell).pivot(index=a, columns=b, values="cell")
    out.columns = [f"{b} = {fmt(c)}" for c in out.columns]
    out.index = [fmt(i) for i in out.index]
    return out.rename_axis(a).reset_index()
