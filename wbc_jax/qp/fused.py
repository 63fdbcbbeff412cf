"""One solve of the fused path as three Pallas (Triton) kernels, one program per problem each: the preparation
(Ruiz equilibration, the rows' kinds and rho, the scaled warm start), the x-update's factorization, then the ADMM
iterations with the convergence-checked extension and the result in the user's units (residuals, infeasibility
certificates, flag, the next rho). Every input reaches the kernels as the user's array: ``P`` and ``A`` as masked
loads of power-of-two tiles (:func:`_tile`), the vectors by index (:func:`_read_rows`; the bounds as their three
blocks, :func:`_read_blocks`), and ``x``, ``z``, ``y`` are written in the user's layout (:func:`_write_rows`): no XLA
pads, slices or concatenations around the kernels. Measured (H100, ``bench rollout --backend warp --scene
transport``, one call, alternated with the kernels' earlier padded vectors): everything but physics at batch 270
0.389 / 0.366 ms against 0.388 / 0.378 ms, at 16384 6.474 against 6.624 ms (docs/performance.md). Passing the
bounds whole instead (read by index like ``wz``) measured worse: XLA then fused the bounds' whole assembly into one
37.5 us kernel at batch 270.

A thread's registers set how many programs run at once (an H100's streaming multiprocessor holds 64K): at 255
registers per thread and 4 warps, 2 programs, so 264 problems on 132 multiprocessors and a second wave for the
campaign's 270. The factorization's matrix products therefore run over their contraction index in chunks read
from memory (:func:`_factor_kernel`; 144 registers, no spills: 3 programs), and the iterations kernel reads its
matrices and per-row constants where each step uses them and keeps its certificates' deltas in its outputs
(still 255 registers, 112 bytes of spills against 640; counted with pip Triton for sm_90a). Measured (H100, same
bench, one call, alternated with the kernels before): batch 270 0.333 / 0.296 ms against 0.403 / 0.357 ms, 16384
5.773 against 6.467 ms; device trace at 270: factorization 91.2 -> 62.7 us, iterations 68.8 -> 62.4 us
(docs/performance.md).

The kernels run 2 warps per program (``num_warps``: the preparation and the iterations; ``factor_warps``: the
factorization). With 4, the factorization took 144 registers and the iterations 255 (112 bytes of spills); with 2,
235 (no spills) and 255 (656 bytes; pip Triton, sm_90a), but a program's reductions and layout changes span 2 warps
instead of 4, and 4 programs fit a multiprocessor (the campaign's 270 problems in one wave). Measured (H100,
``bench rollout``, 9 / 3 rounds, alternated with 4 / 4): everything but physics at batch 16384 5.286 against 5.758
ms (physics + WBC 1,853,937 against 1,761,804 env-steps/s), at 270 0.308 / 0.299 against 0.310 / 0.308 ms; device
trace at 270, the factorization alone at 2 warps 56.8 us against 62.9 (1 warp: 81.1 us, 255 registers and 480
bytes of spills). Before the staged products 2 / 2 had measured worse than 4 / 4 (docs/performance.md).

Why: the XLA path (``admm._step`` in ``lax.scan``, then the extension's ``lax.while_loop``) launches about ten kernels
per iteration and reads ``P``, ``A``, ``K^-1`` and the Schur factors from device memory at every one. Under ``vmap``
the extension's loop also runs every problem of the batch until the slowest has converged: the batch pays the
largest count of the step (a run's mean on the course is 21.6 iterations per step, its most 200). Here one program
per problem loads its matrices once, runs the ``iters`` iterations and the blocks of ``check_every`` more while its
own residuals are outside tolerance (up to ``max_iters``), and stops on its own. Measured (H100, course, Warp
physics): the paper campaign 171.0 s -> 133.2 s, physics + WBC at batch 16384 431,605 -> 530,978 env-steps/s
(docs/performance.md).

The rows come in three blocks, each stored only as large as it is (the tiles a program holds, and the memory it
reads, grow with them):

* the exact block: the first ``ne`` rows (``QPSettings.eq_rows``), ``Ae`` (ne, n), unmasked; the rows held exactly
  (``ex``) enter the x-update's KKT system through ``W = K^-1 Ae'`` and the Schur complement's inverse ``S^-1``;
* the dense block: the rows after them, ``Ai`` (mi, n);
* the box block: the last ``nb`` rows (``QPSettings.box_rows``), bounds on the last ``nb`` variables, stored as the
  diagonal ``db`` (n,) (zero on the other variables).

The preparation (:func:`_prepare_kernel`, :func:`prepare`) reads each problem once and writes the scaled problem
(:class:`Stage`) that the other two read; before it, XLA's equilibration was 27 ops per control step, 1.60 ms at
batch 16384, its residuals and flag 14 ops, 0.63 ms (H100, ``bench trace``). Done inside the factorization and
iterations kernels instead (each scaling its own copy) it doubled both (iterations 3.5 -> 8.6 ms, factorization
3.2 -> 6.2 ms at 16384): the preparation's registers set the kernel's occupancy. One H100, one call, ``bench
rollout`` physics + WBC at 16384 / 270: XLA preparation 1,035,444 / 196,113 env-steps/s; this 1,256,437 / 244,058
(again: 1,253,711 / 242,299).

The factorization (:func:`_factor_kernel`) builds ``K`` from the blocks and inverts it in 2 x 2 blocks of the
variables' halves by Gauss-Jordan sweeps (:func:`sweep_inverse`), then ``W`` and ``S^-1``: one kernel where XLA
launched ~50 (Gram products, cuSOLVER's batched Cholesky, triangular solves, the Schur complement's Cholesky).
The sweeps eliminate two indices at a time (a 2 x 2 pivot block): the course's QP (56 variables, 24 exact rows)
takes 40 sweeps instead of 80. Measured (H100, batch 270): the factorization kernel 56.9 -> 48.7 us per control
step (device trace, twice), everything but physics 0.298 / 0.291 / 0.290 / 0.294 against 0.301 / 0.300 / 0.301 /
0.302 ms (``bench rollout``, 9 rounds, alternated); the paper campaign's flags and iteration counts unchanged. In a
kernel-only benchmark (random SPD stages, batch 270) the sweeps were half of the kernel (~26 us of ~54); four
indices per sweep (a 4 x 4 block inverted in scalars) measured no better than two (docs/performance.md).

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
the user's units (:func:`wbc_jax.qp.rules.termination`, as the XLA path's), evaluated from the scaled iterate with
the scalings (``A x - z = E^-1 (A_s x_s - z_s)``, ``P x + q + A'y = c^-1 D^-1 (P_s x_s + q_s + A_s' y_s)``); the
rho rules, certificates and flag are :mod:`wbc_jax.qp.rules`' too. Results equal the XLA path up to float rounding
(tests compare them in the Pallas interpreter, float64), except the re-estimated rho with the extension: the XLA
path estimates it after the fixed iterations, the kernel from the final iterate.

Inside the iterations kernel ``A x`` is carried from step to step (``A x_next = alpha A xt + (1 - alpha) A x``: the
next iterate is that combination) and recomputed at each block's start, and a step's finiteness is checked on ``xt``
and the exact rows' multiplier step (finite ones make every other new entry finite): two matrix-vector products and
five reductions fewer per iteration. Measured (H100, one call, physics + WBC at 16384 / 270): 1,253,085 / 242,928
before, 1,263,625 / 242,869 with these and the unpadded reads (the iteration count matters more:
:func:`wbc_jax.control.transport.control_qp_settings`).

Shapes are padded to powers of two (Triton's rule, at least 16): padded variables have zero rows and columns in
every matrix, padded rows are ``0 <= 0 <= 0`` with zero rho and dual, padded exact rows have zero ``S^-1``.
``vmap`` adds a grid axis (one program per problem). On a CPU the kernels run in Pallas' interpreter (slow; tests
only); the solver uses them where ``QPSettings.kernel`` says so (``"auto"``: on a GPU).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from wbc_jax.qp import rules
from wbc_jax.qp.scaling import regularize_schur, ruiz_pass
from wbc_jax.qp.settings import BIG, QPResult, QPSettings


class Dims(NamedTuple):
    """The problem's real sizes (static): variables ``n``, exact rows ``ne``, dense rows ``mi``, box rows ``nb``."""

    n: int
    ne: int
    mi: int
    nb: int


