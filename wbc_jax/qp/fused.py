"""The ADMM iterations of one solve, its convergence-checked extension included, as one Pallas (Triton) kernel.

Why: the XLA path (``admm._step`` in ``lax.scan``, then the extension's ``lax.while_loop``) launches about ten kernels
per iteration and reads ``P``, ``A``, ``K^-1`` and the Schur factors from device memory at every one. Under ``vmap``
the extension's loop also runs every problem of the batch until the slowest has converged: the batch pays the
largest count of the step (a run's mean on the course is 21.6 iterations per step, its most 200). Here one program
per problem loads its matrices once, runs the ``iters`` iterations and the blocks of ``check_every`` more while its
own residuals are outside tolerance (up to ``max_iters``), and stops on its own. Measured (H100, course, Warp
physics): the paper campaign 171.0 s -> 133.2 s, physics + WBC at batch 16384 431,605 -> 530,978 env-steps/s
(docs/performance.md); the kernel takes 6.3 ms per control step at 16384 and 0.21 ms at 270, limited by the latency
of its nine matrix-vector reductions per iteration (``num_warps`` 2, 4, 8, 16 timed the same).

The arithmetic is ``admm._step``'s with ``linsolve="inv"`` (explicit inverses ``K^-1`` and ``S^-1``, matrix-vector
products only) and the projection onto the exact rows at the start of each block, as ``admm._run`` does; the
convergence test is OSQP's in the user's units (``admm._unscaled``), evaluated from the scaled iterate with the
scalings (``A x - z = E^-1 (A_s x_s - z_s)``, ``P x + q + A'y = c^-1 D^-1 (P_s x_s + q_s + A_s' y_s)``). Results
equal the XLA path up to float rounding (tests compare them in the Pallas interpreter, float64).

Shapes are padded to powers of two (Triton's rule, at least 16): padded variables have zero rows and columns in
every matrix, padded constraint rows are ``0 <= 0 <= 0`` with zero dual, padded exact rows have zero ``S^-1``.
``vmap`` adds a grid axis (one program per problem). On a CPU the kernel runs in Pallas' interpreter (slow; tests
only); the solver uses it where ``QPSettings.kernel`` says so (``"auto"``: on a GPU).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl


class FusedOut(NamedTuple):
    """The kernel's result for one problem (scaled problem)."""

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


def _kernel(P_ref, A_ref, Ae_ref, Ki_ref, W_ref, Si_ref, q_ref, l_ref, u_ref, le_ref, rho_ref, rdiv_ref, exm_ref,
            free_ref, exe_ref, Ei_ref, Dc_ref, x_ref, z_ref, y_ref,
            xo_ref, zo_ref, yo_ref, dxo_ref, dyo_ref, info_ref, *,
            iters: int, max_iters: int, check_every: int, alpha: float, eps_abs: float, eps_rel: float):
    P, A, Ae, Ki, W, Si = P_ref[...], A_ref[...], Ae_ref[...], Ki_ref[...], W_ref[...], Si_ref[...]
    q, lo, hi, le = q_ref[...], l_ref[...], u_ref[...], le_ref[...]
    rho, rdiv, exm, free, exe = rho_ref[...], rdiv_ref[...], exm_ref[...], free_ref[...] > 0.5, exe_ref[...]
    Ei, Dc = Ei_ref[...], Dc_ref[...]
    ne, m = Ae.shape[0], A.shape[0]
    # (ne, m) selection: exact row i is constraint row i (the exact rows are the first ones)
    sel = (jax.lax.broadcasted_iota(jnp.int32, (ne, m), 0) == jax.lax.broadcasted_iota(jnp.int32, (ne, m), 1))
    sel = sel.astype(P.dtype)

    def project(x):  # admm._project
        xn = x + _mv(W, _mv(Si, exe * (le - _mv(Ae, x))))
        return jnp.where(_finite(xn), xn, x)

    def step(_, c):  # admm._step, linsolve "inv"
        x, z, y, dx, dy, bad = c
        ax = _mv(A, x)
        r = _mv(P, x) + q + _mtv(A, y + rho * (ax - z))
        t = _mv(Ki, r)
        dnu = -_mv(Si, exe * (le - _mv(Ae, x)) + _mv(Ae, t))
        xt = x - t - _mv(W, dnu)
        zt = _mv(A, xt)
        xn = alpha * xt + (1.0 - alpha) * x
        zr = alpha * zt + (1.0 - alpha) * z
        zn = jnp.minimum(jnp.maximum(zr + y / rdiv, lo), hi)
        yn = y + rho * (zr - zn)
        zn = jnp.where(free, alpha * zt + (1.0 - alpha) * ax, zn)
        yn = jnp.where(free, 0.0, yn) + exm * _mtv(sel, dnu)
        ok = _finite(xn, zn, yn)
        return (jnp.where(ok, xn, x), jnp.where(ok, zn, z), jnp.where(ok, yn, y),
                jnp.where(ok, xn - x, dx), jnp.where(ok, yn - y, dy), jnp.where(ok, bad, 1.0))

    def converged(x, z, y):  # admm._unscaled's test, from the scaled iterate
        ax, px, aty = _mv(A, x), _mv(P, x), _mtv(A, y)
        prim = _amax((ax - z) * Ei)
        prim_tol = eps_abs + eps_rel * jnp.maximum(_amax(ax * Ei), _amax(z * Ei))
        dual = _amax((px + q + aty) * Dc)
        dual_tol = eps_abs + eps_rel * jnp.maximum(jnp.maximum(_amax(px * Dc), _amax(aty * Dc)), _amax(q * Dc))
        return (prim <= prim_tol) & (dual <= dual_tol)

    x0 = x_ref[...]
    y0 = y_ref[...]
    c = (project(x0), z_ref[...], y0, jnp.zeros_like(x0), jnp.zeros_like(y0), jnp.zeros((), x0.dtype))
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
    zo_ref[...] = z
    yo_ref[...] = y
    dxo_ref[...] = dx
    dyo_ref[...] = dy
    i = jax.lax.broadcasted_iota(jnp.int32, info_ref.shape, 0)
    info_ref[...] = jnp.where(i == 0, bad, jnp.where(i == 1, k.astype(x.dtype), 0.0)).astype(info_ref.dtype)


