"""The fused path's data layout and the tile helpers its three Pallas kernels share.

A problem's rows come in three blocks, each stored only as large as it is:

* the exact block: the first ``ne`` rows (``QPSettings.eq_rows``), ``Ae`` (NE, N); the rows held exactly enter the
  x-update's KKT system through ``W = K^-1 Ae'`` and the Schur complement's inverse ``S^-1``;
* the dense block: the rows after them, ``Ai`` (MI, N);
* the box block: the last ``nb`` rows (``QPSettings.box_rows``), bounds on the last ``nb`` variables, stored as the
  diagonal ``db`` (N,) laid over the variables (zero on the others).

Every row follows the same ADMM update whatever its block: the blocks partition the storage, not the algorithm.
Tiles are padded to powers of two, at least 16 (Triton's rule): padded variables have zero rows and columns in
every matrix, padded rows are ``0 <= 0 <= 0`` with zero rho and dual. The user's arrays are read and written in
place by masked loads and stores (no padded copies in device memory). Everything here is plain ``jnp`` that lowers
inside a Triton kernel: masked reductions instead of dynamic indexing, elementwise products instead of ``dot``
where full float32 is needed.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

CK = 16  # the factorization's contraction chunk (Triton's dot: every dimension at least 16)
N_IN = 13  # the preparation kernel's inputs: P, A, q, l (3 blocks), u (3 blocks), wy, rho, wx, wz (unpadded)


class Dims(NamedTuple):
    """The problem's real sizes (static): variables ``n``, exact rows ``ne``, dense rows ``mi``, box rows ``nb``."""

    n: int
    ne: int
    mi: int
    nb: int


class Stage(NamedTuple):
    """The preparation kernel's outputs, one problem's scaled data as the other two kernels read it (each per-row
    field a tuple of the exact, dense and box block's)."""

    P: jax.Array  # (N, N) scaled cost
    Ae: jax.Array  # (NE, N) scaled exact rows
    Ai: jax.Array  # (MI, N) scaled dense rows
    db: jax.Array  # (N,) scaled box diagonal
    q: jax.Array  # (N,) scaled linear cost
    kd: jax.Array  # (N,) K's diagonal term: sigma + the box rows' rho db^2 (padded variables: 1)
    D: jax.Array  # (N,) column scaling
    Dc: jax.Array  # (N,) 1 / (c D): the dual residual's unscaling
    lo: tuple  # scaled lower bounds
    hi: tuple  # scaled upper bounds
    rho: tuple  # per-row rho (0 on held rows and padding)
    free: tuple  # 1.0 on rows without bounds
    Ei: tuple  # 1 / row scaling
    x: jax.Array  # (N,) scaled start
    z: tuple  # scaled start
    y: tuple  # scaled start
    exe: jax.Array  # (NE,) 1.0 on the rows held exactly
    le: jax.Array  # (NE,) their right-hand side (0 elsewhere)
    scal: jax.Array  # (16,) [c, rho]


class Factors(NamedTuple):
    """A fused solve's x-update factors and the scaled data they were made from, carried by its result to the next
    solve (``QPSettings.reuse_factors``; each per-row field a tuple of the exact, dense and box block's)."""

    Ki: jax.Array  # (N, N) K^-1
    W: jax.Array  # (N, NE) K^-1 Ae_h'
    Si: jax.Array  # (NE, NE) S^-1
    D: jax.Array  # (N,) column scaling
    Ei: tuple  # 1 / row scaling
    c: jax.Array  # () cost scaling
    rho: tuple  # per-row rho of K
    kd: jax.Array  # (N,) K's diagonal term
    kinds: tuple  # per row: 1.0 without bounds + 2.0 an equality (the rows' kinds the factors hold for)
    rho_s: jax.Array  # () the scalar rho the per-row rho was made from
    fresh: jax.Array  # () bool: factored by the solve that returned them (the next may reuse them)


def pow2(k: int) -> int:
    """The tile size of ``k`` entries: the next power of two, at least 16."""
    return 1 << max(4, (k - 1).bit_length())


def matvec(M, v):
    """``M v`` in full float32 (elementwise products and sums: no TF32)."""
    return jnp.sum(M * v[None, :], axis=1)


def rmatvec(M, v):
    """``M' v`` in full float32."""
    return jnp.sum(M * v[:, None], axis=0)


def is_finite(*vs):
    """() bool, every entry finite (``x - x`` is 0 only for finite ``x``: no boolean reduction)."""
    tot = sum(jnp.sum(v) for v in vs)
    return (tot - tot) == 0.0


def dot(a, b, contract):
    """Full-precision matrix product (IEEE float32 on Triton, no TF32) contracting the axes ``contract``."""
    return jax.lax.dot_general(a, b, (contract, ((), ())), precision=jax.lax.Precision.HIGHEST)


