"""The fused QP solver's kernels against Triton warps per program (the preparation and iterations kernels', and the
factorization's), and with the iterations kernel's operands loaded once per program instead of at each use (a GPU
study; docs/performance.md, open limits).

    python examples/qp_kernel_warps.py [BATCH]          (default 16384; needs a GPU)

Solves BATCH generic QPs of the transport QP's size (56 variables, 24 equality and 54 inequality rows; 64 problems
repeated) with 4 and 16 fixed ADMM iterations, for each setting (operands; warps of the iterations kernel; of the
factorization): the kernels as they are at 2 and 2 warps (the solver's default), operands held at 2-32 warps, as
they are at 4-16 warps, the factorization at 4 and 8. Each setting's programs are built afresh (the solver's jitted
function would otherwise keep its first trace); a call solves the batch REP times in a chain (each solve's q moved
by 1e-30 times the previous solution, so small batches are timed on the device, not by the dispatch), best of 5
calls per solve after the compile, and the solution against the default setting's (bit-identical, or the largest
difference).
"""

import functools
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.bench import qp_problems
from wbc_jax.qp import QPSettings, fused, solve_qp
from wbc_jax.qp import kernel_iterate as iterate

DEFAULT_PARAMS, RELOADED = fused._compiler_params, iterate._operands
SETTINGS = (("reloaded", 2, 2), ("held", 2, 2), ("held", 4, 2), ("held", 8, 2), ("held", 16, 2), ("held", 32, 2),
            ("reloaded", 4, 2), ("reloaded", 8, 2), ("reloaded", 16, 2), ("reloaded", 2, 4), ("reloaded", 2, 8))
REP = 50  # solves per timed call


def held(st, Ki_ref, W_ref, Si_ref, dims):
    """The iterations kernel's operands, each loaded once per program and returned at every use."""
    load = lambda ref: ref[...]  # noqa: E731
    mats = [load(r) for r in (st.P, Ki_ref, st.Ae, st.Ai, st.db, W_ref, Si_ref, st.q, st.le, st.exe)]
    lo, hi, rho, free = ([load(r) for r in refs] for refs in (st.lo, st.hi, st.rho, st.free))
    const = lambda a: (lambda o: a)  # noqa: E731
    return iterate._Operands(*(const(m) for m in mats), lambda b, o: lo[b], lambda b, o: hi[b],
                             lambda b, o: rho[b], lambda b, o: free[b] > 0.5)


def chained(solve):
    """A jitted function of the QP data that solves it REP times in a chain, each solve's ``q`` moved by 1e-30
    times the previous solution (a data dependence, so the solves run one after another on the device)."""
    def chain(P, q, *rest):
        step = lambda x, _: (solve(P, q + 1e-30 * x[..., :1], *rest).x, None)  # noqa: E731
        return jax.lax.scan(step, solve(P, q, *rest).x, None, length=REP - 1)[0]
    return jax.jit(chain)


def main(batch: int, gpu_only: bool = True) -> None:
    if gpu_only and jax.default_backend() != "gpu":
        sys.exit("qp_kernel_warps.py: needs a GPU (on a CPU the kernels run in Pallas' interpreter, without warps)")
    data = [jnp.asarray(x) for x in qp_problems.transport_sized(batch)]
    print(f"{jax.devices()[0].device_kind}, {batch} problems", flush=True)
    for iters in (4, 16):
        s = QPSettings(iters=iters, max_iters=0, eps_abs=1e-4, eps_rel=1e-4, linsolve="inv", adapt_every=0, rho=3.0,
                       ruiz_iters=2, eq_rows=24, kernel="fused")
        reference = None
        for operands, warps, fwarps in SETTINGS:
            fused._compiler_params = lambda interpret, nw, fw, w=warps, f=fwarps: DEFAULT_PARAMS(interpret, w, f)
            iterate._operands = held if operands == "held" else RELOADED
            jax.clear_caches()  # the solver's jitted functions keep their first trace otherwise
            solve = functools.partial(solve_qp, settings=s)
            fn = chained(solve)
            x = np.asarray(jax.block_until_ready(jax.jit(solve)(*data)).x)
            times = []
            for _ in range(5):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*data))
                times.append((time.perf_counter() - t0) / REP)
            reference = x if reference is None else reference
            same = "bit-identical" if np.array_equal(x, reference) else f"max |dx| {np.abs(x - reference).max():.2e}"
            print(f"iters {iters:2d}  operands {operands:8s}  warps {warps:2d}  factorization {fwarps}: "
                  f"{1e3 * min(times):8.4f} ms per solve  {same}",
                  flush=True)
    fused._compiler_params, iterate._operands = DEFAULT_PARAMS, RELOADED


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 16384)
