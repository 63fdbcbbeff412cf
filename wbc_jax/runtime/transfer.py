"""Host values onto the device by a transfer alone.

Outside a trace ``jnp.asarray`` runs a small XLA program per shape and dtype (it lifts the value, and casts it);
on a GPU each is compiled, or read from the persistent compilation cache, while a campaign is set up. The setup's
constants (gains, plans, the per-run model fields, pushes) go through :func:`to_device` instead.
"""

from __future__ import annotations

import jax
import numpy as np


def to_device(x, dtype=None) -> jax.Array:
    """``x`` (a numpy array, a number or a nested sequence of numbers) as a device array on the default device, with
    the dtype ``jnp.asarray(x, dtype)`` gives (``dtype`` or ``x``'s, as JAX canonicalizes it: float32 unless 64-bit
    mode is on) and its values (one IEEE rounding from ``x``), not weak-typed. The host array is copied first, so a
    later change to ``x`` never reaches the device array (a CPU device may share the host buffer)."""
    a = np.asarray(x) if dtype is None else np.asarray(x, dtype=jax.dtypes.canonicalize_dtype(dtype))
    return jax.device_put(np.array(a, dtype=jax.dtypes.canonicalize_dtype(a.dtype), copy=True))
