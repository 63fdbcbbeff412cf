"""A NamedTuple of per-run scalars carried as two arrays: one of its floating fields, one of its integer and bool
fields.

Why: the rollout's accumulators (``wbc_jax.metrics.accumulate.Accum``, 32 scalars per run) are updated at every
control step inside the rollout's loop; carried as separate leaves, each update is an output of its own, which XLA
on a GPU writes in many small kernels, while two arrays are written by one fused kernel each.

A :class:`Packed` reads like the NamedTuple it packs: ``p.max_slip`` is that field's column (shape ``batch`` +
``()``), as a jax or a numpy array like the leaves (``jax.device_get`` gives numpy leaves); bool fields read as
bool. :meth:`Packed.unpack` gives the NamedTuple itself (inside a jitted step: slices XLA fuses into their users),
:func:`pack` the reverse. Every field must be a scalar per run: a Packed of ``batch`` runs has leaves
``batch + (n_float,)`` and ``batch + (n_int,)``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.runtime.transfer import to_device


class Layout(NamedTuple):
    """Where each field of a NamedTuple class lives in a :class:`Packed` (static, hashable)."""

    cls: type  # the NamedTuple class
    kinds: tuple  # per field: "f" (floating), "i" (integer) or "b" (bool; stored as 0 / 1 in the int array)
    cols: tuple  # per field: its column in the float array ("f") or in the int array ("i", "b")


def layout_of(nt) -> Layout:
    """The :class:`Layout` of NamedTuple instance ``nt`` (from its fields' dtypes, in field order)."""
    kinds, cols, nf, ni = [], [], 0, 0
    for name, v in zip(nt._fields, nt):
        dt = np.dtype(v.dtype if hasattr(v, "dtype") else np.asarray(v).dtype)
        if np.issubdtype(dt, np.floating):
            kinds.append("f")
            cols.append(nf)
            nf += 1
        elif dt == np.bool_ or np.issubdtype(dt, np.integer):
            kinds.append("b" if dt == np.bool_ else "i")
            cols.append(ni)
            ni += 1
        else:
            raise TypeError(f"packed field {name!r}: dtype {dt} is neither floating, integer nor bool")
    return Layout(type(nt), tuple(kinds), tuple(cols))


@jax.tree_util.register_pytree_node_class
class Packed:
    """NamedTuple fields in two arrays: ``f`` (..., n_float) floating, ``i`` (..., n_int) int32 (bools as 0 / 1).
    Leading axes (the runs) are the same on both."""

    __slots__ = ("f", "i", "layout")

    def __init__(self, f, i, layout: Layout):
        self.f, self.i, self.layout = f, i, layout

    def tree_flatten(self):
        return (self.f, self.i), self.layout

    @classmethod
    def tree_unflatten(cls, layout, children):
        return cls(*children, layout)

    def _column(self, k: int):
        kind, col = self.layout.kinds[k], self.layout.cols[k]
        x = self.f[..., col] if kind == "f" else self.i[..., col]
        return x != 0 if kind == "b" else x

    def __getattr__(self, name: str):  # only for names that are not attributes: the fields
        if name in Packed.__slots__:  # not set yet (copy / pickle make the object before __init__)
            raise AttributeError(name)
        try:
            k = self.layout.cls._fields.index(name)
        except ValueError:
            raise AttributeError(f"{self.layout.cls.__name__} has no field {name!r}") from None
        return self._column(k)

    @property
    def _fields(self) -> tuple:
        return self.layout.cls._fields

    def unpack(self):
        """The NamedTuple (each field a column of the leaves)."""
        return self.layout.cls(*(self._column(k) for k in range(len(self._fields))))

    def _replace(self, **values: Any) -> "Packed":
        """A Packed with fields set to ``values`` (scalars or arrays broadcast to the leading axes), outside a jit:
        the leaves are edited on the host and placed back like the old ones (same sharding when committed). Leaves
        that are shapes only (``jax.ShapeDtypeStruct``, from ``jax.eval_shape``) stay so: the result's shapes."""
        ks = [self._fields.index(name) for name in values]  # ValueError for a name that is not a field
        if isinstance(self.f, jax.ShapeDtypeStruct) or isinstance(self.i, jax.ShapeDtypeStruct):
            return self
        f, i = np.array(jax.device_get(self.f)), np.array(jax.device_get(self.i))
        for k, v in zip(ks, values.values()):
            kind, col = self.layout.kinds[k], self.layout.cols[k]
            if kind == "f":
                f[..., col] = v
            else:
                i[..., col] = np.asarray(v).astype(i.dtype)
        return Packed(placed_like(self.f, f), placed_like(self.i, i), self.layout)


def placed_like(old, new: np.ndarray):
    """Host array ``new`` placed like the leaf ``old``: after a host ``old``, ``new`` itself; after a device array
    committed to a sharding, on that sharding (another would recompile the chunk function for other input
    shardings); else a default device array (also after a shapes-only ``old``)."""
    if isinstance(old, np.ndarray):
        return new
    return jax.device_put(new, old.sharding) if getattr(old, "committed", False) else to_device(new)


def broadcast_like(old, value):
    """``value`` broadcast to the shape and dtype of the leaf ``old`` and placed like it (:func:`placed_like`: a leaf
    committed elsewhere would change the chunk function's input shardings)."""
    return placed_like(old, np.array(np.broadcast_to(np.asarray(value, old.dtype), old.shape)))


def pack(nt, layout: Layout | None = None) -> Packed:
    """:class:`Packed` of NamedTuple ``nt`` whose fields are scalars (or arrays with the same leading axes, each
    field one value per run). ``layout``: that of ``nt`` (:func:`layout_of`) when None. Floating fields are cast
    to their common dtype, integer and bool fields to int32. ``nt`` needs a field of each kind (floating;
    integer or bool)."""
    layout = layout or layout_of(nt)
    if "f" not in layout.kinds or set(layout.kinds) == {"f"}:
        raise ValueError(f"pack({layout.cls.__name__}): needs a floating field and an integer or bool field")
    fs = [v for v, kind in zip(nt, layout.kinds) if kind == "f"]
    ints = [jnp.asarray(v).astype(jnp.int32) for v, kind in zip(nt, layout.kinds) if kind != "f"]
    dt = jnp.result_type(*fs)
    return Packed(jnp.stack([jnp.asarray(v, dt) for v in fs], axis=-1), jnp.stack(ints, axis=-1), layout)
