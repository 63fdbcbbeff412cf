"""The fused QP solve's time per problem under the paper campaign's settings, for comparing two source trees.

    python examples/qp_fused_timing.py OUT.npz          (needs a GPU)

Solves generic QPs of the transport QP's size (:func:`wbc_jax.bench.qp_problems.transport_sized`) at batch 16384
and 270 with the campaign's loop (8 iterations, then blocks of 4 while unconverged, up to 200; rho 2, alpha 1.3,
24 rows held exactly). A call solves the batch REP times in a chain (each solve's q moved by 1e-30 times the
previous solution, so the small batch is timed on the device, not by the dispatch); the figure is the best of 5
calls per solve after the compile, with the mean iterations and the flags' counts. The solutions go to OUT.npz:
run it under each tree's ``PYTHONPATH`` and compare the files (``numpy.array_equal``) for a change that should not
move them.
"""

import functools
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.bench import qp_problems
from wbc_jax.qp import QPSettings, solve_qp

sys.path.insert(0, "examples")
from qp_kernel_warps import REP, chained  # noqa: E402

SETTINGS = QPSettings(iters=8, max_iters=200, check_every=4, eps_abs=1e-4, eps_rel=1e-4, linsolve="inv",
                      adapt_every=0, rho=2.0, alpha=1.3, ruiz_iters=2, eq_rows=24, kernel="fused")


def main(out_path: str) -> None:
    solve = functools.partial(solve_qp, settings=SETTINGS)
    out = {}
    for batch in (16384, 270):
        data = [jnp.asarray(x) for x in qp_problems.transport_sized(batch)]
        r = jax.block_until_ready(jax.jit(solve)(*data))
        fn = chained(solve)
        jax.block_until_ready(fn(*data))
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*data))
            times.append((time.perf_counter() - t0) / REP)
        out[f"x{batch}"] = np.asarray(r.x)
        iters, flags = float(np.mean(np.asarray(r.iters))), np.bincount(np.asarray(r.flag).ravel())
        print(f"batch {batch}: {1e3 * min(times):.4f} ms per solve of the batch (median {1e3 * np.median(times):.4f}),"
              f" iterations mean {iters:.2f}, flags {flags}")
    np.savez(out_path, **out)


if __name__ == "__main__":
    main(sys.argv[1])
