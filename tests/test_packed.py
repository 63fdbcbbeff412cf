"""wbc_jax.rollout.packed: a NamedTuple of per-run scalars carried as one float and one int array (the rollout's Accum).

Against hand-built values: the fields read back with their values and dtypes (bools as bool), under vmap and jit;
``_replace`` edits only the named field, per run or broadcast, and keeps the leaves' placement; the pytree
structure (static layout) survives jit, device_get, tree_map row slicing and pickling (the AOT cache pickles it).
"""

import pickle
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax.rollout.packed import Packed, layout_of, pack


class NT(NamedTuple):
    a: jax.Array  # float
    flag: jax.Array  # bool
    k: jax.Array  # int32
    b: jax.Array  # float
    n: jax.Array  # int32


def one(x: float, flag: bool, k: int):
    return NT(a=jnp.float32(x), flag=jnp.bool_(flag), k=jnp.int32(k), b=jnp.float32(-2 * x), n=jnp.int32(-k))


def test_layout_columns_follow_field_order():
    lay = layout_of(one(1.0, True, 3))
    assert lay.cls is NT
    assert lay.kinds == ("f", "b", "i", "f", "i")
    assert lay.cols == (0, 0, 1, 1, 2)


def test_layout_rejects_other_dtypes():
    with pytest.raises(TypeError, match="'a'"):
        layout_of(NT(a=jnp.complex64(1), flag=True, k=1, b=1.0, n=1))


def test_pack_needs_both_kinds():
    class Floats(NamedTuple):
        x: jax.Array
        y: jax.Array

    with pytest.raises(ValueError, match="Floats"):
        pack(Floats(jnp.float32(1), jnp.float32(2)))


def test_round_trip_under_vmap_and_jit():
    xs, flags, ks = np.array([0.5, -1.25, 3.0], np.float32), np.array([True, False, True]), np.array([7, -1, 0])
    p = jax.jit(jax.vmap(lambda x, f, k: pack(one(x, f, k))))(xs, flags, ks)
    assert isinstance(p, Packed)
    assert p.f.shape == (3, 2) and p.f.dtype == jnp.float32
    assert p.i.shape == (3, 3) and p.i.dtype == jnp.int32
    np.testing.assert_array_equal(p.a, xs)
    np.testing.assert_array_equal(p.b, -2 * xs)
    np.testing.assert_array_equal(p.k, ks)
    np.testing.assert_array_equal(p.n, -ks)
    assert p.flag.dtype == jnp.bool_
    np.testing.assert_array_equal(p.flag, flags)
    u = p.unpack()
    assert isinstance(u, NT) and u._fields == p._fields
    for name in NT._fields:
        np.testing.assert_array_equal(getattr(u, name), getattr(p, name))
    with pytest.raises(AttributeError, match="no field 'c'"):
        _ = p.c


def test_update_inside_jit_keeps_layout_and_values():
    p0 = jax.vmap(lambda x: pack(one(x, False, 1)))(jnp.arange(4, dtype=jnp.float32))

    @jax.jit
    def step(p):  # an accumulator update as the rollout does it: unpack, edit, pack with the same layout
        u = p.unpack()
        return pack(u._replace(a=u.a + 1, flag=u.flag | (u.a > 1), n=u.n + u.k), p.layout)

    p = step(step(p0))
    np.testing.assert_array_equal(p.a, np.arange(4) + 2.0)
    np.testing.assert_array_equal(p.flag, np.arange(4) + 1 > 1)  # a > 1 before the second step (then kept)
    np.testing.assert_array_equal(p.n, np.full(4, 1))
    np.testing.assert_array_equal(p.b, -2 * np.arange(4.0))


def test_replace_one_field_per_run_or_broadcast():
    p = jax.vmap(lambda x: pack(one(x, False, 2)))(jnp.ones(3, jnp.float32))
    q = p._replace(b=np.array([1.0, np.inf, -3.0]))
    np.testing.assert_array_equal(q.b, [1.0, np.inf, -3.0])
    np.testing.assert_array_equal(q.a, p.a)
    np.testing.assert_array_equal(q.f.shape, p.f.shape)
    r = q._replace(flag=True, k=5)
    np.testing.assert_array_equal(r.flag, [True] * 3)
    np.testing.assert_array_equal(r.k, [5] * 3)
    np.testing.assert_array_equal(r.n, p.n)
    assert isinstance(r.f, jax.Array) and r.f.dtype == p.f.dtype and r.i.dtype == p.i.dtype
    shapes = jax.eval_shape(lambda x: x, p)  # shapes only (how a test builds a campaign without compiling its init)
    assert shapes._replace(b=1.0).f == shapes.f
    with pytest.raises(ValueError):
        p._replace(c=1.0)
    host = jax.device_get(p)._replace(a=0.0)  # host leaves stay on the host
    assert isinstance(host.f, np.ndarray)
    np.testing.assert_array_equal(host.a, np.zeros(3))


def test_pytree_host_slicing_and_pickle():
    p = jax.vmap(lambda x: pack(one(x, True, 4)))(jnp.arange(5, dtype=jnp.float32))
    h = jax.device_get(p)
    assert isinstance(h, Packed) and isinstance(h.f, np.ndarray)
    first2 = jax.tree_util.tree_map(lambda x: np.asarray(x)[:2], h)  # how final_results drops a batch's padding
    np.testing.assert_array_equal(first2.a, [0.0, 1.0])
    np.testing.assert_array_equal(first2.flag, [True, True])
    treedef = jax.tree_util.tree_structure(p)
    assert pickle.loads(pickle.dumps(treedef)) == treedef
    back = pickle.loads(pickle.dumps(h))
    np.testing.assert_array_equal(back.k, h.k)
