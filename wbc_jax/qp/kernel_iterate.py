"""The fused path's third Pallas kernel: one problem's ADMM iterations and its result in the user's units.

From the :class:`~.kernel_layout.Stage` and the factors, one program runs ``iters`` iterations, then blocks of
``check_every`` more while its own residuals are outside tolerance (up to ``max_iters``), and writes ``x``, ``z``,
``y`` in the user's layout with the residuals, the infeasibility certificates' flag and the next rho. The step is
the XLA path's (:func:`wbc_jax.qp.admm._step` with ``linsolve="inv"``, the projection onto the exact rows at each
block's start); the convergence test is OSQP's in the user's units from the scaled iterate
(``A x - z = E^-1 (A_s x_s - z_s)``, ``P x + q + A'y = c^-1 D^-1 (P_s x_s + q_s + A_s' y_s)``). ``A x`` is
carried from step to step (``A x_next = alpha A xt + (1 - alpha) A x``) and recomputed at each block's start, and a
step's finiteness is checked on ``xt`` and the exact rows' multiplier step, whose finiteness implies every other
new entry's. With the extension, rho is re-estimated from the final iterate (the XLA path: after the fixed
iterations).
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from wbc_jax.qp import rules
from wbc_jax.qp.kernel_layout import (
    Dims,
    entry,
    is_finite,
    matvec,
    read_blocks,
    read_rows,
    read_vec,
    rmatvec,
    tile,
    write_rows,
    write_vec,
)
from wbc_jax.qp.settings import QPSettings


class _Outputs(NamedTuple):
    """The kernel's output refs: ``x`` (n,), ``z``, ``y`` (m,) in the user's layout (``x`` and ``y`` hold the last
    step's deltas until the result overwrites them), then (1,) each: flag, iterations, residuals, next rho."""

    x: object
    z: object
    y: object
    flag: object
    iters: object
    prim: object
    dual: object
    rho: object


class _Operands(NamedTuple):
    """The read-only operands, each a function of the offset ``o`` (:func:`_at`) that loads its tile where a step
    uses it (held across the loop, they and the iterate took more registers than a thread has); the per-row ones
    take the block ``b`` (0 exact, 1 dense, 2 box) first."""

    P: Callable
    Ki: Callable
    Ae: Callable
    Ai: Callable
    db: Callable
    W: Callable
    Si: Callable
    q: Callable
    le: Callable
    exe: Callable
    lo: Callable
    hi: Callable
    rho: Callable
    free: Callable


class _Program(NamedTuple):
    """What every part of one program reads: operands, settings, sizes, outputs, the scalings loaded once
    (``Dc`` (N,) ``1 / (c D)``, ``Ei`` the blocks' ``1 / E``) and the barrier ``sync``."""

    ops: _Operands
    s: QPSettings
    dims: Dims
    out: _Outputs
    Dc: jax.Array
    Ei: list
    sync: Callable


def _at(ref, o):
    """``ref[...]`` at the loop-variant offset ``o`` (always 0): a load that is not hoisted out of the loop."""
    return ref[(pl.ds(o, ref.shape[0]),) + (slice(None),) * (len(ref.shape) - 1)]


def _operands(st, Ki_ref, W_ref, Si_ref, dims: Dims) -> _Operands:
    """The :class:`_Operands` of the stage ``st`` (refs) and the factors. The matrices are read at their real sizes
    (:func:`~.kernel_layout.tile` at the loop-variant offset): their padding, zero in storage, comes as zeros
    without being loaded, since the loads' bytes bound an iteration at large batch."""
    n, ne, mi = dims.n, dims.ne, dims.mi

    def real(ref, rows: int, cols: int):
        return lambda o: tile(ref, o, *ref.shape, rows, cols)

    def at(ref):
        return functools.partial(_at, ref)

    lo, hi, rho = (lambda b, o, f=f: _at(f[b], o) for f in (st.lo, st.hi, st.rho))
    free = lambda b, o: _at(st.free[b], o) > 0.5  # noqa: E731
    return _Operands(real(st.P, n, n), real(Ki_ref, n, n), real(st.Ae, ne, n), real(st.Ai, mi, n), at(st.db),
                     real(W_ref, n, ne), real(Si_ref, ne, ne), at(st.q), at(st.le), at(st.exe), lo, hi, rho, free)


def _rows(ops: _Operands, x, o=0):
    """``A x`` per block."""
    return [matvec(ops.Ae(o), x), matvec(ops.Ai(o), x), ops.db(o) * x]


def _rows_t(ops: _Operands, v, o=0):
    """``A' v`` from the blocks' ``v``."""
    return rmatvec(ops.Ae(o), v[0]) + rmatvec(ops.Ai(o), v[1]) + ops.db(o) * v[2]


def _project(ops: _Operands, x):
    """``x`` moved onto the exact rows (:func:`wbc_jax.qp.admm._project`), unchanged where that is not finite."""
    xn = x + matvec(ops.W(0), matvec(ops.Si(0), ops.exe(0) * (ops.le(0) - matvec(ops.Ae(0), x))))
    return jnp.where(is_finite(xn), xn, x)


def _block_start(ops: _Operands, x, c):
    """A block's start: ``x`` projected onto the exact rows, ``A x`` recomputed (no drift); ``c``: (z, y, bad)."""
    x = _project(ops, x)
    return (x, _rows(ops, x)) + tuple(c)


def _step(pg: _Program, c):
    """One ADMM step on the carry ``(x, ax, z, y, bad)`` (``ax = A x``); rejects a non-finite step (``bad`` 1).
    The step's deltas (the certificates' directions) go to the outputs ``x`` and ``y``."""
    ops, alpha, dims = pg.ops, pg.s.alpha, pg.dims
    x, ax, z, y, bad = c
    o = (bad > 2.0).astype(jnp.int32)  # 0 (bad is 0 or 1), but not known to be
    r = matvec(ops.P(o), x) + ops.q(o) + _rows_t(ops, [y[b] + ops.rho(b, o) * (ax[b] - z[b]) for b in range(3)], o)
    t = matvec(ops.Ki(o), r)
    exe_ = ops.exe(o)
    dnu = -matvec(ops.Si(o), exe_ * (ops.le(o) - ax[0]) + exe_ * matvec(ops.Ae(o), t))
    xt = x - t - matvec(ops.W(o), dnu)
    zt = _rows(ops, xt, o)
    xn = alpha * xt + (1.0 - alpha) * x
    axn, zn, yn = [], [], []
    for b in range(3):
        axn.append(alpha * zt[b] + (1.0 - alpha) * ax[b])
        zr = alpha * zt[b] + (1.0 - alpha) * z[b]
        rb = ops.rho(b, o)
        # z's step y / rho; exact rows and padding: y / 1 (l == u)
        zb = jnp.minimum(jnp.maximum(zr + y[b] / jnp.where(rb > 0.0, rb, 1.0), ops.lo(b, o)), ops.hi(b, o))
        yb = y[b] + rb * (zr - zb)
        fb = ops.free(b, o)
        zn.append(jnp.where(fb, axn[b], zb))
        yn.append(jnp.where(fb, 0.0, yb))
    yn[0] = yn[0] + exe_ * dnu
    ok = is_finite(xn, dnu)  # finite xt and dnu make every new entry finite
    keep = lambda new, old: [jnp.where(ok, a, b) for a, b in zip(new, old)]  # noqa: E731
    write_vec(pg.out.x, xn - x, dims.n, ok)
    write_rows(pg.out.y, dims, [a - b for a, b in zip(yn, y)], ok)
    return jnp.where(ok, xn, x), keep(axn, ax), keep(zn, z), keep(yn, y), jnp.where(ok, bad, 1.0)


def _termination(pg: _Program, x, ax, z, y):
    """:func:`wbc_jax.qp.rules.termination` in the user's units, from the scaled iterate (``ax = A x``)."""
    Ei, Dc, ops = pg.Ei, pg.Dc, pg.ops
    return rules.termination([a * e for a, e in zip(ax, Ei)], [a * e for a, e in zip(z, Ei)],
                             matvec(ops.P(0), x) * Dc, _rows_t(ops, y) * Dc, ops.q(0) * Dc, pg.s)


def _iterations(pg: _Program, st, iters: int, max_iters: int, check_every: int, first=None):
    """``iters`` steps from the stage's start, then blocks of ``check_every`` while unconverged, up to
    ``max_iters``: ``(k, carry, test)``, the steps run (() int32), the final ``(x, ax, z, y, bad)`` and the last
    block's :func:`_termination` of it ``(prim, dual, converged)`` (None with no test: ``max_iters <= iters``).

    One loop of blocks, the fixed steps its first block, each block starting with :func:`_block_start` and the
    test after it: the step and the test are each emitted once in the kernel (a second copy of the step, in a
    loop of its own before the blocks, made every block's iterations slower). ``first`` (() int32): the first
    block's length when not ``iters`` (``QPSettings.warm_first_test``)."""
    x0 = st.x[...]
    z0, y0 = [r[...] for r in st.z], [r[...] for r in st.y]
    write_vec(pg.out.x, jnp.zeros_like(x0), pg.dims.n)  # no step yet: zero deltas
    write_rows(pg.out.y, pg.dims, [jnp.zeros_like(v) for v in y0])
    pg.sync()  # before any step's deltas (a step's vectors may sit on other threads than these zeros)
    step = lambda _, c: _step(pg, c)  # noqa: E731
    if max_iters <= iters:
        c = _block_start(pg.ops, x0, (z0, y0, jnp.zeros((), x0.dtype)))
        return jnp.int32(iters), jax.lax.fori_loop(0, iters, step, c), None

    def unconverged(w):
        k, c, (_, _, done) = w
        return (k < max_iters) & (c[4] == 0.0) & (done == 0)

    def block(w):
        k, c, _ = w
        n = jnp.where(k == 0, iters if first is None else first, jnp.minimum(check_every, max_iters - k))
        c = jax.lax.fori_loop(0, n, step, _block_start(pg.ops, c[0], c[2:]))
        x, ax, z, y, _ = c
        prim, dual, conv = _termination(pg, x, ax, z, y)
        return k + n, c, (prim, dual, conv.astype(jnp.int32))

    c = (x0, [jnp.zeros_like(v) for v in z0], z0, y0, jnp.zeros((), x0.dtype))  # ax: set by the block's start
    zero = jnp.zeros((), x0.dtype)
    k, c, (prim, dual, done) = jax.lax.while_loop(unconverged, block, (jnp.int32(0), c, (zero, zero, jnp.int32(0))))
    return k, c, (prim, dual, done > 0)


def _infeasibility(pg: _Program, dx, dy, D, cs, E, l, u):
    """``(pinf, dinf)``: OSQP's certificates on the last step's deltas ``dx``, ``dy`` (scaled), in the user's
    units (:mod:`wbc_jax.qp.rules`); ``l``, ``u``: the bounds' blocks (:func:`~.kernel_layout.read_blocks`)."""
    ops, Ei, s = pg.ops, pg.Ei, pg.s
    pinf = rules.primal_infeasible(l, u, [e * a / cs for a, e in zip(dy, E)],
                                   lambda v: _rows_t(ops, [a * e for a, e in zip(v, Ei)]) / D, s)
    dinf = rules.dual_infeasible(l, u, D * dx, [a * e for a, e in zip(_rows(ops, dx), Ei)],
                                 matvec(ops.P(0), dx) * pg.Dc, jnp.sum(ops.q(0) * dx) / cs, s)
    return pinf, dinf


def _finish(pg: _Program, st, k, c, l_refs, u_refs, test=None) -> None:
    """The result in the user's units, its residuals, flag and next rho, written to the outputs; ``test``: the
    final iterate's :func:`_termination` where the loop computed it (else computed here). In phases with a
    barrier between them (straight-line, the compiler interleaved them and ran out of registers): the residuals
    and, for an unconverged solve only, the certificates; then rho; then the writes."""
    ops, s, dims, out = pg.ops, pg.s, pg.dims, pg.out
    x, ax, z, y, bad = c
    pg.sync()  # every thread's last deltas written
    dx, dy = read_vec(out.x, x.shape[0], dims.n), read_rows(out.y, dims)
    D, scal = st.D[...], st.scal[...]
    cs = entry(scal, 0)
    E = [1.0 / e for e in pg.Ei]
    prim, dual, conv = _termination(pg, x, ax, z, y) if test is None else test
    l, u = list(read_blocks(l_refs, dims)), list(read_blocks(u_refs, dims))
    empty = rules.amax(*[jnp.where(a > b, 1.0, 0.0) for a, b in zip(l, u)]) > 0.0
    # a converged solve's flag does not read the certificates (rules.status); the skipped branch returns values
    # computed from ``conv`` (Triton's lowering of a branch cannot yield a constant)
    no = lambda: (conv & ~conv, conv & ~conv)  # noqa: E731
    pinf, dinf = jax.lax.cond(conv, no, lambda: _infeasibility(pg, dx, dy, D, cs, E, l, u))
    pg.sync()
    xu, zu, yu = D * x, [a * e for a, e in zip(z, pg.Ei)], [e * a / cs for a, e in zip(y, E)]
    flag = rules.status(is_finite(xu, *zu, *yu, prim, dual) & (bad == 0.0), empty, pinf, dinf, conv)
    rho_out = entry(scal, 1)
    if s.adapt_every > 0:
        rho_out = rules.adapt_rho(rho_out, *rules.rel_residuals(ax, z, matvec(ops.P(0), x), _rows_t(ops, y),
                                                                ops.q(0), 1e-30), s)
    fmax = float(jnp.finfo(x.dtype).max)
    pg.sync()  # every thread's reads of the deltas done
    write_vec(out.x, rules.clean(xu, 0.0, fmax), dims.n)
    write_rows(out.z, dims, [rules.clean(v, 0.0, fmax) for v in zu])
    write_rows(out.y, dims, [rules.clean(v, 0.0, fmax) for v in yu])
    # each scalar its own (1,) output: the caller's reshape to () is free
    one = jnp.zeros((1,), x.dtype)
    out.flag[...] = (one + flag).astype(jnp.int32)
    out.iters[...] = jnp.zeros((1,), jnp.int32) + k
    out.prim[...] = rules.clean(one + prim, fmax, fmax)  # NaN residuals: fmax
    out.dual[...] = rules.clean(one + dual, fmax, fmax)
    out.rho[...] = rules.clean(one + rho_out, s.rho, fmax)  # NaN rho: the settings' rho


def iterate_kernel(*refs, s: QPSettings, iters: int, max_iters: int, check_every: int, treedef, dims: Dims, sync,
                   first: bool = False):
    """One problem's solve from its stage and factors (module docstring).

    Args:
        refs: the stage's leaves (``treedef``), the factors ``Ki``, ``W``, ``Si``, the user's bounds ``l`` and
            ``u`` as their three blocks each (for the certificates), with ``first`` the first block's length (1,)
            int32, then the outputs (:class:`_Outputs`).
        s: the settings; iters, max_iters, check_every: the fixed steps, the cap and the block length.
        dims: the real sizes; sync: ``__syncthreads`` on a GPU, :func:`~.kernel_layout.no_sync` in the interpreter.
    """
    n_stage = treedef.num_leaves
    st = jax.tree_util.tree_unflatten(treedef, refs[:n_stage])
    Ki_ref, W_ref, Si_ref = refs[n_stage:n_stage + 3]
    l_refs, u_refs = refs[n_stage + 3:n_stage + 6], refs[n_stage + 6:n_stage + 9]
    first_len = jnp.sum(refs[n_stage + 9][...]).astype(jnp.int32) if first else None
    out = _Outputs(*refs[n_stage + 9 + int(first):])
    Dc = st.Dc[...]
    Ei = [r[...] for r in st.Ei]
    pg = _Program(_operands(st, Ki_ref, W_ref, Si_ref, dims), s, dims, out, Dc, Ei, sync)
    k, c, test = _iterations(pg, st, iters, max_iters, check_every, first_len)
    _finish(pg, st, k, c, l_refs, u_refs, test)
