"""A finished campaign's results: the table (one row per run), the failure summary and warnings, the report.

:func:`results_table` writes one row per run (the factors' levels, rep, seed, success, metrics, flags and
perturbations); :func:`summarize` groups failures by cell and words the campaign's warnings; :func:`campaign_report`
writes the ANOVA report beside the table, keeping the table when the statistics fail.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from wbc_jax.campaign import controllers
from wbc_jax.campaign.design import Design
from wbc_jax.campaign.spec import Spec
from wbc_jax.errors import ReportError, WbcJaxError
from wbc_jax.io_utils import write_json_atomic

FAILED_RUNS_SHOWN = 10  # failed runs named in the warning line (all of them: manifest failed_runs)
QP_FLAG_LIMIT = 0.01  # fraction of a run's control steps with a flagged QP above which the controller did not converge


class Summary(NamedTuple):
    """Failures and warnings of a campaign.

    Attributes:
        cell_columns: the columns that name a cell (m, mu, d first, then the spec's other factors).
        n_cells: number of cells.
        failures_per_cell: per cell with a failed run: its levels, failed runs, runs.
        failed_runs: per failed run: run, push_N, levels, rep, seed, reason, first contact and its time.
        warnings: one line each (zero perturbations, QP-flagged runs, failed runs).
        qp_flagged_runs: runs whose QP was flagged on more than QP_FLAG_LIMIT of their control steps.
    """

    cell_columns: list
    n_cells: int
    failures_per_cell: list
    failed_runs: list
    warnings: list
    qp_flagged_runs: int


def zero_noise_warning(spec: Spec) -> str | None:
    """The warning for a spec without perturbations, or None: only with reps > 1 are identical repetitions a problem
    (one run per cell, e.g. sweeps/paper_exact.toml, is a deliberate deterministic design)."""
    if spec.zero_noise and spec.reps > 1:
        return ("all perturbations are zero: repetitions are identical, within-cell variance is zero and the F "
                "tests are meaningless")
    return None


def factor_columns(spec: Spec) -> list[str]:
    """The results table's factor columns: the spec's factors in design order (m, mu, d for the paper's)."""
    return list(spec.factors)


def results_table(spec: Spec, dz: Design, res: dict, extra_columns=()):
    """One row per run: run, m, mu, d, the other factors' levels (one column each, named like the factor),
    rep, seed, success, the metrics and flags (the controller's, then a plug-in's ``extra_columns``: NaN, with a
    warning, where its finalize returned none), the perturbations."""
    import pandas as pd

    extra = {k: v for k, v in dz.levels.items() if k not in ("m", "mu", "d", "push_N")}
    df = pd.DataFrame(dict(run=np.arange(dz.n), m=dz.m, mu=dz.mu, d=dz.d, **extra, rep=dz.rep, seed=dz.seed,
                           success=res["success"]))
    for k in controllers.info(spec.campaign).columns:
        df[k] = res[k]
    for k in extra_columns:
        if k not in res:
            print(f"warning: the controller's finalize returned no {k!r} (Controller.extra_columns): NaN written",
                  file=sys.stderr, flush=True)
        df[k] = res.get(k, np.full(dz.n, np.nan))
    df["obj_dx_mm"] = dz.obj_dx * 1e3
    df["obj_dy_mm"] = dz.obj_dy * 1e3
    df["obj_yaw_deg"] = np.rad2deg(dz.obj_yaw)
    df["push_N"] = dz.levels["push_N"] if "push_N" in dz.levels else np.linalg.norm(dz.push_force, axis=1)
    return df


def nan_none(x) -> float | None:
    """A float for JSON; None for NaN (e.g. a figure the JAX backend does not report)."""
    x = float(x)
    return None if np.isnan(x) else x


def plain(x):
    """A numpy scalar as the Python number or string it holds (for JSON and messages)."""
    return x.item() if isinstance(x, np.generic) else x


def summarize(spec: Spec, df) -> Summary:
    """Failures per cell, failed runs and the warning lines of a campaign's results table ``df``."""
    cols = list(dict.fromkeys(["m", "mu", "d", *factor_columns(spec)]))  # a cell's values, the paper's first
    cells = df.groupby(cols)["success"].agg(["size", "sum"]).reset_index()
    failures = [dict(**{k: plain(r[k]) for k in cols}, failed=int(r["size"] - r["sum"]), runs=int(r["size"]))
                for _, r in cells.iterrows() if r["size"] != r["sum"]]
    failed_runs = [{"run": int(r.run), "push_N": float(r.push_N),  # the drawn push; a push_N factor's level agrees
                    **{k: plain(r[k]) for k in cols}, "rep": int(r.rep), "seed": int(r.seed),
                    "reason": r.fail_reason, "first_contact": r.first_contact or None,
                    "first_contact_s": nan_none(r.first_contact_s)}
                   for _, r in df[~df.success].iterrows()]
    warnings = [w for w in [zero_noise_warning(spec)] if w]
    flagged = df.qp_flag_fraction.to_numpy(dtype=float) > QP_FLAG_LIMIT
    if flagged.any():
        warnings.append(f"{int(flagged.sum())} of {len(df)} runs had their QP flagged (unconverged or infeasible) on "
                        f"more than {QP_FLAG_LIMIT:.0%} of their control steps (worst "
                        f"{float(df.qp_flag_fraction.max()):.1%}): their controller did not converge, so their "
                        "metrics do not describe it; check the gains and campaign.qp_iters")
    if failures:
        warnings.append(f"{int((~df.success).sum())} of {len(df)} runs failed: " + "; ".join(
            f"run {f['run']} ({', '.join(f'{k} {f[k]}' for k in cols)}, rep {f['rep']}): {f['reason']}"
            + (f" (first at {f['first_contact_s']:.3f} s: {f['first_contact']})" if f["first_contact"] else "")
            for f in failed_runs[:FAILED_RUNS_SHOWN])
            + (" ..." if len(failed_runs) > FAILED_RUNS_SHOWN else "") + " (all: manifest failed_runs)")
    return Summary(cols, int(len(cells)), failures, failed_runs, warnings, int(flagged.sum()))


def campaign_report(out: Path, manifest: dict, warnings: list[str], reporter=None) -> None:
    """The ANOVA report of ``out/results.csv`` into ``out/report`` (the spec's factors and ``[analysis]``; written
    by ``reporter``, a :class:`wbc_jax.analysis.render.ReportWorker`, when given; closed here).

    Raises:
        ReportError: the statistics failed; the failure is written to ``out/report_error.txt`` and the manifest,
            and results.csv stays.
    """
    if reporter is None:  # the statistics loaded here only where this process writes the report
        from wbc_jax.analysis.report import run_report as write
    else:
        write = reporter.run_report  # the same function, in the worker
    spec = manifest.get("spec", {})
    analysis = spec.get("analysis", {})
    metrics = list(controllers.info(spec.get("campaign", {})).report)
    try:
        write(str(out / "results.csv"), str(out / "report"), metrics=metrics,
              factors=list(spec["factors"]) if "factors" in spec else None, order=analysis.get("order", 2),
              alpha=analysis.get("alpha", 0.05))
        if warnings:
            md = out / "report" / "report.md"
            md.write_text("".join(f"> **Campaign warning:** {w}\n\n" for w in warnings) + md.read_text())
    except Exception as e:  # noqa: BLE001  (any failure of the statistics: the finished simulation is kept)
        why = " ".join(f"{type(e).__name__ + ': ' if not isinstance(e, WbcJaxError) else ''}{e}".split())
        (out / "report_error.txt").write_text(why + "\n")
        manifest["files"] = sorted(set(manifest.get("files", [])) | {"report_error.txt"})
        manifest["warnings"].append(f"no report: {why}")
        write_json_atomic(out / "manifest.json", manifest)
        raise ReportError(f"the simulation finished and {out}/results.csv and manifest.json are written, but the "
                          f"report failed ({why}); retry with wbc-jax report {out}/results.csv --out "
                          f"{out}/report") from None
    finally:
        if reporter is not None:
            reporter.close()
