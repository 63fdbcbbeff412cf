"""The report's figures as jobs of :mod:`wbc_jax.analysis.workers` (name -> (function of
:mod:`wbc_jax.analysis.figures`, its arguments)), and their captions."""

from __future__ import annotations

import re

import numpy as np

from wbc_jax.analysis import stats

FIGURE_CAPTIONS = {
    "means.png": "Estimated marginal means ± 95 % CI of each metric per factor level (equal weights over the other "
                 "factors' levels; the model's pooled error), so that a significant main effect shows as CIs apart; "
                 "SDs of the runs: the descriptives tables.",
    "interactions_{}.png": "Interaction plots of {}: EMMs ± 95 % CI for each two-way interaction, in both "
                           "orientations, each titled ordinal or disordinal (lines crossing).",
    "qq.png": "Normal Q-Q plots of standardized model residuals.",
    "success_levels.png": "Success rate (all runs) per level of each factor.",
    "success_pairs.png": "Success rate (all runs) per pair of factors; cells: successes/runs.",
}

Jobs = dict[str, tuple[str, tuple]]


def figure_jobs(res: dict, extra: dict, factors: list[str], metrics: list[str], labels: dict[str, str]) -> Jobs:
    """Every figure of a report with at least one analysed metric.

    Args:
        res: :func:`~wbc_jax.analysis.report.model.analyze_table`'s result.
        extra: :func:`~wbc_jax.analysis.report.model.beyond_anova`'s result.
        factors, metrics: the report's factor and (analysed) metric columns.
        labels: metric -> its axis label.
    """
    fits = {m: r["fit"] for m, r in res["metrics"].items()}
    emms = {m: r["emms"] for m, r in res["metrics"].items()}
    level_emms = {m: {f: stats.emmeans(fits[m], [f]) for f in factors} for m in metrics}
    has_pairs = bool(next(iter(emms.values())))  # a two-way term in the model: interaction plots
    return {"means.png": ("means_grid", (level_emms, factors, metrics, labels)),
            **{interaction_png(m): ("interaction_grid", ({m: emms[m]}, [m], [] if fits[m].reliable else [m], labels))
               for m in (metrics if has_pairs else [])},  # one figure per metric: drawn side by side
            "qq.png": ("qq_grid", ({m: (np.asarray(f.result.resid), None if f.degenerate else f.mse)
                                    for m, f in fits.items()},)),
            **success_jobs(extra, factors)}


def success_jobs(extra: dict, factors) -> Jobs:
    """The success-rate figures."""
    out = {"success_levels.png": ("success_levels", (extra["by_level"], factors))}
    if extra["by_pair"]:
        out["success_pairs.png"] = ("success_pairs", (extra["by_pair"],))
    return out


def interaction_png(metric: str) -> str:
    """The interaction figure's file name of a metric (characters other than letters, digits, ``.-_``: ``_``)."""
    return "interactions_" + re.sub(r"[^A-Za-z0-9._-]", "_", metric) + ".png"


def caption(name: str, metrics) -> str:
    """The caption of figure ``name`` (of a report of ``metrics``)."""
    for m in metrics:
        if name == interaction_png(m):
            return FIGURE_CAPTIONS["interactions_{}.png"].format(m)
    return FIGURE_CAPTIONS[name]
