"""The report's statistics: the ANOVA of every metric the table allows, success rates and ablation comparisons."""

from __future__ import annotations

import numpy as np
import pandas as pd

from wbc_jax.analysis import ablation, stats, success
from wbc_jax.analysis.report.inputs import one_line

HUGE = 1e100  # a metric value at least this large in magnitude overflows the sums of squares (squared: 1e200+)


def analyze_table(data: pd.DataFrame, factors: list[str], metrics: list[str], **kw) -> dict:
    """:func:`wbc_jax.analysis.stats.analyze`, with what it cannot model turned into table-wide warnings.

    A metric with |value| >= HUGE is left out; a metric whose model fails is refitted with main effects only,
    and left out when that fails too. Without successful runs (or without an analysable metric) ``metrics`` of
    the result is empty and the report holds the design table.
    """
    notes, ok = [], []
    for m in metrics:
        big = float(np.nanmax(np.abs(data[m].to_numpy(dtype=float)))) if data[m].notna().any() else 0.0
        if big >= HUGE:
            notes.append(f"metric '{m}' not analysed: values up to {big:.3g} overflow the sums of squares "
                         f"(|value| < {HUGE:g} needed)")
        else:
            ok.append(m)
    if not stats.success_column(data).any():
        notes.append("no successful runs (success is False in every row): no model fitted, design table only")
        ok = []
    try:
        res = stats.analyze(data, factors, ok, **kw) if ok else None
    except Exception:  # noqa: BLE001  (which metric failed is found below, one at a time)
        res = _analyze_one_at_a_time(data, factors, ok, notes, **kw)
    if res is None:
        design = stats.design_table(data, factors)
        res = dict(design=design, metrics={}, warnings=[], n_runs=len(data), n_failed=int(design["failures"].sum()))
    res["warnings"] = list(res["warnings"]) + notes
    return res


def _analyze_one_at_a_time(data: pd.DataFrame, factors: list[str], metrics: list[str], notes: list[str],
                           **kw) -> dict | None:
    """:func:`wbc_jax.analysis.stats.analyze` metric by metric, main effects only where the full model fails; what
    is left out is appended to ``notes``. None when no metric can be fitted."""
    parts = []
    for m in metrics:
        for order in sorted({kw["order"], 1}, reverse=True):
            try:
                parts.append(stats.analyze(data, factors, [m], **dict(kw, order=order)))
                if order != kw["order"]:
                    notes.append(f"metric '{m}': the model with interactions cannot be fitted "
                                 "(too few runs); main effects only")
                break
            except Exception as e:  # noqa: BLE001
                if order == 1:
                    notes.append(f"metric '{m}' not analysed: {one_line(e)}")
    if not parts:
        return None
    return dict(parts[0], metrics={m: r for p in parts for m, r in p["metrics"].items()},
                cell_means=pd.concat([p["cell_means"] for p in parts], ignore_index=True),
                level_means=pd.concat([p["level_means"] for p in parts], ignore_index=True))


def beyond_anova(data: pd.DataFrame, factors, alpha: float) -> dict:
    """Success rates per level and per pair of factors (all runs), and the ablation comparisons."""
    return {"by_level": success.by_level(data, factors),
            "by_pair": {p: success.by_pair(data, *p) for p in success.pairs(factors)},
            "ablation": ablation.compare(data, factors, alpha)}
