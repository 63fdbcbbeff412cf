"""The fused path of :func:`wbc_jax.qp.solve_qp`: one solve as three Pallas (Triton) kernels, one program per
problem each (``QPSettings.kernel="fused"``).

1. :mod:`~wbc_jax.qp.kernel_prepare`: Ruiz equilibration, the rows' kinds and rho, the scaled warm start;
2. :mod:`~wbc_jax.qp.kernel_factor`: the x-update's factors as explicit inverses (``K^-1``, ``W``, ``S^-1``);
3. :mod:`~wbc_jax.qp.kernel_iterate`: the ADMM iterations with the convergence-checked extension, then the result
   in the user's units with its residuals, certificates, flag and next rho.

With ``QPSettings.reuse_factors`` a result carries its factors and what they were made from
(:class:`~wbc_jax.qp.kernel_layout.Factors`); the next solve warm-started from it scales the problem by their
scaling with their rho and, per problem where no row changed kind, keeps them: its factorization program writes
nothing into the outputs aliased to them. It then factors again the solve after. The ADMM step is residual-based,
so kept factors only precondition it: the fixed point and the convergence test are the current problem's; but
the step with them can diverge where the problem moved far from theirs (``FLAG_DIVERGED``, docs/performance.md).

The rows come in three blocks (exact, dense, box; :mod:`~wbc_jax.qp.kernel_layout`). The user's arrays reach the
kernels as they are (masked loads) and ``x``, ``z``, ``y`` are written in the user's layout, so no XLA op pads,
slices or concatenates around the kernels. One program per problem loads its matrices once and stops at its own
convergence, where the XLA path under ``vmap`` launches several kernels per iteration and runs every problem until
the batch's slowest has converged. Results equal the XLA path's (:mod:`wbc_jax.qp.admm`, ``linsolve="inv"``) up to
float rounding, except the re-estimated rho with the extension (:mod:`~wbc_jax.qp.kernel_iterate`). ``vmap`` adds
a grid axis; on a CPU the kernels run in Pallas' interpreter (slow: tests only). Built for float32 (Triton's
lowering of these kernels fails in float64).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from wbc_jax.qp import rules
from wbc_jax.qp.kernel_factor import factor_kernel, factor_or_keep_kernel
from wbc_jax.qp.kernel_iterate import iterate_kernel
from wbc_jax.qp.kernel_layout import Dims, Factors, no_sync, pow2
from wbc_jax.qp.kernel_order import launch, one_wave, predicted_length
from wbc_jax.qp.kernel_prepare import prepare_kernel, stage_shapes
from wbc_jax.qp.settings import QPResult, QPSettings


def solve_fused(P, q, A, l, u, warm, s: QPSettings, iters: int, interpret: bool | None = None) -> QPResult:
    """One problem (already in one floating dtype, bounds finite) through :func:`fused_solve`: the rows split into
    the kernels' blocks, the first ``ne`` exact, the last ``box_rows`` a diagonal, the dense rows between.

    Args:
        warm: None (cold) or ``(x, z, y, rho or None, iters or None, factors or None)`` in the user's units
            (``factors``: :class:`~wbc_jax.qp.kernel_layout.Factors`, read with ``s.reuse_factors``).
        interpret: :func:`fused_solve`'s.
    """
    dt = P.dtype
    m, n = A.shape
    if warm is None:
        wx, wz, wy = jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros(m, dt)
    else:
        wx, wz, wy = (jnp.asarray(v, dt) for v in warm[:3])
    rho = rules.warm_rho(None if warm is None else warm[3], s, dt)
    first = rules.first_block(warm, s, iters)
    old = None
    if s.reuse_factors:
        old = warm[5] if warm is not None and warm[5] is not None else empty_factors(n, m, s, dt)
        rho = jnp.where(old.fresh, jnp.asarray(old.rho_s, dt), rho)
    key = None
    if s.launch_order == "predicted" and warm is not None:
        wk = jnp.zeros((), jnp.int32) if warm[4] is None else warm[4]
        key = predicted_length(l, u, wz, wk, s)
    return fused_solve(P, A, q, l, u, wx, wz, wy, rho, first, old, key, s=s, iters=iters, warm=warm is not None,
                       interpret=interpret)


def _dims(n: int, m: int, s: QPSettings) -> Dims:
    """The kernels' blocks of a problem of ``n`` variables and ``m`` rows: the first ``ne`` exact, the last
    ``s.box_rows`` a diagonal, the dense rows between."""
    nb = s.box_rows
    ne = max(min(s.eq_rows, m - nb), 1)  # one exact-block row that is not held stands for none
    return Dims(n, ne, m - ne - nb, nb)


def empty_factors(n: int, m: int, s: QPSettings, dt=jnp.float32) -> Factors:
    """The :class:`~wbc_jax.qp.kernel_layout.Factors` of a problem of ``n`` variables and ``m`` rows that no solve
    has made yet (``fresh`` False: the next solve factors), e.g. a control loop's first warm start."""
    dims = _dims(n, m, s)
    N, NE, MI = pow2(n), pow2(dims.ne), pow2(dims.mi)
    rows = (NE, MI, N)
    return Factors(jnp.zeros((N, N), dt), jnp.zeros((N, NE), dt), jnp.zeros((NE, NE), dt), jnp.ones(N, dt),
                   tuple(jnp.ones(r, dt) for r in rows), jnp.ones((), dt), tuple(jnp.zeros(r, dt) for r in rows),
                   jnp.zeros(N, dt), tuple(jnp.zeros(r, dt) for r in rows), jnp.ones((), dt), jnp.zeros((), bool))