class Prepared(NamedTuple):
    """One problem after equilibration, in the kernels' layout (rows in three blocks: exact, dense, box; each
    per-row field a tuple of the three, the box block's laid over the variables)."""

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


def _pow2(k: int) -> int:
    return 1 << max(4, (k - 1).bit_length())


def _mv(M, v):  # M v, full float32 (elementwise products and sums: no TF32)
    return jnp.sum(M * v[None, :], axis=1)


def _mtv(M, v):  # M' v
    return jnp.sum(M * v[:, None], axis=0)


def _finite(*vs):  # () bool, every entry finite (Triton-friendly: x - x is 0 only for finite x)
    tot = sum(jnp.sum(v) for v in vs)
    return (tot - tot) == 0.0


def _row_masks(dims: Dims, sizes) -> tuple:
    """Bool masks of each block's real rows (the box block's over the variables ``n - nb .. n - 1``)."""
    NE, MI, N = sizes
    ie, ii, ib = (jax.lax.broadcasted_iota(jnp.int32, (k,), 0) for k in (NE, MI, N))
    return ie < dims.ne, ii < dims.mi, (ib >= dims.n - dims.nb) & (ib < dims.n)


def prepare(P, Ae, Ai, db, q, l, u, wx, wz, wy, rho, *, s: QPSettings, dims: Dims, warm: bool) -> Prepared:
    """``admm._solve_one``'s preparation of one problem, on the kernels' blocks: symmetrize ``P``, Ruiz passes
    (:func:`wbc_jax.qp.scaling.ruiz_pass`), the rows' kinds (free, equality, held exactly), the warm duals in the
    scaled problem and the per-row rho, the start in the scaled problem (:func:`wbc_jax.qp.rules.scaled_start`,
    :func:`wbc_jax.qp.rules.start_on_rows`, as the XLA path). The preparation kernel runs it and writes its result for the other two
    (:class:`Stage`); plain ``jnp`` (runs inside the kernel and outside it).

    Args:
        P: (N, N), Ae: (NE, N), Ai: (MI, N), db: (N,), q: (N,) the problem in the user's units, zero-padded.
        l, u: tuples of the three blocks' bounds (finite, ``+-BIG``; padding 0).
        wx: (N,), wz, wy: tuples of the blocks: the warm point (user's units; ignored when ``warm`` is False).
        rho: () the solve's rho.
    """
    N = P.shape[0]
    masks = _row_masks(dims, (Ae.shape[0], Ai.shape[0], N))
    P = 0.5 * (P + P.T)
    D, E, c = jnp.ones_like(q), [jnp.ones_like(v) for v in l], jnp.ones_like(rho)
    rows = (Ae, Ai)
    for _ in range(s.ruiz_iters):
        P, q, rows, db, d, e, ct = ruiz_pass(P, q, rows, db, dims.n)
        D, E, c = D * d, [a * b for a, b in zip(E, e)], c * ct
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
    z, y = rules.start_on_rows(z, y, (_mv(rows[0], x), _mv(rows[1], x), db * x), ls, us, free)
    ex = jnp.zeros_like(l[0]) if ex is None else jnp.where(ex, 1.0, 0.0)
    return Prepared(P, q, rows[0], rows[1], db, D, tuple(E), c, ls, us, free, ex, rho_v, x, z, y)


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


