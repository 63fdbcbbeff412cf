"""``wbc-jax report``: read a results table, analyse it, and write the report folder (all or nothing)."""

from __future__ import annotations

import time

from wbc_jax.analysis import stats
from wbc_jax.analysis.report import latex, output
from wbc_jax.analysis.report.campaign_sections import R_PLAN, r_sources
from wbc_jax.analysis.report.figure_jobs import figure_jobs, success_jobs
from wbc_jax.analysis.report.inputs import Table, load_table
from wbc_jax.analysis.report.metric_defs import in_display_units, labels, units
from wbc_jax.analysis.report.model import analyze_table, beyond_anova
from wbc_jax.analysis.report.sections import design_only_document, document, title
from wbc_jax.analysis.workers import Workers, start_figures
from wbc_jax.errors import InputError
from wbc_jax.io_utils import check_out_dir


def run_report(results_csv: str, out_dir: str, alpha: float = 0.05, factors: list[str] | None = None,
               metrics: list[str] | None = None, *, figures: bool = True, ss_type: int = 3, order: int | None = None,
               force: bool = False, workers: Workers | None = None) -> dict:
    """Write the ANOVA report of ``results_csv`` into ``out_dir``.

    Args:
        results_csv: results table, one row per run (factors, rep, seed, success, metrics).
        out_dir: output directory, new or empty (or an earlier report with ``force``); untouched on error.
        alpha: significance level (0 < alpha < 1).
        factors: factor columns (default: those the campaign's manifest declares, else those of m, mu, d;
            :func:`~wbc_jax.analysis.report.inputs.load_table`).
        metrics: metric columns (default: see :mod:`wbc_jax.analysis.stats`).
        figures: render the PNG figures (tests switch them off for speed).
        ss_type: sums-of-squares type, 1, 2 or 3.
        order: highest interaction order of the model (2: main effects + two-way; default: the campaign's or 2).
        force: replace ``out_dir`` when it holds an earlier report.
        workers: figure workers (:class:`wbc_jax.analysis.workers.Workers`) that draw the figures side by side
            while this process writes the document (figures beyond their number: drawn here); None: drawn here one
            after another. The caller closes them (:meth:`~wbc_jax.analysis.workers.Workers.close`: those left
            idle, e.g. after an error).

    Returns:
        The content of ``anova.json``.

    Raises:
        InputError: unreadable or malformed input, e.g. repeated run ids, a JSON or a semicolon-separated file
            (one-line message naming the problem).
        OutputError: ``out_dir`` is not a new or empty folder (or an earlier report with ``force``).
        WbcJaxError: the output directory cannot be written.
    """
    started = time.perf_counter()
    if not (isinstance(alpha, (int, float)) and 0 < alpha < 1):
        raise InputError(f"alpha must be between 0 and 1, not {alpha}")
    check_out_dir(out_dir, output.COMMAND, force=force, inputs=[results_csv])
    table = load_table(results_csv, factors, metrics, order)
    factors, df = table.factors, table.frame
    request = output.Request(results_csv, table.raw, alpha, factors, ss_type, table.order, started)
    data = in_display_units(stats.prepare(df, factors, table.metrics), table.metrics, table.is_campaign)
    res = analyze_table(data, factors, table.metrics, alpha=alpha, ss_type=ss_type, order=table.order)
    res["warnings"] = table.warnings + res["warnings"]
    extra = beyond_anova(data, factors, alpha)
    if not res["metrics"]:
        return _write_design_only(request, table, res, extra, out_dir, figures, workers)
    metrics = list(res["metrics"])
    jobs = figure_jobs(res, extra, factors, metrics, labels(metrics, table.is_campaign)) if figures else {}
    pending = start_figures(jobs, workers)  # drawn by the workers while this process writes the document
    manifest = output.manifest(request, len(df), metrics)
    r_json = {"r_sources": r_sources(df, factors).to_dict("records")} if R_PLAN in df.columns else {}
    summary = output.clean(dict(output.summary(res, data, factors, alpha, manifest), **output.extra_json(extra),
                                **r_json, units=units(metrics, table.is_campaign)))
    doc = document(res, summary, table, metrics, alpha, list(jobs), extra)
    images = pending.result()
    manifest["wall_s"] = summary["manifest"]["wall_s"] = output.wall_s(request)
    files = {
        "report.md": doc.markdown().encode(),
        "report.html": doc.html(images, title=title(results_csv, table.campaign)).encode(),
        "anova.json": output.dumps(summary).encode(),
        "anova.tex": latex.document(summary, results_csv, res["level_means"]).encode(),
        "design.csv": res["design"].to_csv(index=False).encode(),
        "cell_means.csv": res["cell_means"].to_csv(index=False).encode(),
        "manifest.json": output.dumps(manifest).encode(),
        **{f"figures/{k}": v for k, v in images.items()},
    }
    output.write_dir_atomic(out_dir, files)
    return summary


def _write_design_only(request: output.Request, table: Table, res: dict, extra: dict, out_dir: str, figures: bool,
                       figure_workers: Workers | None) -> dict:
    """The report of a table without an analysable metric: warnings, the design table and the success rates."""
    jobs = success_jobs(extra, request.factors) if figures else {}
    images = start_figures(jobs, figure_workers).result()
    d = design_only_document(res, extra, request.results_csv, table, request.alpha, list(images))
    manifest = dict(output.manifest(request, res["n_runs"], []), wall_s=output.wall_s(request))
    summary = output.clean({"schema": output.SCHEMA, "alpha": request.alpha, "ss_type": manifest["ss_type"],
                            "n_runs": res["n_runs"], "n_failed": res["n_failed"], "warnings": res["warnings"],
                            "design": res["design"], "metrics": {}, **output.extra_json(extra),
                            "manifest": manifest})
    output.write_dir_atomic(out_dir, {"report.md": d.markdown().encode(),
                                      "report.html": d.html(images, title=title(request.results_csv,
                                                                                table.campaign)).encode(),
                                      "anova.json": output.dumps(summary).encode(),
                                      "design.csv": res["design"].to_csv(index=False).encode(),
                                      "manifest.json": output.dumps(manifest).encode(),
                                      **{f"figures/{k}": v for k, v in images.items()}})
    return summary
