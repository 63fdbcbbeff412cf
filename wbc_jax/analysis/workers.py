"""Worker processes started ahead of time: the process protocol, and the figure workers of a report.

:class:`Workers` are figure workers, one figure each, drawing while the report's process writes the document, so
that the report waits for the longest figure only. Each imports matplotlib and :mod:`wbc_jax.analysis.figures` and
draws a first figure as it starts (the first figure of a process pays for loading fonts and the canvas).

Workers are plain ``python -m <module> <mode> ...`` processes rather than ``multiprocessing`` ones: nothing is
forked from a process that holds JAX's threads, and the caller's main script is not imported again. Protocol: the
parent writes one pickle ``(function name, args, kwargs)`` to a worker's stdin and closes it; the worker writes one
pickle, ``("ok", result)`` or ``("error", exception)``, to stdout and exits (a worker whose stdin closes without a
job exits at once). A worker that dies or cannot start costs only time: its job then runs in the calling process,
where an error of the job itself is raised as usual. An error the job raised in the worker is raised again in the
caller.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

from wbc_jax.errors import WbcJaxError

N_FIGURES = 8  # figure workers of a report: means, Q-Q, 2 success rates and an interaction figure per metric (4)
MIN_CORES = 4  # below this, workers importing side by side slow the process they should relieve


def start_process(module: str, *args: str) -> subprocess.Popen:
    """``python -m module args...`` with this process's ``wbc_jax`` importable; stdin and stdout are pipes."""
    root = str(Path(__file__).resolve().parents[2])  # the folder holding this process's wbc_jax
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])]))
    return subprocess.Popen([sys.executable, "-m", module, *args], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)


def send_job(proc: subprocess.Popen, job: tuple) -> bool:
    """Give ``proc`` its job; False (and the process ended) when it is gone."""
    try:
        proc.stdin.write(pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL))
        proc.stdin.close()
        return True
    except OSError:
        proc.kill()
        proc.wait()
        return False


def read_answer(proc: subprocess.Popen) -> tuple[str, Any]:
    """The job's answer: ("ok", result), ("error", exception) or ("lost", None) when the worker died first."""
    blob = proc.stdout.read()
    proc.stdout.close()
    proc.wait()
    try:
        return pickle.loads(blob)
    except Exception:  # noqa: BLE001  (no or a truncated answer)
        return "lost", None


def close_all(procs: list) -> None:
    """Close the stdin of each process of ``procs`` (emptied) and wait for its end."""
    while procs:
        proc = procs.pop()
        try:
            proc.stdin.close()
        except OSError:
            pass
        proc.wait()


def serve(run_job: Callable[[str, tuple, dict], Any]) -> None:
    """Worker side: read one job from stdin, answer ``run_job(name, args, kwargs)`` on stdout, exit."""
    blob = sys.stdin.buffer.read()
    if not blob:  # closed without a job
        return
    fn, args, kwargs = pickle.loads(blob)
    try:
        answer = ("ok", run_job(fn, args, kwargs))
    except Exception as e:  # noqa: BLE001  (raised again by the parent)
        answer = ("error", e)
    try:
        blob = pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # noqa: BLE001  (an exception that cannot be pickled: its text)
        blob = pickle.dumps(("error", WbcJaxError(f"{type(answer[1]).__name__}: {answer[1]}")))
    sys.stdout.buffer.write(blob)
    sys.stdout.buffer.flush()
    os._exit(0)  # the answer is out: skip the interpreter's teardown (the parent waits for this process's end)


class Workers:
    """``n`` idle figure workers; each renders one figure."""

    def __init__(self, n: int):
        self._procs = [start_process("wbc_jax.analysis.workers") for _ in range(n)]
        self.processes = tuple(self._procs)  # all of them; _procs: those still idle
        self.answered: dict[str, str] = {}  # figure -> "ok" (drawn by a worker), "error" or "lost" (drawn here)
        weakref.finalize(self, close_all, self._procs)  # dropped without close(): closed then

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
            if proc is not None and send_job(proc, (fn, args, {})):
                sent[name] = proc
            else:
                local[name] = (fn, args)
        self.close()
        return Pending(jobs, sent, local, self.answered)

    def close(self) -> None:
        """End the workers that got no job."""
        close_all(self._procs)


class Pending:
    """Figures being drawn (:func:`start_figures`); :meth:`result` waits for them."""

    def __init__(self, jobs: dict, sent: dict, local: dict, answered: dict):
        self._jobs, self._sent, self._local, self._answered = jobs, sent, local, answered

    def result(self) -> dict[str, Any]:
        """Name -> the figure function's result, in the jobs' order. A job without a worker, or whose worker
        failed, is drawn in this process (its own error is raised here)."""
        out = {name: _figure(fn, args) for name, (fn, args) in self._local.items()}
        self._answered.update(dict.fromkeys(self._local, "lost"))
        for name, proc in self._sent.items():
            status, value = read_answer(proc)
            self._answered[name] = status
            out[name] = value if status == "ok" else _figure(*self._jobs[name])
        return {name: out[name] for name in self._jobs}


def start_figures(jobs: dict[str, tuple[str, tuple]], workers: Workers | None) -> Pending:
    """Start the figure jobs (see :meth:`Workers.start`) in ``workers``; None: :meth:`Pending.result` draws them
    one after another in this process."""
    if workers is None:
        return Pending(jobs, {}, jobs, {})
    return workers.start(jobs)


def _figure(fn: str, args: tuple):
    from wbc_jax.analysis import figures  # matplotlib: loaded where a figure is drawn

    return getattr(figures, fn)(*args)


if __name__ == "__main__":
    from wbc_jax.analysis import figures

    figures.warm_up()
    serve(lambda fn, args, kwargs: _figure(fn, args))
