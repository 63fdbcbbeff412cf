"""The report's document, section by section: overview, warnings, significant terms, design, one section per
metric, cell means, success rates, failed runs, figures, the campaign's own sections and the method."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from wbc_jax.analysis import stats
from wbc_jax.analysis.report.campaign_sections import campaign_sections, success_sections
from wbc_jax.analysis.report.document import Doc, fmt
from wbc_jax.analysis.report.envelope_section import claims_section, envelope_section
from wbc_jax.analysis.report.failed_runs import campaign_folder, failed_runs_section
from wbc_jax.analysis.report.figure_jobs import FIGURE_CAPTIONS, caption
from wbc_jax.analysis.report.inputs import Campaign, Table
from wbc_jax.analysis.report.metric_defs import labels, metrics_section
from wbc_jax.analysis.report.metric_section import metric_section


def title(results_csv: str, campaign: Campaign | None) -> str:
    """The report's title: the campaign's name and spec where its manifest names them, else the table's file."""
    if campaign is not None and campaign.spec_path:
        return (f"ANOVA report: {campaign.name} campaign ({campaign.spec_path})" if campaign.name
                else f"ANOVA report: {campaign.spec_path}")
    return f"ANOVA report: {Path(results_csv).name}"


def _title_block(d: Doc, results_csv: str, campaign: Campaign | None) -> None:
    """The title and, where a manifest is beside the table, which command and spec wrote it."""
    d.h(1, title(results_csv, campaign))
    if campaign is not None:
        spec = f" from the spec `{campaign.spec_path}`" if campaign.spec_path else ""
        spec_hash = f" (spec hash `{campaign.spec_hash[:12]}`)" if campaign.spec_hash else ""
        d.p(f"Results `{results_csv}`, written by `{campaign.command}`{spec}{spec_hash}.")


def document(res: dict, summary: dict, table: Table, metrics, alpha: float, images: list[str],
             extra: dict) -> Doc:
    """The report of an analysis with at least one metric.

    Args:
        res: :func:`~wbc_jax.analysis.report.model.analyze_table`'s result.
        summary: ``anova.json`` (:func:`~wbc_jax.analysis.report.output.summary`, cleaned).
        table: the results table as read.
        metrics: the analysed metric columns.
        alpha: significance level.
        images: the figures' file names (drawn or being drawn).
        extra: :func:`~wbc_jax.analysis.report.model.beyond_anova`'s result.
    """
    factors, shown = table.factors, labels(metrics, table.is_campaign)
    d = Doc()
    _title_block(d, summary["manifest"]["input"], table.campaign)
    d.p(_overview(res, summary, factors, metrics, alpha, shown))
    d.h(2, "Warnings")
    warnings = list(res["warnings"]) + [f"{m}: {w}" for m, r in res["metrics"].items() for w in r["warnings"]]
    d.ul(warnings) if warnings else d.p("None.")
    if table.is_campaign:
        metrics_section(d, metrics)
    d.h(2, "Significant terms")
    d.table(_significant_terms(res))
    d.p(f"* p < {alpha:g}.")
    d.h(2, "Design")
    design = res["design"].copy()
    for f in factors:
        design[f] = design[f].map(lambda v: fmt(v, "g"))
    d.table(design)
    for m, r in res["metrics"].items():
        metric_section(d, shown[m], r, res["level_means"][res["level_means"]["metric"] == m], alpha)
    d.h(2, "Cell means (successful runs)")
    d.table(_cell_means(res["cell_means"], factors, metrics, shown))
    success_sections(d, extra, factors, alpha)
    envelope_section(d, table.frame, factors)
    claims_section(d, table.frame, factors, alpha)
    failed_runs_section(d, table.frame, factors, campaign_folder(summary["manifest"]["input"], table.campaign))
    if images:
        d.h(2, "Figures")
        for name in images:
            d.img(name, caption(name, metrics))
    campaign_sections(d, table.frame, factors)
    d.h(2, "Method")
    d.ul(_method(summary, metrics, alpha))
    return d


def design_only_document(res: dict, extra: dict, results_csv: str, table: Table, alpha: float,
                         images: list[str]) -> Doc:
    """The report of a table without an analysable metric: warnings, the design table and the success rates."""
    factors = table.factors
    d = Doc()
    _title_block(d, results_csv, table.campaign)
    d.p(f"{res['n_runs']} runs ({res['n_failed']} failed); factors {', '.join(factors)}; no metric analysed.")
    d.h(2, "Warnings")
    d.ul(res["warnings"])
    d.h(2, "Design")
    d.table(res["design"])
    success_sections(d, extra, factors, alpha)
    envelope_section(d, table.frame, factors)
    claims_section(d, table.frame, factors, alpha)
    failed_runs_section(d, table.frame, factors, campaign_folder(results_csv, table.campaign))
    for name in images:
        d.img(name, FIGURE_CAPTIONS[name])
    return d


