"""The iterations kernel's loop, variant by variant, on the campaign's own noisy QPs (a GPU timing study).

    python examples/qp_kernel_loop_variants.py FILE.npz [BATCH] [VARIANT ...]

FILE.npz from ``python examples/qp_kernel_noisy.py --record FILE.npz`` (the course's recorded control-step QPs
with their warm starts), repeated to BATCH (default 16384) and solved by the fused kernels under the campaign's
settings, with :func:`wbc_jax.qp.kernel_iterate._iterations` (and its helpers) replaced per variant:

* ``one_loop``: the solver (the fixed steps the first block of the tested blocks' loop);
* ``two_loops``: the fixed steps in a loop of their own before the blocks' (the solver before; bit for bit);
* ``test_every_step``: one loop of single steps, each step also testing its input iterate from its own products
  (``A'y`` and ``A' rho (Ax - z)`` apart) and stopping there once past the fixed steps;
* ``test_step``: blocks whose last pass is a test: the step's products with rho's term dropped give
  ``P x + q + A'y``, the test runs under a ``cond`` and the pass's update is discarded (bit for bit);
* ``primal_test``: the tested blocks with the primal half of OSQP's test only (not OSQP's test; timing only);
* ``no_projection``: the blocks without the projection onto the exact rows at their start (timing only).

Prints the best of 7 calls after the compile, the mean ADMM iterations, and whether each variant's solution is
the first variant's bit for bit. Variants are monkeypatches of the kernel's Python: study code, not the solver.
"""

import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.qp import QPResult, QPSettings, rules, solve_qp
from wbc_jax.qp import kernel_iterate as ki

FIELDS = ("P", "q", "A", "l", "u", "wx", "wz", "wy", "wrho")
ORIGINAL = {name: getattr(ki, name) for name in ("_iterations", "_block_start", "_termination")}


def _start(pg, st):
    """The stage's start ``(x0, z0, y0)`` with the certificates' deltas zeroed (as the solver)."""
    x0 = st.x[...]
    z0, y0 = [r[...] for r in st.z], [r[...] for r in st.y]
    ki.write_vec(pg.out.x, jnp.zeros_like(x0), pg.dims.n)
    ki.write_rows(pg.out.y, pg.dims, [jnp.zeros_like(v) for v in y0])
    pg.sync()
    return x0, z0, y0


def two_loops(pg, st, iters, max_iters, check_every):
    x0, z0, y0 = _start(pg, st)
    step = lambda _, c: ki._step(pg, c)  # noqa: E731
    c = jax.lax.fori_loop(0, iters, step, ki._block_start(pg.ops, x0, (z0, y0, jnp.zeros((), x0.dtype))))

    def unconverged(w):
        k, (x, ax, z, y, bad) = w
        return (k < max_iters) & (bad == 0.0) & jnp.logical_not(ki._termination(pg, x, ax, z, y)[2])

    def block(w):
        k, c = w
        n = jnp.minimum(check_every, max_iters - k)
        return k + n, jax.lax.fori_loop(0, n, step, ki._block_start(pg.ops, c[0], c[2:]))

    return jax.lax.while_loop(unconverged, block, (jnp.int32(iters), c))


def _tested_step(pg, c, drop_rho, test_now, zero):
    """One step from the carry with OSQP's test of the carry: ``(x, ax, z, y, ok, dnu)`` of the step and the test
    (int32). ``drop_rho`` (() float 0/1): rho's term left out of the step's ``A'`` product (a test pass); with
    ``test_now`` None the test always runs (from ``A'y`` and ``A' rho (Ax - z)`` computed apart), else under a
    ``cond`` on it (``zero`` its other branch's value)."""
    ops, alpha = pg.ops, pg.s.alpha
    x, ax, z, y, bad = c
    o = (bad > 2.0).astype(jnp.int32)
    px, q = ki.matvec(ops.P(o), x), ops.q(o)
    v = [ops.rho(b, o) * (ax[b] - z[b]) for b in range(3)]
    if test_now is None:
        aty = ki._rows_t(ops, y, o)
        r = px + q + aty + ki._rows_t(ops, v, o)
    else:
        aty = ki._rows_t(ops, [y[b] + (1.0 - drop_rho) * v[b] for b in range(3)], o)
        r = px + q + aty

    def test(a):
        px, aty, q, ax, z = a[:5]
        return rules.termination([u * e for u, e in zip(ax, pg.Ei)], [u * e for u, e in zip(z, pg.Ei)], px * pg.Dc,
                                 aty * pg.Dc, q * pg.Dc, pg.s)[2].astype(jnp.int32)

    args = (px, aty, q, ax, z, zero)
    conv = test(args) if test_now is None else jax.lax.cond(test_now, test, lambda a: a[5], args)
    t = ki.matvec(ops.Ki(o), r)
    exe_ = ops.exe(o)
    dnu = -ki.matvec(ops.Si(o), exe_ * (ops.le(o) - ax[0]) + exe_ * ki.matvec(ops.Ae(o), t))
    xt = x - t - ki.matvec(ops.W(o), dnu)
    zt = ki._rows(ops, xt, o)
    axn, zn, yn = [], [], []
    for b in range(3):
        axn.append(alpha * zt[b] + (1.0 - alpha) * ax[b])
        zr = alpha * zt[b] + (1.0 - alpha) * z[b]
        rb = ops.rho(b, o)
        zb = jnp.minimum(jnp.maximum(zr + y[b] / jnp.where(rb > 0.0, rb, 1.0), ops.lo(b, o)), ops.hi(b, o))
        zn.append(jnp.where(ops.free(b, o), axn[b], zb))
        yn.append(jnp.where(ops.free(b, o), 0.0, y[b] + rb * (zr - zb)))
    yn[0] = yn[0] + exe_ * dnu
    xn = alpha * xt + (1.0 - alpha) * x
    return (xn, axn, zn, yn, ki.is_finite(xn, dnu)), conv


