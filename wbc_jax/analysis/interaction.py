"""Ordinal or disordinal interactions: the rule behind the labels of the report's interaction plots.

Pure functions of tables of means (no plotting), so the rule is unit-tested on hand-made tables.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

SHAPE_RTOL = 1e-9  # line differences within this fraction of the table's largest |mean| count as ties (no side)


def interaction_shape(means) -> str:
    """Ordinal or disordinal, for the interaction plot of a two-way table of means.

    Rule: the plot has the levels of one factor on the x axis and one line per level of the other. It is
    *disordinal* when two lines cross within the plotted range, i.e. the order of the line factor's levels
    reverses across the x levels: for some pair of lines the difference is positive at one x level and negative
    at another. Otherwise (parallel, or diverging, converging, touching without reversing) it is *ordinal*.
    Differences within ``SHAPE_RTOL`` x the largest |mean| are ties. NaN cells are ignored.

    Args:
        means: (n_x, n_lines) array: rows the x-axis levels, columns the lines.

    Returns:
        "disordinal" or "ordinal".
    """
    y = np.asarray(means, float)
    if y.ndim != 2:
        raise ValueError(f"expected a 2-D table of means, got shape {y.shape}")
    tol = SHAPE_RTOL * (np.nanmax(np.abs(y)) if np.isfinite(y).any() else 0.0)
    for i in range(y.shape[1]):
        for j in range(i + 1, y.shape[1]):
            diff = y[:, i] - y[:, j]
            if np.any(diff > tol) and np.any(diff < -tol):
                return "disordinal"
    return "ordinal"


def emm_table(t: pd.DataFrame, xf: str, lf: str) -> pd.DataFrame:
    """(x levels x line levels) table of the ``emm`` column of a two-way EMM table, in first-seen level order."""
    xs, ls = list(dict.fromkeys(t[xf])), list(dict.fromkeys(t[lf]))
    return t.pivot_table(index=xf, columns=lf, values="emm", sort=False).reindex(index=xs, columns=ls)


def interaction_views(pairs: Sequence[str]) -> list[tuple[str, str, str]]:
    """Both orientations of each two-way interaction "A:B": (pair, x factor, line factor), A on x first."""
    return [(p, *o) for p in pairs for o in (p.split(":"), p.split(":")[::-1])]


def shapes(emms: dict[str, pd.DataFrame]) -> list[dict]:
    """Both orientations of every two-way interaction of one metric, classified.

    Args:
        emms: {"A:B": two-way EMM table (columns A, B, emm)}, :func:`wbc_jax.analysis.stats.emmeans`.

    Returns:
        list of dict(interaction, x, lines, shape), A on x first for each "A:B".
    """
    return [dict(interaction=p, x=xf, lines=lf, shape=interaction_shape(emm_table(emms[p], xf, lf).to_numpy()))
            for p, xf, lf in interaction_views(list(emms))]