def _kinds(st) -> tuple:
    """Per row of a :class:`~wbc_jax.qp.kernel_layout.Stage`, each block's: 1.0 without bounds + 2.0 an equality
    (the kinds :func:`~wbc_jax.qp.kernel_prepare.prepare` gives each row its rho by)."""
    return tuple(f + 2.0 * (jnp.abs(h - lo) < rules.EQ_TOL) for f, lo, h in zip(st.free, st.lo, st.hi))


def _pad_matrices(P, A, dims: Dims, interpret: bool):
    """``P`` and ``A`` as the kernels' tiles may read them: in the interpreter (which slices as XLA does) padded
    to whole tiles; on a GPU unpadded, except ``A``'s rows where the dense block's tile (from row ``ne``) would
    start past the end (a static start is bounds-checked)."""
    m = A.shape[0]
    N, NE, MI = pow2(dims.n), pow2(dims.ne), pow2(dims.mi)
    if interpret:
        pn = (0, N - dims.n)
        return jnp.pad(P, (pn, pn)), jnp.pad(A, ((0, max(m, NE, dims.ne + MI) - m), pn))
    if dims.ne + MI > m:
        return P, jnp.pad(A, ((0, dims.ne + MI - m), (0, 0)))
    return P, A


def _bound_blocks(v, dims: Dims, dt) -> list:
    """A per-row vector (m,) as its three blocks (an empty block as one zero), sliced where the rows are
    assembled."""
    m = dims.ne + dims.mi + dims.nb
    parts = (slice(0, dims.ne), slice(dims.ne, m - dims.nb), slice(m - dims.nb, m))
    return [v[p] if p.stop > p.start else jnp.zeros(1, dt) for p in parts]


def _compiler_params(interpret: bool, num_warps: int, factor_warps: int):
    """``(params, factor_params, sync)``: Triton's settings of the preparation and iterations kernels and of the
    factorization kernel, and the barrier (``__syncthreads``; a no-op in the interpreter)."""
    if interpret:
        return None, None, no_sync
    return (plgpu.CompilerParams(num_warps=num_warps, num_stages=1),
            plgpu.CompilerParams(num_warps=factor_warps, num_stages=1), plgpu.debug_barrier)


