"""The device memory a campaign's batch takes per run, measured, against the estimate that refuses a batch too large.

    python examples/campaign_memory.py SPEC [BACKEND]   (BACKEND: jax or warp; default the spec's)

Builds the spec as a campaign does and compiles its chunk program
(:func:`wbc_jax.bench.campaign_step.compiled_chunk`) twice on this machine's device: with one logged sample and with
a chunk's samples. XLA's memory analysis of each gives the bytes of the program's arguments (state, model, plan,
gains), outputs (the state and the logs) and temporaries (the QP's and the physics' workspaces); per run, and per
further logged sample, they are what :func:`wbc_jax.campaign.size.check_size` estimates with ``RUN_BYTES`` and
``LOG_SAMPLE_BYTES``, and the arguments what it estimates with ``INPUT_BYTES`` for a run that another device steps.
MuJoCo Warp's buffers outside XLA's (its kernels' own scratch) are not counted.
"""

import sys

import jax

from wbc_jax.bench.campaign_step import compiled_chunk
from wbc_jax.campaign import build as B
from wbc_jax.campaign.size import INPUT_BYTES, LOG_SAMPLE_BYTES, RUN_BYTES
from wbc_jax.campaign.spec import load_spec


def program_bytes(built: B.Built, n_logs: int) -> tuple[int, int, int]:
    """(arguments, outputs, temporaries) [bytes] of ``built``'s chunk program with ``n_logs`` logged samples."""
    ma = compiled_chunk(built.sim, built.batch, n_logs).memory_analysis()
    return ma.argument_size_in_bytes, ma.output_size_in_bytes, ma.temp_size_in_bytes


def main(path: str, backend: str | None) -> None:
    spec = B.with_backend(load_spec(path), backend)
    built = B.build(spec)
    n, logs = len(built.design.m), built.logs_per_chunk
    one = program_bytes(built, 1)
    full = program_bytes(built, logs) if logs > 1 else one
    per_run = sum(one) / n
    per_sample = (sum(full) - sum(one)) / n / max(1, logs - 1)
    print(f"{jax.devices()[0].device_kind}: {path}, {built.sim.robot.backend} physics, {n} runs, {logs} logged "
          f"samples per chunk")
    print(f"per run, one sample: arguments {one[0] / n / 1024:.1f} KiB, outputs {one[1] / n / 1024:.1f} KiB, "
          f"temporaries {one[2] / n / 1024:.1f} KiB: {per_run / 1024:.1f} KiB (estimate {RUN_BYTES / 1024:.0f} KiB, "
          f"{RUN_BYTES / per_run:.1f}x)")
    print(f"per further sample and run: {per_sample:.0f} B (estimate {LOG_SAMPLE_BYTES} B"
          + (f", {LOG_SAMPLE_BYTES / per_sample:.1f}x)" if per_sample > 0 else ")"))
    print(f"a run's inputs (the arguments): {one[0] / n / 1024:.1f} KiB (estimate {INPUT_BYTES / 1024:.0f} KiB, "
          f"{INPUT_BYTES * n / one[0]:.1f}x)")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None)
