"""Where a batch's runs run: one device, one program over every device, or one block of runs per process.

:func:`choose` picks a :class:`Spread` from the device and process counts and the physics backend:

* ``one``: a single device.
* ``mesh`` (JAX physics, several devices): the run axis padded and split over every device of every process,
  one SPMD program in which each device steps its own runs (:mod:`wbc_jax.rollout.sharding`).
* ``blocks`` (Warp physics, several processes): the runs padded to a multiple of the process count and dealt out in
  turn (process i: runs i, i + P, i + 2P, ...), so that every block holds the same mix of the design's cells
  (contiguous blocks of a factorial design hold different cells, whose runs take different work, and the campaign
  waits for the slowest process); process i steps block i on its first local device with the single-device program,
  and the processes meet only to gather results (an all-gather over one device per process). XLA cannot put MuJoCo
  Warp's kernels into one program over several devices with mujoco-mjx 3.17 and warp-lang 1.18 (``shard_map`` and
  ``pmap`` crash XLA's compiler, a GSPMD program runs slower than one GPU), while one process per GPU keeps each
  GPU's speed. For the same reason one process that sees several GPUs runs Warp on its first GPU only (``one``;
  :attr:`Spread.note` says so): start one process per GPU (docs/cluster.md).

Every process builds the same whole batch (the design is deterministic); :meth:`Spread.place` keeps this
process's part, :meth:`Spread.gather` brings every run's results back to every process's host. Between chunks,
:meth:`Spread.gather_start` puts the gather on the devices ahead of the next chunk and :meth:`Gathering.finish`
collects it on the host while that chunk runs: with several processes the runs meet in one on-device all-gather
(each device's queue runs in order, so a gather dispatched after the next chunk would wait for it).
:meth:`Spread.own_start` instead brings only this process's runs to its host, without a collective (a Warp
campaign's checkpoint blocks between chunks: ``wbc_jax.campaign.blocks``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from wbc_jax.rollout import runs


class Gathering(NamedTuple):
    """A gather in flight (:meth:`Spread.gather_start`): each leaf whole on this process's device or host (run axes
    still padded), its copy to the host started when fetched early."""

    leaves: list
    treedef: object
    n: int
    axes: object
    order: np.ndarray | None = None  # ("blocks") the rows of the gathered blocks in run order

    def finish(self):
        """The first ``n`` runs of the gathered tree (``order``'s rows) as host numpy arrays (waits for the
        copies)."""
        tree = jax.tree_util.tree_unflatten(self.treedef, [np.asarray(x) for x in self.leaves])
        return runs.first(tree, self.n, self.axes) if self.order is None else runs.take(tree, self.order, self.axes)


@functools.lru_cache(maxsize=None)
def _replicate(sharding: NamedSharding):
    """A jitted identity whose outputs are placed whole on every device of ``sharding``'s mesh (an all-gather)."""
    return jax.jit(lambda leaves: leaves, out_shardings=sharding)


