"""Which half of OSQP's termination test fails, test by test, in the transport controller's solves under noise.

    python examples/qp_test_outcomes.py

The closed loop of ``examples/qp_settings_study.py`` (the paper campaign's first 1.5 s, 8 runs, its noise and
pushes) is recorded with the campaign's QP settings; each recorded problem is solved again from its recorded warm
start (the XLA path, as the CPU runs it; the iterations equal the recorded ones), with the extension's loop
counting, at each convergence test, whether the primal half (``||A x - z||``) and the dual half
(``||P x + q + A'y||``) hold. Where the primal half fails the dual half need not be computed: the printed share
is what a test that skips it would save. On a 2-core CPU: ~10 minutes, most of it compiling.
"""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

sys.path.insert(0, str(Path(__file__).parent))
from qp_settings_study import FIELDS, record, small_spec  # noqa: E402

from wbc_jax.qp import rules  # noqa: E402
from wbc_jax.qp.admm import _run, _start, _unscaled, row_kinds  # noqa: E402
from wbc_jax.qp.scaling import equilibrate, mv  # noqa: E402


def counted_solve(P, q, A, l, u, warm, s, iters):
    """``wbc_jax.qp.admm.solve_xla`` up to its extension, whose loop counts its tests: (iterations, (4,) int32:
    tests, primal half failing alone, dual half failing alone, both failing)."""
    P = 0.5 * (P + P.T)
    sp = equilibrate(P, q, A, l, u, s.ruiz_iters, s.unroll)
    free, eq, ex = row_kinds(sp, l, u, s)
    rho = rules.warm_rho(warm[3], s, P.dtype)
    st, w = _start(sp, warm, eq, free, ex, s, P.dtype)
    first = rules.first_block(warm, s, iters)
    st, rho, cont = _run(sp, st, rho, w, free, ex, s, iters, first)
    k0 = jnp.asarray(iters if first is None else first, jnp.int32)

    def body(c):
        st, k, count, _ = c
        un = _unscaled(P, q, A, sp, st, s)
        p_ok = rules.primal_test((mv(A, un.x),), (un.z,), s)[1]
        d_ok = rules.dual_test(mv(P, un.x), mv(A.T, un.y), q, s)[1]
        count = count + jnp.stack([True, ~p_ok & d_ok, p_ok & ~d_ok, ~p_ok & ~d_ok]).astype(jnp.int32)
        go = (k < s.max_iters) & ~un.converged & ~st.bad
        step = jnp.minimum(s.check_every, s.max_iters - k)
        st = jax.tree_util.tree_map(lambda a, b: jnp.where(go, a, b), cont(st, s.check_every, step), st)
        return st, jnp.where(go, k + step, k), count, go

    _, k, count, _ = lax.while_loop(lambda c: c[3], body, (st, k0, jnp.zeros(4, jnp.int32), jnp.asarray(True)))
    return k, count


def main():
    problems, qp = record(small_spec())
    print(f"{problems['q'].shape[0]} solves recorded; settings {qp}")

    def one(P, q, A, l, u, wx, wz, wy, wrho, wk):
        return counted_solve(P, q, A, l, u, (wx, wz, wy, wrho, wk, None), qp, qp.iters)

    args = [jnp.asarray(problems[f], jnp.float32) for f in FIELDS[:9]] + [jnp.asarray(problems["wk"], jnp.int32)]
    k, count = (np.asarray(v) for v in jax.jit(jax.vmap(one))(*args))
    tests, prim_only, dual_only, both = count.sum(0)
    print(f"iterations per solve {k.mean():.3f} (recorded {problems['k'].mean():.3f}, equal in "
          f"{np.mean(k == problems['k']):.4f} of solves)")
    print(f"tests {tests} ({tests / len(k):.3f} per solve): primal half failing alone {prim_only}, dual half alone "
          f"{dual_only}, both {both}, passing {tests - prim_only - dual_only - both}")
    skip = prim_only + both
    print(f"the dual half needed in none of the {skip} tests where the primal half fails: {skip / tests:.3f} of the "
          f"tests, {skip / max(prim_only + dual_only + both, 1):.3f} of the failing ones")


if __name__ == "__main__":
    main()
