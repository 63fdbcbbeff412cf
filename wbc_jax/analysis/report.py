"""The ANOVA report of a results table (``wbc-jax report RESULTS.csv --out DIR``).

Reads the CSV, checks it, runs :func:`wbc_jax.analysis.stats.analyze`, and writes into DIR:

- ``report.md``: warnings first, design, summary of significant terms, per metric the ANOVA
  table, assumption tests, simple main effects and descriptives, cell means, figures, method.
- ``report.html``: the same, self-contained (figures embedded as base64 PNG).
- ``anova.json``: ``metrics`` maps each metric to ``anova`` (a list of rows with keys
  source, sum_sq, df, mean_sq, F, p, partial_eta_sq; the last row is Residual),
  ``f_tests_reliable``, ``significant``, ``assumptions``, ``simple_effects`` and
  ``warnings``; plus ``alpha``, ``ss_type``, ``factors`` (levels), table-wide ``warnings``,
  ``design`` and ``manifest``. NaN is written as null.
- for a campaign's table with ``R_plan``: a section (and ``anova.json`` ``r_sources``) with R from the simulator's
  and from the QP's planned object forces per cell and the boundary rule's share of each (:func:`r_sources`).
- ``design.csv``, ``cell_means.csv`` (mean, sd, n per cell and metric; CI baselines).
- ``manifest.json``: input path and SHA-256, arguments, package versions, wall time.
- ``figures/means.png`` (metric means +- SD per factor level), ``figures/interactions_<metric>.png`` (one per
  metric: EMM +- 95 % CI per two-way interaction), ``figures/qq.png`` (residual Q-Q plots),
  ``figures/success_levels.png`` and ``figures/success_pairs.png`` (success rate per factor level and per
  pair of factors, :mod:`wbc_jax.analysis.success`).

Besides the ANOVA: success rates per factor level and per pair of factors (all runs; ``anova.json``
``success``), and for a ``variant`` or ``observer`` factor each level against the reference controller
(:mod:`wbc_jax.analysis.ablation`: Welch t and Mann-Whitney U on max slip and R, Fisher's exact test on
success; ``anova.json`` ``ablation``).

Factors and model order: as given; else, for a campaign's ``results.csv`` with its ``manifest.json`` beside it,
the spec's factors and ``[analysis] order``; else m, mu, d and order 2.

Nothing partial is left in DIR: everything is built in memory, written to a temporary
sibling directory, and renamed into place. DIR must be new or empty, or (``force``) hold an
earlier report (:func:`wbc_jax.io_utils.check_out_dir`); it is never the folder of the input.

A table the statistics cannot fully model still gets a report, with the reason among its
warnings: a metric with values too large for sums of squares (|value| >= ``HUGE``) or one
whose model cannot be fitted (e.g. no residual degrees of freedom in a 1-rep table with a
missing value) is fitted with main effects only or left out; a table without successful
runs gets the design table only.
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import json
import math
import platform
import re
import time
from pathlib import Path

import numpy as np
import pandas as pd

from wbc_jax.analysis import interaction, render, stats
from wbc_jax.errors import InputError, WbcJaxError
from wbc_jax.io_utils import atomic_dir, check_out_dir, read_capped

SCHEMA = "wbc_jax.analysis.report/1"
COMMAND = "wbc-jax report"
CAMPAIGN_METRICS = ("R", "T", "S")
QP_FLAG = "qp_flag_fraction"  # a campaign's results.csv column: the report's QP convergence section
QP_FLAG_LINE = 0.001  # wbc_jax.metrics.paper.QP_FLAG_FRACTION (not imported: the report stays JAX-free)
R_PLAN = "R_plan"  # a campaign's results.csv column: the report's "R: simulator vs planned forces" section
R_SOURCE_COLUMNS = (("R", "R (simulator)"), ("R_plan", "R (QP plan)"), ("boundary_fraction", "rule share, simulator [%]"),
                    ("boundary_cone_fraction", "of which on/outside the cone [%]"),
                    ("boundary_fraction_plan", "rule share, plan [%]"),
                    ("boundary_cone_fraction_plan", "of which on/outside the cone, plan [%]"))
CLEARANCE = "min_clearance_mm"  # a campaign's results.csv column: the report's clearance section  # the metrics of a campaign's report (its results.csv has more columns)
FIGURE_CAPTIONS = {
    "means.png": "Mean ± SD of each metric per factor level (rows: metrics, columns: factors).",
    "interactions_{}.png": "Interaction plots of {}: EMMs ± 95 % CI for each two-way interaction, in both "
                           "orientations, each titled ordinal or disordinal (lines crossing).",
    "qq.png": "Normal Q-Q plots of standardized model residuals.",
    "success_levels.png": "Success rate (all runs) per level of each factor.",
    "success_pairs.png": "Success rate (all runs) per pair of factors; cells: successes/runs.",
}
HUGE = 1e100  # a metric value at least this large in magnitude overflows the sums of squares (squared: 1e200+)
RESULTS_LIMIT = 64 << 20  # largest results CSV read [bytes] (16384 runs: about 6 MB)


def run_report(results_csv: str, out_dir: str, alpha: float = 0.05, factors: list[str] | None = None,
               metrics: list[str] | None = None, *, figures: bool = True, ss_type: int = 3, order: int | None = None,
               force: bool = False, workers: render.Workers | None = None) -> dict:
    """Write the ANOVA report of ``results_csv`` into ``out_dir``.

    Args:
        results_csv: results table, one row per run (factors, rep, seed, success, metrics).
        out_dir: output directory, new or empty (or an earlier report with ``force``); untouched on error.
        alpha: significance level (0 < alpha < 1).
        factors: factor columns (default: the campaign's, :func:`campaign_defaults`, else those of m, mu, d).
        metrics: metric columns (default: see :mod:`wbc_jax.analysis.stats`).
        figures: render the PNG figures (tests switch them off for speed).
        ss_type: sums-of-squares type, 1, 2 or 3.
        order: highest interaction order of the model (2: main effects + two-way; default: the campaign's or 2).
        force: replace ``out_dir`` when it holds an earlier report.
        workers: figure workers (:class:`wbc_jax.analysis.render.Workers`) that draw the figures side by side
            while this process writes the document (figures beyond their number: drawn here); None: drawn here one
            after another. The caller closes them (:meth:`~wbc_jax.analysis.render.Workers.close`: those left
            idle, e.g. after an error).

    Returns:
        The content of ``anova.json``.

    Raises:
        InputError: unreadable or malformed input (one-line message naming the problem).
        OutputError: ``out_dir`` is not a new or empty folder (or an earlier report with ``force``).
        WbcJaxError: the output directory cannot be written.
    """
    t0 = time.perf_counter()
    if not (isinstance(alpha, (int, float)) and 0 < alpha < 1):
        raise InputError(f"alpha must be between 0 and 1, not {alpha}")
    check_out_dir(out_dir, COMMAND, force=force, inputs=[results_csv])
    raw, df = read_results(results_csv)
    camp_factors, camp_order = campaign_defaults(results_csv, df)
    factors = stats.infer_factors(df, factors if factors is not None else camp_factors)
    order = order if order is not None else camp_order
    _check_categorical(df, factors)
    if metrics is None and "fail_reason" in df.columns:  # a campaign's results.csv: the campaign report's metrics
        metrics = [m for m in CAMPAIGN_METRICS if m in df.columns] or None
    metrics = stats.infer_metrics(df, factors, metrics)
    data = stats.prepare(df, factors, metrics)
    res = _analyze(data, factors, metrics, alpha=alpha, ss_type=ss_type, order=order)
    extra = _beyond_anova(data, factors, alpha)
    if not res["metrics"]:
        return _write_design_only(res, extra, results_csv, raw, out_dir, alpha, factors, metrics, ss_type, order,
                                  t0, figures, workers)
    metrics = list(res["metrics"])

    jobs = {}
    if figures:
        fits = {m: r["fit"] for m, r in res["metrics"].items()}
        emms = {m: r["emms"] for m, r in res["metrics"].items()}
        has_pairs = bool(next(iter(emms.values())))  # a two-way term in the model: interaction plots
        jobs = {"means.png": ("means_grid", (res["level_means"], factors, metrics)),
                **{_interaction_png(m): ("interaction_grid", ({m: emms[m]}, [m], [] if fits[m].reliable else [m]))
                   for m in (metrics if has_pairs else [])},  # one figure per metric: drawn side by side
                "qq.png": ("qq_grid", ({m: (np.asarray(f.result.resid), None if f.degenerate else f.mse)
                                        for m, f in fits.items()},)),
                **_success_jobs(extra, factors)}
    pending = render.start(jobs, workers)  # drawn by the workers while this process writes the document

    manifest = {
        "command": COMMAND, "input": str(results_csv), "sha256": hashlib.sha256(raw).hexdigest(), "rows": len(df),
        "alpha": alpha, "factors": factors, "metrics": metrics, "ss_type": stats.SS_NAMES[ss_type], "order": order,
        "versions": _versions(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    r_json = {"r_sources": r_sources(df, factors).to_dict("records")} if R_PLAN in df.columns else {}
    summary = _clean(dict(_summary(res, data, factors, metrics, alpha, manifest), **_extra_json(extra), **r_json))
    doc = _document(res, summary, factors, metrics, alpha, list(jobs), df, extra)
    images = pending.result()
    manifest["wall_s"] = summary["manifest"]["wall_s"] = round(time.perf_counter() - t0, 3)
    files = {
        "report.md": doc.markdown().encode(),
        "report.html": doc.html(images, title=f"ANOVA report: {Path(results_csv).name}").encode(),
        "anova.json": _dumps(summary).encode(),
        "design.csv": res["design"].to_csv(index=False).encode(),
        "cell_means.csv": res["cell_means"].to_csv(index=False).encode(),
        "manifest.json": _dumps(manifest).encode(),
        **{f"figures/{k}": v for k, v in images.items()},
    }
    write_dir_atomic(out_dir, files)
    return summary


def campaign_defaults(results_csv: str, df: pd.DataFrame) -> tuple[list[str] | None, int]:
    """(factors, model order) of the campaign that wrote ``results_csv``: its ``manifest.json`` beside it
    (``wbc-jax campaign``: the spec's factors and ``[analysis] order``), the factors only if all are columns of
    ``df``; (None, 2) otherwise."""
    try:
        man = json.loads((Path(results_csv).parent / "manifest.json").read_text())
        spec = man["spec"] if man.get("command") == "wbc-jax campaign" else {}
        names = [str(f) for f in spec.get("factors", {})]
        order = spec.get("analysis", {}).get("order", 2)
    except (OSError, ValueError, TypeError, AttributeError, KeyError):
        return None, 2
    ok = bool(names) and all(f in df.columns for f in names)
    return (names if ok else None), (int(order) if isinstance(order, int) and order >= 1 else 2)


# --------------------------------------------------------------------------- beyond the ANOVA


def _beyond_anova(data: pd.DataFrame, factors, alpha: float) -> dict:
    """Success rates per level and per pair of factors (all runs), and the ablation comparisons."""
    from wbc_jax.analysis import ablation, success

    return {"by_level": success.by_level(data, factors),
            "by_pair": {p: success.by_pair(data, *p) for p in success.pairs(factors)},
            "ablation": ablation.compare(data, factors, alpha)}


def _extra_json(extra: dict) -> dict:
    return {"success": {"by_level": extra["by_level"],
                        "by_pair": {":".join(p): t for p, t in extra["by_pair"].items()}},
            "ablation": extra["ablation"]}


def _interaction_png(metric: str) -> str:
    """The interaction figure's file name of a metric (characters other than letters, digits, ``.-_``: ``_``)."""
    return "interactions_" + re.sub(r"[^A-Za-z0-9._-]", "_", metric) + ".png"


def _caption(name: str, metrics) -> str:
    """The caption of figure ``name`` (of a report of ``metrics``)."""
    for m in metrics:
        if name == _interaction_png(m):
            return FIGURE_CAPTIONS["interactions_{}.png"].format(m)
    return FIGURE_CAPTIONS[name]


def _success_jobs(extra: dict, factors) -> dict[str, tuple[str, tuple]]:
    """The success-rate figures as :mod:`wbc_jax.analysis.render` jobs."""
    out = {"success_levels.png": ("success_levels", (extra["by_level"], factors))}
    if extra["by_pair"]:
        out["success_pairs.png"] = ("success_pairs", (extra["by_pair"],))
    return out


def _success_sections(d: "_Doc", extra: dict, factors, alpha: float) -> None:
    """The report's success-rate tables and, for an ablation factor, the comparisons with the reference."""
    from wbc_jax.analysis import ablation, success

    d.h(2, "Success rate (all runs)")
    d.p("Share of runs with success = True per factor level and per pair of factors, pooled over the other "
        "factors and the repetitions (failed runs included; cells: successes/runs (rate)).")
    lv = extra["by_level"]
    d.table(pd.DataFrame({"factor": lv["factor"], "level": lv["level"].map(lambda v: _f(v, "g")),
                          "successes/runs": [f"{s}/{n}" for s, n in zip(lv["successes"], lv["runs"])],
                          "rate [%]": (100 * lv["rate"]).map(lambda v: _f(v, ".1f"))}))
    for (a, b), t in extra["by_pair"].items():
        d.h(3, f"{a} × {b}")
        d.table(success.wide(t, a, b, fmt=lambda v: _f(v, "g")))
    t = extra["ablation"]
    if len(t):
        d.h(2, "Controller variants against the reference")
        d.p("Each level of " + ", ".join(f"`{f}`" for f in pd.unique(t["factor"])) + " against the reference "
            "(" + ", ".join(f"{f} = {ablation.REFERENCE[f]}" for f in pd.unique(t["factor"])) + "), pooled over "
            "the other factors: Welch's t test and the Mann-Whitney U test on max slip [mm] and R (successful "
            "runs), Fisher's exact test on success (all runs); two-sided, Bonferroni over the levels compared.")
        d.ul(ablation.answers(t, alpha))
        d.table(pd.DataFrame({
            "factor": t["factor"], "level": t["level"].map(lambda v: _f(v, "g")), "metric": t["metric"],
            "test": t["test"], "n": t["n"], "n ref": t["n_ref"], "value": t["value"].map(_f),
            "ref value": t["value_ref"].map(_f), "statistic": t["statistic"].map(_f),
            "p": t["p"].map(lambda v: _f(v, ".3g")), "p Bonferroni": t["p_bonf"].map(lambda v: _f(v, ".3g")),
            "differs": ["yes" if x else "no" for x in t["differs"]]}))


# --------------------------------------------------------------------------- robust analysis


def _check_categorical(df: pd.DataFrame, factors: list[str]) -> None:
    """A factor needs repeated levels: a column with about one row per value (a measurement) is refused."""
    for f in factors:
        n_lv = int(df[f].nunique(dropna=True))
        if n_lv > 2 and 2 * n_lv > len(df):
            raise InputError(f"factor '{f}' has {n_lv} distinct values in {len(df)} rows: a continuous column, "
                             "not a factor (name the factors with --factors)")


def _analyze(data: pd.DataFrame, factors: list[str], metrics: list[str], **kw) -> dict:
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
        res = None
        parts = []
        for m in ok:
            for order in sorted({kw["order"], 1}, reverse=True):
                try:
                    parts.append(stats.analyze(data, factors, [m], **dict(kw, order=order)))
                    if order != kw["order"]:
                        notes.append(f"metric '{m}': the model with interactions cannot be fitted "
                                     "(too few runs); main effects only")
                    break
                except Exception as e:  # noqa: BLE001
                    if order == 1:
                        notes.append(f"metric '{m}' not analysed: {_one_line(e)}")
        if parts:
            res = dict(parts[0], metrics={m: r for p in parts for m, r in p["metrics"].items()},
                       cell_means=pd.concat([p["cell_means"] for p in parts], ignore_index=True),
                       level_means=pd.concat([p["level_means"] for p in parts], ignore_index=True))
    if res is None:
        design = stats.design_table(data, factors)
        res = dict(design=design, metrics={}, warnings=[], n_runs=len(data), n_failed=int(design["failures"].sum()))
    res["warnings"] = list(res["warnings"]) + notes
    return res


def _write_design_only(res, extra, results_csv, raw, out_dir, alpha, factors, metrics, ss_type, order, t0,
                       figures, workers) -> dict:
    """The report of a table without an analysable metric: warnings, the design table and the success rates."""
    d = _Doc()
    d.h(1, f"ANOVA report: {Path(results_csv).name}")
    d.p(f"{res['n_runs']} runs ({res['n_failed']} failed); factors {', '.join(factors)}; no metric analysed.")
    d.h(2, "Warnings")
    d.ul(res["warnings"])
    d.h(2, "Design")
    d.table(res["design"])
    _success_sections(d, extra, factors, alpha)
    images = render.start(_success_jobs(extra, factors) if figures else {}, workers).result()
    for name in images:
        d.img(name, FIGURE_CAPTIONS[name])
    manifest = {"command": COMMAND, "input": str(results_csv), "sha256": hashlib.sha256(raw).hexdigest(),
                "rows": res["n_runs"], "alpha": alpha, "factors": factors, "metrics": [],
                "ss_type": stats.SS_NAMES[ss_type], "order": order, "versions": _versions(),
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "wall_s": round(time.perf_counter() - t0, 3)}
    summary = _clean({"schema": SCHEMA, "alpha": alpha, "ss_type": manifest["ss_type"], "n_runs": res["n_runs"],
                      "n_failed": res["n_failed"], "warnings": res["warnings"], "design": res["design"],
                      "metrics": {}, **_extra_json(extra), "manifest": manifest})
    write_dir_atomic(out_dir, {"report.md": d.markdown().encode(),
                               "report.html": d.html(images, title=f"ANOVA report: {Path(results_csv).name}").encode(),
                               "anova.json": _dumps(summary).encode(),
                               "design.csv": res["design"].to_csv(index=False).encode(),
                               "manifest.json": _dumps(manifest).encode(),
                               **{f"figures/{k}": v for k, v in images.items()}})
    return summary


# --------------------------------------------------------------------------- input / output


def read_results(path: str) -> tuple[bytes, pd.DataFrame]:
    """Raw bytes and parsed table of a results CSV; every failure is a one-line InputError."""
    try:
        raw = read_capped(path, RESULTS_LIMIT, what="results")
    except FileNotFoundError:
        raise InputError(f"results file not found: {path}") from None
    except IsADirectoryError:
        raise InputError(f"results path is a directory, not a file: {path}") from None
    except OSError as e:
        raise InputError(f"cannot read results file {path}: {e.strerror or e}") from None
    if not raw.strip():
        raise InputError(f"results file is empty: {path}")
    try:
        df = pd.read_csv(io.BytesIO(raw))
    except pd.errors.EmptyDataError:
        raise InputError(f"results file is empty: {path}") from None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"results file {path} is not a readable CSV: {_one_line(e)}") from None
    df.columns = [str(c).strip() for c in df.columns]
    if df.empty:
        raise InputError(f"results file has a header but no rows: {path}")
    return raw, df


def write_dir_atomic(out_dir: str, files: dict[str, bytes]) -> None:
    """Write ``files`` (relative path -> bytes) as directory ``out_dir``, all or nothing."""
    out = Path(out_dir).absolute()
    if out.exists() and not out.is_dir():
        raise WbcJaxError(f"output path exists and is not a directory: {out_dir}")
    try:
        with atomic_dir(out) as tmp:
            for rel, data in files.items():
                p = tmp / rel
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(data)
    except OSError as e:
        raise WbcJaxError(f"cannot write report to {out_dir}: {e.strerror or e}") from None


def _one_line(e: Exception) -> str:
    return " ".join(str(e).split())


def _versions() -> dict:
    from wbc_jax.version import __version__

    return {"wbc_jax": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": _version("scipy"), "pandas": pd.__version__, "statsmodels": _version("statsmodels"),
            "matplotlib": _version("matplotlib")}


def _version(name: str) -> str:
    """An installed package's version without importing it (matplotlib's import alone took 0.26 s)."""
    from importlib import import_module, metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:  # not installed as a distribution: ask the module
        return import_module(name).__version__


def _clean(x):
    """JSON-safe copy: numpy scalars to Python, NaN/inf to None, DataFrames to records."""
    if isinstance(x, pd.DataFrame):
        return [_clean(r) for r in x.to_dict(orient="records")]
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer, int)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    return x


def _dumps(obj) -> str:
    return json.dumps(_clean(obj), indent=1, allow_nan=False) + "\n"


def _summary(res: dict, data: pd.DataFrame, factors, metrics, alpha: float, manifest: dict) -> dict:
    per = {}
    for m, r in res["metrics"].items():
        fit = r["fit"]
        per[m] = {
            "formula": fit.formula, "n": fit.n, "mse": fit.mse, "df_resid": fit.df_resid,
            "ss_type": fit.ss_type, "anova": fit.table, "f_tests_reliable": fit.reliable,
            "unreliable_reasons": fit.unreliable_reasons,
            "significant": r["significant"], "assumptions": r["assumptions"],
            "simple_effects": r["simple_effects"],
            "interaction_shapes": interaction.shapes(r["emms"]),
            "warnings": r["warnings"],
        }
    return {
        "schema": SCHEMA, "alpha": alpha, "ss_type": manifest["ss_type"],
        "contrasts": "sum-to-zero (C(x, Sum))", "model_order": manifest["order"],
        "factors": {f: stats.levels(data[f]) for f in factors}, "n_runs": res["n_runs"],
        "n_failed": res["n_failed"], "warnings": res["warnings"], "design": res["design"],
        "metrics": per, "manifest": manifest,
    }


# --------------------------------------------------------------------------- document


class _Doc:
    """A list of blocks rendered to Markdown or to self-contained HTML."""

    def __init__(self):
        self.blocks: list[tuple] = []

    def h(self, level: int, text: str):
        self.blocks.append(("h", level, text))

    def p(self, text: str):
        self.blocks.append(("p", text))

    def ul(self, items: list[str]):
        if items:
            self.blocks.append(("ul", list(items)))

    def table(self, df: pd.DataFrame):
        self.blocks.append(("table", pd.DataFrame([[_f(v) for v in r] for r in df.itertuples(index=False)],
                                                  columns=[str(c) for c in df.columns], dtype=object)))

    def img(self, name: str, caption: str):
        self.blocks.append(("img", name, caption))

    def markdown(self) -> str:
        out = []
        for b in self.blocks:
            if b[0] == "h":
                out.append("#" * b[1] + " " + b[2])
            elif b[0] == "p":
                out.append(b[1])
            elif b[0] == "ul":
                out.append("\n".join(f"- {i}" for i in b[1]))
            elif b[0] == "table":
                df = b[1]
                esc = lambda s: str(s).replace("|", "\\|")  # noqa: E731
                rows = ["| " + " | ".join(esc(c) for c in df.columns) + " |",
                        "|" + "---|" * len(df.columns)]
                rows += ["| " + " | ".join(esc(v) for v in r) + " |" for r in df.itertuples(index=False)]
                out.append("\n".join(rows))
            elif b[0] == "img":
                out.append(f"![{b[2]}](figures/{b[1]})")
        return "\n\n".join(out) + "\n"

    def html(self, images: dict[str, bytes], title: str) -> str:
        e = html.escape
        out = []
        for b in self.blocks:
            if b[0] == "h":
                out.append(f"<h{b[1]}>{e(b[2])}</h{b[1]}>")
            elif b[0] == "p":
                out.append("<p>" + re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", e(b[1])) + "</p>")
            elif b[0] == "ul":
                out.append("<ul>" + "".join(f"<li>{e(i)}</li>" for i in b[1]) + "</ul>")
            elif b[0] == "table":
                df = b[1]
                head = "".join(f"<th>{e(str(c))}</th>" for c in df.columns)
                body = "".join("<tr>" + "".join(f"<td>{e(v)}</td>" for v in r) + "</tr>"
                               for r in df.itertuples(index=False))
                out.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            elif b[0] == "img" and b[1] in images:
                data = base64.b64encode(images[b[1]]).decode()
                out.append(f'<figure><img alt="{e(b[2])}" src="data:image/png;base64,{data}">'
                           f"<figcaption>{e(b[2])}</figcaption></figure>")
        style = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
                 "table{border-collapse:collapse;margin:.5em 0;font-size:90%}"
                 "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}th{background:#eee}"
                 "img{max-width:100%}figcaption{font-size:90%;color:#444}")
        return (f'<!doctype html>\n<html><head><meta charset="utf-8"><title>{e(title)}</title>'
                f"<style>{style}</style></head><body>\n" + "\n".join(out) + "\n</body></html>\n")


def _f(x, spec: str = ".4g") -> str:
    if x is None or (isinstance(x, (float, np.floating)) and not np.isfinite(x)):
        return ""
    if isinstance(x, (float, np.floating, int, np.integer)):
        return format(x, spec)
    return str(x)


def _document(res: dict, summary: dict, factors, metrics, alpha: float, images: list[str],
              df: pd.DataFrame | None = None, extra: dict | None = None) -> _Doc:
    d = _Doc()
    man = summary["manifest"]
    d.h(1, f"ANOVA report: {Path(man['input']).name}")
    lv = "; ".join(f"{f}: {', '.join(_f(v, 'g') for v in summary['factors'][f])}" for f in factors)
    d.p(f"{res['n_runs']} runs ({res['n_failed']} failed, excluded), factors {lv}; metrics {', '.join(metrics)}; "
        f"alpha = {alpha:g}; type {summary['ss_type']} sums of squares, sum-to-zero contrasts; model: "
        + ("main effects + two-way interactions" if summary["model_order"] == 2 else f"interactions up to order {summary['model_order']}")
        + (f" (interactions of order > {summary['model_order']} pooled into the error)"
           if summary["model_order"] < len(factors) else "")
        + "; residual df " + ", ".join(f"{m} {_f(summary['metrics'][m]['df_resid'], 'g')}" for m in metrics)
        + ".")

    d.h(2, "Warnings")
    allw = list(res["warnings"]) + [f"{m}: {w}" for m, r in res["metrics"].items() for w in r["warnings"]]
    d.ul(allw) if allw else d.p("None.")

    d.h(2, "Significant terms")
    sources = list(next(iter(res["metrics"].values()))["anova"]["source"][:-1])
    rows = []
    for m, r in res["metrics"].items():
        t = r["anova"].set_index("source")
        cells = [("unreliable" if not r["fit"].reliable else
                  f"F={_f(t.loc[s, 'F'])}, p={_f(t.loc[s, 'p'], '.3g')}" + (" *" if s in r["significant"] else ""))
                 for s in sources]
        failed = [a["test"] for a in r["assumptions"] if a["ok"] is False]
        not_run = [a["test"] for a in r["assumptions"] if a["ok"] is None]
        rows.append([m, *cells, ", ".join(failed + [f"{t} not run" for t in not_run]) or "none"])
    d.table(pd.DataFrame(rows, columns=["metric", *sources, "assumption tests failed / not run"]))
    d.p(f"* p < {alpha:g}.")

    d.h(2, "Design")
    des = res["design"].copy()
    for f in factors:
        des[f] = des[f].map(lambda v: _f(v, "g"))
    d.table(des)

    for m, r in res["metrics"].items():
        _metric_section(d, m, r, res["level_means"], alpha)

    d.h(2, "Cell means (successful runs)")
    cm = res["cell_means"]
    wide = cm[cm["metric"] == metrics[0]][factors].reset_index(drop=True).map(lambda v: _f(v, "g"))
    for m in metrics:
        t = cm[cm["metric"] == m].reset_index(drop=True)
        wide[m] = [f"{_f(a)} ± {_f(s)} ({n})" for a, s, n in zip(t["mean"], t["sd"], t["n"])]
    d.table(wide)

    if extra is not None:
        _success_sections(d, extra, factors, alpha)
    if images:
        d.h(2, "Figures")
        for name in images:
            d.img(name, _caption(name, metrics))

    if df is not None and R_PLAN in df.columns:
        _r_sources_section(d, df, factors)
    if df is not None and CLEARANCE in df.columns:
        _clearance_section(d, df, factors)
    if df is not None and QP_FLAG in df.columns:
        _qp_section(d, df, factors)

    d.h(2, "Method")
    d.ul([
        "Runs with success = False are counted in the design table and excluded from every model and mean; "
        "a missing metric value drops that run from that metric only.",
        f"Per metric, an OLS model ({summary['metrics'][metrics[0]]['formula'].split('~', 1)[1].strip()}) with "
        "sum-to-zero contrasts (statsmodels ols, C(x, Sum)); ANOVA by anova_lm with type "
        f"{summary['ss_type']} sums of squares (equal to types I and II for balanced data). "
        "Partial eta squared = SS_effect / (SS_effect + SS_residual).",
        "Assumptions on the model residuals: Lilliefors-corrected Kolmogorov-Smirnov and Shapiro-Wilk for "
        "normality; Levene (mean-centred) and Brown-Forsythe (median-centred) across cells for equal variances. "
        f"A test with p < {alpha:g} is flagged, never hidden.",
        f"F tests are marked unreliable when the residual SS is below {stats.PERFECT_FIT_RTOL:g} x the model SS "
        "(R's rule), a cell has zero within-cell variance, or no residual degrees of freedom remain.",
        "Simple main effects for each significant two-way interaction, in both directions: estimated marginal "
        "means with equal weights over the other factors; simple-effect F per level of the conditioning factor; "
        "pairwise EMM differences with SE, t, df, Bonferroni-adjusted p and Bonferroni 95 % CI, one family per "
        "conditioning level, all with the pooled model MSE and residual df (as SPSS EMMEANS COMPARE, R emmeans).",
    ])
    return d


def r_sources(df: pd.DataFrame, factors) -> pd.DataFrame:
    """Per cell (successful runs), the means of R from the simulator's and from the QP's planned object forces and
    the boundary rule's shares (columns of :data:`R_SOURCE_COLUMNS` present in ``df``; shares as fractions)."""
    ok = stats.successful(df)
    cols = [c for c, _ in R_SOURCE_COLUMNS if c in ok.columns]
    num = ok[list(factors)].join(ok[cols].apply(pd.to_numeric, errors="coerce"))
    out = num.groupby(list(factors), sort=True)[cols].mean().reset_index()
    out.insert(len(factors), "n", num.groupby(list(factors), sort=True).size().to_numpy())
    return out


def _r_sources_section(d: _Doc, df: pd.DataFrame, factors) -> None:
    """R from the simulator's contact forces next to R from the QP's planned object forces, with the boundary
    rule's share of each (the fraction of the window's samples whose 1/H the rule set to 0)."""
    t = r_sources(df, factors)
    d.h(2, "R: simulator forces vs the QP's planned forces (successful runs)")
    d.p("R (simulator): the paper's robustness metric of the contact forces MuJoCo applies to the object (every "
        "physics step); R (QP plan): the same metric of the object contact forces the whole-body QP planned "
        "(F_c = E_c Lambda_b per contact, every control step). Rule share: the fraction of the metric window's "
        "samples whose integrand 1/H the boundary rule set to 0 (a contact without load, or a force on or outside "
        "the circular cone); 'on/outside the cone' is the part of a share with every contact loaded. "
        "Means per cell.")
    shown = t[list(factors)].map(lambda v: _f(v, "g"))
    shown["n"] = t["n"]
    for c, name in R_SOURCE_COLUMNS:
        if c in t.columns:
            shown[name] = t[c].map(lambda v: _f(100 * v, ".2f")) if "[%]" in name else t[c].map(_f)
    d.table(shown)


def _clearance_section(d: _Doc, df: pd.DataFrame, factors) -> None:
    """Per cell, the smallest clearance over its runs (all runs, failed ones included) with its time and pair."""
    c = pd.to_numeric(df[CLEARANCE], errors="coerce")
    d.h(2, "Clearance (all runs)")
    d.p("Smallest signed distance between a non-foot robot geom and the floor, blocks or wall over each run [mm] "
        "(negative: penetration; inf: none reported, e.g. on the Warp backend without penetration); per cell the "
        "run with the smallest.")
    rows = []
    for key, g in df.assign(_c=c).groupby(factors, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        i = g["_c"].idxmin() if g["_c"].notna().any() else g.index[0]
        r = g.loc[i]
        pair = r.get("min_clearance_pair", "")
        rows.append([*(_f(v, "g") for v in key), "inf" if r["_c"] == np.inf else _f(r["_c"], ".3f"),
                     int(r["run"]) if "run" in g else "", _f(r.get("min_clearance_s", np.nan), ".3f"),
                     pair if isinstance(pair, str) else ""])
    d.table(pd.DataFrame(rows, columns=[*factors, "min clearance [mm]", "run", "at [s]", "pair"]))


def _qp_section(d: _Doc, df: pd.DataFrame, factors) -> None:
    """Per cell, the share of control steps whose QP ended outside its tolerance (all runs): mean and worst run."""
    f = pd.to_numeric(df[QP_FLAG], errors="coerce")
    d.h(2, "QP convergence (all runs)")
    d.p("Share of each run's control steps whose whole-body QP ended its ADMM iterations (the solver's cap "
        "included) outside its tolerance (OSQP's test); a run above "
        f"{100 * QP_FLAG_LINE:g} % is `qp_flagged`. Per cell: mean over the runs, the worst run, how many runs are "
        "flagged, and the ADMM iterations per control step (mean over the runs' means, most in one step).")
    cols = {"_f": f}
    for k in ("qp_iters_mean", "qp_iters_max"):
        cols[k] = pd.to_numeric(df[k], errors="coerce") if k in df else np.nan
    g = df.assign(**cols).groupby(factors, sort=True)
    rows = [[*(_f(v, "g") for v in (key if isinstance(key, tuple) else (key,))), _f(100 * s["_f"].mean(), ".3f"),
             _f(100 * s["_f"].max(), ".3f"), f"{int((s['_f'] > QP_FLAG_LINE).sum())}/{len(s)}",
             _f(s["qp_iters_mean"].mean(), ".1f"), _f(s["qp_iters_max"].max(), "g")] for key, s in g]
    d.table(pd.DataFrame(rows, columns=[*factors, "mean [%]", "worst run [%]", "runs flagged", "iterations mean",
                                        "iterations max"]))


def _metric_section(d: _Doc, m: str, r: dict, level_means: pd.DataFrame, alpha: float) -> None:
    fit = r["fit"]
    d.h(2, f"Metric {m}")
    d.p(f"Model {fit.formula}; n = {fit.n}; residual df = {_f(fit.df_resid, 'g')}; MSE = {_f(fit.mse)}.")
    if not fit.reliable:
        d.p("**F tests unreliable**: " + "; ".join(fit.unreliable_reasons)
            + ". F, p and partial eta squared are omitted below (anova.json keeps the raw numbers).")
    t = fit.table
    shown = pd.DataFrame({
        "source": t["source"], "SS": t["sum_sq"].map(_f), "df": t["df"].map(lambda v: _f(v, "g")),
        "MS": t["mean_sq"].map(_f),
        "F": t["F"].map(_f) if fit.reliable else "",
        "p": t["p"].map(lambda v: _f(v, ".3g")) if fit.reliable else "",
        "partial η²": t["partial_eta_sq"].map(lambda v: _f(v, ".3f")) if fit.reliable else "",
        "sig.": ["*" if s in r["significant"] else "" for s in t["source"]],
    })
    d.h(3, f"ANOVA (type {fit.ss_type} SS)")
    d.table(shown)
    d.h(3, "Assumptions")
    d.table(pd.DataFrame([{
        "test": a["test"], "assumption": a["assumption"], "statistic": _f(a["statistic"]), "p": _f(a["p"], ".3g"),
        "result": {True: "ok", False: f"REJECTED (p < {alpha:g})", None: "not run"}[a["ok"]], "note": a["note"],
    } for a in r["assumptions"]]))
    if r["simple_effects"]:
        d.h(3, "Simple main effects")
        for s in r["simple_effects"]:
            d.h(4, f"{s['effect']} at each level of {s['by']}")
            d.p(s["method"] + ".")
            te = s["tests"].copy()
            te[s["by"]] = te[s["by"]].map(lambda v: _f(v, "g"))
            for c, spec in (("F", ".4g"), ("p", ".3g"), ("partial_eta_sq", ".3f"), ("df2", "g")):
                te[c] = te[c].map(lambda v, spec=spec: _f(v, spec))
            d.table(te)
            pr = s["pairs"].copy()
            for c in pr.columns:
                spec = "g" if c in (s["by"], "level_a", "level_b", "df") else (".3g" if c.startswith("p_") else ".4g")
                pr[c] = pr[c].map(lambda v, spec=spec: _f(v, spec))
            d.table(pr)
    elif fit.reliable:
        d.p("No significant two-way interaction: no simple main effects.")
    if r["emms"]:
        d.h(3, "Interaction shapes")
        d.p("Disordinal: two lines of the interaction plot cross within the plotted range (the order of the line "
            "factor's levels reverses across the x-axis levels; EMMs); ordinal otherwise.")
        d.table(pd.DataFrame(interaction.shapes(r["emms"])))
    d.h(3, "Descriptives per factor level (successful runs)")
    lm = level_means[level_means["metric"] == m]
    d.table(pd.DataFrame({"factor": lm["factor"], "level": lm["level"].map(lambda v: _f(v, "g")),
                          "mean": lm["mean"].map(_f), "SD": lm["sd"].map(_f), "n": lm["n"]}))
