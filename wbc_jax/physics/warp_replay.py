"""MuJoCo Warp's captured CUDA graphs replayed with a cheaper host-side lookup.

MJX runs MuJoCo Warp's step as one ``warp.jax_callable`` in Warp's CUDA graph mode: at every call XLA enters Warp's
Python FFI callback, which keys the graph it captured earlier by every buffer address of the call (the step's ~560
inputs and ~170 outputs), read one ``ctypes`` object at a time, and launches that graph. At small batches that
Python is on the control step's critical path: the device waits for it.

:func:`install` gives Warp's ``FfiCallable.ffi_callback`` a fast path for that replay: the same addresses read at
once with numpy (:func:`frame_key`, where XLA lays the call's buffer descriptors out at one stride, as its call
frame does), looked up in a per-callable map to the key Warp's own callback stored its capture under, and that
capture's graph launched on the call's stream, as Warp's callback launches it. Whatever the fast path does not
recognise (a first call, new addresses, another graph mode, the CPU, a layout it cannot read at once) goes to Warp's
callback unchanged, which captures, and the map then learns the new key. The graphs launched, their arguments and
streams are Warp's own: results are those of Warp's callback.
"""

from __future__ import annotations

import ctypes

import numpy as np

BUFFER_STRUCT = 48  # sizeof(XLA_FFI_Buffer): struct_size, extension_start, dtype, data, rank, dims
DATA_OFFSET = 24  # offsetof(XLA_FFI_Buffer, data)
BUFFER_TYPE = 1  # XLA_FFI_ArgType_BUFFER == XLA_FFI_RetType_BUFFER
MAX_KEYS = 256  # fast keys kept per callable (Warp's own cache bounds the graphs)
counts = {"fast": 0, "warp": 0}  # calls replayed by the fast path, calls left to Warp's callback (CUDA, WARP mode)


def _data_pointers(size: int, types, entries) -> np.ndarray | None:
    """The ``data`` field of each of ``size`` ``XLA_FFI_Buffer`` descriptors whose addresses are the void* array
    ``entries`` (``types``: their kinds, int32), read with one numpy view when the descriptors are all buffers at one
    positive stride (a multiple of 8 bytes, at least a descriptor long) and each holds its own struct size; None
    otherwise."""
    if size == 0:
        return np.zeros(0, np.uint64)
    kinds = np.frombuffer((ctypes.c_int32 * size).from_address(ctypes.addressof(types.contents)), np.int32)
    addr = np.frombuffer((ctypes.c_uint64 * size).from_address(ctypes.addressof(entries.contents)), np.uint64)
    if not (kinds == BUFFER_TYPE).all():
        return None
    stride = int(addr[1] - addr[0]) if size > 1 else BUFFER_STRUCT
    if stride < BUFFER_STRUCT or stride % 8 or (size > 2 and not (np.diff(addr) == stride).all()):
        return None
    words = (stride * (size - 1) + BUFFER_STRUCT) // 8
    block = np.frombuffer((ctypes.c_uint64 * words).from_address(int(addr[0])), np.uint64)
    step = stride // 8
    if not (block[0::step] == BUFFER_STRUCT).all():
        return None
    return block[DATA_OFFSET // 8::step].copy()


def frame_key(call_frame) -> bytes | None:
    """Every argument's and result's buffer address of an ``XLA_FFI_CallFrame`` (a ``ctypes`` pointer to it) as
    bytes (inputs first, then outputs), or None when :func:`_data_pointers` cannot read either at once."""
    cf = call_frame.contents
    ins = _data_pointers(int(cf.args.size), cf.args.types, cf.args.args)
    outs = None if ins is None else _data_pointers(int(cf.rets.size), cf.rets.types, cf.rets.rets)
    return None if outs is None else ins.tobytes() + outs.tobytes()


def install() -> bool:
    """Give Warp's ``FfiCallable.ffi_callback`` the fast replay path (module docstring); once per process, before
    MJX creates its callables (they bind the callback when created). False when this Warp has no such class."""
    try:
        from warp._src.jax import ffi as wffi
        from warp._src.jax import xla_ffi
    except ImportError:
        return False
    cls = getattr(wffi, "FfiCallable", None)
    if cls is None or getattr(cls.ffi_callback, "wbc_fast_replay", False):
        return cls is not None
    original = cls.ffi_callback
    warp_mode = wffi.JaxCallableGraphMode.WARP

    def slow_key(self, call_frame, ordinal: int, call_id: int) -> int:
        """The key Warp's callback stores a capture under (its own expression)."""
        cf = call_frame.contents
        inputs = ctypes.cast(cf.args.args, ctypes.POINTER(ctypes.POINTER(xla_ffi.XLA_FFI_Buffer)))
        outputs = ctypes.cast(cf.rets.rets, ctypes.POINTER(ctypes.POINTER(xla_ffi.XLA_FFI_Buffer)))
        ip = [inputs[i].contents.data for i in self.array_input_indices]
        op = [outputs[i].contents.data for i in self.array_output_indices]
        return hash((ordinal, call_id, *ip, *op))

    def ffi_callback(self, call_frame, platform):
        if (platform != wffi._FFI_PLATFORM_CUDA or self.graph_mode != warp_mode
                or call_frame.contents.extension_start):
            return original(self, call_frame, platform)
        try:
            cf = call_frame.contents
            attr = ctypes.cast(cf.attrs.attrs[0], ctypes.POINTER(xla_ffi.XLA_FFI_Scalar)).contents
            call_id = ctypes.cast(attr.value, ctypes.POINTER(ctypes.c_int64)).contents.value
            ordinal = xla_ffi.get_device_ordinal_from_callframe(cf)
            addresses = frame_key(call_frame)
            fast = None if addresses is None else (ordinal, call_id, addresses)
        except Exception:  # noqa: BLE001 - Warp's callback reports what is wrong with the frame
            return original(self, call_frame, platform)
        keys = self.__dict__.setdefault("wbc_fast_keys", {})
        if fast is not None:
            with wffi._FFI_CALLBACK_LOCK:
                key = keys.get(fast)
                capture = None if key is None else self.captures.get(key)
                if capture is not None:
                    stream = xla_ffi.get_stream_from_callframe(cf)
                    core = wffi.wp._src.context.runtime.core
                    if core.wp_cuda_graph_launch(capture.graph.graph_exec, stream):
                        self.captures.move_to_end(key)
                        counts["fast"] += 1
                        return None
        counts["warp"] += 1
        out = original(self, call_frame, platform)
        if fast is not None and out is None:
            with wffi._FFI_CALLBACK_LOCK:
                key = slow_key(self, call_frame, ordinal, call_id)
                if key in self.captures:
                    if len(keys) >= MAX_KEYS:
                        keys.clear()
                    keys[fast] = key
        return out

    ffi_callback.wbc_fast_replay = True
    cls.ffi_callback = ffi_callback
    return True
