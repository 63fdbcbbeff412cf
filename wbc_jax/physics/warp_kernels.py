"""MuJoCo Warp's kernels compiled ahead of their first use, by a pool of threads.

Warp compiles a kernel module when one of its kernels is first launched, one module at a time, inside the first
physics step; on a machine whose Warp kernel cache (``~/.cache/warp``, ``WARP_CACHE_PATH``) is empty that is most of a
first campaign. :func:`preload` compiles every MuJoCo Warp module at once (``warp.force_load`` with several workers),
so the cost is that of the largest module; modules that a launch specializes further still compile on first use.
"""

from __future__ import annotations

import os
import threading
import time


def kernel_modules() -> list:
    """MuJoCo Warp's registered kernel modules (``warp`` ``Module`` objects; MJX imported first, which declares
    them); Warp's own modules left out."""
    from warp._src.context import user_modules

    from wbc_jax.physics import backend  # noqa: F401  (MJX imports MuJoCo Warp, which declares its kernels)

    return [module for name, module in list(user_modules.items()) if not name.startswith("warp")]


def preload(workers: int, device: str = "cuda:0") -> tuple[int, float]:
    """Compile (or load from Warp's kernel cache) every MuJoCo Warp module on ``device`` with ``workers`` threads.
    Returns (modules, seconds)."""
    import warp as wp

    t0 = time.perf_counter()
    modules = kernel_modules()
    wp.force_load(device=device, modules=modules, max_workers=workers)
    return len(modules), time.perf_counter() - t0


class Preload:
    """:func:`preload` running in a background thread, started at construction: the caller goes on (setup, tracing)
    while Warp compiles. :meth:`result` waits for it and returns (modules, seconds), or raises what it raised."""

    def __init__(self, workers: int, device: str = "cuda:0"):
        self._out: dict = {}
        self._thread = threading.Thread(target=self._run, args=(workers, device), name="warp-preload", daemon=True)
        self._thread.start()

    def _run(self, workers: int, device: str) -> None:
        try:
            self._out["result"] = preload(workers, device)
        except BaseException as e:  # re-raised in the caller's thread by result()
            self._out["error"] = e

    def result(self) -> tuple[int, float]:
        """(modules, seconds) once the preload has ended."""
        self._thread.join()
        if "error" in self._out:
            raise self._out["error"]
        return self._out["result"]


def start_preload(backend: str, workers: int | None = None) -> Preload | None:
    """A :class:`Preload` of MuJoCo Warp's modules on this process's first local GPU with ``workers`` threads
    (None: the CPU count) when ``backend`` is ``"warp"`` and JAX runs on a GPU; None otherwise (on a CPU, Warp's
    kernels compile on first use)."""
    import jax

    workers = (os.cpu_count() or 1) if workers is None else workers
    if backend != "warp" or jax.default_backend() != "gpu" or workers <= 0:
        return None
    # this process's GPU (one process per GPU: --local-device-ids), as Warp numbers the visible devices
    return Preload(workers, f"cuda:{jax.local_devices()[0].local_hardware_id or 0}")
