"""Ruiz equilibration of a dense QP and the dense linear-algebra helpers the solver shares.

The equilibrated problem is ``Pb = c D P D``, ``qb = c D q``, ``Ab = E A D``, ``lb = E l``, ``ub = E u``: OSQP's
Ruiz passes on the KKT matrix ``[[P, A'], [A, 0]]``, except that the cost is scaled in each pass by the mean column
norm of ``P`` alone (OSQP also takes ``||q||_inf``), which keeps the scaled problem's good rho independent of a
constant factor on the whole cost, as whole-body-control gains apply.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

_MIN_SCALING = 1e-4
_MAX_SCALING = 1e4
_MIN_COST_SCALING = 1e-8  # wider than OSQP: keeps the cost scale-invariant over 1e-6..1e6
_MAX_COST_SCALING = 1e8
HI = lax.Precision.HIGHEST  # no TF32 on GPU: the iteration needs full float32


class Scaled(NamedTuple):
    """Equilibrated problem: ``P = c D P0 D``, ``q = c D q0``, ``A = E A0 D``, ``l = E l0``, ``u = E u0``."""

    P: jax.Array  # (n, n)
    q: jax.Array  # (n,)
    A: jax.Array  # (m, n)
    l: jax.Array  # (m,)
    u: jax.Array  # (m,)
    D: jax.Array  # (n,) column scaling
    E: jax.Array  # (m,) row scaling
    c: jax.Array  # () cost scaling


def mv(M, v):
    """Matrix-vector (or matrix-matrix) product at full precision."""
    return jnp.matmul(M, v, precision=HI)


def all_finite(*vs):
    """() bool: every entry of every array is finite."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in vs]))


def _limit(v):
    """OSQP's ``limit_scaling``: tiny norms -> 1, huge -> clipped."""
    return jnp.where(v < _MIN_SCALING, 1.0, jnp.minimum(v, _MAX_SCALING))


def absmax(M, axis: int):
    """``max |M|`` along ``axis`` (0 along an empty axis); no ``initial`` where the axis is not empty, so that it also
    lowers inside a Triton kernel."""
    if M.shape[axis] == 0:
        return jnp.max(jnp.abs(M), axis=axis, initial=0.0)
    return jnp.max(jnp.abs(M), axis=axis)


def ruiz_pass(P, q, rows, diag, n: int):
    """One Ruiz pass on ``[[P, A'], [A, 0]]`` with cost scaling (module docstring), ``A``'s rows given in blocks.

    Args:
        P: (N, N) cost; q: (N,) linear cost.
        rows: tuple of dense row blocks of ``A``, each (r, N).
        diag: (N,) a block of rows that bound one variable each, laid over the variables (row of variable j: ``A``'s
            entry ``diag[j]``; 0 where no such row), or None.
        n: the problem's variables (the cost is scaled by the mean of ``P``'s column norms over them; padding
            variables, if ``N > n``, have zero rows and columns).

    Returns:
        ``(P, q, rows, diag, d, e, ct)``: the scaled parts, the pass's column scaling d (N,), row scalings e (a tuple
        with one (r,) per block, then diag's (N,) when given) and cost scaling ct ().
    """
    col = absmax(P, 0)
    for M in rows:
        col = jnp.maximum(col, absmax(M, 0))
    if diag is not None:
        col = jnp.maximum(col, jnp.abs(diag))
    d = lax.rsqrt(_limit(col))
    e = [lax.rsqrt(_limit(absmax(M, 1))) for M in rows]
    P = d[:, None] * P * d[None, :]
    rows = tuple(ek[:, None] * M * d[None, :] for ek, M in zip(e, rows))
    if diag is not None:
        e.append(lax.rsqrt(_limit(jnp.abs(diag))))
        diag = e[-1] * diag * d
    q = d * q
    ct = 1.0 / jnp.clip(jnp.sum(absmax(P, 0)) / n, _MIN_COST_SCALING, _MAX_COST_SCALING)
    return ct * P, ct * q, rows, diag, d, tuple(e), ct


def equilibrate(P, q, A, l, u, ruiz_iters: int, unroll: int | bool = 1) -> Scaled:
    """Ruiz equilibration of ``[[P, A'], [A, 0]]`` with cost scaling (module docstring; :func:`ruiz_pass`).

    Args:
        P: (n, n), q: (n,), A: (m, n), l, u: (m,) the problem (bounds finite, ``+-BIG``).
        ruiz_iters: passes (0: no scaling, ``D = E = c = 1``).
        unroll: ``lax.scan``'s unroll of the passes.

    Returns:
        The scaled problem with its scalings.
    """
    n, m = P.shape[0], A.shape[0]
    dt = P.dtype

    def one_pass(carry, _):
        P, q, A, D, E, c = carry
        P, q, (A,), _, d, (e,), ct = ruiz_pass(P, q, (A,), None, n)
        return (P, q, A, D * d, E * e, ct * c), None

    init = (P, q, A, jnp.ones(n, dt), jnp.ones(m, dt), jnp.ones((), dt))
    if ruiz_iters > 0:
        init, _ = lax.scan(one_pass, init, None, length=ruiz_iters, unroll=unroll)
    P, q, A, D, E, c = init
    P = 0.5 * (P + P.T)
    return Scaled(P, q, A, E * l, E * u, D, E, c)


def regularize_schur(S, held):
    """The x-update's Schur complement ``S`` (k, k) made symmetric, plus on its diagonal the dtype's epsilon times its
    largest diagonal entry (dependent equality rows; the residual form of the step corrects what it leaves) on the
    ``held`` (k,) rows and 1 on the others, whose multiplier then stays 0. Masked reductions instead of
    ``jnp.diagonal``, so the same function runs in XLA and inside the fused path's Triton kernel."""
    k = S.shape[0]
    eye = lax.broadcasted_iota(jnp.int32, (k, k), 0) == lax.broadcasted_iota(jnp.int32, (k, k), 1)
    info = jnp.finfo(S.dtype)
    reg = float(info.eps) * jnp.max(jnp.abs(jnp.sum(jnp.where(eye, S, 0.0), axis=1))) + float(info.tiny)
    return 0.5 * (S + S.T) + jnp.where(eye, jnp.where(held, reg, 1.0)[:, None], 0.0)


def factor(K, linsolve: str):
    """Linear solver for ``K x = b`` (K (n, n) symmetric positive definite).

    Returns:
        The lower Cholesky factor (``linsolve="chol"``) or the explicit inverse
        ``L^-T L^-1`` (``"inv"``), for :func:`solve`.
    """
    L = jnp.linalg.cholesky(K)
    if linsolve == "inv":
        Li = jax.scipy.linalg.solve_triangular(L, jnp.eye(K.shape[0], dtype=K.dtype), lower=True)
        return jnp.matmul(Li.T, Li, precision=HI)
    return L


def solve(fac, b, linsolve: str):
    """``K^-1 b`` from :func:`factor`'s output."""
    if linsolve == "inv":
        return mv(fac, b)
    return jax.scipy.linalg.cho_solve((fac, True), b)
