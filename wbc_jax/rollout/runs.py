"""Rows of batched pytrees along the run axis: take some runs, keep the first n, join sub-batches.

A batch's leaves carry the run axis first, except those marked None in its ``in_axes`` pytree: the fields of a
batched mjx.Model that every run shares, and the Warp data's shared contact list
(:func:`wbc_jax.rollout.state.state_axes`). Those pass through whole. Host (numpy) leaves stay on the host, device
leaves on the device.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def leaves_and_axes(tree, in_axes=0):
    """(leaves, treedef, each leaf's run axis: 0 or None) of ``tree`` with run axes ``in_axes`` (0 or a pytree
    of 0 / None matching ``tree``)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    return leaves, treedef, ([in_axes] * len(leaves) if isinstance(in_axes, int) else treedef.flatten_up_to(in_axes))


def take(tree, idx, in_axes=0):
    """Rows ``idx`` of every batched leaf (``in_axes`` 0) of ``tree``; unbatched leaves (None) unchanged."""
    leaves, treedef, axes = leaves_and_axes(tree, in_axes)
    host = np.asarray(idx)  # host leaves (several processes' gathered states) are indexed on the host
    return jax.tree_util.tree_unflatten(treedef, [x if a is None else x[host] if isinstance(x, np.ndarray) else x[idx]
                                                  for x, a in zip(leaves, axes)])


def first(tree, n: int, in_axes=0):
    """The first ``n`` runs of a host pytree (drops a sharded batch's padding), as numpy arrays."""
    leaves, treedef, axes = leaves_and_axes(tree, in_axes)
    return jax.tree_util.tree_unflatten(treedef, [np.asarray(x) if a is None else np.asarray(x)[:n]
                                                  for x, a in zip(leaves, axes)])


def concat(trees: list, in_axes=0):
    """Leafwise concatenation of pytrees along the run axis (unbatched leaves: the first tree's): device arrays
    stay on the device (the result keeps the chunk function's input types and placement, so feeding it back does
    not compile again), host arrays on the host."""
    if len(trees) == 1:
        return trees[0]
    flat = [leaves_and_axes(t, in_axes) for t in trees]
    treedef, axes = flat[0][1], flat[0][2]

    def cat(xs, a):
        if a is None:
            return xs[0]
        return np.concatenate(xs) if isinstance(xs[0], np.ndarray) else jnp.concatenate(xs)

    return jax.tree_util.tree_unflatten(treedef, [cat([f[0][i] for f in flat], a) for i, a in enumerate(axes)])