@functools.partial(jax.jit, static_argnames=("s", "iters", "warm", "num_warps", "factor_warps", "interpret"))
def fused_solve(P, A, q, l, u, wx, wz, wy, rho, first=None, old=None, key=None, *, s: QPSettings, iters: int,
                warm: bool, num_warps: int = 2, factor_warps: int = 2, interpret: bool | None = None) -> QPResult:
    """One QP solved by the three kernels.

    Args:
        P: (n, n) cost; A: (m, n) the rows in the blocks of :func:`_dims`: the exact block's ``ne`` first, the box
            block's ``s.box_rows`` (nb) last (row ``m - nb + i`` bounds variable ``n - nb + i`` alone), the dense
            block's between; q: (n,); all in the user's units.
        l, u: (m,) bounds (finite, ``+-BIG``).
        wx: (n,), wz, wy: (m,) the warm start (user's units; ignored when ``warm`` is False).
        rho: () the solve's rho (:func:`wbc_jax.qp.rules.warm_rho`).
        first: None, or () int32 the iterations before the first convergence test
            (:func:`wbc_jax.qp.rules.first_block`; None: ``iters``).
        old: None, or an earlier solve's :class:`~wbc_jax.qp.kernel_layout.Factors` (``s.reuse_factors``): where
            they are ``fresh`` the problem is scaled by their scaling (and ``rho`` should be theirs), and where its
            rows' kinds are theirs too the factorization keeps them (its program writes nothing); the result
            carries the factors used, ``fresh`` where this solve factored.
        key: None, or () the problem's launch key under ``vmap`` (``s.launch_order``, :mod:`~.kernel_order`).
        s: the solver's settings; iters: the fixed iterations; warm: start from ``wx, wz, wy``.
        num_warps, factor_warps: Triton warps per program of the preparation and iterations kernels, and of the
            factorization kernel; interpret: Pallas' interpreter (None: on a CPU; False lowers for a GPU anywhere).

    Returns:
        :class:`~wbc_jax.qp.settings.QPResult`, rows in their order (exact, dense, box).
    """
    m, n = A.shape
    dims = _dims(n, m, s)
    ne = dims.ne
    given = old is not None
    N, NE = pow2(n), pow2(ne)
    dt = P.dtype
    interpret = jax.default_backend() == "cpu" if interpret is None else interpret
    P, A = _pad_matrices(P, A, dims, interpret)
    lb, ub = _bound_blocks(l, dims, dt), _bound_blocks(u, dims, dt)
    ins = [P, A, q, *lb, *ub, wy, jnp.reshape(rho, (1,)).astype(dt), wx, wz]
    if given:
        ins += [jnp.reshape(old.fresh, (1,)).astype(dt), old.D, *old.Ei, jnp.reshape(old.c, (1,)).astype(dt)]
    params, fparams, sync = _compiler_params(interpret, num_warps, factor_warps)
    sd = lambda *sh: jax.ShapeDtypeStruct(sh, dt)  # noqa: E731
    shapes = stage_shapes(dims, dt)
    treedef = jax.tree_util.tree_structure(shapes)
    with jax.named_scope("qp_equilibrate"):
        st = pl.pallas_call(
            functools.partial(prepare_kernel, s=s, dims=dims, warm=warm, treedef=treedef, given=given),
            interpret=interpret, compiler_params=params, out_shape=jax.tree_util.tree_leaves(shapes),
            name="admm_prepare")(*ins)
    st = jax.tree_util.tree_unflatten(treedef, st)
    if given:  # the old factors kept where the rows' kinds are theirs (with their rho and K's diagonal)
        kinds = _kinds(st)
        keep = old.fresh & functools.reduce(jnp.logical_and, [jnp.all(a == b) for a, b in zip(kinds, old.kinds)])
        st = st._replace(rho=tuple(jnp.where(keep, o, r) for o, r in zip(old.rho, st.rho)),
                         kd=jnp.where(keep, old.kd, st.kd))
    factor_ins = (st.P, st.Ae, st.Ai, st.kd, st.rho[0], st.rho[1], st.exe)
    with jax.named_scope("qp_factor"):
        if given:
            factors = pl.pallas_call(
                functools.partial(factor_or_keep_kernel, n=n, ne=ne, sync=sync), interpret=interpret,
                compiler_params=fparams, out_shape=[sd(N, N), sd(N, NE), sd(NE, NE)], name="admm_factor",
                input_output_aliases={8: 0, 9: 1, 10: 2},
            )(*factor_ins, jnp.reshape(keep, (1,)).astype(dt), old.Ki, old.W, old.Si)
        else:
            factors = pl.pallas_call(
                functools.partial(factor_kernel, n=n, ne=ne, sync=sync), interpret=interpret,
                compiler_params=fparams, out_shape=[sd(N, N), sd(N, NE), sd(NE, NE)], name="admm_factor",
            )(*factor_ins)
    kern = functools.partial(iterate_kernel, s=s, iters=iters, max_iters=max(s.max_iters, iters),
                             check_every=max(s.check_every, 1), treedef=treedef, dims=dims, sync=sync,
                             first=first is not None)
    extra = [] if first is None else [jnp.reshape(first, (1,)).astype(jnp.int32)]
    with jax.named_scope("qp_iterations"):
        i1 = jax.ShapeDtypeStruct((1,), jnp.int32)
        x, z, y, flag, k, prim, dual, rho_out = launch(
            kern, [sd(n), sd(m), sd(m), i1, i1, sd(1), sd(1), sd(1)], key,
            (*jax.tree_util.tree_leaves(st), *factors, *lb, *ub, *extra), interpret=interpret, compiler_params=params,
            name="admm_iterations", wave=0 if interpret else one_wave(num_warps))
    carried = None
    if given:
        carried = Factors(*factors, st.D, st.Ei, st.scal[0], st.rho, st.kd, kinds, st.scal[1], ~keep)
    return QPResult(x=x, y=y, z=z, prim_res=prim[0], dual_res=dual[0], flag=flag[0], iters=k[0], rho=rho_out[0],
                    factors=carried)