def _dot(a, b, contract):  # full-precision matrix product (IEEE float32 on Triton, no TF32)
    return jax.lax.dot_general(a, b, (contract, ((), ())), precision=jax.lax.Precision.HIGHEST)


class Stage(NamedTuple):
    """The preparation kernel's outputs, one problem's scaled data as the other two kernels read it (rows in the
    three blocks: each per-row field a tuple of the exact, dense and box block's)."""

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


N_IN = 13  # the preparation kernel's inputs: P, A, q, l (3 blocks), u (3 blocks), wy, rho, wx, wz (unpadded)


def _entry(v, k: int):  # () v[k] (a masked sum: a Triton kernel cannot index a value)
    return jnp.sum(jnp.where(jax.lax.broadcasted_iota(jnp.int32, v.shape, 0) == k, v, 0.0))


try:  # JAX >= 0.8: masked loads and stores of a ref's view (Triton-specific)
    from jax.experimental.pallas.triton import load as _triton_load
    from jax.experimental.pallas.triton import store as _triton_store

    def _masked_load(ref, idx, mask):
        return _triton_load(ref.at[idx], mask=mask, other=0.0)

    def _masked_store(ref, idx, val, mask):
        _triton_store(ref.at[idx], val, mask=mask)
except ImportError:  # earlier JAX: pallas.load(ref, idx, mask, other), pallas.store(ref, idx, val, mask)
    def _masked_load(ref, idx, mask):
        return pl.load(ref, idx, mask=mask, other=0.0)

    def _masked_store(ref, idx, val, mask):
        pl.store(ref, idx, val, mask=mask)


def _tile(ref, row0: int, rows: int, cols: int, n_rows: int, n_cols: int):
    """The (rows, cols) tile of ``ref`` from row ``row0``, zero outside its first ``n_rows`` rows and ``n_cols``
    columns: a masked load, so the matrix needs no padding in device memory (on a GPU ``ref`` is the user's
    unpadded matrix: the masked entries past its end are never read; Triton's tiles are powers of two)."""
    r = jax.lax.broadcasted_iota(jnp.int32, (rows, cols), 0)
    c = jax.lax.broadcasted_iota(jnp.int32, (rows, cols), 1)
    return _masked_load(ref, (pl.ds(row0, rows), pl.ds(0, cols)), (r < n_rows) & (c < n_cols))


def _row_index(dims: Dims):
    """Per block (exact, dense, box): the user's row index of each of the block's entries (int32, the box block's
    laid over the variables: variable ``i`` is bounded by row ``m - n + i``) and the mask of its real entries. Built
    in the kernel (iota): an index array is not bounds-checked at trace time as a static slice start is. Masked
    entries are never read or written on a GPU; their index is ``m`` (past the end), which Pallas' interpreter
    clamps when it reads and drops when it writes (a negative index would wrap onto a real row)."""
    m = dims.ne + dims.mi + dims.nb
    masks = _row_masks(dims, (_pow2(dims.ne), _pow2(dims.mi), _pow2(dims.n)))
    ie, ii, ib = (jax.lax.broadcasted_iota(jnp.int32, (mk.shape[0],), 0) for mk in masks)
    return tuple(jnp.where(mk, i, m) for i, mk in zip((ie, ii + dims.ne, ib + (m - dims.n)), masks)), masks


def _read_rows(ref, dims: Dims) -> tuple:
    """The three blocks of a per-row vector ``ref`` (m,) in the user's row order, zero on padding."""
    idx, masks = _row_index(dims)
    return tuple(_masked_load(ref, (i,), mk) for i, mk in zip(idx, masks))


