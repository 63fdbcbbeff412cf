"""MuJoCo Warp's kernels compiled ahead of their first use, by a pool of threads.

Warp compiles a kernel module when one of its kernels is first launched, one module at a time, inside the first
physics step; on a machine whose Warp kernel cache (``~/.cache/warp``, ``WARP_CACHE_PATH``) is empty that is most of a
first campaign. :func:`preload` compiles every MuJoCo Warp module at once (``warp.force_load`` with several workers),
so the cost is that of the largest module; modules that a launch specializes further still compile on first use.
"""

from __future__ import annotations

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
