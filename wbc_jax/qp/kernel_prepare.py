"""The fused path's first Pallas kernel: one problem's preparation, written as a :class:`~.kernel_layout.Stage`.

It reads the user's arrays once and writes the scaled problem the factorization and iterations kernels read:
Ruiz equilibration, the rows' kinds (free, equality, held exactly), the per-row rho and the scaled warm start, the
same arithmetic as the XLA path's preparation (:func:`wbc_jax.qp.admm.solve_xla`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.qp import rules
from wbc_jax.qp.kernel_layout import (
    N_IN,
    Dims,
    Stage,
    entry,
    masked_load,
    matvec,
    pow2,
    read_blocks,
    read_rows,
    read_vec,
    row_index,
    row_masks,
    tile,
)
from wbc_jax.qp.scaling import ruiz_pass
from wbc_jax.qp.settings import BIG, QPSettings

N_GIVEN = 6  # the preparation kernel's inputs of a given scaling: flag, D, 1 / E (3 blocks), c


class Prepared(NamedTuple):
    """One problem after equilibration, in the kernels' layout (each per-row field a tuple of the exact, dense and
    box block's, the box block's laid over the variables)."""

    P: jax.Array  # (N, N) scaled cost, symmetric
    q: jax.Array  # (N,) scaled linear cost
    Ae: jax.Array  # (NE, N) scaled exact rows
    Ai: jax.Array  # (MI, N) scaled dense rows
    db: jax.Array  # (N,) scaled box diagonal
    D: jax.Array  # (N,) column scaling
    E: tuple  # row scalings
    c: jax.Array  # () cost scaling
    l: tuple  # scaled lower bounds (+-BIG rows: E BIG, still far outside every iterate)
    u: tuple  # scaled upper bounds
    free: tuple  # bool, no bounds
    ex: jax.Array  # (NE,) 1.0 on the exact rows held exactly (l == u), else 0.0
    rho: tuple  # per-row rho (0: held rows, padding)
    x: jax.Array  # (N,) scaled start (0 cold)
    z: tuple  # scaled start (in the bounds; A x on free rows)
    y: tuple  # scaled start (0 on free rows and padding)


def prepare(P, Ae, Ai, db, q, l, u, wx, wz, wy, rho, *, s: QPSettings, dims: Dims, warm: bool,
            given=None) -> Prepared:
    """The XLA path's preparation of one problem on the kernels' blocks: symmetrize ``P``, Ruiz passes
    (:func:`wbc_jax.qp.scaling.ruiz_pass`), the rows' kinds, the per-row rho and the start in the scaled problem
    (:func:`wbc_jax.qp.rules.scaled_start`, :func:`wbc_jax.qp.rules.start_on_rows`). Plain ``jnp``.

    Args:
        P: (N, N), Ae: (NE, N), Ai: (MI, N), db: (N,), q: (N,) the problem in the user's units, zero-padded.
        l, u: tuples of the three blocks' bounds (finite, ``+-BIG``; padding 0).
        wx: (N,), wz, wy: tuples of the blocks: the warm point (user's units; ignored when ``warm`` is False).
        rho: () the solve's rho.
        given: None, or ``(use, D, E, c)``: where ``use`` (() bool), the problem is scaled by this column scaling
            (N,), row scalings (a tuple of the three blocks') and cost scaling () instead of its Ruiz passes'.
    """
    N = P.shape[0]
    masks = row_masks(dims, (Ae.shape[0], Ai.shape[0], N))
    P = 0.5 * (P + P.T)

    def equilibrated(P, q, rows, db):
        D, E, c = jnp.ones_like(q), tuple(jnp.ones_like(v) for v in l), jnp.ones_like(rho)
        for _ in range(s.ruiz_iters):
            P, q, rows, db, d, e, ct = ruiz_pass(P, q, rows, db, dims.n)
            D, E, c = D * d, tuple(a * b for a, b in zip(E, e)), c * ct
        return P, q, rows, db, D, E, c

    if given is None:
        P, q, rows, db, D, E, c = equilibrated(P, q, (Ae, Ai), db)
    else:  # one branch per problem: a kept scaling spares the Ruiz passes (and their registers)
        use, Dg, Eg, cg = given

        def scaled(P, q, rows, db):
            rows = tuple(e[:, None] * M * Dg[None, :] for e, M in zip(Eg, rows))
            return cg * Dg[:, None] * P * Dg[None, :], cg * Dg * q, rows, Eg[2] * db * Dg, Dg, tuple(Eg), cg

        P, q, rows, db, D, E, c = jax.lax.cond(use, scaled, equilibrated, P, q, (Ae, Ai), db)
    P = 0.5 * (P + P.T)
    ls, us = tuple(e * v for e, v in zip(E, l)), tuple(e * v for e, v in zip(E, u))
    free = tuple((a <= -BIG) & (b >= BIG) for a, b in zip(l, u))
    eq = [jnp.abs(b - a) < rules.EQ_TOL for a, b in zip(ls, us)]
    ex = masks[0] & eq[0] & ~free[0] if s.eq_rows > 0 else None  # (no bool constants: they do not lower)
    if warm:
        x, z, y = rules.scaled_start(wx, wz, wy, D, E, c)
    else:
        x, z, y = jnp.zeros_like(q), tuple(jnp.zeros_like(v) for v in l), tuple(jnp.zeros_like(v) for v in l)
    act = rules.active_rows(y, P.dtype) if warm and s.warm_active_scale != 1.0 else (None,) * 3
    exs = (ex, None, None)
    rho_v = tuple(jnp.where(mk, rules.rho_vec(rho, rules.row_weights(e, f, x, a, s), f, s), 0.0)
                  for mk, e, f, x, a in zip(masks, eq, free, exs, act))
    z, y = rules.start_on_rows(z, y, (matvec(rows[0], x), matvec(rows[1], x), db * x), ls, us, free)
    ex = jnp.zeros_like(l[0]) if ex is None else jnp.where(ex, 1.0, 0.0)
    return Prepared(P, q, rows[0], rows[1], db, D, tuple(E), c, ls, us, free, ex, rho_v, x, z, y)


def stage_shapes(dims: Dims, dt) -> Stage:
    """The :class:`~.kernel_layout.Stage` of one problem as ``jax.ShapeDtypeStruct`` leaves (the kernel's outputs)."""
    N, NE, MI = pow2(dims.n), pow2(dims.ne), pow2(dims.mi)
    sd = lambda *sh: jax.ShapeDtypeStruct(sh, dt)  # noqa: E731
    rowb = (sd(NE), sd(MI), sd(N))
    return Stage(sd(N, N), sd(NE, N), sd(MI, N), sd(N), sd(N), sd(N), sd(N), sd(N), rowb, rowb, rowb, rowb, rowb,
                 sd(N), rowb, rowb, sd(NE), sd(NE), sd(16))


def prepare_kernel(*refs, s: QPSettings, dims: Dims, warm: bool, treedef, given: bool = False):
    """:func:`prepare` of one problem, written as a :class:`~.kernel_layout.Stage` (``treedef``'s leaves, after the
    ``N_IN`` inputs and, with ``given``, :data:`N_GIVEN` more: the flag (1,) (1.0: use them), ``D`` (N,), the row
    blocks' ``1 / E`` and ``c`` (1,) of a scaling to use instead of the Ruiz passes'). Reads the user's arrays as
    they are: ``P`` and the exact and dense blocks of ``A`` as tiles, the box block's diagonal and the vectors by
    index, the bounds from their three blocks."""
    P_ref, A_ref, q_ref = refs[:3]
    wy_ref, rho_ref, wx_ref, wz_ref = refs[9:N_IN]
    N, NE, MI = pow2(dims.n), pow2(dims.ne), pow2(dims.mi)
    P = tile(P_ref, 0, N, N, dims.n, dims.n)
    Ae, Ai = tile(A_ref, 0, NE, N, dims.ne, dims.n), tile(A_ref, dims.ne, MI, N, dims.mi, dims.n)
    (_, _, rb), (_, _, mb) = row_index(dims)
    db = masked_load(A_ref, (rb, jax.lax.broadcasted_iota(jnp.int32, (N,), 0)), mb)  # A[m - n + i, i]
    q, wx = read_vec(q_ref, N, dims.n), read_vec(wx_ref, N, dims.n)
    l, u = read_blocks(refs[3:6], dims), read_blocks(refs[6:9], dims)
    wy, wz = read_rows(wy_ref, dims), read_rows(wz_ref, dims)
    n_in = N_IN + (N_GIVEN if given else 0)
    out = jax.tree_util.tree_unflatten(treedef, refs[n_in:])
    rho = entry(read_vec(rho_ref, 16, 1), 0)
    scaling = None
    if given:
        use_ref, D_ref, E0_ref, E1_ref, E2_ref, c_ref = refs[N_IN:n_in]
        Eg = tuple(1.0 / r[...] for r in (E0_ref, E1_ref, E2_ref))
        scaling = (entry(read_vec(use_ref, 16, 1), 0) > 0.5, D_ref[...], Eg, entry(read_vec(c_ref, 16, 1), 0))
    pr = prepare(P, Ae, Ai, db, q, l, u, wx, wz, wy, rho, s=s, dims=dims, warm=warm, given=scaling)
    i = jax.lax.broadcasted_iota(jnp.int32, q.shape, 0)
    vals = Stage(pr.P, pr.Ae, pr.Ai, pr.db, pr.q, jnp.where(i < dims.n, s.sigma + pr.db * pr.db * pr.rho[2], 1.0),
                 pr.D, 1.0 / (pr.c * pr.D), pr.l, pr.u, pr.rho, tuple(jnp.where(f, 1.0, 0.0) for f in pr.free),
                 tuple(1.0 / e for e in pr.E), pr.x, pr.z, pr.y, pr.ex, jnp.where(pr.ex > 0.5, pr.l[0], 0.0),
                 jnp.where(jax.lax.broadcasted_iota(jnp.int32, (16,), 0) == 0, pr.c, rho))
    for ref, v in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(vals)):
        ref[...] = v
