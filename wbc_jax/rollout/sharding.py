"""Spread the run axis of a batch over all local devices (JAX sharding, no code change in the rollout).

Every batched leaf (leading run axis) is padded to a multiple of the device count by repeating the last
run and placed with ``NamedSharding(mesh, P("runs"))`` (empty ones replicated); unbatched leaves (``in_axes``
None, e.g. the shared fields of the batched ``mjx.Model``) are replicated. ``jax.jit`` then partitions the vmapped
rollout along the run axis by itself (GSPMD): each device steps its own runs, with no communication.
Trim outputs with ``[:n_runs]``.

Several processes (``wbc_jax.rollout.distributed``: one per host or per GPU): ``jax.devices()`` lists the devices of
all of them and :func:`run_mesh` spans them; every process builds the same batch and :func:`shard_runs` makes
global arrays of it, each process supplying its own devices' shards. :func:`over_runs` runs a vmapped function
on each device's own runs (``shard_map``): no communication between devices, not even for the batched
solver loops' conditions (a plain ``jax.jit`` of the sharded batch all-reduces those at every iteration).
On one CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` fakes N devices (used by the tests).
A state's leaves without a run axis (Warp's shared contact list, ``in_axes`` None) are placed whole on every
device. Campaigns use this layout with JAX physics only; Warp physics runs a block of runs per process
(:mod:`wbc_jax.rollout.spread`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P


def run_mesh(devices=None) -> Mesh:
    """1-D mesh named "runs" over ``devices`` (default: all devices)."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), ("runs",))


def padded_size(n_runs: int, n_devices: int) -> int:
    """Smallest multiple of n_devices >= n_runs."""
    return -(-n_runs // n_devices) * n_devices


def _pad(x, n: int):
    xp = np if jax.process_count() > 1 else jnp  # several processes: whole host arrays, cut by _place
    x = xp.asarray(x)
    extra = n - x.shape[0]
    return x if extra == 0 else xp.concatenate([x, xp.repeat(x[-1:], extra, axis=0)], axis=0)


def _place(x, sharding: NamedSharding):
    """``x`` (the whole array, the same in every process) placed with ``sharding``: a global array whose shards
    each process fills from its own copy when the mesh spans several processes."""
    if jax.process_count() == 1:
        return jax.device_put(x, sharding)
    a = np.asarray(x)
    return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])


def shard_runs(tree, mesh: Mesh, in_axes=0):
    """Pad and place a pytree whose batched leaves carry the run axis first.

    Args:
        tree: pytree; in_axes: 0 (every leaf batched) or a matching pytree of 0 / None.
        mesh: from :func:`run_mesh`.

    Returns:
        The padded, sharded pytree (batched leaves have ``padded_size(B, mesh.size)`` runs).
    """
    axes = jax.tree_util.tree_map(lambda _: in_axes, tree) if isinstance(in_axes, int) else in_axes
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    ax_leaves = treedef.flatten_up_to(axes)
    sizes = {jnp.shape(x)[0] for x, a in zip(leaves, ax_leaves) if a == 0}
    if len(sizes) > 1:
        raise ValueError(f"batched leaves disagree on the run count: {sorted(sizes)}")
    n = padded_size(sizes.pop(), mesh.size) if sizes else 0
    runs, rep = NamedSharding(mesh, P("runs")), NamedSharding(mesh, P())
    # an empty batched leaf (MJX's unused fields, e.g. (B, 0)) is replicated: jit returns empty outputs replicated,
    # and a state leaf placed otherwise would make the next chunk's call compile the whole program a second time
    out = [_place(_pad(x, n), runs if np.size(x) else rep) if a == 0 else _place(x, rep)
           for x, a in zip(leaves, ax_leaves)]
    return jax.tree_util.tree_unflatten(treedef, out)


def shard_batch(b, mesh: Mesh | None = None):
    """A :class:`wbc_jax.rollout.batch.Batch` with every per-run input padded and sharded over ``mesh`` (all
    devices by default). Returns (sharded Batch, number of real runs)."""
    mesh = mesh or run_mesh()
    n = int(jnp.shape(b.mu_ground)[0])
    return b._replace(
        model=shard_runs(b.model, mesh, b.in_axes), state=shard_runs(b.state, mesh, b.state_axes),
        plan=shard_runs(b.plan, mesh),
        om=shard_runs(b.om, mesh), gains=shard_runs(b.gains, mesh), push=shard_runs(b.push, mesh),
        mu_ground=shard_runs(b.mu_ground, mesh)), n


def over_runs(fn, mesh: Mesh, in_axes, out_axes=0):
    """``fn`` (vmapped over the run axis: batched arguments and outputs carry it first) run by each device on its
    own shard of the runs (``jax.shard_map``), jitted.

    Args:
        fn: function of positional pytrees.
        mesh: from :func:`run_mesh`.
        in_axes: tuple, one entry per argument: 0 (batched) or a matching pytree of 0 / None (None: the leaf is
            the same for every run and every device gets it whole).
        out_axes: 0 (every output batched) or a pytree prefix of the outputs of 0 / None. None: an output with
            no run axis that is scratch (Warp's shared contact list, :func:`wbc_jax.physics.backend.data_axes`): each
            device keeps its own copy, and the value read back is device 0's.

    Returns:
        The jitted function; its outputs are split over ``mesh`` along the run axis, empty ones replicated (as
        :func:`shard_runs` places them: an output fed back in does not compile the function again).
    """
    def spec(a):
        return P() if a is None else P("runs")

    def specs(axes):
        return jax.tree_util.tree_map(spec, axes, is_leaf=lambda v: v is None)

    return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=specs(tuple(in_axes)), out_specs=specs(out_axes),
                                 check_vma=False))
