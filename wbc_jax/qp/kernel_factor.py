"""The fused path's second Pallas kernel: the x-update's factorization of one problem, as explicit inverses.

``K = P + Ae' diag(re) Ae + Ai' diag(ri) Ai + diag(kd)`` (the box rows and sigma in ``kd``; padded variables:
identity) is inverted in 2 x 2 blocks of the variables' halves through the first half's inverse and the second
half's Schur complement, each by Gauss-Jordan sweeps (:func:`sweep_inverse`); then ``W = K^-1 Ae_h'`` and the
inverse of ``S = Ae_h W`` (``Ae_h``: the exact rows held), regularized as the XLA path does
(:func:`wbc_jax.qp.scaling.regularize_schur`). The result equals the XLA path's ``linsolve="inv"`` factors up to
rounding (:func:`wbc_jax.qp.admm._kkt_factor`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from wbc_jax.qp.kernel_layout import CK, dot, entry, read_vec
from wbc_jax.qp.scaling import regularize_schur


def sweep_inverse(T, count: int):
    """``T^-1`` of a symmetric positive definite ``T`` (N, N) by Gauss-Jordan elimination without pivoting, in the
    symmetric form of Beaton's sweep operator, two indices per sweep (each sweep reads two rows, which are also the
    columns, and inverts their 2 x 2 pivot block; an odd count ends with one single-index sweep).

    Only the first ``count`` indices are swept: the rest must be padding (identity rows and columns), whose entries
    of the result are then meaningless (the caller masks them). No pivoting is needed for a positive definite
    matrix (each pivot block is a Schur complement's diagonal block, positive definite); the ADMM step's residual
    form corrects what rounding leaves. Plain ``jnp`` on register tiles (masked reductions instead of dynamic
    indexing), so it runs inside the Triton kernel and outside it (tests).
    """
    N = T.shape[0]
    ri = jax.lax.broadcasted_iota(jnp.int32, (N, N), 0)
    ci = jax.lax.broadcasted_iota(jnp.int32, (N, N), 1)
    vi = jax.lax.broadcasted_iota(jnp.int32, (N,), 0)

    def row(T, k):  # row k = column k
        return jnp.sum(jnp.where(ri == k, T, 0.0), axis=0)

    def entry(v, k):
        return jnp.sum(jnp.where(vi == k, v, 0.0))

    def single(k, T):  # T_kk = d: T_k. -> T_k. / d, T_kk -> -1 / d, T_ij -> T_ij - T_ik T_kj / d
        rk = row(T, k)
        v = jnp.where(vi == k, -1.0, rk) / entry(rk, k)
        return jnp.where(ri == k, v[None, :], jnp.where(ci == k, v[:, None], T - rk[:, None] * v[None, :]))

    def pair(j, T):  # B = (k, k + 1), T_BB = [[a, b], [b, c]]: T_B. -> T_BB^-1 T_B., T_BB -> -T_BB^-1
        k = 2 * j
        r1, r2 = row(T, k), row(T, k + 1)
        a, b, c = entry(r1, k), entry(r1, k + 1), entry(r2, k + 1)
        idet = 1.0 / (a * c - b * b)
        p1 = jnp.where(vi == k, -1.0, jnp.where(vi == k + 1, 0.0, r1))  # the rows with -I in place of T_BB
        p2 = jnp.where(vi == k + 1, -1.0, jnp.where(vi == k, 0.0, r2))
        v1, v2 = (c * p1 - b * p2) * idet, (a * p2 - b * p1) * idet
        rest = T - r1[:, None] * v1[None, :] - r2[:, None] * v2[None, :]
        return jnp.where(ri == k, v1[None, :], jnp.where(ri == k + 1, v2[None, :], jnp.where(
            ci == k, v1[:, None], jnp.where(ci == k + 1, v2[:, None], rest))))

    T = jax.lax.fori_loop(0, count // 2, pair, T)
    return -(single(count - 1, T) if count % 2 else T)


def _chunked(count: int, body, acc):
    """``acc`` plus the sum of ``body(k)`` over the chunks ``k`` (slices of ``CK`` indices) of ``range(count)``."""
    ck = min(CK, count)
    return jax.lax.fori_loop(0, count // ck, lambda j, a: jax.tree_util.tree_map(
        jnp.add, a, body(pl.ds(pl.multiple_of(j * ck, ck), ck))), acc)


def _gram(X_ref, w_ref, s1: slice, s2: slice):
    """The chunk body of ``X' diag(w) X`` in the variables' two halves: ``k -> (11, 12, 22 blocks)``."""
    def body(k):
        X1, X2 = X_ref[k, s1], X_ref[k, s2]
        w = w_ref[k][:, None]
        return dot(X1 * w, X1, ((0,), (0,))), dot(X1 * w, X2, ((0,), (0,))), dot(X2 * w, X2, ((0,), (0,)))
    return body


def _sym_plus_diag(M, kd, r, c):
    """``(M + M') / 2 + diag(kd)`` (``r``, ``c``: the tile's row and column indices)."""
    M = 0.5 * (M + M.T)
    return M + jnp.where(r == c, kd[None, :], 0.0)


def _invert_k(P_ref, Ae_ref, Ai_ref, kd_ref, re_ref, ri_ref, Ki_ref, n: int, sync) -> None:
    """``K^-1`` (N, N) written to ``Ki_ref``, zero on padded variables, in 2 x 2 blocks of the halves:
    ``X = K11^-1 K12``, ``S2 = K22 - K12' X``, ``K^-1 = [[K11^-1 + X S2^-1 X', -X S2^-1], [., S2^-1]]``.

    Each product runs over its contraction index in chunks (:func:`_chunked`), both operands read from memory:
    intermediate factors are staged in ``Ki_ref`` and overwritten by their final values once no product reads them
    (held in registers, the operands spilled). ``sync`` orders each write before other threads' reads.
    """
    N = P_ref.shape[0]
    H = N // 2
    NE, MI = Ae_ref.shape[0], Ai_ref.shape[0]
    s1, s2 = slice(0, H), slice(H, N)
    r = jax.lax.broadcasted_iota(jnp.int32, (H, H), 0)
    c = jax.lax.broadcasted_iota(jnp.int32, (H, H), 1)
    K = (P_ref[s1, s1], P_ref[s1, s2], P_ref[s2, s2])
    K = _chunked(NE, _gram(Ae_ref, re_ref, s1, s2), K)
    K11, K12, K22 = _chunked(MI, _gram(Ai_ref, ri_ref, s1, s2), K)
    K11i = sweep_inverse(_sym_plus_diag(K11, kd_ref[s1], r, c), min(n, H))
    Ki_ref[s1, s1] = K11i
    Ki_ref[s1, s2] = K12
    sync()
    X = _chunked(H, lambda k: dot(Ki_ref[s1, k], Ki_ref[k, s2], ((1,), (0,))), jnp.zeros((H, H), K12.dtype))
    Ki_ref[s2, s1] = X  # K11^-1 K12, read by the next three products
    sync()
    S2 = _chunked(H, lambda k: dot(Ki_ref[k, s2], Ki_ref[pl.ds(H + k.start, k.size), s1], ((0,), (0,))), -K22)
    S2i = jnp.where((r < n - H) & (c < n - H), sweep_inverse(_sym_plus_diag(-S2, kd_ref[s2], r, c), n - H), 0.0)
    Ki_ref[s2, s2] = S2i  # final
    sync()
    XS = _chunked(H, lambda k: dot(Ki_ref[s2, k], Ki_ref[pl.ds(H + k.start, k.size), s2], ((1,), (0,))),
                  jnp.zeros((H, H), K12.dtype))
    Ki_ref[s1, s2] = -XS  # final
    sync()
    # Ki11 = K11^-1 + XS X'
    G = _chunked(H, lambda k: dot(Ki_ref[s1, pl.ds(H + k.start, k.size)], Ki_ref[s2, k], ((1,), (1,))),
                 jnp.zeros((H, H), K12.dtype))
    Ki11 = jnp.where((r < n) & (c < n), Ki_ref[s1, s1] - G, 0.0)
    sync()
    Ki_ref[s1, s1] = Ki11  # final
    Ki_ref[s2, s1] = -XS.T  # final
    sync()


def factor_kernel(P_ref, Ae_ref, Ai_ref, kd_ref, re_ref, ri_ref, exe_ref, Ki_ref, W_ref, Si_ref, *, n: int,
                  ne: int, sync):
    """The x-update's factors of one problem from its :class:`~.kernel_layout.Stage` (module docstring).

    Args:
        P_ref: (N, N), Ae_ref: (NE, N), Ai_ref: (MI, N) the scaled cost and rows; kd_ref: (N,) K's diagonal term;
            re_ref: (NE,), ri_ref: (MI,) the rows' rho; exe_ref: (NE,) 1.0 on the exact rows held.
        Ki_ref: (N, N) out, ``K^-1``, zero on padded variables; W_ref: (N, NE) out, ``W``; Si_ref: (NE, NE) out,
            ``S^-1``, zero on the rows not held.
        n, ne: the real variables and exact rows; sync: ``__syncthreads`` on a GPU,
            :func:`~.kernel_layout.no_sync` in the interpreter.
    """
    _invert_k(P_ref, Ae_ref, Ai_ref, kd_ref, re_ref, ri_ref, Ki_ref, n, sync)
    N, NE = P_ref.shape[0], Ae_ref.shape[0]
    exe = exe_ref[...]
    # W = K^-1 Ah' (Ah: the held rows), S = Ah W
    W = _chunked(N, lambda k: dot(Ki_ref[:, k], Ae_ref[:, k] * exe[:, None], ((1,), (1,))),
                 jnp.zeros((N, NE), Ki_ref.dtype))
    W_ref[...] = W
    sync()
    S = _chunked(N, lambda k: dot(Ae_ref[:, k] * exe[:, None], W_ref[k, :], ((1,), (0,))), jnp.zeros((NE, NE), W.dtype))
    Si_ref[...] = sweep_inverse(regularize_schur(S, exe > 0.5), ne) * (exe[:, None] * exe[None, :])


def factor_or_keep_kernel(P_ref, Ae_ref, Ai_ref, kd_ref, re_ref, ri_ref, exe_ref, keep_ref, Ki_old, W_old, Si_old,
                          Ki_ref, W_ref, Si_ref, *, n: int, ne: int, sync):
    """:func:`factor_kernel` where ``keep_ref`` (1,) is 0.0; where it is 1.0 the program writes nothing, so the
    outputs, aliased to ``Ki_old``, ``W_old``, ``Si_old`` (the factors of an earlier solve,
    ``QPSettings.reuse_factors``), keep them."""
    del Ki_old, W_old, Si_old  # the outputs' buffers

    @pl.when(entry(read_vec(keep_ref, 16, 1), 0) < 0.5)
    def _():
        factor_kernel(P_ref, Ae_ref, Ai_ref, kd_ref, re_ref, ri_ref, exe_ref, Ki_ref, W_ref, Si_ref, n=n, ne=ne,
                      sync=sync)
