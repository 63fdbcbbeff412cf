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


def test_addresses_gathered_at_any_stride_null_kept_far_or_misaligned_left_to_warp():
    from warp._src.jax.xla_ffi import XLA_FFI_Buffer

    def entry(rank):  # XLA's layout: each struct followed by its dimensions, so the stride follows the rank
        return type(f"Entry{rank}", (ctypes.Structure,), {"_fields_": (("buffer", XLA_FFI_Buffer),
                                                                       ("dims", ctypes.c_int64 * rank))})

    kinds = [entry(r) for r in (0, 3, 1, 2)]
    size = sum(ctypes.sizeof(k) for k in kinds)
    block = (ctypes.c_char * size)()
    addrs, at = [], ctypes.addressof(block)
    for k, kind in enumerate(kinds):
        kind.from_address(at).buffer.data = 8192 * (k + 1)
        addrs.append(at)
        at += ctypes.sizeof(kind)
    ptrs = (ctypes.c_void_p * 4)(*addrs)
    assert warp_ffi.data_addresses(ctypes.addressof(ptrs), 4).tolist() == [8192, 16384, 24576, 32768]
    shuffled = (ctypes.c_void_p * 4)(addrs[2], addrs[0], addrs[3], addrs[1])
    assert warp_ffi.data_addresses(ctypes.addressof(shuffled), 4).tolist() == [24576, 8192, 32768, 16384]
    kinds[1].from_address(addrs[1]).buffer.data = None  # an empty array's buffer: no address
    assert warp_ffi.data_addresses(ctypes.addressof(ptrs), 4).tolist() == [8192, 0, 24576, 32768]
    bufs = ctypes.cast(ptrs, ctypes.POINTER(ctypes.POINTER(XLA_FFI_Buffer)))
    assert [bufs[i].contents.data for i in range(4)] == [8192, None, 24576, 32768]  # what Warp's key holds
    far = (ctypes.c_void_p * 2)(addrs[0], addrs[0] + warp_ffi.MAX_SPAN + 8)
    assert warp_ffi.data_addresses(ctypes.addressof(far), 2) is None
    odd = (ctypes.c_void_p * 2)(addrs[0], addrs[1] + 4)
    assert warp_ffi.data_addresses(ctypes.addressof(odd), 2) is None
    assert warp_ffi.data_addresses(0, 0).shape == (0,)


@wp.kernel
def _rows(a: wp.array(dtype=wp.float32), m: wp.array2d(dtype=wp.float32), e: wp.array(dtype=wp.float32),
          s: wp.array(dtype=wp.float32)):
    i = wp.tid()
    s[i] = a[i] + m[i, 0] + m[i, 1] + m[i, 2]


def _rows_call(a: wp.array(dtype=wp.float32), m: wp.array2d(dtype=wp.float32), e: wp.array(dtype=wp.float32),
               s: wp.array(dtype=wp.float32)):
    wp.launch(_rows, dim=a.shape[0], inputs=[a, m, e], outputs=[s])


def test_key_of_mixed_ranks_and_an_empty_array_is_warps(monkeypatch):
    """XLA's own call frame with buffers of ranks 1 and 2 and a 0-size one: the gathered addresses are those
    ctypes reads (0 for a null one) and the key equals Warp's."""
    from warp._src.jax import xla_ffi
    from warp._src.jax.xla_ffi import XLA_FFI_Buffer

    warp_ffi.install()
    found = []

    def record(callable_, call_frame, platform):
        frame = call_frame.contents
        if frame.args.size:
            ins, outs = (ctypes.cast(g, ctypes.POINTER(ctypes.POINTER(XLA_FFI_Buffer)))
                         for g in (frame.args.args, frame.rets.rets))
            read = [ins[i].contents.data for i in range(frame.args.size)]
            got = warp_ffi.data_addresses(ctypes.cast(frame.args.args, ctypes.c_void_p).value, frame.args.size)
            attr = ctypes.cast(frame.attrs.attrs[0], ctypes.POINTER(xla_ffi.XLA_FFI_Scalar)).contents
            call_id = ctypes.cast(attr.value, ctypes.POINTER(ctypes.c_int64)).contents.value
            want = hash((xla_ffi.get_device_ordinal_from_callframe(frame), call_id,
                         *[ins[i].contents.data for i in callable_.array_input_indices],
                         *[outs[i].contents.data for i in callable_.array_output_indices]))
            found.append((read, None if got is None else got.tolist(), want, warp_ffi.capture_key(callable_, frame)))
        return "recorded"

    monkeypatch.setattr(warp_ffi, "_fast_launch", record)
    f = wp.jax_callable(_rows_call, num_outputs=1)
    a, m, e = jnp.arange(4, dtype=jnp.float32), jnp.ones((4, 3), jnp.float32), jnp.zeros((0,), jnp.float32)
    (s,) = jax.jit(f)(a, m, e)
    np.testing.assert_array_equal(np.asarray(s), np.asarray(a + 3))
    assert len(found) == 1, found
    read, got, want, key = found[0]
    assert got == [r or 0 for r in read], found
    assert key == want, found
