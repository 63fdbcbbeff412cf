"""Success rates of a campaign per factor level and per pair of factors (all runs, failed ones included).

Where the controller stops succeeding (e.g. push magnitude x speed in ``sweeps/robustness.toml``) is read from
these tables: the share of runs with ``success`` True, pooled over the other factors' levels and the
repetitions. Pure functions on the results table; the report (:mod:`wbc_jax.analysis.report`) renders them and
:func:`wbc_jax.analysis.figures.success_grid` plots them.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import pandas as pd

from wbc_jax.analysis.table import levels, success_column


def _rates(df: pd.DataFrame, by: Sequence[str]) -> pd.DataFrame:
    """Runs, successes and rate per combination of the ``by`` columns' levels (the full grid)."""
    by = list(by)
    grid = pd.MultiIndex.from_product([levels(df[f]) for f in by], names=by)
    g = success_column(df).astype(int).groupby([df[f] for f in by])
    out = pd.DataFrame({"runs": g.size().reindex(grid, fill_value=0).astype(int),
                        "successes": g.sum().reindex(grid, fill_value=0).astype(int)}).reset_index()
    out["rate"] = out["successes"] / out["runs"].where(out["runs"] > 0)
    return out


def by_level(df: pd.DataFrame, factors: Sequence[str]) -> pd.DataFrame:
    """Long table: factor, level, runs, successes, rate (NaN without runs) for every level of every factor."""
    parts = [_rates(df, [f]).rename(columns={f: "level"}).assign(factor=f) for f in factors]
    return pd.concat(parts, ignore_index=True)[["factor", "level", "runs", "successes", "rate"]]


def pairs(factors: Sequence[str]) -> list[tuple[str, str]]:
    """Every pair of factors, in the factors' order."""
    return list(itertools.combinations(factors, 2))


def by_pair(df: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Long table: a, b, runs, successes, rate for every combination of the two factors' levels."""
    return _rates(df, [a, b])


def wide(t: pd.DataFrame, a: str, b: str, fmt=str) -> pd.DataFrame:
    """:func:`by_pair` as rows = levels of ``a``, columns = levels of ``b``, cells ``successes/runs (rate %)``;
    ``fmt`` formats the level labels."""
    cell = [f"{s}/{n} ({100 * r:.0f} %)" if n else "" for s, n, r in zip(t["successes"], t["runs"], t["rate"])]
    out = t.assign(cell=cell).pivot(index=a, columns=b, values="cell")
    out.columns = [f"{b} = {fmt(c)}" for c in out.columns]
    out.index = [fmt(i) for i in out.index]
    return out.rename_axis(a).reset_index()
