"""JAX process configuration shared by the CLI, the benchmarks and the tests.

The persistent compilation cache is on by default: MJX + WBC programs take tens of
seconds to compile, and a second run of the same shapes then loads them from disk.
Location: ``$WBC_JAX_CACHE`` or ``~/.cache/wbc_jax/jax``; ``WBC_JAX_CACHE=off`` disables it.

GPU programs are compiled with XLA's deterministic ops (:data:`DETERMINISTIC_FLAG`) by default: XLA's GPU scatter
adds (MJX's segment sums) otherwise use atomics whose order changes from call to call, and a closed loop near its
failure boundary then fails in one run and succeeds in the next, so a campaign's run could not be replayed.
``WBC_JAX_DETERMINISTIC=off`` leaves the flag out; a flag given in ``XLA_FLAGS`` is kept as given. XLA reads
``XLA_FLAGS`` when JAX starts its first backend, so the flag is set before anything runs on a device.
"""

from __future__ import annotations

import importlib.util
import os
import threading
from importlib import metadata
from pathlib import Path

DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops"
OFF = ("off", "0", "none", "false", "no")
_configured = False


def cache_dir() -> Path | None:
    """Directory of the persistent compilation cache, or None when disabled."""
    env = os.environ.get("WBC_JAX_CACHE", "")
    if env.lower() in OFF:
        return None
    return Path(env) if env else Path.home() / ".cache" / "wbc_jax" / "jax"


def _cuda_plugin_installed() -> bool:
    """JAX can start a CUDA backend here (a CUDA plugin is installed and ``JAX_PLATFORMS`` does not exclude it);
    decided without starting a backend."""
    platforms = os.environ.get("JAX_PLATFORMS", "").lower()
    if platforms and "cuda" not in platforms and "gpu" not in platforms:
        return False
    if any(importlib.util.find_spec(m) is not None for m in ("jax_cuda12_plugin", "jax_cuda13_plugin")):
        return True
    return any((d.metadata["Name"] or "").lower().replace("_", "-").startswith("jax-cuda")
               for d in metadata.distributions())


def xla_flag_value(flags: str, flag: str) -> bool | None:
    """The boolean value of ``flag`` (e.g. :data:`DETERMINISTIC_FLAG`) in an ``XLA_FLAGS`` string; None when absent.
    The last occurrence counts, as in XLA."""
    value = None
    for item in flags.split():
        name, _, text = item.partition("=")
        if name == flag:
            value = text.lower() not in ("false", "0")
    return value


def with_xla_flag(flags: str, flag: str, value: bool) -> str:
    """``flags`` (an ``XLA_FLAGS`` string) with ``flag`` set to ``value`` (earlier occurrences removed)."""
    kept = [item for item in flags.split() if item.partition("=")[0] != flag]
    return " ".join([*kept, f"{flag}={'true' if value else 'false'}"])


def deterministic_ops() -> bool:
    """This process's ``XLA_FLAGS`` turn XLA's GPU deterministic ops on."""
    return bool(xla_flag_value(os.environ.get("XLA_FLAGS", ""), DETERMINISTIC_FLAG))


def backends_started() -> bool:
    """JAX has started its backends (``XLA_FLAGS`` is read then; later changes take no effect)."""
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def set_deterministic_ops(value: bool) -> bool:
    """Set :data:`DETERMINISTIC_FLAG` in ``XLA_FLAGS`` to ``value``. Returns whether this process's programs compile
    with it: True when it was already so, or when JAX has not started its backends yet."""
    flags = os.environ.get("XLA_FLAGS", "")
    if bool(xla_flag_value(flags, DETERMINISTIC_FLAG)) == value:
        return True
    if backends_started():
        return False
    os.environ["XLA_FLAGS"] = with_xla_flag(flags, DETERMINISTIC_FLAG, value)
    return True


def xla_record() -> dict:
    """What a manifest records of the XLA settings that shape a compiled program: ``XLA_FLAGS`` as set and whether
    the GPU deterministic ops are on."""
    return dict(flags=os.environ.get("XLA_FLAGS", ""), deterministic_ops=deterministic_ops())


def configure() -> None:
    """Enable the persistent compilation cache and, where a CUDA backend can start, XLA's deterministic ops
    (module docstring; idempotent)."""
    global _configured
    if _configured:
        return
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = os.environ.get("WBC_JAX_DETERMINISTIC", "").lower() not in OFF
    if wanted and xla_flag_value(flags, DETERMINISTIC_FLAG) is None and _cuda_plugin_installed():
        set_deterministic_ops(True)
    import jax

    d = cache_dir()
    if d is not None:
        d.mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", str(d))
        # every program, the small eager-op programs of setup included
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _configured = True


def start_backend() -> threading.Thread:
    """Start JAX's default backend (the device's client: on a GPU the CUDA context and its memory pool) in a daemon
    thread, so that it starts while this process goes on importing MJX and MuJoCo Warp (Python, seconds).

    The thread also makes the first transfer (one scalar): XLA sets up a GPU's memory pool at a device's first
    allocation, which would otherwise be the main thread's first transfer, after the imports.

    Call after :func:`configure` and after ``jax.distributed.initialize`` (both must precede the backend). An error
    starting the backend is left to the main thread: its first use of a device raises it there. Returns the thread.
    """
    import jax
    import numpy as np

    def start():
        try:
            jax.device_put(np.zeros((), np.float32), jax.local_devices()[0]).block_until_ready()
        except Exception:  # noqa: BLE001  (raised again where the main thread first uses a device)
            pass

    thread = threading.Thread(target=start, name="wbc-jax-backend", daemon=True)
    thread.start()
    return thread
