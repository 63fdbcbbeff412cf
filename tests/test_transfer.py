"""``wbc_jax.runtime.transfer.to_device``: ``jnp.asarray``'s dtype and values, no program compiled, no aliasing."""

import jax
import jax.monitoring
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax.runtime.transfer import to_device

COMPILES = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: COMPILES.append(name) if name == "/jax/core/compile/jaxpr_trace_duration" else None)


@pytest.mark.parametrize("x, dtype", [
    (np.array([0.1, 1e-3, 2000.0, 1.0 / 3.0]), None),  # float64 host values: float32 on the device
    ((2000.0, 300.0, 1.0 / 3.0), float),  # Python numbers with the gains' dtype=float
    (0.98, float),
    (np.array([[0, 7], [0, 2**32 - 1]], dtype=np.uint32), None),  # PRNG keys
    (np.arange(5, dtype=np.int64), None),
])
def test_same_dtype_and_values_as_jnp_asarray(x, dtype):
    got, ref = to_device(x, dtype), jnp.asarray(x, dtype=dtype)
    assert (got.dtype, got.shape, jax.typeof(got).weak_type) == (ref.dtype, ref.shape, False)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))


def test_no_program_and_no_alias():
    shape = (3, 11, 2)  # a shape no other test lifts
    host = np.linspace(0.0, 1.0, 66).reshape(shape)
    COMPILES.clear()
    dev = to_device(host)
    assert COMPILES == []
    host[0, 0, 0] = 5.0  # the device array keeps the values it was given
    assert float(dev[0, 0, 0]) == 0.0
    jnp.asarray(np.ones(shape[::-1]))  # the probe sees the program jnp.asarray compiles for a new shape
    if not COMPILES:
        pytest.skip("this JAX lifts host arrays without a program: the probe cannot tell")
