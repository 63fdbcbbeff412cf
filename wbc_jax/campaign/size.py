"""How many runs a campaign spec makes and whether their batch fits in memory, before anything is built."""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import numpy as np

from wbc_jax.campaign.build import LOG_EVERY
from wbc_jax.campaign.spec import Spec
from wbc_jax.errors import LimitError
from wbc_jax.robot.model import load_mj_model, scene_path

# memory estimate of a batched rollout, per run [bytes]: the chunk program's arguments, outputs and temporaries (state,
# model, plan, the QP's and the physics' workspaces) with one logged sample, and each further sample of a chunk. About
# twice what `python examples/campaign_memory.py SPEC` measures for the shipped specs on either physics
# (docs/performance.md): a margin for MuJoCo Warp's own buffers and other specs, not so much that a batch which fits
# is refused
RUN_BYTES = 1 << 20
LOG_SAMPLE_BYTES = 1 << 10
# the whole batch stays on each process's first device (the Job's built batch) while its share runs: a run that
# another device steps still holds its inputs there (model, state, plan, gains: the program's arguments), about
# twice the measured arguments
INPUT_BYTES = 256 << 10


def n_runs_of(spec: Spec) -> int:
    """Number of runs of a spec (cells x reps), without building the design."""
    return int(np.prod([len(v) for v in spec.factors.values()])) * spec.reps


def memory_need(spec: Spec, parts: int = 1, runs: int | None = None) -> tuple[float, int | None]:
    """(a device's memory estimate [bytes], the available memory [bytes] or None where unknown:
    :func:`_available_memory`). The estimate: the ``ceil(n / parts)`` runs the device steps x (RUN_BYTES + a chunk's
    log samples x LOG_SAMPLE_BYTES), the batch's other runs x INPUT_BYTES. ``parts``: the devices the n runs are
    split over (``Spread.parts``); CPU devices share the host's memory and count as one. ``runs``: n, a batch of the
    spec's runs (None: the spec's n, :func:`n_runs_of`)."""
    c = spec.campaign
    samples = max(1.0, c["chunk_seconds"] / (_timestep(c) * c["control_substeps"] * LOG_EVERY))
    n = n_runs_of(spec) if runs is None else int(runs)
    own = own_runs(n, parts)
    return own * (RUN_BYTES + samples * LOG_SAMPLE_BYTES) + (n - own) * INPUT_BYTES, _available_memory()


def check_size(spec: Spec, allow_large: bool = False, parts: int = 1) -> None:
    """Refuse a campaign whose batch would not fit in memory (an estimate, before the design is built).

    Raises:
        LimitError: the estimate (:func:`memory_need`, a device's share of ``parts``) exceeds the available memory,
            unless ``allow_large``.
    """
    need, avail = memory_need(spec, parts)
    if avail and need > avail and not allow_large:
        n, k = n_runs_of(spec), own_memories(parts)
        share = f" ({own_runs(n, parts):,} on each of {k} devices)" if k > 1 else ""
        raise LimitError(f"{spec.path}: {n:,} runs{share} need about {need / 2**30:,.1f} GiB, "
                         f"{avail / 2**30:,.1f} GiB available; fewer levels or reps, a smaller "
                         "campaign.chunk_seconds, or --allow-large to try anyway")


def own_memories(parts: int) -> int:
    """The number of separate memories ``parts`` devices have: ``parts`` on accelerators, 1 on the CPU."""
    return max(1, int(parts)) if jax.default_backend() != "cpu" else 1


def own_runs(n: int, parts: int) -> int:
    """The runs of an ``n``-run batch one device steps: ``ceil(n / own_memories(parts))``."""
    return -(-int(n) // own_memories(parts))


def _timestep(campaign: dict) -> float:
    """The physics timestep [s] of a spec's ``campaign`` table: its scene's ``opt.timestep``."""
    return _scene_timestep(str(scene_path(campaign["scene"])))


@functools.lru_cache(maxsize=8)
def _scene_timestep(path: str) -> float:
    """``opt.timestep`` [s] of the scene file ``path`` (compiled once per process)."""
    return float(load_mj_model(path).opt.timestep)


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
