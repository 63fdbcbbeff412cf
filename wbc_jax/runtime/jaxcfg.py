"""JAX process configuration shared by the CLI, the benchmarks and the tests.

The persistent compilation cache is on by default: MJX + WBC programs take tens of
seconds to compile, and a second run of the same shapes then loads them from disk.
Location: ``$WBC_JAX_CACHE`` or ``~/.cache/wbc_jax/jax``; ``WBC_JAX_CACHE=off`` disables it.
"""

from __future__ import annotations

import os
from pathlib import Path

_configured = False


def cache_dir() -> Path | None:
    """Directory of the persistent compilation cache, or None when disabled."""
    env = os.environ.get("WBC_JAX_CACHE", "")
    if env.lower() in ("off", "0", "none", "false"):
        return None
    return Path(env) if env else Path.home() / ".cache" / "wbc_jax" / "jax"


def configure() -> None:
    """Enable the persistent compilation cache (idempotent)."""
    global _configured
    if _configured:
        return
    import jax

    d = cache_dir()
    if d is not None:
        d.mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", str(d))
        # every program, the small eager-op programs of setup included
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _configured = True
