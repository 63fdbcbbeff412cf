"""Static configuration compared and hashed by value, so jit caches key on what a program depends on."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np


def value_key(x: Any) -> Any:
    """A hashable key of ``x`` by value: numpy arrays by dtype, shape and elements, dataclasses by type and fields,
    tuples and lists element by element; anything else as it is (it must be hashable)."""
    if isinstance(x, np.ndarray):
        return ("ndarray", x.dtype.str, x.shape, tuple(x.ravel().tolist()))
    if isinstance(x, ByValue):
        return x.key
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return (type(x).__qualname__,) + tuple(value_key(getattr(x, f.name)) for f in dataclasses.fields(x))
    if isinstance(x, (tuple, list)):
        return (type(x).__name__,) + tuple(value_key(v) for v in x)
    return x


def axes_key(axes: Any) -> tuple:
    """A hashable key of a pytree of run axes (``in_axes``: leaves 0 or None) by value: its leaves and structure."""
    leaves, treedef = jax.tree_util.tree_flatten(axes, is_leaf=lambda v: v is None)
    return tuple(leaves), treedef


class ByValue:
    """Equality and hash of a frozen dataclass by its fields' values (:func:`value_key`; numpy fields included).

    Declare the dataclass with ``eq=False`` so that these methods are kept. The key is computed once per instance.
    """

    @property
    def key(self) -> tuple:
        """The instance's value key (cached: the fields of a frozen dataclass do not change)."""
        cached = self.__dict__.get("_value_key")
        if cached is None:
            cached = (type(self).__qualname__,) + tuple(value_key(getattr(self, f.name))
                                                        for f in dataclasses.fields(self))
            object.__setattr__(self, "_value_key", cached)
        return cached

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)
