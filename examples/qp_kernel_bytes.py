"""The fused QP solver's iterations kernel with its matrices at half the bytes: a GPU study of what bounds it.

See docs/performance.md, open limits.

    python examples/qp_kernel_bytes.py [BATCH]          (default 16384; needs a GPU)

Solves BATCH generic QPs of the transport QP's size (56 variables, 24 equality and 54 inequality rows; 64 problems
repeated) with 4, 16 and 32 fixed ADMM iterations, twice each: with the iterations kernel's six matrices (the
stage's ``P``, ``Ae``, ``Ai`` and the factors ``K^-1``, ``W``, ``S^-1``) in float32 as the solver stores them, and
cast to float16 before that kernel (half their bytes; the arithmetic stays float32, the solution differs: a timing
study only). The difference between the 32- and 16-iteration times over 16 is one iteration's cost; best of 7
calls after the compile.
"""

import functools
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.bench import qp_problems
from wbc_jax.qp import QPSettings, fused, solve_qp

PALLAS_CALL = fused.pl.pallas_call
HALF = {"on": False}


def pallas_call(kernel, *args, **kwargs):
    """``pl.pallas_call``; the iterations kernel's call casts its matrices to float16 while ``HALF["on"]``."""
    call = PALLAS_CALL(kernel, *args, **kwargs)
    if kwargs.get("name") != "admm_iterations":
        return call
    n_stage = kernel.keywords["treedef"].num_leaves  # the stage's leaves (P, Ae, Ai first), then Ki, W, Si

    def run(*operands):
        operands = list(operands)
        if HALF["on"]:
            for i in (0, 1, 2, n_stage, n_stage + 1, n_stage + 2):
                operands[i] = operands[i].astype(jnp.float16)
        return call(*operands)
    return run


def main(batch: int) -> None:
    if jax.default_backend() != "gpu":
        sys.exit("qp_kernel_bytes.py: needs a GPU (on a CPU the kernels run in Pallas' interpreter)")
    rng = np.random.default_rng(3)
    probs = [qp_problems.random_generic_qp(rng, n=56, m_eq=24, m_in=54) for _ in range(64)]
    idx = np.arange(batch) % len(probs)
    data = [jnp.asarray(np.stack([getattr(p, k) for p in probs])[idx], jnp.float32) for k in ("P", "q", "A", "l", "u")]
    print(f"{jax.devices()[0].device_kind}, {batch} problems", flush=True)
    fused.pl.pallas_call = pallas_call
    try:
        for iters in (4, 16, 32):
            s = QPSettings(iters=iters, max_iters=0, eps_abs=1e-4, eps_rel=1e-4, linsolve="inv", adapt_every=0,
                           rho=3.0, ruiz_iters=2, eq_rows=24, kernel="fused")
            for half in (False, True):
                HALF["on"] = half
                jax.clear_caches()  # the solver's jitted functions keep their first trace otherwise
                fn = jax.jit(functools.partial(solve_qp, settings=s))
                jax.block_until_ready(fn(*data))
                times = []
                for _ in range(7):
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(*data))
                    times.append(time.perf_counter() - t0)
                print(f"iters {iters:2d}  matrices {'float16' if half else 'float32'}: {1e3 * min(times):8.3f} ms",
                      flush=True)
    finally:
        fused.pl.pallas_call = PALLAS_CALL


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 16384)
