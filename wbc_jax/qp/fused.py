"""One solve of the fused path as two Pallas (Triton) kernels, one program per problem each: the x-update's
factorization, then the ADMM iterations with the convergence-checked extension.

Why: the XLA path (``admm._step`` in ``lax.scan``, then the extension's ``lax.while_loop``) launches about ten kernels
per iteration and reads ``P``, ``A``, ``K^-1`` and the Schur factors from device memory at every one. Under ``vmap``
the extension's loop also runs every problem of the batch until the slowest has converged: the batch pays the
largest count of the step (a run's mean on the course is 21.6 iterations per step, its most 200). Here one program
per problem loads its matrices once, runs the ``iters`` iterations and the blocks of ``check_every`` more while its
own residuals are outside tolerance (up to ``max_iters``), and stops on its own. Measured (H100, course, Warp
physics): the paper campaign 171.0 s -> 133.2 s, physics + WBC at batch 16384 431,605 -> 530,978 env-steps/s
(docs/performance.md).

The rows come in three blocks, each stored only as large as it is (a program's matrices live in the registers of
one streaming multiprocessor, so their size sets how many problems run at once):

* the exact block: the first ``ne`` rows (``QPSettings.eq_rows``), ``Ae`` (ne, n), unmasked; the rows held exactly
  (``ex``) enter the x-update's KKT system through ``W = K^-1 Ae'`` and the Schur complement's inverse ``S^-1``;
* the dense block: the rows after them, ``Ai`` (mi, n);
* the box block: the last ``nb`` rows (``QPSettings.box_rows``), bounds on the last ``nb`` variables, stored as the
  diagonal ``db`` (n,) (zero on the other variables).

The factorization (:func:`_factor_kernel`) builds ``K`` from the blocks and inverts it in 2 x 2 blocks of the
variables' halves by Gauss-Jordan sweeps (:func:`sweep_inverse`), then ``W`` and ``S^-1``: one kernel where XLA
launched ~50 (Gram products, cuSOLVER's batched Cholesky, triangular solves, the Schur complement's Cholesky).

Measured on H100s (course, Warp physics; ``bench rollout`` physics + WBC, env-steps/s at batch 270 / 16384; each run
one call on one machine, the earlier variant re-measured in the same run):

* run 1: rows in one (128, 64) matrix, the exact rows again and a (32, 128) selection: 186,373 / 747,817; rows in
  blocks (the iterations kernel 6.31 -> 3.18 ms per control step at 16384, ``bench trace``): 199,088 / 904,777.
* run 2: blocks 201,582 / 903,970; factorization in Pallas, whole-tile sweeps, 8 warps: 212,198 / 889,724;
  factorization and iterations in one kernel, 8 warps: 212,612 / 907,895.
* run 3: blocks 200,846 / 906,038; whole-tile sweeps, 4 warps: 149,516 (the machine's first measurement) /
  1,003,361; one kernel, 4 warps: 214,204 / 899,189; **2 x 2 blocks, 4 warps (this): 219,705 / 1,058,577**.

The factorization kernel alone at 16384 problems: whole-tile sweeps 4.05 / 3.56 / 5.51 ms with 2 / 4 / 8 warps
(one warp: 21 ms, spilled), 2 x 2 blocks 4.02 / 2.94 / 4.83 ms; the iterations kernel, 20 iterations: 4.97 ms with
4 warps, 5.47 ms with 8, 9.5 ms with one.

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

from wbc_jax.qp.scaling import regularize_schur


class Block(NamedTuple):
    """One block of rows, each field ``(r,)`` for the block's ``r`` rows (in the kernel the box block's are laid out
    over the variables: its row i at variable ``n - nb + i``)."""

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


def sweep_inverse(T, count: int):
    """``T^-1`` of a symmetric positive definite ``T`` (N, N) by Gauss-Jordan elimination without pivoting, in the
    symmetric form of Beaton's sweep operator (each sweep reads one row, which is also the column).

    Only the first ``count`` indices are swept: the rest must be padding (identity rows and columns), whose entries
    of the result are then meaningless (the caller masks them). No pivoting is needed for a positive definite
    matrix (each pivot is a Schur complement's diagonal entry, > 0); the ADMM step's residual form corrects what
    rounding leaves. Plain ``jnp`` on register tiles (masked reductions instead of dynamic indexing), so it runs
    inside the Triton kernel and outside it (tests).
    """
    N = T.shape[0]
    ri = jax.lax.broadcasted_iota(jnp.int32, (N, N), 0)
    ci = jax.lax.broadcasted_iota(jnp.int32, (N, N), 1)
    vi = jax.lax.broadcasted_iota(jnp.int32, (N,), 0)

    def sweep(k, T):
        rk = jnp.sum(jnp.where(ri == k, T, 0.0), axis=0)  # row k = column k
        d = jnp.sum(jnp.where(vi == k, rk, 0.0))
        v = jnp.where(vi == k, -1.0, rk) / d
        return jnp.where(ri == k, v[None, :], jnp.where(ci == k, v[:, None], T - rk[:, None] * (rk[None, :] / d)))

    return -jax.lax.fori_loop(0, count, sweep, T)


def _dot(a, b, contract):  # full-precision matrix product (IEEE float32 on Triton, no TF32)
    return jax.lax.dot_general(a, b, (contract, ((), ())), precision=jax.lax.Precision.HIGHEST)


def _factor_kernel(P_ref, Ae_ref, Ai_ref, kd_ref, re_ref, ri_ref, exe_ref, Ki_ref, W_ref, Si_ref, *, n: int, ne: int):
    """``admm._kkt_factor`` with ``linsolve="inv"`` for one problem, in 2 x 2 blocks of the variables' halves.

    ``K = P + A' diag(rho) A + diag(kd)`` (the box rows and sigma in ``kd``; padded variables: identity) is inverted
    through its first half's inverse and the Schur complement of the second half (two sweeps of half the size: the
    sweeps are sequential, and a half-size tile's are cheaper), then ``W = K^-1 Ae_h'`` and ``S^-1``, ``S = Ae_h W``
    regularized as the XLA path does (:func:`wbc_jax.qp.scaling.regularize_schur`; ``Ae_h``: the held exact rows;
    ``S^-1`` zero on the others). ``K^-1`` is zero on padded variables.
    """
    N = P_ref.shape[0]
    H = N // 2
    s1, s2 = slice(0, H), slice(H, N)
    re, ri_, exe = re_ref[...], ri_ref[...], exe_ref[...]
    Ae1, Ae2, Ai1, Ai2 = Ae_ref[:, s1], Ae_ref[:, s2], Ai_ref[:, s1], Ai_ref[:, s2]
    r = jax.lax.broadcasted_iota(jnp.int32, (H, H), 0)
    c = jax.lax.broadcasted_iota(jnp.int32, (H, H), 1)

    def gram(Xa, Xb):  # Xa' diag(rho) Xb over the exact and the dense rows
        return _dot(Xa[0] * re[:, None], Xb[0], ((0,), (0,))) + _dot(Xa[1] * ri_[:, None], Xb[1], ((0,), (0,)))

    def sym(M, kd=None):
        M = 0.5 * (M + M.T)
        return M if kd is None else M + jnp.where(r == c, kd[None, :], 0.0)

    K11 = sym(P_ref[s1, s1] + gram((Ae1, Ai1), (Ae1, Ai1)), kd_ref[s1])
    K12 = P_ref[s1, s2] + gram((Ae1, Ai1), (Ae2, Ai2))
    K22 = sym(P_ref[s2, s2] + gram((Ae2, Ai2), (Ae2, Ai2)), kd_ref[s2])
    K11i = sweep_inverse(K11, min(n, H))
    X = _dot(K11i, K12, ((1,), (0,)))  # K11^-1 K12
    S2i = jnp.where((r < n - H) & (c < n - H), sweep_inverse(sym(K22 - _dot(K12, X, ((0,), (0,)))), n - H), 0.0)
    XS = _dot(X, S2i, ((1,), (0,)))
    Ki11 = jnp.where((r < n) & (c < n), K11i + _dot(XS, X, ((1,), (1,))), 0.0)
    Ki_ref[s1, s1] = Ki11
    Ki_ref[s1, s2] = -XS
    Ki_ref[s2, s1] = -XS.T
    Ki_ref[s2, s2] = S2i
    Ah1, Ah2 = Ae1 * exe[:, None], Ae2 * exe[:, None]
    W1 = _dot(Ki11, Ah1, ((1,), (1,))) - _dot(XS, Ah2, ((1,), (1,)))
    W2 = -_dot(XS, Ah1, ((0,), (1,))) + _dot(S2i, Ah2, ((1,), (1,)))
    W_ref[s1, :] = W1
    W_ref[s2, :] = W2
    S = regularize_schur(_dot(Ah1, W1, ((1,), (0,))) + _dot(Ah2, W2, ((1,), (0,))), exe > 0.5)
    Si_ref[...] = sweep_inverse(S, ne) * (exe[:, None] * exe[None, :])


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


@functools.partial(jax.jit, static_argnames=("sigma", "iters", "max_iters", "check_every", "alpha", "eps_abs",
                                             "eps_rel", "num_warps", "factor_warps"))
def fused_solve(P, Ae, Ai, db, q, ex_e, Dc, x, exact: Block, dense: Block, box: Block, *, sigma: float, iters: int,
                max_iters: int, check_every: int, alpha: float, eps_abs: float, eps_rel: float,
                num_warps: int = 4, factor_warps: int = 4) -> FusedOut:
    """The x-update's factorization (one kernel), then ``iters`` ADMM iterations of one scaled problem and blocks of
    ``check_every`` while unconverged (a second kernel).

    Args:
        P: (n, n) the scaled cost; Ae: (ne, n) the exact block's rows (unmasked); Ai: (mi, n) the dense block's rows;
            db: (nb,) the box block's diagonal (row i bounds variable ``n - nb + i``).
        q: (n,) scaled linear cost; ex_e: (ne,) bool, exact-block rows held exactly (their ``l == u``).
        Dc: (n,) ``1 / (c D)`` (column and cost scaling), for the convergence test.
        x: (n,) start. exact, dense, box: :class:`Block` of each (bounds finite, ``+-BIG``; ``rho`` 0 on held rows).
        sigma: the proximal term of ``K = P + sigma I + A' diag(rho) A``.
        iters / max_iters / check_every: as ``QPSettings`` (``max_iters <= iters``: no extension).
        alpha: over-relaxation. eps_abs, eps_rel: the test's tolerances.
        num_warps, factor_warps: Triton warps per program of the iteration and the factorization kernel.

    Returns:
        :class:`FusedOut`.
    """
    n, ne, mi, nb = P.shape[0], Ae.shape[0], Ai.shape[0], db.shape[0]
    N, NE, MI = _pow2(n), _pow2(ne), _pow2(mi)
    dt = P.dtype
    pn, pe, pi = (0, N - n), (0, NE - ne), (0, MI - mi)
    ex_f = jnp.pad(ex_e.astype(dt), pe)
    le = jnp.pad(jnp.where(ex_e, exact.l, 0.0), pe)
    P, Ae, Ai = jnp.pad(P, (pn, pn)), jnp.pad(Ae, (pe, pn)), jnp.pad(Ai, (pi, pn))
    db_p = jnp.pad(db, (n - nb, N - n))
    blocks = _padded_block(exact, NE) + _padded_block(dense, MI) + _padded_block(box, N, n - nb)
    rho_e, rho_i, rho_b = blocks[2], blocks[N_BLOCK + 2], blocks[2 * N_BLOCK + 2]
    kd = jnp.where(jnp.arange(N) < n, sigma + db_p * db_p * rho_b, 1.0)  # padded variables: identity
    interpret = jax.default_backend() == "cpu"
    params = fparams = None
    if not interpret:
        from jax.experimental.pallas import triton as plgpu

        params = plgpu.CompilerParams(num_warps=num_warps, num_stages=1)
        fparams = plgpu.CompilerParams(num_warps=factor_warps, num_stages=1)
    with jax.named_scope("qp_factor"):
        Ki, W, Si = pl.pallas_call(
            functools.partial(_factor_kernel, n=n, ne=ne), interpret=interpret, compiler_params=fparams,
            out_shape=[jax.ShapeDtypeStruct(s, dt) for s in ((N, N), (N, NE), (NE, NE))], name="admm_factor",
        )(P, Ae, Ai, kd, rho_e, rho_i, ex_f)
    args = [P, Ki, Ae, Ai, db_p, W, Si, jnp.pad(q, pn), le, ex_f, jnp.pad(Dc, pn, constant_values=1.0),
            jnp.pad(x, pn)] + blocks
    sizes = (N, NE, MI, N, NE, MI, N, NE, MI, N, N, 16)  # x, z (3 blocks), y (3), dy (3), dx, info
    kern = functools.partial(_kernel, iters=iters, max_iters=max_iters, check_every=check_every, alpha=alpha,
                             eps_abs=eps_abs, eps_rel=eps_rel)
    xo, ze, zi, zb, ye, yi, yb, dye, dyi, dyb, dxo, info = pl.pallas_call(
        kern, out_shape=[jax.ShapeDtypeStruct((s,), dt) for s in sizes], interpret=interpret, compiler_params=params,
        name="admm_iterations")(*args)
    rows = lambda e, i, b: jnp.concatenate([e[:ne], i[:mi], b[n - nb:n]])  # noqa: E731
    return FusedOut(xo[:n], rows(ze, zi, zb), rows(ye, yi, yb), dxo[:n], rows(dye, dyi, dyb), info[0] > 0,
                    info[1].astype(jnp.int32))
