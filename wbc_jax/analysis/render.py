"""The report's work in processes started ahead of time: its figures side by side, and a campaign's whole report
made ready during the rollout.

Where a campaign report's time went, drawn in the campaign process (paper campaign, 270 runs, an H100 host with
16 cores, 2026-11-27): importing the statistics and matplotlib (0.8 s), the first analysis in a process (1.7 s,
against 0.3 s for a second one: the statistics modules finish loading on first use), the document (1.0 s) and the
figures one after another (4.4-5.0 s, the interaction grid of all metrics 2.7-3.1 s of it;
:mod:`wbc_jax.analysis.figures`).

- :class:`Workers`: figure workers, one figure each, drawing while the report's process writes the document, so
  that the report waits for the longest figure only (the report draws one interaction figure per metric). Each
  imports matplotlib and the figures module and draws a first figure as it starts.
- :class:`ReportWorker`: one process that starts its own figure workers, imports the report's modules and
  analyses a small synthetic table once, then writes one report. A campaign starts it once its first chunk is
  traced and compiled, so that all of this overlaps the rollout (the campaign process itself must stay free:
  MuJoCo Warp launches every physics step from a Python callback that needs the process's interpreter lock; and
  started before the first chunk, the workers' imports slowed that chunk's tracing by ~1 s).

Workers are plain ``python -m wbc_jax.analysis.render figures|report`` processes rather than ``multiprocessing``
ones: nothing is forked from a process that holds JAX's threads, and the caller's main script is not imported
again. Protocol: the parent writes one pickle ``(function name, args, kwargs)`` to a worker's stdin and closes it;
the worker writes one pickle, ``("ok", result)`` or ``("error", exception)``, to stdout and exits (a worker whose
stdin closes without a job exits at once). A worker that dies or cannot start costs only time: its job then runs
in the calling process, where an error of the job itself is raised as usual. An error the job raised in the
worker is raised again in the caller.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import weakref
from pathlib import Path
from typing import Any

N_FIGURES = 8  # figure workers of a report: means, Q-Q, 2 success rates and an interaction figure per metric (4)
MIN_CORES = 4  # below this, workers importing side by side slow the process they should relieve


def _start(*mode: str) -> subprocess.Popen:
    root = str(Path(__file__).resolve().parents[2])  # the folder holding this process's wbc_jax
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])]))
    return subprocess.Popen([sys.executable, "-m", "wbc_jax.analysis.render", *mode], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)


def _send(proc: subprocess.Popen, job: tuple) -> bool:
    """Give ``proc`` its job; False (and the process ended) when it is gone."""
    try:
        proc.stdin.write(pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL))
        proc.stdin.close()
        return True
    except OSError:
        proc.kill()
        proc.wait()
        return False


def _answer(proc: subprocess.Popen) -> tuple[str, Any]:
    """The job's answer: ("ok", result), ("error", exception) or ("lost", None) when the worker died first."""
    blob = proc.stdout.read()
    proc.stdout.close()
    proc.wait()
    try:
        return pickle.loads(blob)
    except Exception:  # noqa: BLE001  (no or a truncated answer)
        return "lost", None


def _close(procs: list) -> None:
    while procs:
        proc = procs.pop()
        try:
            proc.stdin.close()
        except OSError:
            pass
        proc.wait()


class Workers:
    """``n`` idle figure workers; each renders one figure."""

    def __init__(self, n: int):
        self._procs = [_start("figures") for _ in range(n)]
        self.processes = tuple(self._procs)  # all of them; _procs: those still idle
        self.answered: dict[str, str] = {}  # figure -> "ok" (drawn by a worker), "error" or "lost" (drawn here)
        weakref.finalize(self, _close, self._procs)  # dropped without close(): closed then

    @classmethod
    def for_machine(cls, n: int = N_FIGURES) -> Workers | None:
        """Up to ``n`` workers, one core left to the caller, where the machine has at least :data:`MIN_CORES`
        cores; else None (the figures are drawn in the caller)."""
        cores = os.cpu_count() or 1
        return cls(min(n, cores - 1)) if cores >= MIN_CORES else None

    def start(self, jobs: dict[str, tuple[str, tuple]]) -> Pending:
        """Give each job (name -> (function of :mod:`wbc_jax.analysis.figures`, its positional arguments)) to an
        idle worker (more jobs than idle workers: the rest are drawn in this process by :meth:`Pending.result`);
        closes the workers left idle."""
        sent, local = {}, {}
        for name, (fn, args) in jobs.items():
            proc = self._procs.pop() if self._procs else None
            if proc is not None and _send(proc, (fn, args, {})):
                sent[name] = proc
            else:
                local[name] = (fn, args)
        self.close()
        return Pending(jobs, sent, local, self.answered)

    def close(self) -> None:
        """End the workers that got no job."""
        _close(self._procs)


class Pending:
    """Figures being drawn (:func:`start`); :meth:`result` waits for them."""

    def __init__(self, jobs: dict, sent: dict, local: dict, answered: dict):
        self._jobs, self._sent, self._local, self._answered = jobs, sent, local, answered

    def result(self) -> dict[str, Any]:
        """Name -> the figure function's result, in the jobs' order. A job without a worker, or whose worker
        failed, is drawn in this process (its own error is raised here)."""
        out = {name: _figure(fn, args) for name, (fn, args) in self._local.items()}
        self._answered.update(dict.fromkeys(self._local, "lost"))
        for name, proc in self._sent.items():
            status, value = _answer(proc)
            self._answered[name] = status
            out[name] = value if status == "ok" else _figure(*self._jobs[name])
        return {name: out[name] for name in self._jobs}


