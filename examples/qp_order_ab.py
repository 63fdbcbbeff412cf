"""The campaign's step with the QP batch in slowest-first order against the batch's order, in one process.

    python examples/qp_order_ab.py [SPEC] [STEPS] [BATCHES]
        (defaults: sweeps/paper_campaign.toml 100 16384,27000; needs a GPU to mean anything)

The spec's runs are repeated to each batch size (from the start state) and stepped by the campaign's chunk program
compiled twice: with :func:`wbc_jax.qp.fused.slowest_first` (the fused QP kernels take the batch ordered by the warm
start's ADMM iterations, largest first) and with it replaced by a plain call. Prints each program's ADMM iterations
per control step, whether both programs' outputs are equal bit for bit (on a GPU, MuJoCo Warp's atomics make two
runs of one program differ too), and the best and median of 4 alternated timed calls of each.
"""

import sys
import time

import jax
import numpy as np

from wbc_jax.bench.campaign_step import compiled_chunk, fresh_state, repeated
from wbc_jax.bench.rollout import qp_iterations
from wbc_jax.campaign.build import LOG_EVERY, build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.qp import fused
from wbc_jax.rollout.batch import chunk_args

ORDERED = fused.slowest_first


def unordered(solve):
    """:func:`wbc_jax.qp.fused.slowest_first`'s signature, the batch's own order."""
    return lambda priority, *args: solve(*args)


def main(spec_path: str, steps: int, batches: list[int]) -> None:
    built = build(load_spec(spec_path))
    sim = built.sim
    n_logs = max(1, steps // LOG_EVERY)
    n_ctl = n_logs * LOG_EVERY
    print(f"{jax.devices()[0].device_kind}: {spec_path}, {n_ctl} control steps per call", flush=True)
    for B in batches:
        b = repeated(built.batch, built.batch.state, fresh_state(sim, built.batch, B), B)
        args = chunk_args(b)
        programs, outs = {}, {}
        for name, wrap in (("batch order", unordered), ("slowest first", ORDERED)):
            fused.slowest_first = wrap
            jax.clear_caches()  # the solver's jitted functions keep their first trace otherwise
            try:
                programs[name] = compiled_chunk(sim, b, n_logs)
            finally:
                fused.slowest_first = ORDERED
            outs[name] = jax.block_until_ready(programs[name](*args))
            print(f"batch {B} {name}: ADMM iterations per control step "
                  f"{qp_iterations(b.state, outs[name][0], n_ctl):.2f}", flush=True)
        leaves = [jax.tree_util.tree_leaves(outs[name]) for name in programs]
        same = all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in zip(*leaves))
        print(f"batch {B}: outputs {'bit for bit' if same else 'different'}", flush=True)
        times = {name: [] for name in programs}
        for _ in range(4):
            for name, f in programs.items():
                t0 = time.perf_counter()
                jax.block_until_ready(f(*args))
                times[name].append(time.perf_counter() - t0)
        for name, t in times.items():
            print(f"batch {B} {name:13s}: best {1e3 * min(t):.1f} ms, median {1e3 * np.median(t):.1f} ms per call, "
                  f"{B * n_ctl * sim.n_substeps / min(t):,.0f} env-steps/s", flush=True)
        print(f"batch {B}: slowest first / batch order = {min(times['batch order']) / min(times['slowest first']):.3f}",
              flush=True)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "sweeps/paper_campaign.toml",
         int(sys.argv[2]) if len(sys.argv) > 2 else 100,
         [int(x) for x in (sys.argv[3] if len(sys.argv) > 3 else "16384,27000").split(",")])
