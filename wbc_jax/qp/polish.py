"""Solution polishing (``QPSettings.polish``): primal-dual active-set passes on the equilibrated problem.

After the ADMM iterations, each pass guesses the active rows from ``A x + y`` (OSQP's rule), solves the
equality-constrained KKT system on them (fixed shapes: inactive rows masked; one regularized n x n Cholesky plus
iterative refinement) and guesses again from that solution and its raw multipliers. The point with the smallest
KKT error is kept; only a finite, non-increasing one replaces the iterate, so polishing never makes a result worse
or non-finite, and infeasible problems keep their flags. After OSQP's polishing (Stellato et al. 2020, Sec. 4),
repeated as active-set passes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from wbc_jax.qp.rules import scaled_residuals
from wbc_jax.qp.scaling import HI, Scaled, all_finite, mv
from wbc_jax.qp.settings import BIG, QPSettings


def _kkt_error(sp: Scaled, x, z, y):
    """Relative KKT error ``max(prim, dual)`` of ``(x, z, y)`` (:func:`wbc_jax.qp.rules.rel_residuals`
    with offset 1) in the scaled problem; ``z`` in ``[l, u]`` and ``y`` in its normal
    cone are assumed. Returns ()."""
    return jnp.maximum(*scaled_residuals(sp, x, z, y, 1.0))


def _guess_active(sp: Scaled, ax, y, eq, free):
    """Active set guessed from row values and duals (OSQP's polishing rule).

    Args:
        sp: scaled problem.
        ax: (m,) row values ``A x``.
        y: (m,) duals.
        eq: (m,) bool, equality rows (always active).
        free: (m,) bool, rows without bounds (never active).

    Returns:
        ``(lo, up)``: (m,) bool, inequality rows held at their lower / upper bound,
        where ``ax + y`` lies below ``l`` / above ``u``.
    """
    w = ax + y
    ineq = ~eq & ~free
    lo = ineq & (w < sp.l) & (sp.l > -BIG)
    up = ineq & (w > sp.u) & (sp.u < BIG) & ~lo
    return lo, up


def _kkt_solve(sp: Scaled, lo, up, eq, s: QPSettings):
    """Solve the equality-constrained QP on an active set (fixed shapes).

    The system is ``[[P, A_a'], [A_a, -I_i]] [x; y] = [-q; b_a]``: active rows
    (``eq | lo | up``) are held at their bound ``b``, inactive rows get ``y = 0``
    through the identity block. It is solved with the regularization ``+delta I`` /
    ``-delta I`` (``delta = polish_delta``) reduced to ``x``: one Cholesky of
    ``P + delta I + A' diag(act / delta) A`` (n x n, always positive definite), then
    ``polish_refine`` steps of iterative refinement against the unregularized system.

    Args:
        sp: scaled problem.
        lo, up: (m,) bool, inequality rows at their lower / upper bound.
        eq: (m,) bool, equality rows.
        s: settings (``polish_delta``, ``polish_refine``).

    Returns:
        ``(x, y)``: (n,) solution and (m,) multipliers of the active rows (zero on the
        others, signs not corrected).
    """
    n = sp.P.shape[0]
    dt = sp.P.dtype
    act = lo | up | eq
    a = act.astype(dt)
    Aa = a[:, None] * sp.A
    rhs = jnp.concatenate([-sp.q, a * jnp.where(lo, sp.l, sp.u)])
    K = jnp.block([[sp.P, Aa.T], [Aa, jnp.diag(a - 1.0)]])
    # Regularized bottom block -diag(e): e = delta on active rows, 1 on inactive ones.
    e_inv = a / s.polish_delta + (1.0 - a)
    gram = jnp.matmul(sp.A.T * (a * e_inv)[None, :], sp.A, precision=HI)
    L = jnp.linalg.cholesky(sp.P + s.polish_delta * jnp.eye(n, dtype=dt) + gram)

    def solve(r):
        x = jax.scipy.linalg.cho_solve((L, True), r[:n] + mv(Aa.T, e_inv * r[n:]))
        return jnp.concatenate([x, e_inv * (mv(Aa, x) - r[n:])])

    v = solve(rhs)
    for _ in range(s.polish_refine):
        v = v + solve(rhs - mv(K, v))
    return v[:n], jnp.where(act, v[n:], 0.0)


def polish(sp: Scaled, x, z, y, eq, free, s: QPSettings):
    """Solution polishing by primal-dual active-set passes, keeping the best point.

    Pass k guesses the active set from ``(A x, y)`` of the previous point (the ADMM
    iterate for the first pass, then the last pass's solution with its raw
    multipliers), solves the KKT system on it (:func:`_kkt_solve`) and projects the
    multipliers onto the normal cone (wrong signs dropped). A pass's point replaces the
    current best only when it is finite and its KKT error (:func:`_kkt_error`) is not
    larger, so polishing never makes the result worse or non-finite.

    Args:
        sp: scaled problem.
        x, z, y: (n,), (m,), (m,) the ADMM iterate (scaled problem).
        eq, free: (m,) bool, equality / unbounded rows.
        s: settings (``polish_passes``, ``polish_delta``, ``polish_refine``).

    Returns:
        ``(x, z, y)``, the best point found.
    """
    def one_pass(carry, _):
        best, err, ax, y = carry
        lo, up = _guess_active(sp, ax, y, eq, free)
        x, y = _kkt_solve(sp, lo, up, eq, s)
        ax = mv(sp.A, x)
        y_cone = jnp.where(lo, jnp.minimum(y, 0.0), jnp.where(up, jnp.maximum(y, 0.0), y))
        cand = (x, jnp.clip(ax, sp.l, sp.u), y_cone)
        e = _kkt_error(sp, *cand)
        ok = all_finite(*cand, e) & (e <= err)
        best = tuple(jnp.where(ok, c, b) for c, b in zip(cand, best))
        return (best, jnp.where(ok, e, err), jnp.nan_to_num(ax), jnp.nan_to_num(y)), None

    best = (x, z, y)
    carry = (best, _kkt_error(sp, *best), mv(sp.A, x), y)
    (best, _, _, _), _ = lax.scan(one_pass, carry, None, length=s.polish_passes)
    return best
