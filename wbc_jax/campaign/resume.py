"""Where a campaign's chunks start: from the beginning, or from the checkpoint of an interrupted run (``--resume``).

Process 0 loads the checkpoint (``wbc_jax.campaign.checkpoint``: checked against this run's identity and the fresh
state's structure) and hands it to the other processes. Each session of a run is recorded (git commit, versions),
so a resumed campaign's manifest names every code version it ran under.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.campaign import checkpoint
from wbc_jax.campaign.job import Job
from wbc_jax.campaign.manifest import session_record
from wbc_jax.errors import WbcJaxError
from wbc_jax.rollout import distributed, runs


class Start(NamedTuple):
    """Where the chunks start: the state, the chunks done, the earlier sessions' wall time [s], their chunk marks,
    the last finished chunk's object goal (None before any) and every session's record, this one's last
    (:func:`wbc_jax.campaign.manifest.session_record`)."""

    state: object
    done: int
    wall_before: float
    marks: list
    p_goal: object
    sessions: list


def _shared(state, done: int, spread, n: int, axes):
    """Process 0's resume point (its loaded state of ``n`` runs, run axes ``axes``, and chunk count) in every
    process, the state placed as ``spread`` (:class:`wbc_jax.rollout.spread.Spread`) places the batch."""
    from jax.experimental import multihost_utils

    if distributed.is_multiprocess():
        state, done = multihost_utils.broadcast_one_to_all((runs.first(jax.device_get(state), n, axes),
                                                            np.int32(done)))
    return spread.place_state(state, n, axes), int(done)


def start_point(job: Job, state0, resume: bool) -> Start:
    """The chunks' starting point: the checkpoint's when resuming (checked against the fresh state ``state0``),
    else the batch's initial state (an old checkpoint is deleted)."""
    sp, n_chunks = job.spread, job.built.n_chunks
    start = Start(job.batch.state, 0, 0.0, [], None, [])
    if not resume:
        if job.writer and job.ckpt.exists():  # an empty one, or one --force discards (preflight.check_outputs)
            shutil.rmtree(job.ckpt)
            job.status.saved = 0
        return start._replace(sessions=[session_record(0)])
    st = meta = problem = None
    if job.writer:
        try:
            st, meta = checkpoint.load_state(job.ckpt, state0, job.identity, n_chunks, job.built.batch.state_axes,
                                             job.built.logs_per_chunk)
        except WbcJaxError as e:
            problem = e
    distributed.agree(problem)
    state, done = start.state, 0
    if sp.mode != "one":  # every process: process 0's resume point, placed as the batch
        state, done = _shared(state0 if st is None else st, meta["chunks_done"] if meta else 0, sp,
                              job.built.design.n, job.built.batch.state_axes)
    elif st is not None:
        state, done = st, meta["chunks_done"]
    if meta is not None:
        start = Start(state, done, meta["wall_s"], meta["marks"],
                      np.asarray(meta["p_goal"]) if meta.get("p_goal") is not None else None,
                      list(meta.get("sessions") or [dict(git_commit=None, chunks_before=0)]))
    else:
        start = start._replace(state=state, done=done)
    start = start._replace(sessions=[*start.sessions, session_record(done)])
    if job.writer:
        print(f"resuming from {job.ckpt}: {done} of {n_chunks} chunks done" if meta is not None else
              f"no checkpoint at {job.ckpt}: starting from the beginning", flush=True)
    return start


def kept(ck: Path | None) -> tuple[int, int]:
    """(chunks done, chunk count) of the checkpoint in ``ck``; (0, 0) without one."""
    meta = checkpoint.peek(ck) if ck is not None else None
    try:
        return int(meta["chunks_done"]), int(meta["n_chunks"])
    except (KeyError, TypeError, ValueError):
        return 0, 0
