"""What a running campaign shows and measures: setup stage lines, the progress bar and the chunks' wall times.

A mark is recorded per finished chunk (``dict(chunk, wall_s, fresh_process)``; kept in the checkpoint, so a resumed
run's figures cover every session); the first chunk of each process includes the compile, so the steady rate and
the time left come from the others (:func:`throughput`, :func:`time_left`).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import NamedTuple, Sequence

import numpy as np


def stage(text: str) -> None:
    """A setup stage's line on stdout, printed as the stage starts: ``text...``."""
    print(f"{text}...", flush=True)


def time_left(walls: Sequence[float], fresh: Sequence[bool], chunks_left: int) -> float | None:
    """Seconds the ``chunks_left`` remaining chunks take: the median wall time [s] of the finished chunks not marked
    ``fresh`` (a process's first chunk, which includes the compile) times ``chunks_left``; 0 when none is left,
    None before a steady chunk finished."""
    if chunks_left <= 0:
        return 0.0
    steady = [wall for wall, first in zip(walls, fresh) if not first]
    return float(np.median(steady)) * chunks_left if steady else None


def clock(seconds: float | None) -> str:
    """``seconds`` as ``m:ss`` (``h:mm:ss`` from an hour); ``?`` for None."""
    if seconds is None:
        return "?"
    minutes, secs = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


class Throughput(NamedTuple):
    """Figures from the chunk marks: ``compile_estimate`` [s] (the first chunk less a steady one; None without a
    steady chunk), ``first_chunk`` [s] (None when none ran here), ``env_steps_per_s`` (physics steps of all runs per
    second of steady chunks, else of the whole rollout)."""

    compile_estimate: float | None
    first_chunk: float | None
    env_steps_per_s: float


def throughput(marks: list[dict], n_runs: int, chunk_s: float, seconds: float, dt_physics: float,
               wall_rollout: float) -> Throughput:
    """Rates of a campaign from its chunk ``marks``: ``n_runs`` runs, ``chunk_s`` simulated seconds per chunk,
    ``seconds`` simulated in all, physics step ``dt_physics`` [s], ``wall_rollout`` the chunks' wall time [s]."""
    steady = [mk["wall_s"] for mk in marks if not mk["fresh_process"]]
    per_chunk = float(np.median(steady)) if steady else None
    first = [mk["wall_s"] for mk in marks if mk["fresh_process"]]
    compile_s = (first[0] - per_chunk) if (first and per_chunk) else None
    rate = n_runs * chunk_s / dt_physics / per_chunk if per_chunk else n_runs * seconds / dt_physics / wall_rollout
    return Throughput(compile_s, first[0] if first else None, rate)


class ProgressBar:
    """A tqdm bar on stderr counting whole chunks, shown in simulated seconds, with the time left
    (:func:`time_left`), the runs and their physics-step rate as a postfix. While the first chunk compiles and runs
    (:meth:`compiling`) a thread ticks its elapsed time in the postfix every ``tick_s`` seconds."""

    def __init__(self, n_chunks: int, done: int, chunk_s: float, n_runs: int, dt_physics: float,
                 tick_s: float = 1.0):
        from tqdm import tqdm

        self.n_runs, self.dt_physics, self.chunk_s, self.tick_s = n_runs, dt_physics, chunk_s, tick_s
        self._walls: list[float] = []
        self._fresh: list[bool] = []
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None
        self._bar = tqdm(total=n_chunks, initial=done, unit_scale=chunk_s, unit="sim-s", file=sys.stderr,
                         bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} sim-s [{elapsed}{postfix}]")

    def compiling(self, text: str) -> None:
        """Tick ``text: m:ss`` (time since this call) in the postfix until the next :meth:`chunk_done`."""
        started = time.perf_counter()
        self._stop.clear()

        def tick() -> None:
            while True:
                self._bar.set_postfix_str(f"{text}: {clock(time.perf_counter() - started)}")
                if self._stop.wait(self.tick_s):
                    return

        self._ticker = threading.Thread(target=tick, name="progress-ticker", daemon=True)
        self._ticker.start()

    def _stop_ticking(self) -> None:
        if self._ticker is not None:
            self._stop.set()
            self._ticker.join()
            self._ticker = None

    def chunk_done(self, wall_s: float, fresh: bool = False) -> None:
        """One chunk finished in ``wall_s`` seconds; ``fresh``: it was this process's first (with the compile)."""
        self._stop_ticking()
        self._walls.append(wall_s)
        self._fresh.append(fresh)
        step = 1 if self._bar.n < self._bar.total else 0
        left = time_left(self._walls, self._fresh, self._bar.total - self._bar.n - step)
        rate = self.n_runs * self.chunk_s / self.dt_physics / wall_s
        self._bar.set_postfix_str(f"{clock(left)} left, {self.n_runs} runs, {rate:,.0f} env-steps per second",
                                  refresh=False)
        self._bar.update(step)
        self._bar.refresh()

    def close(self) -> None:
        self._stop_ticking()
        self._bar.close()
