"""One ADMM segment (a fixed number of iterations at fixed rho) as a single Pallas kernel.

The XLA path (``admm._step`` in ``lax.scan``) reads ``P``, ``A`` (three times) and the factor from device memory at
every iteration and launches about ten kernels per iteration; in a batched control loop that makes the solver
memory- and launch-bound (``wbc-jax bench components``). Here one kernel per problem loads ``P``, ``A`` and the
explicit inverse ``K^-1`` of ``P + sigma I + A' diag(rho) A`` once and runs all iterations of the segment on chip.

The iteration is ``admm._step``'s residual form with ``linsolve="inv"``: five matrix-vector products (``A x``,
``A' w``, ``P x``, ``K^-1 r``, ``A xt``; carrying ``A x`` instead lets rounding drift into the residual and was
measurably less accurate in float32). Results equal the XLA path up to float rounding (tests compare them). Shapes are padded to powers of two (Triton's block rule): padded variables have zero rows and columns,
padded constraint rows are ``0 <= 0 <= 0`` with zero dual. ``vmap`` adds a grid axis (one program per problem).
On a CPU backend the kernel runs in Pallas' interpreter (slow; for tests only).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl


def _pow2(k: int) -> int:
    return 1 << max(4, (k - 1).bit_length())


def _kernel(P_ref, A_ref, K_ref, q_ref, l_ref, u_ref, rho_ref, x_ref, z_ref, y_ref,
            xo_ref, zo_ref, yo_ref, dxo_ref, dyo_ref, bad_ref, *, iters: int, alpha: float):
    P = P_ref[...]
    A = A_ref[...]
    K = K_ref[...]
    q = q_ref[...]
    lo = l_ref[...]
    hi = u_ref[...]
    rho = rho_ref[...]

    def mv(M, v):  # M v
        return jnp.sum(M * v[None, :], axis=1)

    def mtv(M, v):  # M' v
        return jnp.sum(M * v[:, None], axis=0)

    def body(_, c):
        x, z, y, dx, dy, bad = c
        w = y + rho * (mv(A, x) - z)
        r = mv(P, x) + q + mtv(A, w)
        xt = x - mv(K, r)
        zt = mv(A, xt)
        xn = alpha * xt + (1.0 - alpha) * x
        zr = alpha * zt + (1.0 - alpha) * z
        zn = jnp.minimum(jnp.maximum(zr + y / rho, lo), hi)
        yn = y + rho * (zr - zn)
        tot = jnp.sum(xn) + jnp.sum(zn) + jnp.sum(yn)
        ok = (tot - tot) == 0.0  # False iff some entry is NaN or +-inf (Triton-friendly isfinite)
        return (jnp.where(ok, xn, x), jnp.where(ok, zn, z), jnp.where(ok, yn, y),
                jnp.where(ok, xn - x, dx), jnp.where(ok, yn - y, dy), jnp.where(ok, bad, 1.0))

    x0 = x_ref[...]
    z0 = z_ref[...]
    y0 = y_ref[...]
    c = (x0, z0, y0, jnp.zeros_like(x0), jnp.zeros_like(y0), jnp.zeros((), x0.dtype))
    x, z, y, dx, dy, bad = jax.lax.fori_loop(0, iters, body, c)
    xo_ref[...] = x
    zo_ref[...] = z
    yo_ref[...] = y
    dxo_ref[...] = dx
    dyo_ref[...] = dy
    bad_ref[...] = jnp.full(bad_ref.shape, bad, bad_ref.dtype)


@functools.partial(jax.jit, static_argnames=("iters", "alpha", "num_warps"))
def fused_segment(P, A, Kinv, q, l, u, rho_v, x, z, y, *, iters: int, alpha: float, num_warps: int = 8):
    """``iters`` ADMM iterations of one (scaled) problem at fixed per-row rho, in one kernel.

    Args:
        P: (n, n), A: (m, n), Kinv: (n, n) inverse of ``P + sigma I + A' diag(rho_v) A``; q: (n,);
        l, u: (m,) finite bounds (the solver's +-BIG for infinite ones); rho_v: (m,) > 0; x: (n,), z, y: (m,).
    Returns:
        (x, z, y, dx, dy, bad): the last iterate, the last accepted steps in x and y, and bad () bool, True when a
        non-finite step was rejected (the iterate then stays at the last finite one).
    """
    n, m = P.shape[0], A.shape[0]
    N, M = _pow2(n), _pow2(m)
    pn, pm = (0, N - n), (0, M - m)
    args = (jnp.pad(P, (pn, pn)), jnp.pad(A, (pm, pn)), jnp.pad(Kinv, (pn, pn)), jnp.pad(q, pn), jnp.pad(l, pm),
            jnp.pad(u, pm), jnp.pad(rho_v, pm, constant_values=1.0), jnp.pad(x, pn), jnp.pad(z, pm), jnp.pad(y, pm))
    dt = P.dtype
    shapes = [jax.ShapeDtypeStruct((N,), dt), jax.ShapeDtypeStruct((M,), dt), jax.ShapeDtypeStruct((M,), dt),
              jax.ShapeDtypeStruct((N,), dt), jax.ShapeDtypeStruct((M,), dt), jax.ShapeDtypeStruct((N,), dt)]
    interpret = jax.default_backend() == "cpu"
    params = None
    if not interpret:
        from jax.experimental.pallas import triton as plgpu

        params = plgpu.CompilerParams(num_warps=num_warps, num_stages=1)
    xo, zo, yo, dxo, dyo, bad = pl.pallas_call(
        functools.partial(_kernel, iters=iters, alpha=alpha), out_shape=shapes, interpret=interpret,
        compiler_params=params, name="admm_segment")(*args)
    return xo[:n], zo[:m], yo[:m], dxo[:n], dyo[:m], bad[0] > 0
