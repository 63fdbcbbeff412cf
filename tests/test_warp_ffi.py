"""The short relaunch path of MJX's Warp calls (wbc_jax.physics.warp_ffi): the buffers' addresses read with numpy
are those Warp reads one by one through ctypes, on XLA's own call frames; other layouts go to Warp's path."""

import ctypes

import numpy as np
import pytest

wp = pytest.importorskip("warp")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from wbc_jax.physics import warp_ffi  # noqa: E402


@wp.kernel
def _mix(a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float32), c: wp.array(dtype=wp.float32),
         s: wp.array(dtype=wp.float32), d: wp.array(dtype=wp.float32)):
    i = wp.tid()
    s[i] = a[i] + b[i] * c[i]
    d[i] = a[i] - c[i]


def _call(a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float32), c: wp.array(dtype=wp.float32),
          s: wp.array(dtype=wp.float32), d: wp.array(dtype=wp.float32)):
    wp.launch(_mix, dim=a.shape[0], inputs=[a, b, c], outputs=[s, d])


def test_addresses_read_from_xlas_call_frame_are_warps(monkeypatch):
    from warp._src.jax.xla_ffi import XLA_FFI_Buffer

    warp_ffi.install()
    warp_ffi.install()  # once per process: installing again keeps Warp's callback as the one wrapped
    seen, keys = [], []

    def record(callable_, call_frame, platform):
        frame = call_frame.contents
        for group, size in ((frame.args.args, frame.args.size), (frame.rets.rets, frame.rets.size)):
            bufs = ctypes.cast(group, ctypes.POINTER(ctypes.POINTER(XLA_FFI_Buffer)))
            got = warp_ffi.data_addresses(ctypes.cast(group, ctypes.c_void_p).value, size)
            seen.append(([bufs[i].contents.data for i in range(size)], None if got is None else got.tolist()))
        if frame.args.size:  # the graph's key, as Warp's callback makes it
            from warp._src.jax import xla_ffi

            ins, outs = (ctypes.cast(g, ctypes.POINTER(ctypes.POINTER(XLA_FFI_Buffer)))
                         for g in (frame.args.args, frame.rets.rets))
            attr = ctypes.cast(frame.attrs.attrs[0], ctypes.POINTER(xla_ffi.XLA_FFI_Scalar)).contents
            call_id = ctypes.cast(attr.value, ctypes.POINTER(ctypes.c_int64)).contents.value
            want = hash((xla_ffi.get_device_ordinal_from_callframe(frame), call_id,
                         *[ins[i].contents.data for i in callable_.array_input_indices],
                         *[outs[i].contents.data for i in callable_.array_output_indices]))
            keys.append((want, warp_ffi.capture_key(callable_, frame)))
        return "recorded"  # Warp's callback runs the call

    monkeypatch.setattr(warp_ffi, "_fast_launch", record)
    f = wp.jax_callable(_call, num_outputs=2)
    a, b, c = (jnp.arange(4, dtype=jnp.float32) + k for k in range(3))
    s, d = jax.jit(f)(a, b, c)
    np.testing.assert_array_equal(np.asarray(s), np.asarray(a + b * c))
    np.testing.assert_array_equal(np.asarray(d), np.asarray(a - c))
    seen = [(w, g) for w, g in seen if w]  # the first callback is XLA's metadata query, without buffers
    assert [len(w) for w, _ in seen] == [3, 2], seen
    assert all(w == g for w, g in seen), seen
    assert len(keys) == 1 and keys[0][0] == keys[0][1], keys
    assert warp_ffi.counts["recorded"] >= 2 and "fast" not in warp_ffi.counts


def test_buffers_not_in_one_array_or_without_an_address_are_left_to_warp():
    from warp._src.jax.xla_ffi import XLA_FFI_Buffer

    class Entry(ctypes.Structure):  # XLA's layout: each struct followed by its dimensions
        _fields_ = (("buffer", XLA_FFI_Buffer), ("dims", ctypes.c_int64 * 5))

    row = (Entry * 3)()
    for k in range(3):
        row[k].buffer.data = 8192 * (k + 1)
    in_row = (ctypes.c_void_p * 3)(*[ctypes.addressof(row) + k * ctypes.sizeof(Entry) for k in range(3)])
    got = warp_ffi.data_addresses(ctypes.addressof(in_row), 3)
    assert got is not None and got.tolist() == [8192, 16384, 24576]
    shuffled = (ctypes.c_void_p * 3)(in_row[0], in_row[2], in_row[1])  # not at one stride
    assert warp_ffi.data_addresses(ctypes.addressof(shuffled), 3) is None
    row[1].buffer.data = None  # a buffer without an address
    assert warp_ffi.data_addresses(ctypes.addressof(in_row), 3) is None
    assert warp_ffi.data_addresses(0, 0).shape == (0,)