def _write_rows(ref, dims: Dims, blocks, where=True) -> None:
    """The three blocks' values written to ``ref`` (m,) in the user's row order (padding not written; nothing
    where the scalar ``where`` is False)."""
    idx, masks = _row_index(dims)
    for i, mk, v in zip(idx, masks, blocks):
        _masked_store(ref, (i,), v, mk & where)


def _read_blocks(refs, dims: Dims) -> tuple:
    """A per-row vector given as its three blocks (``refs``: exact (ne,), dense (mi,), box (nb,)), in the kernels'
    layout: zero on padding, the box block laid over the variables."""
    ib = jax.lax.broadcasted_iota(jnp.int32, (_pow2(dims.n),), 0)
    mb = _row_masks(dims, (1, 1, ib.shape[0]))[2]
    return (_read_vec(refs[0], _pow2(dims.ne), dims.ne), _read_vec(refs[1], _pow2(dims.mi), dims.mi),
            _masked_load(refs[2], (jnp.where(mb, ib - (dims.n - dims.nb), dims.nb),), mb))


def _read_vec(ref, size: int, n: int):
    """``ref`` (n,) as a (size,) tile, zero past its end."""
    i = jax.lax.broadcasted_iota(jnp.int32, (size,), 0)
    return _masked_load(ref, (i,), i < n)


def _write_vec(ref, v, n: int, where=True) -> None:
    """The first ``n`` entries of the tile ``v`` written to ``ref`` (n,) (nothing where the scalar ``where`` is
    False)."""
    i = jax.lax.broadcasted_iota(jnp.int32, v.shape, 0)
    _masked_store(ref, (i,), v, (i < n) & where)


def _prepare_kernel(*refs, s: QPSettings, dims: Dims, warm: bool, treedef):
    """:func:`prepare` of one problem and its scaled start, written as a :class:`Stage`; everything read from the
    user's arrays as they are: ``P`` and the exact and dense blocks of ``A`` as tiles (:func:`_tile`), the box
    block's diagonal and the vectors by index (:func:`_read_vec`, :func:`_read_rows`; the bounds from their three
    blocks, :func:`_read_blocks`)."""
    P_ref, A_ref, q_ref = refs[:3]
    wy_ref, rho_ref, wx_ref, wz_ref = refs[9:N_IN]
    N, NE, MI = _pow2(dims.n), _pow2(dims.ne), _pow2(dims.mi)  # the tiles' sizes (fused_solve's)
    P = _tile(P_ref, 0, N, N, dims.n, dims.n)
    Ae, Ai = _tile(A_ref, 0, NE, N, dims.ne, dims.n), _tile(A_ref, dims.ne, MI, N, dims.mi, dims.n)
    (_, _, rb), (_, _, mb) = _row_index(dims)
    db = _masked_load(A_ref, (rb, jax.lax.broadcasted_iota(jnp.int32, (N,), 0)), mb)  # A[m - n + i, i]
    q, wx = _read_vec(q_ref, N, dims.n), _read_vec(wx_ref, N, dims.n)
    l, u = _read_blocks(refs[3:6], dims), _read_blocks(refs[6:9], dims)
    wy, wz = _read_rows(wy_ref, dims), _read_rows(wz_ref, dims)
    out = jax.tree_util.tree_unflatten(treedef, refs[N_IN:])
    rho = _entry(_read_vec(rho_ref, 16, 1), 0)
    pr = prepare(P, Ae, Ai, db, q, l, u, wx, wz, wy, rho, s=s, dims=dims, warm=warm)
    i = jax.lax.broadcasted_iota(jnp.int32, q.shape, 0)
    vals = Stage(pr.P, pr.Ae, pr.Ai, pr.db, pr.q, jnp.where(i < dims.n, s.sigma + pr.db * pr.db * pr.rho[2], 1.0),
                 pr.D, 1.0 / (pr.c * pr.D), pr.l, pr.u, pr.rho, tuple(jnp.where(f, 1.0, 0.0) for f in pr.free),
                 tuple(1.0 / e for e in pr.E), pr.x, pr.z, pr.y, pr.ex, jnp.where(pr.ex > 0.5, pr.l[0], 0.0),
                 jnp.where(jax.lax.broadcasted_iota(jnp.int32, (16,), 0) == 0, pr.c, rho))
    for ref, v in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(vals)):
        ref[...] = v


