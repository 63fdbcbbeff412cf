"""wbc_jax.runtime.aot: exported programs are reloaded without tracing, give the same results, and are keyed safely;
wbc_jax.runtime.static: static configuration keys by value."""

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax.runtime import aot
from wbc_jax.runtime.static import ByValue, axes_key, value_key


class Pair(NamedTuple):
    a: jax.Array
    b: jax.Array


@jax.tree_util.register_pytree_node_class
class WithStatic:
    """A pytree node whose static data is a numpy array (like MJX's models), compared by value."""

    def __init__(self, x, table):
        self.x, self.table = x, table

    def tree_flatten(self):
        return (self.x,), (aot_wrapper(self.table),)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(children[0], aux[0].array)


class aot_wrapper:  # hashable by content, like mjx's _NumPyArrayHashWrapper
    def __init__(self, array):
        self.array = array

    def __hash__(self):
        return hash(self.array.tobytes())

    def __eq__(self, other):
        return np.array_equal(self.array, other.array)


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("WBC_JAX_CACHE", str(tmp_path))
    aot._LOADED.clear()
    yield tmp_path / "exported"
    aot._LOADED.clear()


def test_second_process_loads_without_tracing(store):
    traces = []

    def f(p: Pair, k):
        traces.append(1)
        return Pair(jnp.sin(p.a) * k, p.b @ p.b.T), jnp.sum(p.a)

    args = (Pair(jnp.arange(3.0), jnp.ones((2, 4))), jnp.float32(2.0))
    out1 = aot.cached_jit("f", f, "v1")(*args)
    assert len(traces) == 1 and len(list(store.glob("f-*.bin"))) == 1
    aot._LOADED.clear()  # a new process: only the disk entry is left
    g = aot.cached_jit("f", f, "v1")
    out2 = g(*args)
    assert len(traces) == 1  # loaded, not traced
    np.testing.assert_array_equal(out1[0].a, out2[0].a)
    np.testing.assert_array_equal(out1[0].b, out2[0].b)
    np.testing.assert_array_equal(out1[1], out2[1])
    assert isinstance(out2[0], Pair)
    np.testing.assert_allclose(out2[0].a, np.sin(np.arange(3.0)) * 2.0, rtol=1e-6)
    g(*args)
    assert g._cache_size() == 1  # the same shapes again: no new variant


def test_key_covers_static_shapes_and_static_data(store):
    traces = []

    def f(w: WithStatic):
        traces.append(1)
        return w.x * jnp.asarray(w.table, w.x.dtype).sum()

    x = jnp.ones(3)
    f1 = aot.cached_jit("g", f, "v1")
    np.testing.assert_allclose(f1(WithStatic(x, np.array([1.0, 2.0]))), 3.0 * np.ones(3))
    # equal static data in a different object: same entry (digest by value, not by address)
    aot._LOADED.clear()
    np.testing.assert_allclose(aot.cached_jit("g", f, "v1")(WithStatic(x, np.array([1.0, 2.0]))), 3.0 * np.ones(3))
    assert len(traces) == 1
    # different static data, static text or shape: a new program, with the right result
    np.testing.assert_allclose(f1(WithStatic(x, np.array([1.0, 5.0]))), 6.0 * np.ones(3))
    np.testing.assert_allclose(aot.cached_jit("g", f, "v2")(WithStatic(x, np.array([1.0, 2.0]))), 3.0 * np.ones(3))
    np.testing.assert_allclose(f1(WithStatic(jnp.ones(4), np.array([1.0, 2.0]))), 3.0 * np.ones(4))
    assert len(traces) == 4 and len(list(store.glob("g-*.bin"))) == 4


def test_tracers_and_disabled_cache_use_plain_jit(store, monkeypatch):
    f = aot.cached_jit("h", lambda x: jnp.cos(x) ** 2, "v1")
    grad = jax.grad(lambda x: f(x).sum())(jnp.ones(2))  # under a transformation: plain jit, differentiable
    np.testing.assert_allclose(grad, -np.sin(2.0) * np.ones(2), rtol=1e-6)
    assert not store.exists() or not list(store.glob("h-*.bin"))
    monkeypatch.setenv("WBC_JAX_CACHE", "off")
    g = aot.cached_jit("k", lambda x: x + 1, "v1")
    np.testing.assert_array_equal(g(jnp.zeros(2)), np.ones(2))
    assert not list(store.parent.glob("**/k-*.bin"))


def test_damaged_entry_is_recomputed(store):
    f = aot.cached_jit("d", lambda x: 2 * x, "v1")
    f(jnp.ones(2))
    (entry,) = store.glob("d-*.bin")
    entry.write_bytes(b"not a program")
    aot._LOADED.clear()
    np.testing.assert_array_equal(aot.cached_jit("d", lambda x: 2 * x, "v1")(jnp.ones(2)), 2 * np.ones(2))
    aot.cached_value("v", "s1", lambda: {"a": np.arange(3)})
    np.testing.assert_array_equal(aot.cached_value("v", "s1", lambda: None)["a"], np.arange(3))  # read back


def test_failed_export_falls_back_to_plain_jit(store, monkeypatch):
    """A program jax.export cannot hold (e.g. a custom call it refuses) still runs, with plain jit, and leaves no
    entry; the custom calls the key makes safe (Pallas' Triton kernels) are passed as disabled checks."""
    seen = {}

    def refuse(fn, disabled_checks=()):
        seen["checks"] = [str(c) for c in disabled_checks]
        raise ValueError("Cannot serialize code with custom calls whose targets have no compatibility guarantees")

    monkeypatch.setattr(jax.export, "export", refuse)
    f = aot.cached_jit("r", lambda t: {"y": t["x"] * 2.0}, "v1")
    with pytest.warns(UserWarning, match="r not exported"):
        out = f({"x": jnp.arange(3.0)})
    np.testing.assert_array_equal(out["y"], [0.0, 2.0, 4.0])
    assert f._cache_size() == 1
    assert seen["checks"] == ["custom_call:__gpu$xla.gpu.triton"]
    assert not store.exists() or not list(store.glob("r-*.bin"))


@dataclasses.dataclass(frozen=True, eq=False)
class Config(ByValue):
    """A frozen static configuration with numpy fields, hashed by value."""

    name: str
    slots: np.ndarray
    nested: tuple = ()


def test_static_configuration_keys_by_value():
    a = Config("x", np.array([1, 2, 3]), (np.zeros(2), 1.5))
    b = Config("x", np.array([1, 2, 3]), (np.zeros(2), 1.5))
    assert a is not b and a == b and hash(a) == hash(b) and {a: 1}[b] == 1
    assert a != Config("x", np.array([1, 2, 4]), (np.zeros(2), 1.5))
    assert a != Config("x", np.array([[1, 2, 3]]), (np.zeros(2), 1.5))  # shape counts
    assert a != Config("x", np.array([1, 2, 3], np.int8), (np.zeros(2), 1.5))  # dtype counts
    assert a != Config("x", np.array([1, 2, 3]), (np.zeros(3), 1.5))  # nested arrays count
    assert value_key([1, (2,)]) != value_key((1, (2,)))


def test_axes_key_by_value():
    axes = {"a": 0, "b": None, "c": (0, None)}
    assert axes_key(axes) == axes_key({"a": 0, "b": None, "c": (0, None)})
    assert axes_key(axes) != axes_key({"a": 0, "b": 0, "c": (0, None)})
    hash(axes_key(axes))