def _overview(res: dict, summary: dict, factors, metrics, alpha: float, shown: dict[str, str]) -> str:
    """The paragraph under the title: runs, factors and levels, metrics, alpha, the model, residual df."""
    order = summary["model_order"]
    levels = "; ".join(f"{f}: {', '.join(fmt(v, 'g') for v in summary['factors'][f])}" for f in factors)
    model = "main effects + two-way interactions" if order == 2 else f"interactions up to order {order}"
    pooled = f" (interactions of order > {order} pooled into the error)" if order < len(factors) else ""
    df_resid = ", ".join(f"{m} {fmt(summary['metrics'][m]['df_resid'], 'g')}" for m in metrics)
    return (f"{res['n_runs']} runs ({res['n_failed']} failed, excluded), factors {levels}; metrics "
            f"{', '.join(shown[m] for m in metrics)}; alpha = {alpha:g}; type {summary['ss_type']} sums of squares, "
            f"sum-to-zero contrasts; model: {model}{pooled}; residual df {df_resid}.")


def _significant_terms(res: dict) -> pd.DataFrame:
    """Per metric, F and p of every model term (* where significant) and the assumption tests failed or not run."""
    sources = list(next(iter(res["metrics"].values()))["anova"]["source"][:-1])
    rows = []
    for m, r in res["metrics"].items():
        t = r["anova"].set_index("source")
        cells = [("unreliable" if not r["fit"].reliable else
                  f"F={fmt(t.loc[s, 'F'])}, p={fmt(t.loc[s, 'p'], '.3g')}" + (" *" if s in r["significant"] else ""))
                 for s in sources]
        failed = [a["test"] for a in r["assumptions"] if a["ok"] is False]
        not_run = [a["test"] for a in r["assumptions"] if a["ok"] is None]
        rows.append([m, *cells, ", ".join(failed + [f"{t} not run" for t in not_run]) or "none"])
    return pd.DataFrame(rows, columns=["metric", *sources, "assumption tests failed / not run"])


def _cell_means(cm: pd.DataFrame, factors, metrics, shown: dict[str, str]) -> pd.DataFrame:
    """One row per cell, one column per metric: mean ± SD (n) of the successful runs."""
    wide = cm[cm["metric"] == metrics[0]][factors].reset_index(drop=True).map(lambda v: fmt(v, "g"))
    for m in metrics:
        t = cm[cm["metric"] == m].reset_index(drop=True)
        wide[shown[m]] = [f"{fmt(a)} ± {fmt(s)} ({n})" for a, s, n in zip(t["mean"], t["sd"], t["n"])]
    return wide


def _method(summary: dict, metrics, alpha: float) -> list[str]:
    """The method section's items."""
    rhs = summary["metrics"][metrics[0]]["formula"].split("~", 1)[1].strip()
    return [
        "Runs with success = False are counted in the design table and excluded from every model and mean; "
        "a missing metric value drops that run from that metric only.",
        f"Per metric, an OLS model ({rhs}) with sum-to-zero contrasts (statsmodels ols, C(x, Sum)); ANOVA by "
        f"anova_lm with type {summary['ss_type']} sums of squares (equal to types I and II for balanced data). "
        "Partial eta squared = SS_effect / (SS_effect + SS_residual).",
        "Assumptions on the model residuals: Lilliefors-corrected Kolmogorov-Smirnov and Shapiro-Wilk for "
        "normality; Levene (mean-centred) and Brown-Forsythe (median-centred) across cells for equal variances. "
        f"A test with p < {alpha:g} is flagged, never hidden. Levene and Brown-Forsythe are not run where the "
        "runs' absolute deviations from their cell's centre vary in no cell (every cell with 2 runs or zero "
        "variance): their statistic would be a ratio of rounding errors.",
        f"F tests are marked unreliable when the residual SS is below {stats.PERFECT_FIT_RTOL:g} x the model SS "
        "(R's rule), a cell has zero within-cell variance, or no residual degrees of freedom remain.",
        "Simple main effects for each significant two-way interaction, in both directions: estimated marginal "
        "means with equal weights over the other factors; simple-effect F per level of the conditioning factor; "
        "pairwise EMM differences with SE, t, df, Bonferroni-adjusted p and Bonferroni 95 % CI, one family per "
        "conditioning level, all with the pooled model MSE and residual df (as SPSS EMMEANS COMPARE, R emmeans).",
    ]
