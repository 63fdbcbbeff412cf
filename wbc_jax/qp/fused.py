"""The ADMM iterations of one solve, its convergence-checked extension included, as one Pallas (Triton) kernel.

Why: the XLA path (``admm._step`` in ``lax.scan``, then the extension's ``lax.while_loop``) launches about ten kernels
per iteration and reads ``P``, ``A``, ``K^-1`` and the Schur factors from device memory at every one. Under ``vmap``
the extension's loop also runs every problem of the batch until the slowest has converged: the batch pays the
largest count of the step (a run's mean on the course is 21.6 iterations per step, its most 200). Here one program
per problem loads its matrices once, runs the ``iters`` iterations and the blocks of ``check_every`` more while its
own residuals are outside tolerance (up to ``max_iters``), and stops on its own. Measured (H100, course, Warp
physics): the paper campaign 171.0 s -> 133.2 s, physics + WBC at batch 16384 431,605 -> 530,978 env-steps/s
(docs/performance.md).

The rows come in three blocks, each stored only as large as it is (a program's matrices live in the registers of
one streaming multiprocessor, so their size sets how many problems run at once: ``num_warps`` 2, 4, 8, 16 timed the
same, which is what a register-bound kernel does):

* the exact block: the first ``ne`` rows (``QPSettings.eq_rows``), ``Ae`` (ne, n), unmasked; the rows held exactly
  (``ex``) enter the x-update's KKT system through ``W = K^-1 Ae'`` and the Schur complement's inverse ``S^-1``;
* the dense block: the rows after them, ``Ai`` (mi, n);
* the box block: the last ``nb`` rows (``QPSettings.box_rows``), bounds on the last ``nb`` variables, stored as the
  diagonal ``db`` (n,) (zero on the other variables).

Measured (H100, course, Warp physics, batch 16384, ``bench trace``): the kernel 6.31 ms -> 3.18 ms per control step
against all rows in one (128, 64) matrix with the exact rows again in their own and a (32, 128) selection matrix
(transport: 24 exact, 22 dense, 32 box rows; 56 variables); ``bench rollout``, physics + WBC, one run: 747,817 ->
904,777 env-steps/s at 16384, 186,373 -> 199,088 at 270.

Every row follows the same ADMM update whatever its block (an exact-block row that is not held is an ordinary ADMM
row), so the blocks are a partition of the storage, not of the algorithm. The arithmetic is ``admm._step``'s with
``linsolve="inv"`` (explicit inverses ``K^-1`` and ``S^-1``, matrix-vector products only) and the projection onto
the exact rows at the start of each block of iterations, as ``admm._run`` does; the convergence test is OSQP's in
the user's units (``admm._unscaled``), evaluated from the scaled iterate with the scalings
(``A x - z = E^-1 (A_s x_s - z_s)``, ``P x + q + A'y = c^-1 D^-1 (P_s x_s + q_s + A_s' y_s)``). Results equal the
XLA path up to float rounding (tests compare them in the Pallas interpreter, float64).

Shapes are padded to powers of two (Triton's rule, at least 16): padded variables have zero rows and columns in
every matrix, padded rows are ``0 <= 0 <= 0`` with zero rho and dual, padded exact rows have zero ``S^-1``.
``vmap`` adds a grid axis (one program per problem). On a CPU the kernel runs in Pallas' interpreter (slow; tests
only); the solver uses it where ``QPSettings.kernel`` says so (``"auto"``: on a GPU).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl


class Block(NamedTuple):
    """One block of rows (shapes ``(r,)``; the box block's are over the variables, ``(n,)``)."""

    l: jax.Array  # lower bounds (finite: +-BIG)
    u: jax.Array  # upper bounds
    rho: jax.Array  # per-row rho (0: exact rows, padding)
    free: jax.Array  # bool, no bounds: z = A x, y = 0
    Ei: jax.Array  # 1 / row scaling, for the convergence test
    z: jax.Array  # start
    y: jax.Array  # start


class FusedOut(NamedTuple):
    """The kernel's result for one problem (scaled problem); z, y, dy in the row order ``(exact, dense, box)``."""

    x: jax.Array  # (n,)
    z: jax.Array  # (m,)
    y: jax.Array  # (m,)
    dx: jax.Array  # (n,) last accepted step in x
    dy: jax.Array  # (m,) last accepted step in y
    bad: jax.Array  # () bool, a non-finite step was rejected
    iters: jax.Array  # () int32, iterations run


def _pow2(k: int) -> int:
    return 1 << max(4, (k - 1).bit_length())


def _mv(M, v):  # M v, full float32 (elementwise products and sums: no TF32)
    return jnp.sum(M * v[None, :], axis=1)


def _mtv(M, v):  # M' v
    return jnp.sum(M * v[:, None], axis=0)


def _amax(v):
    return jnp.max(jnp.abs(v))


def _finite(*vs):  # () bool, every entry finite (Triton-friendly: x - x is 0 only for finite x)
    tot = sum(jnp.sum(v) for v in vs)
    return (tot - tot) == 0.0


N_BLOCK = len(Block._fields)


def _kernel(P_ref, Ki_ref, Ae_ref, Ai_ref, db_ref, W_ref, Si_ref, q_ref, le_ref, exe_ref, Dc_ref, x_ref, *refs,
            iters: int, max_iters: int, check_every: int, alpha: float, eps_abs: float, eps_rel: float):
    blk_refs = [refs[i * N_BLOCK:(i + 1) * N_BLOCK] for i in range(3)]  # exact, dense, box: Block's fields
    xo_ref, *out_refs = refs[3 * N_BLOCK:]
    P, Ki, Ae, Ai, db, W, Si = (r[...] for r in (P_ref, Ki_ref, Ae_ref, Ai_ref, db_ref, W_ref, Si_ref))
    q, le, exe, Dc = q_ref[...], le_ref[...], exe_ref[...], Dc_ref[...]
    lo, hi, rho, free, Ei, z0, y0 = ([r[...] for r in field] for field in zip(*blk_refs))  # each: 3 blocks
    free = [f > 0.5 for f in free]
    rdiv = [jnp.where(r > 0.0, r, 1.0) for r in rho]  # z's step y / rho; exact rows and padding: y / 1 (l == u)

    def rows(x):  # A x per block
        return [_mv(Ae, x), _mv(Ai, x), db * x]

    def rows_t(v):  # A' v from the blocks' v
        return _mtv(Ae, v[0]) + _mtv(Ai, v[1]) + db * v[2]

    def project(x):  # admm._project
        xn = x + _mv(W, _mv(Si, exe * (le - _mv(Ae, x))))
        return jnp.where(_finite(xn), xn, x)

    def step(_, c):  # admm._step, linsolve "inv"
        x, z, y, dx, dy, bad = c
        ax = rows(x)
        r = _mv(P, x) + q + rows_t([y[b] + rho[b] * (ax[b] - z[b]) for b in range(3)])
        t = _mv(Ki, r)
        dnu = -_mv(Si, exe * (le - ax[0]) + exe * _mv(Ae, t))
        xt = x - t - _mv(W, dnu)
        zt = rows(xt)
        xn = alpha * xt + (1.0 - alpha) * x
        zn, yn = [], []
        for b in range(3):
            zr = alpha * zt[b] + (1.0 - alpha) * z[b]
            zb = jnp.minimum(jnp.maximum(zr + y[b] / rdiv[b], lo[b]), hi[b])
            yb = y[b] + rho[b] * (zr - zb)
            zn.append(jnp.where(free[b], alpha * zt[b] + (1.0 - alpha) * ax[b], zb))
            yn.append(jnp.where(free[b], 0.0, yb))
        yn[0] = yn[0] + exe * dnu
        ok = _finite(xn, *zn, *yn)
        keep = lambda new, old: [jnp.where(ok, a, b) for a, b in zip(new, old)]  # noqa: E731
        return (jnp.where(ok, xn, x), keep(zn, z), keep(yn, y), jnp.where(ok, xn - x, dx),
                keep([a - b for a, b in zip(yn, y)], dy), jnp.where(ok, bad, 1.0))

    def converged(x, z, y):  # admm._unscaled's test, from the scaled iterate
        ax, px, aty = rows(x), _mv(P, x), rows_t(y)
        prim = functools.reduce(jnp.maximum, [_amax((ax[b] - z[b]) * Ei[b]) for b in range(3)])
        a_max = functools.reduce(jnp.maximum, [_amax(ax[b] * Ei[b]) for b in range(3)])
        z_max = functools.reduce(jnp.maximum, [_amax(z[b] * Ei[b]) for b in range(3)])
        prim_tol = eps_abs + eps_rel * jnp.maximum(a_max, z_max)
        dual = _amax((px + q + aty) * Dc)
        dual_tol = eps_abs + eps_rel * jnp.maximum(jnp.maximum(_amax(px * Dc), _amax(aty * Dc)), _amax(q * Dc))
        return (prim <= prim_tol) & (dual <= dual_tol)

    x0 = x_ref[...]
    c = (project(x0), z0, y0, jnp.zeros_like(x0), [jnp.zeros_like(v) for v in y0], jnp.zeros((), x0.dtype))
    c = jax.lax.fori_loop(0, iters, step, c)
    k = jnp.int32(iters)
    if max_iters > iters:
        def unconverged(w):
            k, c = w
            x, z, y, _, _, bad = c
            return (k < max_iters) & (bad == 0.0) & jnp.logical_not(converged(x, z, y))

        def block(w):
            k, c = w
            active = jnp.minimum(check_every, max_iters - k)
            c = (project(c[0]),) + tuple(c[1:])
            return k + active, jax.lax.fori_loop(0, active, step, c)

        k, c = jax.lax.while_loop(unconverged, block, (k, c))
    x, z, y, dx, dy, bad = c
    xo_ref[...] = x
    dxo_ref, info_ref = out_refs[9], out_refs[10]
    dxo_ref[...] = dx
    for b in range(3):
        out_refs[b][...] = z[b]
        out_refs[3 + b][...] = y[b]
        out_refs[6 + b][...] = dy[b]
    i = jax.lax.broadcasted_iota(jnp.int32, info_ref.shape, 0)
    info_ref[...] = jnp.where(i == 0, bad, jnp.where(i == 1, k.astype(x.dtype), 0.0)).astype(info_ref.dtype)


def _padded_block(b: Block, size: int, front: int = 0) -> list:
    """The block's fields as kernel inputs of length ``size`` (``front`` zeros first: the box block's place among the
    variables); padding is ``0 <= 0 <= 0`` with zero rho, not free, row scaling 1."""
    dt = b.l.dtype
    pad = lambda v, c=0.0: jnp.pad(v.astype(dt), (front, size - front - v.shape[0]), constant_values=c)  # noqa: E731
    return [pad(b.l), pad(b.u), pad(b.rho), pad(b.free), pad(b.Ei, 1.0), pad(b.z), pad(b.y)]


@functools.partial(jax.jit, static_argnames=("iters", "max_iters", "check_every", "alpha", "eps_abs", "eps_rel",
                                             "num_warps"))
def fused_iterations(P, Kinv, Ae, Ai, db, W, Sinv, q, ex_e, Dc, x, exact: Block, dense: Block, box: Block, *,
                     iters: int, max_iters: int, check_every: int, alpha: float, eps_abs: float, eps_rel: float,
                     num_warps: int = 8) -> FusedOut:
    """``iters`` ADMM iterations of one scaled problem, then blocks of ``check_every`` while unconverged.

    Args:
        P: (n, n) the scaled cost; Kinv: (n, n) inverse of ``P + sigma I + A' diag(rho) A``.
        Ae: (ne, n) the exact block's rows (unmasked); Ai: (mi, n) the dense block's rows; db: (nb,) the box block's
            diagonal (row i bounds variable ``n - nb + i``).
        W: (n, ne) ``Kinv Ae_h'`` and Sinv: (ne, ne) the inverse of the Schur complement ``Ae_h W`` (``admm.KKT``,
            ``Ae_h`` the held rows of ``Ae``; identity on rows not held).
        q: (n,) scaled linear cost; ex_e: (ne,) bool, exact-block rows held exactly (their ``l == u``).
        Dc: (n,) ``1 / (c D)`` (column and cost scaling), for the convergence test.
        x: (n,) start. exact, dense, box: :class:`Block` of each (bounds finite, ``+-BIG``; ``rho`` 0 on held rows).
        iters / max_iters / check_every: as ``QPSettings`` (``max_iters <= iters``: no extension).
        alpha: over-relaxation. eps_abs, eps_rel: the test's tolerances. num_warps: Triton warps per program.

    Returns:
        :class:`FusedOut`.
    """
    n, ne, mi, nb = P.shape[0], Ae.shape[0], Ai.shape[0], db.shape[0]
    N, NE, MI = _pow2(n), _pow2(ne), _pow2(mi)
    dt = P.dtype
    pn, pe, pi = (0, N - n), (0, NE - ne), (0, MI - mi)
    ex_f = ex_e.astype(dt)
    le = jnp.where(ex_e, exact.l, 0.0)
    args = [jnp.pad(P, (pn, pn)), jnp.pad(Kinv, (pn, pn)), jnp.pad(Ae, (pe, pn)), jnp.pad(Ai, (pi, pn)),
            jnp.pad(db, (n - nb, N - n)), jnp.pad(W, (pn, pe)), jnp.pad(Sinv * (ex_f[:, None] * ex_f[None, :]), (pe, pe)),
            jnp.pad(q, pn), jnp.pad(le, pe), jnp.pad(ex_f, pe), jnp.pad(Dc, pn, constant_values=1.0), jnp.pad(x, pn)]
    args += _padded_block(exact, NE) + _padded_block(dense, MI) + _padded_block(box, N, n - nb)
    sizes = (N, NE, MI, N, NE, MI, N, NE, MI, N, N, 16)  # x, z (3 blocks), y (3), dy (3), dx, info
    shapes = [jax.ShapeDtypeStruct((s,), dt) for s in sizes]
    interpret = jax.default_backend() == "cpu"
    params = None
    if not interpret:
        from jax.experimental.pallas import triton as plgpu

        params = plgpu.CompilerParams(num_warps=num_warps, num_stages=1)
    kern = functools.partial(_kernel, iters=iters, max_iters=max_iters, check_every=check_every, alpha=alpha,
                             eps_abs=eps_abs, eps_rel=eps_rel)
    xo, ze, zi, zb, ye, yi, yb, dye, dyi, dyb, dxo, info = pl.pallas_call(
        kern, out_shape=shapes, interpret=interpret, compiler_params=params, name="admm_iterations")(*args)
    rows = lambda e, i, b: jnp.concatenate([e[:ne], i[:mi], b[n - nb:n]])  # noqa: E731
    return FusedOut(xo[:n], rows(ze, zi, zb), rows(ye, yi, yb), dxo[:n], rows(dye, dyi, dyb), info[0] > 0,
                    info[1].astype(jnp.int32))