@functools.partial(jax.jit, static_argnames=("iters", "max_iters", "check_every", "alpha", "eps_abs", "eps_rel",
                                             "num_warps"))
def fused_iterations(P, A, Ae, Kinv, W, Sinv, q, l, u, rho_v, ex, free, E, Dc, x, z, y, *, iters: int,
                     max_iters: int, check_every: int, alpha: float, eps_abs: float, eps_rel: float,
                     num_warps: int = 8) -> FusedOut:
    """``iters`` ADMM iterations of one scaled problem, then blocks of ``check_every`` while unconverged.

    Args:
        P: (n, n), A: (m, n) the scaled problem; Ae: (ne, n) its exact rows (``A[:ne]`` masked by ``ex``).
        Kinv: (n, n) inverse of ``P + sigma I + A' diag(rho_v) A``; W: (n, ne) ``Kinv Ae'``; Sinv: (ne, ne) inverse
            of the Schur complement (``admm.KKT``; identity on rows not held).
        q: (n,), l, u: (m,) finite (``+-BIG``); rho_v: (m,) per-row rho (0 on exact rows); ex, free: (m,) bool.
        E: (m,) row scaling; Dc: (n,) ``1 / (c D)`` (column and cost scaling), for the convergence test.
        x: (n,), z, y: (m,) start (scaled). iters / max_iters / check_every: as ``QPSettings`` (``max_iters <=
            iters``: no extension). alpha: over-relaxation. eps_abs, eps_rel: the test's tolerances.
        num_warps: Triton warps per program.

    Returns:
        :class:`FusedOut`.
    """
    n, m, ne = P.shape[0], A.shape[0], Ae.shape[0]
    N, M, NE = _pow2(n), _pow2(m), _pow2(ne)
    dt = P.dtype
    pn, pm, pe = (0, N - n), (0, M - m), (0, NE - ne)
    le = jnp.where(ex[:ne], l[:ne], 0.0)
    ex_f, free_f = ex.astype(dt), free.astype(dt)
    args = (jnp.pad(P, (pn, pn)), jnp.pad(A, (pm, pn)), jnp.pad(Ae, (pe, pn)), jnp.pad(Kinv, (pn, pn)),
            jnp.pad(W, (pn, pe)), jnp.pad(Sinv * (ex_f[:ne, None] * ex_f[None, :ne]), (pe, pe)),
            jnp.pad(q, pn), jnp.pad(l, pm), jnp.pad(u, pm), jnp.pad(le, pe), jnp.pad(rho_v, pm),
            jnp.pad(jnp.where(ex, 1.0, rho_v), pm, constant_values=1.0), jnp.pad(ex_f, pm), jnp.pad(free_f, pm),
            jnp.pad(ex_f[:ne], pe), jnp.pad(1.0 / E, pm, constant_values=1.0), jnp.pad(Dc, pn, constant_values=1.0),
            jnp.pad(x, pn), jnp.pad(z, pm), jnp.pad(y, pm))
    shapes = [jax.ShapeDtypeStruct(s, dt) for s in ((N,), (M,), (M,), (N,), (M,), (16,))]
    interpret = jax.default_backend() == "cpu"
    params = None
    if not interpret:
        from jax.experimental.pallas import triton as plgpu

        params = plgpu.CompilerParams(num_warps=num_warps, num_stages=1)
    kern = functools.partial(_kernel, iters=iters, max_iters=max_iters, check_every=check_every, alpha=alpha,
                             eps_abs=eps_abs, eps_rel=eps_rel)
    xo, zo, yo, dxo, dyo, info = pl.pallas_call(kern, out_shape=shapes, interpret=interpret, compiler_params=params,
                                                name="admm_iterations")(*args)
    return FusedOut(xo[:n], zo[:m], yo[:m], dxo[:n], dyo[:m], info[0] > 0, info[1].astype(jnp.int32))