def _factor_kernel(P_ref, Ae_ref, Ai_ref, kd_ref, re_ref, ri_ref, exe_ref, Ki_ref, W_ref, Si_ref, *, n: int,
                   ne: int, sync):
    """``admm._kkt_factor`` with ``linsolve="inv"`` for one problem, in 2 x 2 blocks of the variables' halves,
    every matrix product staged through device memory.

    ``K = P + Ae' diag(re) Ae + Ai' diag(ri) Ai + diag(kd)`` (the box rows and sigma in ``kd``; padded variables:
    identity) is inverted through its first half's inverse ``K11^-1`` and the Schur complement ``S2`` of the second
    half (two sweeps of half the size, :func:`sweep_inverse`: the sweeps are sequential, and a half-size tile's are
    cheaper): ``X = K11^-1 K12``, ``S2 = K22 - K12' X``, ``K^-1 = [[K11^-1 + X S2^-1 X', -X S2^-1], [., S2^-1]]``;
    then ``W = K^-1 Ae_h'`` and ``S^-1``, ``S = Ae_h W`` regularized as the XLA path does
    (:func:`wbc_jax.qp.scaling.regularize_schur`; ``Ae_h``: the rows held, ``exe`` 1). Outputs: ``Ki`` (N, N)
    ``K^-1``, zero on padded variables; ``W`` (N, NE); ``Si`` (NE, NE) ``S^-1``, zero on the rows not held.

    Each matrix product runs over its contraction index in chunks of ``CK`` (a loop), both operands read from memory
    at each chunk: the inputs from the preparation's outputs, the intermediate factors from this kernel's own outputs
    (``Ki``, ``W``: each written where a later product reads it, and overwritten by its final value once no product
    reads it any more). ``sync`` (``__syncthreads``; :func:`_no_sync` in the interpreter) orders each write before
    the reads of other threads. Held whole in registers, the products' operands took all 255 registers of a thread
    and spilled, and the kernel ran at 2 programs per streaming multiprocessor (4 warps).
    """
    N = P_ref.shape[0]
    H = N // 2
    NE, MI = Ae_ref.shape[0], Ai_ref.shape[0]
    s1, s2 = slice(0, H), slice(H, N)
    r = jax.lax.broadcasted_iota(jnp.int32, (H, H), 0)
    c = jax.lax.broadcasted_iota(jnp.int32, (H, H), 1)

    def chunks(count, body, acc):  # acc + the sum over the chunks k of body(k's slice)
        ck = min(CK, count)
        return jax.lax.fori_loop(0, count // ck, lambda j, a: jax.tree_util.tree_map(
            jnp.add, a, body(pl.ds(pl.multiple_of(j * ck, ck), ck))), acc)

    def sym(M, kd=None):
        M = 0.5 * (M + M.T)
        return M if kd is None else M + jnp.where(r == c, kd[None, :], 0.0)

    # K = P + Ae' diag(re) Ae + Ai' diag(ri) Ai + diag(kd), its three blocks, summed over the rows in chunks
    def gram(X_ref, w_ref):
        def body(k):
            X1, X2 = X_ref[k, s1], X_ref[k, s2]
            w = w_ref[k][:, None]
            return _dot(X1 * w, X1, ((0,), (0,))), _dot(X1 * w, X2, ((0,), (0,))), _dot(X2 * w, X2, ((0,), (0,)))
        return body

    K = (P_ref[s1, s1], P_ref[s1, s2], P_ref[s2, s2])
    K = chunks(NE, gram(Ae_ref, re_ref), K)
    K11, K12, K22 = chunks(MI, gram(Ai_ref, ri_ref), K)
    K11i = sweep_inverse(sym(K11, kd_ref[s1]), min(n, H))
    Ki_ref[s1, s1] = K11i
    Ki_ref[s1, s2] = K12
    sync()
    X = chunks(H, lambda k: _dot(Ki_ref[s1, k], Ki_ref[k, s2], ((1,), (0,))), jnp.zeros((H, H), K12.dtype))
    Ki_ref[s2, s1] = X  # K11^-1 K12, read by the next three products
    sync()
    S2 = chunks(H, lambda k: _dot(Ki_ref[k, s2], Ki_ref[pl.ds(H + k.start, k.size), s1], ((0,), (0,))), -K22)
    S2i = jnp.where((r < n - H) & (c < n - H), sweep_inverse(sym(-S2, kd_ref[s2]), n - H), 0.0)
    Ki_ref[s2, s2] = S2i  # final
    sync()
    XS = chunks(H, lambda k: _dot(Ki_ref[s2, k], Ki_ref[pl.ds(H + k.start, k.size), s2], ((1,), (0,))),
                jnp.zeros((H, H), K12.dtype))
    Ki_ref[s1, s2] = -XS  # final
    sync()
    # Ki11 = K11^-1 + XS X'
    G = chunks(H, lambda k: _dot(Ki_ref[s1, pl.ds(H + k.start, k.size)], Ki_ref[s2, k], ((1,), (1,))),
               jnp.zeros((H, H), K12.dtype))
    Ki11 = jnp.where((r < n) & (c < n), Ki_ref[s1, s1] - G, 0.0)
    sync()
    Ki_ref[s1, s1] = Ki11  # final
    Ki_ref[s2, s1] = -XS.T  # final
    sync()
    exe = exe_ref[...]
    # W = K^-1 Ah' (Ah: the held rows), S = Ah W
    W = chunks(N, lambda k: _dot(Ki_ref[:, k], Ae_ref[:, k] * exe[:, None], ((1,), (1,))),
               jnp.zeros((N, NE), K12.dtype))
    W_ref[...] = W
    sync()
    S = chunks(N, lambda k: _dot(Ae_ref[:, k] * exe[:, None], W_ref[k, :], ((1,), (0,))), jnp.zeros((NE, NE), W.dtype))
    Si_ref[...] = sweep_inverse(regularize_schur(S, exe > 0.5), ne) * (exe[:, None] * exe[None, :])