@dataclass(frozen=True)
class Spread:
    """A batch's layout over devices and processes (module docstring).

    Attributes:
        mode: "one", "mesh" or "blocks".
        mesh: the run mesh over every device ("mesh"), else None.
        note: a line for the console when a layout leaves devices idle, else "".
        process, processes: ("blocks") this process's block and the number of blocks (process index and count).
    """

    mode: str
    mesh: object = None
    note: str = ""
    process: int = 0
    processes: int = 1

    @property
    def parts(self) -> int:
        """The number of devices the runs are split over (each steps ``ceil(n / parts)`` of an n-run batch)."""
        return self.processes if self.mode == "blocks" else self.mesh.size if self.mode == "mesh" else 1

    def describe(self) -> str:
        """" x N ..." after a device name for the console ("" on one device)."""
        if self.mode == "blocks":
            return f" x {self.processes} processes, a block of runs each"
        if self.mode == "mesh":
            procs = jax.process_count()
            return f" x {self.mesh.size}" + (f" over {procs} processes" if procs > 1 else "")
        return ""

    def block(self, n: int) -> np.ndarray:
        """("blocks") This process's rows of an n-run batch: ``ceil(n / processes)`` rows, runs ``process``,
        ``process + processes``, ...; past the last run padded with the last run."""
        k = -(-n // self.processes)
        return np.minimum(self.process + self.processes * np.arange(k), n - 1)

    def own_rows(self, n: int) -> range:
        """("blocks") The real runs of an n-run batch in this process's block, in block order (its padding left
        out; empty where the block is all padding)."""
        return range(self.process, n, self.processes)

    def run_order(self, n: int) -> np.ndarray:
        """("blocks") (n,) for each run of an n-run batch its row in the blocks joined in process order."""
        k, r = -(-n // self.processes), np.arange(n)
        return (r % self.processes) * k + r // self.processes

    def own_start(self, tree, n: int, axes=0) -> Gathering:
        """("blocks") This process's real runs of ``tree`` (its block as :meth:`place` placed it, of an n-run
        batch) on their way to the host, without any collective: :meth:`Gathering.finish` returns them."""
        leaves, treedef, _ = runs.leaves_and_axes(tree, axes)
        for x in leaves:
            if isinstance(x, jax.Array):
                x.copy_to_host_async()
        return Gathering(leaves, treedef, len(self.own_rows(n)), axes)

    def place(self, b, own_contacts: bool = False):
        """``b`` (a :class:`wbc_jax.rollout.batch.Batch`, whole in every process) as this process steps it: itself
        ("one"), padded and sharded over the mesh ("mesh"), or this process's block on its device ("blocks"; with
        ``own_contacts`` Warp's shared contact list sized for the block and ``state_axes`` with it,
        :func:`wbc_jax.rollout.batch.with_contact_list`: the campaign's, whose chunk program is compiled for the
        placed batch)."""
        if self.mode == "mesh":
            from wbc_jax.rollout.sharding import shard_batch

            return shard_batch(b, self.mesh)[0]
        if self.mode == "blocks":
            from wbc_jax.rollout.batch import take_runs, with_contact_list

            b = take_runs(b, self.block(int(np.shape(b.mu_ground)[0])))
            return with_contact_list(b) if own_contacts else b
        return b

    def place_state(self, state, n: int, axes=0):
        """A host state of all ``n`` runs (the same in every process) placed as :meth:`place` places a campaign's
        batch (``own_contacts``)."""
        if self.mode == "mesh":
            from wbc_jax.rollout.sharding import shard_runs

            return shard_runs(state, self.mesh, axes)
        if self.mode == "blocks":
            from wbc_jax.rollout.state import with_contact_list

            rows = self.block(n)
            state = runs.take(state, rows, axes)
            return jax.device_put(with_contact_list(state, axes, len(rows))[0])
        return state

    def gather_start(self, tree, n: int, axes=0, fetch: bool = True) -> Gathering:
        """Start :meth:`gather` of ``tree``: the collective is dispatched now, ahead of whatever this process
        dispatches next to its devices, and (``fetch``) the copies to the host begin; :meth:`Gathering.finish`
        returns the host arrays. Every process calls it at the same point (a collective with several processes),
        while only those that need the result call ``finish`` (the others pass ``fetch=False``)."""
        leaves, treedef, ax = runs.leaves_and_axes(tree, axes)
        if self.mode == "blocks":
            leaves = self._blocks_whole(leaves, ax)
        elif self.mode == "mesh" and jax.process_count() > 1:
            whole = _replicate(NamedSharding(self.mesh, P()))(leaves)
            leaves = [x.addressable_data(0) for x in whole]
        for x in leaves if fetch else ():
            if isinstance(x, jax.Array):
                x.copy_to_host_async()
        return Gathering(leaves, treedef, n, axes, self.run_order(n) if self.mode == "blocks" else None)

    def _blocks_whole(self, leaves: list, axes: list) -> list:
        """("blocks") Each leaf with a run axis as every process's block joined in process order (:meth:`run_order`
        gives each run's row) on this process's device; the others (axes None) as they are, this process's own."""
        devices = [jax.local_devices(process_index=p)[0] for p in range(self.processes)]
        mesh = Mesh(np.asarray(devices), ("process",))
        mine = [i for i, a in enumerate(axes) if a is not None]
        blocks = [jax.make_array_from_single_device_arrays(
            (self.processes * np.shape(leaves[i])[0], *np.shape(leaves[i])[1:]), NamedSharding(mesh, P("process")),
            [jax.device_put(leaves[i], devices[self.process])]) for i in mine]
        out = list(leaves)
        for i, x in zip(mine, _replicate(NamedSharding(mesh, P()))(blocks)):
            out[i] = x.addressable_data(0)
        return out

    def gather(self, tree, n: int, axes=0):
        """The first ``n`` runs of ``tree`` (placed as :meth:`place` places them; run axes ``axes``) as host
        numpy arrays, whole, in every process (a collective with several processes)."""
        return self.gather_start(tree, n, axes).finish()

def choose(backend: str) -> Spread:
    """The layout for a batch of ``backend`` ("jax" or "warp") physics on this process's devices."""
    if jax.device_count() == 1:
        return Spread("one")
    if backend != "warp":
        from wbc_jax.rollout.sharding import run_mesh

        return Spread("mesh", run_mesh())
    note = (f"note: Warp physics runs on 1 of this process's {jax.local_device_count()} GPUs (one process per GPU "
            f"uses them all: docs/cluster.md)" if jax.local_device_count() > 1 else "")
    if jax.process_count() == 1:
        return Spread("one", note=note)
    return Spread("blocks", note=note, process=jax.process_index(), processes=jax.process_count())
