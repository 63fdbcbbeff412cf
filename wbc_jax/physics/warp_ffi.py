"""MJX's Warp calls relaunched with less host work: the buffers' addresses read with numpy.

In its CUDA graph mode (``warp.JaxCallableGraphMode.WARP``) Warp's FFI callback relaunches the graph it captured for
an earlier call whose buffers had the same addresses (its key: the device, the call's id and every array buffer's
address). It reads each address through ctypes, a few Python objects per buffer, and MJX's step passes several
hundred buffers, so at a small batch the GPU waits on that Python. :func:`install` makes the callbacks of Warp
callables created afterwards take a shorter path for such a relaunch: where the call frame's buffer structs lie
close together (XLA keeps them in one array), the addresses are read as one numpy gather (:func:`data_addresses`),
the key is made as Warp makes it and the captured graph found is launched on the call's stream, as Warp's own
path does. Any other call (the first of a key, a metadata query, another layout or
graph mode, the CPU) goes to Warp's callback unchanged, so what runs on the device is the same.
"""

from __future__ import annotations

import ctypes
import functools

import numpy as np

counts: dict[str, int] = {}  # this process's calls by outcome: "fast" (the short path) or why Warp's path ran
MAX_SPAN = 1 << 20  # [bytes] the most memory the structs of one call's buffers may spread over
refused: list[tuple[int, int, int]] = []  # the first few refused layouts: (buffers, span [bytes], misaligned)


class _Words:
    """``__array_interface__`` of ``n`` uint64 words at ``address`` (a view made without a ctypes type per size)."""

    def __init__(self, address: int, n: int):
        self.__array_interface__ = {"data": (address, True), "shape": (n,), "typestr": "<u8", "version": 3}


def _words(address: int, n: int) -> np.ndarray:
    """(n,) uint64 view of the memory at ``address`` (nothing copied, nothing read until indexed)."""
    return np.asarray(_Words(address, n))


@functools.lru_cache(maxsize=None)
def _data_offset() -> int:
    """``XLA_FFI_Buffer.data``'s offset in the struct, in uint64 words."""
    from warp._src.jax.xla_ffi import XLA_FFI_Buffer

    return XLA_FFI_Buffer.data.offset // 8


def data_addresses(pointers: int, n: int) -> np.ndarray | None:
    """The ``data`` addresses ((n,) uint64; 0 for a buffer without one, e.g. an empty array) of the ``n``
    ``XLA_FFI_Buffer`` structs that the array of ``n`` pointers at address ``pointers`` points to, read as one
    gather: only the structs' ``data`` fields are read. None where a struct is misaligned or the structs spread
    over more than :data:`MAX_SPAN` bytes (XLA keeps a call's buffers in one array; any order and stride is read;
    the first few refusals are kept in :data:`refused`)."""
    if n == 0:
        return np.zeros(0, np.uint64)
    ptrs = _words(pointers, n)
    lo = int(ptrs.min())
    span = int(ptrs.max()) - lo
    if lo == 0 or span > MAX_SPAN or (ptrs & np.uint64(7)).any():
        if len(refused) < 4:
            refused.append((n, span, int((ptrs & np.uint64(7)).astype(bool).sum())))
        return None
    at = (ptrs - np.uint64(lo)) // np.uint64(8) + np.uint64(_data_offset())
    return _words(lo, span // 8 + _data_offset() + 1)[at]


def capture_key(callable_, frame) -> int | None:
    """The key under which ``callable_`` (a Warp ``FfiCallable`` in its CUDA graph mode) keeps the graph of the
    call ``frame`` (an ``XLA_FFI_CallFrame``), made as Warp makes it (the device, the call's id, each array input's
    and output's address); None where the buffers' addresses cannot be read at one stride."""
    from warp._src.jax import xla_ffi

    ins = data_addresses(ctypes.cast(frame.args.args, ctypes.c_void_p).value or 0, frame.args.size)
    outs = data_addresses(ctypes.cast(frame.rets.rets, ctypes.c_void_p).value or 0, frame.rets.size)
    if ins is None or outs is None:
        return None
    index = getattr(callable_, "wbc_jax_index", None)
    if index is None:
        index = callable_.wbc_jax_index = (np.asarray(callable_.array_input_indices, np.int64),
                                           np.asarray(callable_.array_output_indices, np.int64))
    attr = ctypes.cast(frame.attrs.attrs[0], ctypes.POINTER(xla_ffi.XLA_FFI_Scalar)).contents
    call_id = ctypes.cast(attr.value, ctypes.POINTER(ctypes.c_int64)).contents.value
    ordinal = xla_ffi.get_device_ordinal_from_callframe(frame)
    ptrs = np.concatenate((ins[index[0]], outs[index[1]]))
    # Warp's key holds ctypes' reading of each address: None for a null one
    return hash((ordinal, call_id, *(ptrs.tolist() if ptrs.all() else [a or None for a in ptrs.tolist()])))


def _fast_launch(callable_, call_frame, platform) -> str:
    """Launch the graph ``callable_`` (a Warp ``FfiCallable``) captured for this call's key, as Warp's callback
    would: "fast"; else nothing done and why (:data:`counts`' keys): the call needs Warp's own path."""
    import warp as wp
    from warp._src.jax import ffi, xla_ffi

    frame = call_frame.contents
    if platform != ffi._FFI_PLATFORM_CUDA or callable_.graph_mode != wp.JaxCallableGraphMode.WARP:
        return "other_mode"
    extension = frame.extension_start
    if extension and extension.contents.type == xla_ffi.XLA_FFI_Extension_Type.Metadata:
        return "metadata"  # XLA's query of the handler's traits
    with ffi._FFI_CALLBACK_LOCK:  # as Warp's callback
        key = capture_key(callable_, frame)
        if key is None:
            return "layout"
        capture = callable_.captures.get(key)
        if capture is None:
            return "new_key"
        stream = xla_ffi.get_stream_from_callframe(frame)
        if not wp._src.context.runtime.core.wp_cuda_graph_launch(capture.graph.graph_exec, stream):
            return "launch_error"  # Warp's path launches it again and reports the error
        callable_.captures.move_to_end(key)
        return "fast"


def install() -> None:
    """Make every Warp callable created from now on try :func:`_fast_launch` before Warp's callback (once per
    process)."""
    from warp._src.jax import ffi

    original = ffi.FfiCallable.ffi_callback
    if getattr(original, "warp_original", None) is not None:
        return

    @functools.wraps(original)
    def ffi_callback(self, call_frame, platform):
        try:
            outcome = _fast_launch(self, call_frame, platform)
        except Exception as e:  # Warp's own path handles the call and reports any error
            outcome = f"error {type(e).__name__}: {e}"[:200]
        counts[outcome] = counts.get(outcome, 0) + 1
        return None if outcome == "fast" else original(self, call_frame, platform)

    ffi_callback.warp_original = original
    ffi.FfiCallable.ffi_callback = ffi_callback
