"""Spread the run axis of a batch over all local devices (JAX sharding, no code change in the rollout).

Every batched leaf (leading run axis) is padded to a multiple of the device count by repeating the last
run and placed with ``NamedSharding(mesh, P("runs"))`` (empty ones replicated); unbatched leaves (``in_axes``
None, e.g. the shared fields of the batched ``mjx.Model``) are replicated. ``jax.jit`` then partitions the vmapped
rollout along the run axis by itself (GSPMD): each device steps its own runs, with no communication.
Trim outputs with ``[:n_runs]``.

Several hosts: call ``jax.distributed.initialize()`` on every host before anything else; ``jax.devices()``
then lists the devices of all hosts and :func:`run_mesh` spans them (each host must build the same batch).
On one CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` fakes N devices (used by the tests).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P


def run_mesh(devices=None) -> Mesh:
    """1-D mesh named "runs" over ``devices`` (default: all devices)."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), ("runs",))


def padded_size(n_runs: int, n_devices: int) -> int:
    """Smallest multiple of n_devices >= n_runs."""
    return -(-n_runs // n_devices) * n_devices


def _pad(x, n: int):
    x = jnp.asarray(x)
    extra = n - x.shape[0]
    return x if extra == 0 else jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)], axis=0)


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
    out = [jax.device_put(_pad(x, n), runs if np.size(x) else rep) if a == 0 else jax.device_put(x, rep)
           for x, a in zip(leaves, ax_leaves)]
    return jax.tree_util.tree_unflatten(treedef, out)


def shard_batch(b, mesh: Mesh | None = None):
    """A :class:`wbc_jax.sim.batch.Batch` with every per-run input padded and sharded over ``mesh`` (all
    devices by default). Returns (sharded Batch, number of real runs)."""
    mesh = mesh or run_mesh()
    n = int(jnp.shape(b.mu_ground)[0])
    return b._replace(
        model=shard_runs(b.model, mesh, b.in_axes), state=shard_runs(b.state, mesh), plan=shard_runs(b.plan, mesh),
        om=shard_runs(b.om, mesh), gains=shard_runs(b.gains, mesh), push=shard_runs(b.push, mesh),
        mu_ground=shard_runs(b.mu_ground, mesh)), n