def start(jobs: dict[str, tuple[str, tuple]], workers: Workers | None) -> Pending:
    """Start the figure jobs (see :meth:`Workers.start`) in ``workers``; None: :meth:`Pending.result` draws them
    one after another in this process."""
    if workers is None:
        return Pending(jobs, {}, jobs, {})
    return workers.start(jobs)


class ReportWorker:
    """A process that makes itself ready to write one report (see the module docstring)."""

    def __init__(self, n_figures: int = N_FIGURES):
        """Start the worker; it starts ``n_figures`` figure workers of its own (0: it draws them itself)."""
        self._procs = [_start("report", str(n_figures))]
        self.process = self._procs[0]
        self.answered: str | None = None  # "ok" or "error" (the worker wrote or failed), "lost" (written here)
        weakref.finalize(self, _close, self._procs)

    @classmethod
    def for_machine(cls) -> ReportWorker | None:
        """A report worker with up to :data:`N_FIGURES` figure workers, two cores left to the caller and the
        report worker, where the machine has at least :data:`MIN_CORES` cores; else None."""
        cores = os.cpu_count() or 1
        return cls(min(N_FIGURES, cores - 2)) if cores >= MIN_CORES else None

    def run_report(self, *args, **kwargs) -> dict:
        """:func:`wbc_jax.analysis.report.run_report` in the worker (its figures in the worker's own figure
        workers); its error, if any, is raised here; a lost worker: the report is written by this process."""
        from wbc_jax.analysis.report import run_report

        proc = self._procs.pop() if self._procs else None
        status, value = _answer(proc) if proc is not None and _send(proc, ("run_report", args, kwargs)) else \
            ("lost", None)
        self.answered = status
        if status == "error":
            raise value
        return value if status == "ok" else run_report(*args, **kwargs)

    def close(self) -> None:
        """End the worker if it got no job."""
        _close(self._procs)


def _figure(fn: str, args: tuple):
    from wbc_jax.analysis import figures

    return getattr(figures, fn)(*args)


def _warm_figures() -> None:
    """Draw one small figure with the calls the report's figures make (the first figure of a process pays for
    loading fonts and the canvas)."""
    from wbc_jax.analysis import figures

    fig, ax = figures._axes(2, 2)
    for a in ax.flat:
        a.errorbar([0.0, 1.0], [0.0, 1.0], yerr=[[0.1, 0.1], [0.1, 0.1]], marker="o", capsize=3, lw=1.3,
                   label="a=1")
        a.set_xticks([0, 1], ["0.1", "0.2"])
        a.set_xlabel("a")
        a.set_ylabel("R EMM (95% CI)")
        a.set_title("R: a × b, ordinal", fontsize=9)
        a.legend(fontsize=7, framealpha=0.6)
        a.grid(alpha=0.3)
    fig.suptitle("warm-up")
    figures._png(fig)


def _warm_report(n_figures: int) -> Workers | None:
    """Start this report worker's ``n_figures`` figure workers, then analyse a small synthetic 2 x 2 x 2 table (3
    repetitions) the way a report does (the statistics modules' first use)."""
    import numpy as np
    import pandas as pd

    workers = Workers(n_figures) if n_figures > 0 else None
    from wbc_jax.analysis import report, stats

    rng = np.random.default_rng(0)
    grid = np.array(np.meshgrid([0.2, 0.4], [0.4, 1.0], [0.06, 0.1], range(3), indexing="ij")).reshape(4, -1).T
    df = pd.DataFrame(grid, columns=["m", "mu", "d", "rep"]).assign(success=True)
    factors, metrics = ["m", "mu", "d"], list(report.CAMPAIGN_METRICS)
    for k in metrics:
        df[k] = rng.standard_normal(len(df)) + df["m"]
    data = stats.prepare(df, factors, metrics)
    report._analyze(data, factors, metrics, alpha=0.05, ss_type=3, order=2)
    report._beyond_anova(data, factors, 0.05)
    return workers


def _serve(mode: str, n_figures: int = 0) -> None:
    """Worker: get ready (``mode`` "figures", or "report" with ``n_figures`` figure workers), read one job from
    stdin, write its answer to stdout."""
    if mode == "figures":
        _warm_figures()
        workers = None
    else:
        workers = _warm_report(n_figures)
    blob = sys.stdin.buffer.read()
    if not blob:  # closed without a job
        return
    fn, args, kwargs = pickle.loads(blob)
    try:
        if mode == "figures":
            answer = ("ok", _figure(fn, args))
        else:
            from wbc_jax.analysis import report

            answer = ("ok", getattr(report, fn)(*args, workers=workers, **kwargs))
    except Exception as e:  # noqa: BLE001  (raised again by the parent)
        answer = ("error", e)
    finally:
        if workers is not None:
            workers.close()
    try:
        blob = pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # noqa: BLE001  (an exception that cannot be pickled: its text)
        from wbc_jax.errors import WbcJaxError

        blob = pickle.dumps(("error", WbcJaxError(f"{type(answer[1]).__name__}: {answer[1]}")))
    sys.stdout.buffer.write(blob)
    sys.stdout.buffer.flush()
    os._exit(0)  # the answer is out: skip the interpreter's teardown (the parent waits for this process's end)


if __name__ == "__main__":
    _serve(sys.argv[1], *map(int, sys.argv[2:]))
