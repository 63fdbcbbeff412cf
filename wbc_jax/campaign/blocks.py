"""The checkpoint of a Warp campaign over several processes: each process writes its own block of runs.

With Warp physics every process steps a block of the batch on its GPU (``wbc_jax.rollout.spread``, "blocks").
Gathering every run after each chunk for one checkpoint file would make every process wait for the slowest GPU
and for process 0's host copy of the whole batch at every chunk; instead, after chunk K, process I copies its own
runs to its host and writes ``block_K_I.npz`` (``wbc_jax.campaign.checkpoint.save_block``) in the background
while chunk K+1 runs. The processes meet once per chunk on the host only (``wbc_jax.rollout.distributed``'s host
barrier, a chunk late: after chunk K+1 has finished and block K is written), while their GPUs go on with chunk
K+2; then process 0 writes ``meta.json`` naming every block of chunk K with its SHA-256 (shared through the
coordination service). So a process runs at most one chunk ahead of the slowest, and at any time ``meta.json``
names chunk K-1 or K, whose blocks are both kept; older blocks are deleted. The last chunk is gathered whole (the
results need every run) and saved as one state file; then the blocks go (:meth:`Blocks.finish`).

Resuming reads the blocks named in ``meta.json`` (``wbc_jax.campaign.checkpoint.load_state``), so process 0 must see
every process's block: one host, or the output folder's parent on a shared filesystem for several hosts.
"""

from __future__ import annotations

import itertools
import json
import os
from pathlib import Path

import jax

from wbc_jax.campaign import checkpoint
from wbc_jax.rollout import distributed

ABANDON_WAIT_S = 30.0  # how long a stopping process waits for the others to stop at the same chunk
_RUNS = itertools.count()  # campaigns of this process; every process runs the same sequence, so the names agree


class Blocks:
    """This process's part of a blocked checkpoint (module docstring) for one campaign run.

    Args:
        ck: the checkpoint folder (the same path in every process: DIR's parent + ``.<DIR name>.campaign-ckpt``).
        spread: the run's ``Spread`` in "blocks" mode.
        n: the batch's run count.
        writer: this process writes ``meta.json`` (process 0).
        on_meta: called (process 0) with the chunk count ``meta.json`` names after each write.
    """

    def __init__(self, ck: Path, spread, n: int, writer: bool, on_meta=None):
        self.ck, self.spread, self.n, self.writer, self.on_meta = ck, spread, n, writer, on_meta
        self.tag = f"wbc_jax/campaign-blocks/{next(_RUNS)}"
        self.saver = checkpoint.Writer()
        self.pending: tuple[int, dict] | None = None  # (chunk, meta fields) of the block being written
        self.entry: dict | None = None  # that block's meta.json entry once written
        distributed.host_barrier(f"{self.tag}/start")  # process 0 has cleared an old checkpoint (resume.start_point)

    def chunk_done(self, own, done: int, meta: dict) -> None:
        """After chunk ``done``: the previous chunk's blocks committed (:meth:`commit`), then this process's runs
        (``own``: :meth:`wbc_jax.rollout.spread.Spread.own_start` of the state) written in the background.
        ``meta``: process 0's meta.json fields for this chunk (identity, marks, wall time...)."""
        self.commit()
        flat = jax.tree_util.tree_leaves(own.finish())
        rows = self.spread.own_rows(self.n)
        self.saver.run(lambda: checkpoint.save_block(self.ck, flat, done, self.spread.process, rows),
                       lambda entry: setattr(self, "entry", entry))
        self.pending = (done, meta)

    def commit(self, timeout_s: float = distributed.HOST_WAIT_S) -> None:
        """The pending chunk's blocks: this process's written (waits), every process's announced, then (process 0)
        ``meta.json`` naming them; blocks two chunks older go. Every process calls it at the same points; one that
        does not within ``timeout_s`` fails the others' commit (an error from the coordination service)."""
        self.saver.join()
        if self.pending is None:
            return
        done, meta = self.pending
        self.pending = None
        key = f"{self.tag}/{done}"
        distributed.share(f"{key}/{self.spread.process}", json.dumps(self.entry))
        distributed.host_barrier(key, timeout_s)
        if self.writer:
            entries = [json.loads(distributed.shared(f"{key}/{p}")) for p in range(self.spread.processes)]
            checkpoint.save_block_meta(self.ck, meta, entries)
            if self.on_meta is not None:
                self.on_meta(done)
        checkpoint.prune_blocks(self.ck, done - 1)

    def finish(self) -> None:
        """Once process 0 has saved the last chunk's whole state (every process calls it): the blocks go."""
        self.saver.join()
        distributed.host_barrier(f"{self.tag}/whole")
        checkpoint.prune_blocks(self.ck, 1 << 62)
        if not self.writer:  # a checkpoint folder of this process's own (another host, another working folder)
            try:
                os.rmdir(self.ck)
            except OSError:  # not empty (process 0's), or already gone
                pass

    def abandon(self, timeout_s: float = ABANDON_WAIT_S) -> None:
        """The run stops (a signal, an error): the block in progress completes and, where every process stops at
        the same chunk (a signal to the whole job) within ``timeout_s``, is committed; otherwise ``meta.json``
        stays as it is (the last committed chunk)."""
        try:
            self.commit(timeout_s)
        except Exception:  # noqa: BLE001  (a partner that did not stop here: the last committed chunk is kept)
            pass

