"""``wbc-jax warmup [--spec SPEC] [--backend warp|jax]``: compile once what a spec's first campaign compiles.

A campaign's first run on a machine compiles MuJoCo Warp's kernels (Warp's kernel cache, ``~/.cache/warp`` or
``WARP_CACHE_PATH``) and the JAX programs of its shapes (the persistent compilation cache,
``wbc_jax.runtime.jaxcfg``), and computes the course plans (kept beside that cache). This command does all three for
a spec's shapes and prints each stage's wall time, so a cluster image or a user runs it once and later campaigns of
that spec start warm:

1. setup: the spec built as the campaign builds it (plans, batched model, initial states; their small programs; on
   Warp the chunk program traced from the batch's shapes, then compiled while the initial states' first MuJoCo Warp
   call compiles the model's kernels, as the campaign does: ``wbc_jax.campaign.build.states_and_program``);
2. on Warp, from the start: MuJoCo Warp's step modules compiled on the GPU by a pool of threads
   (:func:`wbc_jax.physics.warp_kernels.preload`) while the main thread builds the spec and compiles the chunk
   program; at the first call of each MJX Warp function, the kernels MuJoCo Warp builds for the model, compiled by
   the pool before the call runs (:class:`wbc_jax.physics.warp_kernels.CompileAhead`);
3. the first chunk, run: it loads the compiled programs and captures Warp's CUDA graph.

Warp's cache holds the compiled modules; where the CUDA driver is older than Warp's CUDA toolkit, the driver
also translates them on load and keeps that in its own cache (``~/.nv/ComputeCache``, ``CUDA_CACHE_PATH``), which
an image should keep too.
"""

from __future__ import annotations

import argparse
import time

DEFAULT_SPEC = "sweeps/paper_campaign.toml"


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``warmup`` subcommand on ``subparsers``."""
    w = subparsers.add_parser("warmup", help="compile Warp's kernels and the JAX programs a spec's first campaign "
                                             "needs (run once per machine or image)")
    w.add_argument("--spec", default=DEFAULT_SPEC, help="the campaign spec whose shapes are compiled")
    w.add_argument("--backend", default=None, choices=["auto", "jax", "warp"],
                   help="physics backend instead of the spec's campaign.backend (default: the spec's)")
    w.add_argument("--workers", type=int, default=None, help="threads compiling Warp's kernel modules (default: "
                                                             "the CPU count; 0: none, kernels compile on first use)")
    return w


def warmup(spec_path: str, backend: str | None = None, workers: int | None = None) -> dict:
    """Compile what the spec's first campaign compiles (module docstring). Returns each stage's wall time [s] (and
    the number of Warp modules preloaded)."""
    import jax

    from wbc_jax.campaign.build import backend_of, build, build_ahead, chunk_fn, states_and_program, with_backend
    from wbc_jax.campaign.progress import stage
    from wbc_jax.campaign.spec import load_spec
    from wbc_jax.physics import warp_kernels
    from wbc_jax.rollout.batch import chunk_args

    t_start = time.perf_counter()
    spec = with_backend(load_spec(spec_path), backend)
    preload = warp_kernels.start_preload(backend_of(spec), workers)  # Warp compiles while the setup runs
    stage(f"building {spec_path}" + (" (MuJoCo Warp's kernels compiling meanwhile)" if preload else ""))
    # as the campaign does (wbc_jax.campaign.runner), so the persistent cache holds the program it looks up: on Warp
    # the chunk program compiled from the batch's shapes before the initial states; an exported program (JAX
    # physics) compiles on its first call
    warp = backend_of(spec) == "warp"
    built, with_states = build_ahead(spec) if warp else (build(spec), None)
    stages = dict(setup_s=time.perf_counter() - t_start)
    stage("compiling the chunk program")
    t0 = time.perf_counter()
    if warp:
        built, program, _ = states_and_program(built, with_states, preload and preload.ahead)
    else:
        program = chunk_fn(built.sim, built.batch.in_axes, built.logs_per_chunk, state_axes=built.batch.state_axes)
    stages["compile_chunk_s"] = time.perf_counter() - t0
    if preload is not None:
        stages["warp_modules"], stages["warp_preload_s"] = preload.result()
    stage("running the first chunk")
    t0 = time.perf_counter()
    jax.block_until_ready(program(*chunk_args(built.batch)))
    stages.update(first_chunk_s=time.perf_counter() - t0, total_s=time.perf_counter() - t_start)
    if preload is not None and preload.ahead is not None:  # the model's own kernels, compiled at first calls
        stages["warp_ahead_modules"] = preload.ahead.summary()["modules"]
    print("warmup: " + ", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in stages.items()),
          flush=True)
    return stages


def main(args: argparse.Namespace) -> int:
    """The ``warmup`` subcommand."""
    if args.workers is not None and args.workers < 0:
        from wbc_jax.errors import InputError

        raise InputError(f"--workers {args.workers}: expected an integer >= 0")
    from wbc_jax.campaign.spec import load_spec
    from wbc_jax.runtime import jaxcfg

    load_spec(args.spec)  # a bad spec fails in a second, before JAX and MuJoCo MJX load
    jaxcfg.start_backend()  # the device's client starts while MJX imports
    warmup(args.spec, args.backend, args.workers)
    return 0
