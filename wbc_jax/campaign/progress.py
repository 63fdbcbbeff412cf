"""What a running campaign shows and measures: the progress bar and the chunks' wall times.

A mark is recorded per finished chunk (``dict(chunk, wall_s, fresh_process)``; kept in the checkpoint, so a resumed
run's figures cover every session); the first chunk of each process includes the compile, so the steady rate comes
from the others (:func:`throughput`).
"""

from __future__ import annotations

import sys
from typing import NamedTuple

import numpy as np


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
    """A tqdm bar on stderr counting whole chunks, shown in simulated seconds, with the runs and their physics-step
    rate as a postfix; the time left comes from whole chunks, so it is never negative."""

    def __init__(self, n_chunks: int, done: int, chunk_s: float, n_runs: int, dt_physics: float):
        from tqdm import tqdm

        self.n_runs, self.dt_physics, self.chunk_s = n_runs, dt_physics, chunk_s
        self._bar = tqdm(total=n_chunks, initial=done, unit_scale=chunk_s, unit="sim-s", file=sys.stderr,
                         bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} sim-s [{elapsed}<{remaining}{postfix}]")

    def chunk_done(self, wall_s: float) -> None:
        """One chunk finished in ``wall_s`` seconds."""
        if self._bar.n < self._bar.total:
            self._bar.update(1)
        self._bar.set_postfix_str(f"{self.n_runs} runs, "
                                  f"{self.n_runs * self.chunk_s / self.dt_physics / wall_s:,.0f} env-steps per second")

    def close(self) -> None:
        self._bar.close()
