"""The fused QP solver's iterations kernel against the bytes it loads: a GPU study (docs/performance.md, open limits).

    python examples/qp_kernel_bytes.py [BATCH]          (default 16384; needs a GPU)

Solves BATCH generic QPs of the transport QP's size (56 variables, 24 equality and 54 inequality rows; 64 problems
repeated) with 4, 16 and 32 fixed ADMM iterations and converged (4, then blocks of 4 up to 200), each with the
iterations kernel's six matrices (the stage's ``P``, ``Ae``, ``Ai`` and the factors ``K^-1``, ``W``, ``S^-1``)

* ``padded``: read as whole padded tiles (powers of two, zero padding);
* ``real``: read at their real sizes (the solver: masked loads, the padding never loaded);
* ``float16``: read at their real sizes after a cast to float16 before the kernel (half the bytes again; the
  arithmetic stays float32, the solution differs: a timing study only).

Prints the best of 7 calls after the compile and whether ``real`` solves bit for bit as ``padded``. The difference
between the 32- and 16-iteration times over 16 is one iteration's cost.
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

PALLAS_CALL, OPERANDS = fused.pl.pallas_call, iterate._operands
MATRICES = ("P", "Ki", "Ae", "Ai", "W", "Si")
VARIANT = {"name": "real"}


def operands(st, Ki_ref, W_ref, Si_ref, dims):
    """The kernel's operands; with ``padded`` the six matrices loaded as whole tiles."""
    ops = OPERANDS(st, Ki_ref, W_ref, Si_ref, dims)
    if VARIANT["name"] != "padded":
        return ops
    refs = (st.P, Ki_ref, st.Ae, st.Ai, W_ref, Si_ref)
    return ops._replace(**{k: functools.partial(iterate._at, r) for k, r in zip(MATRICES, refs)})


def pallas_call(kernel, *args, **kwargs):
    """``pl.pallas_call``; with ``float16`` the iterations kernel's call casts its six matrices first."""
    call = PALLAS_CALL(kernel, *args, **kwargs)
    if kwargs.get("name") != "admm_iterations":
        return call
    n_stage = kernel.keywords["treedef"].num_leaves  # the stage's leaves (P, Ae, Ai first), then Ki, W, Si

    def run(*args):
        args = list(args)
        if VARIANT["name"] == "float16":
            for i in (0, 1, 2, n_stage, n_stage + 1, n_stage + 2):
                args[i] = args[i].astype(jnp.float16)
        return call(*args)
    return run


def main(batch: int) -> None:
    if jax.default_backend() != "gpu":
        sys.exit("qp_kernel_bytes.py: needs a GPU (on a CPU the kernels run in Pallas' interpreter)")
    data = [jnp.asarray(x) for x in qp_problems.transport_sized(batch)]
    print(f"{jax.devices()[0].device_kind}, {batch} problems", flush=True)
    fused.pl.pallas_call, iterate._operands = pallas_call, operands
    try:
        for iters, max_iters in ((4, 0), (16, 0), (32, 0), (4, 200)):
            s = QPSettings(iters=iters, max_iters=max_iters, eps_abs=1e-4, eps_rel=1e-4, linsolve="inv",
                           adapt_every=0, rho=3.0, ruiz_iters=2, eq_rows=24, kernel="fused")
            out = {}
            for name in ("padded", "real", "float16"):
                VARIANT["name"] = name
                jax.clear_caches()  # the solver's jitted functions keep their first trace otherwise
                fn = jax.jit(functools.partial(solve_qp, settings=s))
                out[name] = jax.block_until_ready(fn(*data))
                times = []
                for _ in range(7):
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(*data))
                    times.append(time.perf_counter() - t0)
                mean_iters = float(np.mean(np.asarray(out[name].iters)))
                print(f"iters {iters:2d} (cap {max_iters:3d})  {name:8s}: {1e3 * min(times):8.3f} ms  "
                      f"{mean_iters:.2f} iterations on average", flush=True)
            same = all(np.array_equal(np.asarray(getattr(out["padded"], k)), np.asarray(getattr(out["real"], k)))
                       for k in ("x", "y", "z", "iters", "flag"))
            print(f"  real against padded: {'bit for bit' if same else 'DIFFERENT'}", flush=True)
    finally:
        fused.pl.pallas_call, iterate._operands = PALLAS_CALL, OPERANDS


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 16384)
