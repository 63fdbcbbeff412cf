"""How many runs a campaign spec makes and whether their batch fits in memory, before anything is built."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from wbc_jax.campaign.build import LOG_EVERY
from wbc_jax.campaign.spec import Spec
from wbc_jax.errors import LimitError

# memory estimate of a batched rollout, per run [bytes]: state, model, plan and QP workspace, plus the logged samples
# of one chunk; deliberately generous round numbers (not measured), only meant to stop batches that cannot fit
RUN_BYTES = 4 << 20
LOG_SAMPLE_BYTES = 64 << 10


def n_runs_of(spec: Spec) -> int:
    """Number of runs of a spec (cells x reps), without building the design."""
    return int(np.prod([len(v) for v in spec.factors.values()])) * spec.reps


def check_size(spec: Spec, allow_large: bool = False) -> None:
    """Refuse a campaign whose batch would not fit in memory (an estimate, before the design is built).

    Raises:
        LimitError: runs x (RUN_BYTES + a chunk's log samples x LOG_SAMPLE_BYTES) exceeds the available memory,
            unless ``allow_large``.
    """
    c = spec.campaign
    n = n_runs_of(spec)
    samples = max(1.0, c["chunk_seconds"] / (0.002 * c["control_substeps"] * LOG_EVERY))  # 2 ms physics step
    need = n * (RUN_BYTES + samples * LOG_SAMPLE_BYTES)
    avail = _available_memory()
    if avail and need > avail and not allow_large:
        raise LimitError(f"{spec.path}: {n:,} runs need about {need / 2**30:,.1f} GiB, "
                         f"{avail / 2**30:,.1f} GiB available; fewer levels or reps, a smaller "
                         "campaign.chunk_seconds, or --allow-large to try anyway")


def _available_memory() -> int | None:
    """Available memory [bytes]: the accelerator's free memory, else the host's MemAvailable; None if unknown."""
    try:
        st = jax.local_devices()[0].memory_stats() or {}
        if "bytes_limit" in st:
            return int(st["bytes_limit"] - st.get("bytes_in_use", 0))
    except Exception:  # noqa: BLE001  (CPU devices have no memory stats)
        pass
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None