def _take(pg, c, new, take, fin):
    """The carry after a step: ``new`` where ``take``, the deltas written; ``bad`` set where not ``fin``."""
    x, ax, z, y, bad = c
    xn, axn, zn, yn, _ = new
    ki.write_vec(pg.out.x, xn - x, pg.dims.n, take)
    ki.write_rows(pg.out.y, pg.dims, [a - b for a, b in zip(yn, y)], take)
    keep = lambda n, o: [jnp.where(take, a, b) for a, b in zip(n, o)]  # noqa: E731
    return jnp.where(take, xn, x), keep(axn, ax), keep(zn, z), keep(yn, y), jnp.where(fin, bad, 1.0)


def test_every_step(pg, st, iters, max_iters, check_every):
    x0, z0, y0 = _start(pg, st)

    def body(w):
        k, c, _ = w
        restart = (k >= iters) & ((k - iters) % check_every == 0) & (k > 0)
        c = jax.lax.cond(restart, lambda c: ki._block_start(pg.ops, c[0], c[2:]), lambda c: c, c)
        new, conv = _tested_step(pg, c, 0.0, None, None)
        done = (conv > 0) & (k >= iters)
        c = _take(pg, c, new, new[4] & jnp.logical_not(done), new[4] | done)
        return jnp.where(done, k, k + 1), c, done.astype(jnp.int32)

    c = ki._block_start(pg.ops, x0, (z0, y0, jnp.zeros((), x0.dtype)))
    k, c, _ = jax.lax.while_loop(lambda w: (w[0] < max_iters) & (w[1][4] == 0.0) & (w[2] == 0), body,
                                 (jnp.int32(0), c, jnp.int32(0)))
    return k, c


def test_step(pg, st, iters, max_iters, check_every):
    x0, z0, y0 = _start(pg, st)

    def block(w):
        k, c, _ = w
        n = jnp.where(k == 0, iters, jnp.minimum(check_every, max_iters - k))

        def body(j, cc):
            c, conv = cc
            last = j == n
            new, conv = _tested_step(pg, c, last.astype(x0.dtype), last, conv)
            return _take(pg, c, new, new[4] & jnp.logical_not(last), new[4] | last), conv

        c, conv = jax.lax.fori_loop(0, n + 1, body, (ki._block_start(pg.ops, c[0], c[2:]), jnp.int32(0)))
        return k + n, c, conv

    c = (x0, [jnp.zeros_like(v) for v in z0], z0, y0, jnp.zeros((), x0.dtype))
    k, c, _ = jax.lax.while_loop(lambda w: (w[0] < max_iters) & (w[1][4] == 0.0) & (w[2] == 0), block,
                                 (jnp.int32(0), c, jnp.int32(0)))
    return k, c


def primal_only(pg, x, ax, z, y):
    axu, zu = [a * e for a, e in zip(ax, pg.Ei)], [a * e for a, e in zip(z, pg.Ei)]
    prim = rules.amax(*(a - b for a, b in zip(axu, zu)))
    return prim, prim, prim <= pg.s.eps_abs + pg.s.eps_rel * jnp.maximum(rules.amax(*axu), rules.amax(*zu))


VARIANTS = {
    "one_loop": {},
    "two_loops": {"_iterations": two_loops},
    "test_every_step": {"_iterations": test_every_step},
    "test_step": {"_iterations": test_step},
    "primal_test": {"_termination": primal_only},
    "no_projection": {"_block_start": lambda ops, x, c: (x, ki._rows(ops, x)) + tuple(c)},
}


def main(path: str, batch: int, names: list[str]) -> None:
    if jax.default_backend() != "gpu":
        sys.exit("qp_kernel_loop_variants.py: timing needs a GPU (on a CPU the kernels run in Pallas' interpreter)")
    f = np.load(path)
    s = QPSettings(**{**json.loads(str(f["settings"])), "linsolve": "inv", "kernel": "fused"})
    data = [jnp.asarray(np.concatenate([f[k]] * -(-batch // len(f["P"])))[:batch]) for k in FIELDS]
    print(f"{jax.devices()[0].device_kind}, {batch} problems", flush=True)

    def solve(P, q, A, l, u, wx, wz, wy, wrho):
        return solve_qp(P, q, A, l, u, warm=QPResult(wx, wy, wz, 0.0, 0.0, 0, 0, wrho), settings=s)

    first = None
    try:
        for name in names or list(VARIANTS):
            for key, fn in {**ORIGINAL, **VARIANTS[name]}.items():
                setattr(ki, key, fn)
            jax.clear_caches()  # the solver's jitted functions keep their first trace otherwise
            fn = jax.jit(solve)
            out = jax.block_until_ready(fn(*data))
            times = []
            for _ in range(7):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*data))
                times.append(time.perf_counter() - t0)
            first = out if first is None else first
            same = all(np.array_equal(np.asarray(getattr(out, k)), np.asarray(getattr(first, k)))
                       for k in ("x", "y", "z", "iters"))
            print(f"{name:16s} {1e3 * min(times):8.3f} ms  iterations mean {float(np.mean(out.iters)):6.2f}  "
                  f"flagged {int(np.sum(np.asarray(out.flag) != 0))}  {'bit for bit' if same else 'differs'}",
                  flush=True)
    finally:
        for key, fn in ORIGINAL.items():
            setattr(ki, key, fn)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 16384, sys.argv[3:])