CK = 16  # the products' contraction chunk (Triton's dot: every dimension at least 16)


def _no_sync() -> None:
    """The kernels' ``sync`` in Pallas' interpreter, which runs a program's operations in order (one thread)."""


def _kernel(*refs, s: QPSettings, iters: int, max_iters: int, check_every: int, treedef, dims: Dims, sync):
    """One problem's solve from its :class:`Stage` and factorization: ``iters`` iterations, blocks of
    ``check_every`` while outside tolerance, then the result in the user's units with its residuals, certificates
    and flag (the user's bounds ``l``, ``u`` read at the end, for the certificates), written in the user's layout:
    ``x`` (n,), ``z`` and ``y`` (m,) in the rows' order."""
    n_stage = treedef.num_leaves
    st = jax.tree_util.tree_unflatten(treedef, refs[:n_stage])
    Ki_ref, W_ref, Si_ref = refs[n_stage:n_stage + 3]
    l_refs, u_refs = refs[n_stage + 3:n_stage + 6], refs[n_stage + 6:n_stage + 9]
    x_ref, z_ref, y_ref, flag_ref, iters_ref, prim_ref, dual_ref, rho_ref = refs[n_stage + 9:]
    Dc = st.Dc[...]
    Ei = [r[...] for r in st.Ei]
    alpha = s.alpha

    # the matrices, constant vectors and per-row constants, each read where it is used (held across the loop, they
    # and the iterate's vectors took more registers than a thread has)
    def at(ref, o):  # ref[...] at the loop-variant offset o (always 0): not hoisted out of the loop
        return ref[(pl.ds(o, ref.shape[0]),) + (slice(None),) * (len(ref.shape) - 1)]

    lo, hi, rho = (lambda b, o, f=f: at(f[b], o) for f in (st.lo, st.hi, st.rho))
    free = lambda b, o: at(st.free[b], o) > 0.5  # noqa: E731
    P, Ki, Ae, Ai, db, W, Si, q, le, exe = (functools.partial(at, r) for r in (
        st.P, Ki_ref, st.Ae, st.Ai, st.db, W_ref, Si_ref, st.q, st.le, st.exe))

    def rows(x, o=0):  # A x per block
        return [_mv(Ae(o), x), _mv(Ai(o), x), db(o) * x]

    def rows_t(v, o=0):  # A' v from the blocks' v
        return _mtv(Ae(o), v[0]) + _mtv(Ai(o), v[1]) + db(o) * v[2]

    def project(x):  # admm._project
        xn = x + _mv(W(0), _mv(Si(0), exe(0) * (le(0) - _mv(Ae(0), x))))
        return jnp.where(_finite(xn), xn, x)

    def step(_, c):  # admm._step, linsolve "inv"; ax = A x carried (A x_next = alpha A xt + (1 - alpha) A x)
        x, ax, z, y, bad = c
        o = (bad > 2.0).astype(jnp.int32)  # 0 (bad is 0 or 1), but not known to be
        r = _mv(P(o), x) + q(o) + rows_t([y[b] + rho(b, o) * (ax[b] - z[b]) for b in range(3)], o)
        t = _mv(Ki(o), r)
        exe_ = exe(o)
        dnu = -_mv(Si(o), exe_ * (le(o) - ax[0]) + exe_ * _mv(Ae(o), t))
        xt = x - t - _mv(W(o), dnu)
        zt = rows(xt, o)
        xn = alpha * xt + (1.0 - alpha) * x
        axn, zn, yn = [], [], []
        for b in range(3):
            axn.append(alpha * zt[b] + (1.0 - alpha) * ax[b])
            zr = alpha * zt[b] + (1.0 - alpha) * z[b]
            rb = rho(b, o)
            # z's step y / rho; exact rows and padding: y / 1 (l == u)
            zb = jnp.minimum(jnp.maximum(zr + y[b] / jnp.where(rb > 0.0, rb, 1.0), lo(b, o)), hi(b, o))
            yb = y[b] + rb * (zr - zb)
            fb = free(b, o)
            zn.append(jnp.where(fb, axn[b], zb))
            yn.append(jnp.where(fb, 0.0, yb))
        yn[0] = yn[0] + exe_ * dnu
        # finite xt and dnu make every new entry finite (z, y: sums and clips of finite values); two reductions
        # where checking all seven vectors took seven (each a barrier across the program's warps)
        ok = _finite(xn, dnu)
        keep = lambda new, old: [jnp.where(ok, a, b) for a, b in zip(new, old)]  # noqa: E731
        # the step's deltas (the infeasibility certificates' directions, read after the loop) go to the outputs
        # x and y, which hold them until the result overwrites them: carried, they and the iterate took more
        # registers than a thread has
        _write_vec(x_ref, xn - x, dims.n, ok)
        _write_rows(y_ref, dims, [a - b for a, b in zip(yn, y)], ok)
        return jnp.where(ok, xn, x), keep(axn, ax), keep(zn, z), keep(yn, y), jnp.where(ok, bad, 1.0)

    def start(x, c):  # a block's start: x projected onto the exact rows, A x recomputed (no drift)
        x = project(x)
        return (x, rows(x)) + tuple(c)

    def test(x, ax, z, y):  # rules.termination in the user's units, from the scaled iterate (ax = A x, carried)
        return rules.termination([a * e for a, e in zip(ax, Ei)], [a * e for a, e in zip(z, Ei)],
                                 _mv(P(0), x) * Dc, rows_t(y) * Dc, q(0) * Dc, s)

    x0 = st.x[...]
    z0, y0 = [r[...] for r in st.z], [r[...] for r in st.y]
    _write_vec(x_ref, jnp.zeros_like(x0), dims.n)  # no step yet: zero deltas
    _write_rows(y_ref, dims, [jnp.zeros_like(v) for v in y0])
    sync()  # before any step's deltas (a step's vectors may sit on other threads than these zeros)
    c = start(x0, (z0, y0, jnp.zeros((), x0.dtype)))
    c = jax.lax.fori_loop(0, iters, step, c)
    k = jnp.int32(iters)
    if max_iters > iters:
        def unconverged(w):
            k, c = w
            x, ax, z, y, bad = c
            return (k < max_iters) & (bad == 0.0) & jnp.logical_not(test(x, ax, z, y)[2])

        def block(w):
            k, c = w
            active = jnp.minimum(check_every, max_iters - k)
            return k + active, jax.lax.fori_loop(0, active, step, start(c[0], c[2:]))

        k, c = jax.lax.while_loop(unconverged, block, (k, c))
    x, ax, z, y, bad = c
    # the epilogue in phases, a barrier between them (so the compiler does not interleave them: straight-line, the
    # certificates, the residuals and the result took more registers than a thread has): the certificates, then
    # the residuals and the next rho, then the result
    sync()  # every thread's last deltas written
    dx, dy = _read_vec(x_ref, x0.shape[0], dims.n), _read_rows(y_ref, dims)
    D, scal = st.D[...], st.scal[...]
    cs = _entry(scal, 0)
    E = [1.0 / e for e in Ei]
    l, u = list(_read_blocks(l_refs, dims)), list(_read_blocks(u_refs, dims))
    pinf = rules.primal_infeasible(l, u, [e * a / cs for a, e in zip(dy, E)],
                                   lambda v: rows_t([a * e for a, e in zip(v, Ei)]) / D, s)
    dinf = rules.dual_infeasible(l, u, D * dx, [a * e for a, e in zip(rows(dx), Ei)], _mv(P(0), dx) * Dc,
                                 jnp.sum(q(0) * dx) / cs, s)
    empty = rules.amax(*[jnp.where(a > b, 1.0, 0.0) for a, b in zip(l, u)]) > 0.0
    sync()
    prim, dual, conv = test(x, ax, z, y)
    xu, zu, yu = D * x, [a * e for a, e in zip(z, Ei)], [e * a / cs for a, e in zip(y, E)]
    flag = rules.status(_finite(xu, *zu, *yu, prim, dual) & (bad == 0.0), empty, pinf, dinf, conv)
    rho_out = _entry(scal, 1)
    if s.adapt_every > 0:
        rho_out = rules.adapt_rho(rho_out, *rules.rel_residuals(ax, z, _mv(P(0), x), rows_t(y), q(0), 1e-30), s)
    fmax = float(jnp.finfo(x.dtype).max)
    sync()  # every thread's reads of the deltas done
    _write_vec(x_ref, rules.clean(xu, 0.0, fmax), dims.n)
    _write_rows(z_ref, dims, [rules.clean(v, 0.0, fmax) for v in zu])
    _write_rows(y_ref, dims, [rules.clean(v, 0.0, fmax) for v in yu])
    # each scalar its own (1,) output: the caller's reshape to () is free (sliced from one info vector they were five
    # slices and two conversions, ~6 us per control step at batch 270, H100)
    one = jnp.zeros((1,), x.dtype)
    flag_ref[...] = (one + flag).astype(jnp.int32)
    iters_ref[...] = jnp.zeros((1,), jnp.int32) + k
    prim_ref[...] = rules.clean(one + prim, fmax, fmax)  # NaN residuals: fmax
    dual_ref[...] = rules.clean(one + dual, fmax, fmax)
    rho_ref[...] = rules.clean(one + rho_out, s.rho, fmax)  # NaN rho: the settings' rho