def entry(v, k: int):
    """() ``v[k]`` (a masked sum: a Triton kernel cannot index a value)."""
    return jnp.sum(jnp.where(jax.lax.broadcasted_iota(jnp.int32, v.shape, 0) == k, v, 0.0))


def no_sync() -> None:
    """The kernels' ``sync`` in Pallas' interpreter, which runs a program's operations in order (one thread)."""


def row_masks(dims: Dims, sizes) -> tuple:
    """Bool masks of each block's real rows (the box block's over the variables ``n - nb .. n - 1``)."""
    NE, MI, N = sizes
    ie, ii, ib = (jax.lax.broadcasted_iota(jnp.int32, (k,), 0) for k in (NE, MI, N))
    return ie < dims.ne, ii < dims.mi, (ib >= dims.n - dims.nb) & (ib < dims.n)


def masked_load(ref, idx, mask):
    """``ref[idx]`` where ``mask``, 0 elsewhere (entries outside the mask are never read)."""
    return plgpu.load(ref.at[idx], mask=mask, other=0.0)


def masked_store(ref, idx, val, mask):
    """``ref[idx] = val`` where ``mask`` (entries outside it are not written)."""
    plgpu.store(ref.at[idx], val, mask=mask)


def tile(ref, row0: int, rows: int, cols: int, n_rows: int, n_cols: int):
    """The (rows, cols) tile of ``ref`` from row ``row0``, zero outside its first ``n_rows`` rows and ``n_cols``
    columns: a masked load, so ``ref`` can be the user's unpadded matrix."""
    r = jax.lax.broadcasted_iota(jnp.int32, (rows, cols), 0)
    c = jax.lax.broadcasted_iota(jnp.int32, (rows, cols), 1)
    return masked_load(ref, (pl.ds(row0, rows), pl.ds(0, cols)), (r < n_rows) & (c < n_cols))


def row_index(dims: Dims):
    """Per block (exact, dense, box): the user's row index of each of the block's entries (int32, the box block's
    laid over the variables: variable ``i`` is bounded by row ``m - n + i``) and the mask of its real entries.

    Built in the kernel (iota), since an index array is not bounds-checked at trace time as a static slice start
    is. Masked entries get the index ``m`` (past the end), which Pallas' interpreter clamps when it reads and drops
    when it writes (a negative index would wrap onto a real row).
    """
    m = dims.ne + dims.mi + dims.nb
    masks = row_masks(dims, (pow2(dims.ne), pow2(dims.mi), pow2(dims.n)))
    ie, ii, ib = (jax.lax.broadcasted_iota(jnp.int32, (mk.shape[0],), 0) for mk in masks)
    return tuple(jnp.where(mk, i, m) for i, mk in zip((ie, ii + dims.ne, ib + (m - dims.n)), masks)), masks


def read_rows(ref, dims: Dims) -> tuple:
    """The three blocks of a per-row vector ``ref`` (m,) in the user's row order, zero on padding."""
    idx, masks = row_index(dims)
    return tuple(masked_load(ref, (i,), mk) for i, mk in zip(idx, masks))


def write_rows(ref, dims: Dims, blocks, where=True) -> None:
    """The three blocks' values written to ``ref`` (m,) in the user's row order (padding not written; nothing
    where the scalar ``where`` is False)."""
    idx, masks = row_index(dims)
    for i, mk, v in zip(idx, masks, blocks):
        masked_store(ref, (i,), v, mk & where)


def read_blocks(refs, dims: Dims) -> tuple:
    """A per-row vector given as its three blocks (``refs``: exact (ne,), dense (mi,), box (nb,)), in the kernels'
    layout: zero on padding, the box block laid over the variables."""
    ib = jax.lax.broadcasted_iota(jnp.int32, (pow2(dims.n),), 0)
    mb = row_masks(dims, (1, 1, ib.shape[0]))[2]
    return (read_vec(refs[0], pow2(dims.ne), dims.ne), read_vec(refs[1], pow2(dims.mi), dims.mi),
            masked_load(refs[2], (jnp.where(mb, ib - (dims.n - dims.nb), dims.nb),), mb))


def read_vec(ref, size: int, n: int):
    """``ref`` (n,) as a (size,) tile, zero past its end."""
    i = jax.lax.broadcasted_iota(jnp.int32, (size,), 0)
    return masked_load(ref, (i,), i < n)


def write_vec(ref, v, n: int, where=True) -> None:
    """The first ``n`` entries of the tile ``v`` written to ``ref`` (n,) (nothing where the scalar ``where`` is
    False)."""
    i = jax.lax.broadcasted_iota(jnp.int32, v.shape, 0)
    masked_store(ref, (i,), v, (i < n) & where)
