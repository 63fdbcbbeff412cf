"""The report's work in processes started ahead of time: its figures side by side, and a campaign's whole report
made ready during the rollout.

- :class:`~wbc_jax.analysis.workers.Workers` (re-exported here): figure workers, one figure each, drawing while
  the report's process writes the document.
- :class:`ReportWorker`: one process that starts its own figure workers, imports the report's modules and
  analyses a small synthetic table once (the statistics modules finish loading on first use), then writes one
  report. A campaign starts it once its first chunk is traced and compiled, so that all of this overlaps the
  rollout: the campaign process itself stays free (MuJoCo Warp launches every physics step from a Python callback
  that needs the process's interpreter lock).

The process protocol is :mod:`wbc_jax.analysis.workers`'.
"""

from __future__ import annotations

import os
import sys
import weakref

from wbc_jax.analysis.workers import (
    MIN_CORES,
    N_FIGURES,
    Workers,
    close_all,
    read_answer,
    send_job,
    serve,
    start_process,
)

__all__ = ["ReportWorker", "Workers"]


class ReportWorker:
    """A process that makes itself ready to write one report (see the module docstring)."""

    def __init__(self, n_figures: int = N_FIGURES):
        """Start the worker; it starts ``n_figures`` figure workers of its own (0: it draws them itself)."""
        self._procs = [start_process("wbc_jax.analysis.render", str(n_figures))]
        self.process = self._procs[0]
        self.answered: str | None = None  # "ok" or "error" (the worker wrote or failed), "lost" (written here)
        weakref.finalize(self, close_all, self._procs)

    @classmethod
    def for_machine(cls) -> ReportWorker | None:
        """A report worker with up to :data:`N_FIGURES` figure workers, two cores left to the caller and the
        report worker, where the machine has at least :data:`MIN_CORES` cores; else None."""
        cores = os.cpu_count() or 1
        return cls(min(N_FIGURES, cores - 2)) if cores >= MIN_CORES else None

    def run_report(self, *args, **kwargs) -> dict:
        """:func:`wbc_jax.analysis.report.run_report` in the worker (its figures in the worker's own figure
        workers); its error, if any, is raised here; a lost worker: the report is written by this process."""
        proc = self._procs.pop() if self._procs else None
        status, value = read_answer(proc) if proc is not None and send_job(proc, ("run_report", args, kwargs)) \
            else ("lost", None)
        self.answered = status
        if status == "error":
            raise value
        if status == "ok":
            return value
        from wbc_jax.analysis.report import run_report  # the statistics: loaded only where a report is written

        return run_report(*args, **kwargs)

    def close(self) -> None:
        """End the worker if it got no job."""
        close_all(self._procs)


def _warm_report(n_figures: int) -> Workers | None:
    """Start this report worker's ``n_figures`` figure workers, then analyse a small synthetic 2 x 2 x 2 table (3
    repetitions) the way a report does (the statistics modules' first use)."""
    import numpy as np
    import pandas as pd

    workers = Workers(n_figures) if n_figures > 0 else None
    from wbc_jax.analysis import stats
    from wbc_jax.analysis.report import CAMPAIGN_METRICS
    from wbc_jax.analysis.report.model import analyze_table, beyond_anova

    rng = np.random.default_rng(0)
    grid = np.array(np.meshgrid([0.2, 0.4], [0.4, 1.0], [0.06, 0.1], range(3), indexing="ij")).reshape(4, -1).T
    df = pd.DataFrame(grid, columns=["m", "mu", "d", "rep"]).assign(success=True)
    factors, metrics = ["m", "mu", "d"], list(CAMPAIGN_METRICS)
    for k in metrics:
        df[k] = rng.standard_normal(len(df)) + df["m"]
    data = stats.prepare(df, factors, metrics)
    analyze_table(data, factors, metrics, alpha=0.05, ss_type=3, order=2)
    beyond_anova(data, factors, 0.05)
    return workers


def _serve_report(n_figures: int) -> None:
    """Report worker: get ready (``n_figures`` figure workers), write the one report asked for on stdin."""
    workers = _warm_report(n_figures)

    def run_job(fn: str, args: tuple, kwargs: dict):
        from wbc_jax.analysis import report

        try:
            return getattr(report, fn)(*args, workers=workers, **kwargs)
        finally:
            if workers is not None:
                workers.close()

    serve(run_job)
    if workers is not None:  # closed without a job
        workers.close()


if __name__ == "__main__":
    _serve_report(*map(int, sys.argv[1:]))