@functools.partial(jax.jit, static_argnames=("s", "iters", "warm", "ne", "num_warps", "factor_warps"))
def fused_solve(P, A, q, l, u, wx, wz, wy, rho, *, s: QPSettings, iters: int, warm: bool, ne: int,
                num_warps: int = 2, factor_warps: int = 2) -> QPResult:
    """One QP solved by the three kernels: its preparation, its factorization, then the iterations and everything
    after them.

    Args:
        P: (n, n) cost; A: (m, n) the rows: the exact block's ``ne`` first, the box block's ``s.box_rows`` last
            (row ``m - nb + i`` bounds variable ``n - nb + i`` alone), the dense block's between; q: (n,); all in
            the user's units. ``P`` and ``A`` reach the preparation kernel as they are (masked loads, no padded
            copies; in Pallas' interpreter, on a CPU, padded first).
        l, u: (m,) bounds (finite, ``+-BIG``).
        wx: (n,), wz, wy: (m,) the warm start (user's units; ignored when ``warm`` is False).
        rho: () the solve's rho (:func:`wbc_jax.qp.rules.warm_rho`).
        s: the solver's settings (``sigma``, ``alpha``, tolerances, ``iters``/``max_iters``/``check_every``, rho
            rules, ``box_rows``); iters: the fixed iterations; warm: start from ``wx, wz, wy``; ne: the exact
            block's rows.
        num_warps, factor_warps: Triton warps per program of the preparation and iteration kernels, and of the
            factorization kernel (module docstring).

    Returns:
        :class:`~wbc_jax.qp.settings.QPResult`, rows in their order (exact, dense, box).
    """
    (m, n), nb = A.shape, s.box_rows
    dims = Dims(n, ne, m - ne - nb, nb)
    mi = dims.mi
    N, NE, MI = _pow2(n), _pow2(ne), _pow2(mi)
    dt = P.dtype
    interpret = jax.default_backend() == "cpu"
    if interpret:  # the interpreter slices as XLA does: every tile inside its matrix
        pn = (0, N - n)
        P, A = jnp.pad(P, (pn, pn)), jnp.pad(A, ((0, max(m, NE, ne + MI) - m), pn))
    elif ne + MI > m:  # the dense block's tile starts at row ne (a static start past 0 is bounds-checked)
        A = jnp.pad(A, ((0, ne + MI - m), (0, 0)))
    # the bounds as their blocks: XLA then builds each block where the rows are assembled (as one fusion of all
    # the rows, the bounds' assembly cost 37.5 us per control step at batch 270, H100)
    parts = (slice(0, ne), slice(ne, m - nb), slice(m - nb, m))
    lb, ub = ([v[p] if p.stop > p.start else jnp.zeros(1, dt) for p in parts] for v in (l, u))
    ins = [P, A, q, *lb, *ub, wy, jnp.reshape(rho, (1,)).astype(dt), wx, wz]
    params = fparams = None
    sync = _no_sync
    if not interpret:
        from jax.experimental.pallas import triton as plgpu

        params = plgpu.CompilerParams(num_warps=num_warps, num_stages=1)
        fparams = plgpu.CompilerParams(num_warps=factor_warps, num_stages=1)
        sync = plgpu.debug_barrier  # __syncthreads
    sd = lambda *sh: jax.ShapeDtypeStruct(sh, dt)  # noqa: E731
    rowb = (sd(NE), sd(MI), sd(N))
    shapes = Stage(sd(N, N), sd(NE, N), sd(MI, N), sd(N), sd(N), sd(N), sd(N), sd(N), rowb, rowb, rowb, rowb, rowb,
                   sd(N), rowb, rowb, sd(NE), sd(NE), sd(16))
    treedef = jax.tree_util.tree_structure(shapes)
    with jax.named_scope("qp_equilibrate"):
        st = pl.pallas_call(
            functools.partial(_prepare_kernel, s=s, dims=dims, warm=warm, treedef=treedef), interpret=interpret,
            compiler_params=params, out_shape=jax.tree_util.tree_leaves(shapes), name="admm_prepare")(*ins)
    st = jax.tree_util.tree_unflatten(treedef, st)
    with jax.named_scope("qp_factor"):
        factors = pl.pallas_call(
            functools.partial(_factor_kernel, n=n, ne=ne, sync=sync), interpret=interpret, compiler_params=fparams,
            out_shape=[sd(N, N), sd(N, NE), sd(NE, NE)], name="admm_factor",
        )(st.P, st.Ae, st.Ai, st.kd, st.rho[0], st.rho[1], st.exe)
    kern = functools.partial(_kernel, s=s, iters=iters, max_iters=max(s.max_iters, iters),
                             check_every=max(s.check_every, 1), treedef=treedef, dims=dims, sync=sync)
    with jax.named_scope("qp_iterations"):
        i1 = jax.ShapeDtypeStruct((1,), jnp.int32)
        x, z, y, flag, k, prim, dual, rho_out = pl.pallas_call(
            kern, out_shape=[sd(n), sd(m), sd(m), i1, i1, sd(1), sd(1), sd(1)], interpret=interpret,
            compiler_params=params, name="admm_iterations",
        )(*jax.tree_util.tree_leaves(st), *factors, *lb, *ub)
    return QPResult(x=x, y=y, z=z, prim_res=prim[0], dual_res=dual[0], flag=flag[0], iters=k[0], rho=rho_out[0])
