"""OSQP's per-row step sizes, rho estimate, termination test and infeasibility certificates, written once for the
solver's two paths: the XLA ops of :mod:`wbc_jax.qp.admm` and the Pallas kernels of :mod:`wbc_jax.qp.fused`.

Everything here is plain ``jnp`` that also lowers inside a Triton kernel (no dynamic indexing, no boolean
reductions, no ``initial`` on a non-empty reduction). A row quantity is passed as a tuple of blocks of rows (the
XLA path: one block, all of ``A``'s rows; the kernels: the exact, dense and box blocks), so that norms and sums run
over every row whatever the storage.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp

from wbc_jax.qp.scaling import Scaled, absmax, mv
from wbc_jax.qp.settings import (
    BIG,
    FIRST_TEST_BLOCKS,
    FLAG_DUAL_INFEASIBLE,
    FLAG_MAX_ITER,
    FLAG_NONFINITE,
    FLAG_PRIMAL_INFEASIBLE,
    FLAG_SOLVED,
    QPSettings,
)

EQ_TOL = 1e-4  # scaled |u - l| below this marks an equality row (OSQP's RHO_TOL)


def amax(*vs):
    """() ``max |v|`` over every entry of every array (0 for empty ones)."""
    return functools.reduce(jnp.maximum, [absmax(v.reshape(-1), 0) for v in vs])


def row_weights(eq, free, ex, act, s: QPSettings):
    """Per-row rho factors (each argument a bool array of the rows): equality rows ``rho_eq_scale``, inequality rows
    1, free rows 0 (they use ``rho_min``), rows held exactly in the x-update (``ex``; None: none) 0; when warm
    (``act`` given), inequality rows active at the warm point (nonzero dual) ``warm_active_scale``."""
    w = jnp.where(eq, s.rho_eq_scale, 1.0)
    if act is not None:
        w = jnp.where(eq, w, jnp.where(act, s.warm_active_scale, 1.0))
    return jnp.where(free if ex is None else free | ex, 0.0, w)


def rho_vec(rho, w, free, s: QPSettings):
    """Per-row rho from the scalar ``rho`` and :func:`row_weights`' ``w``."""
    return jnp.where(free, s.rho_min, rho * w)


def warm_rho(wr, s: QPSettings, dt):
    """() the rho a solve starts from: the warm result's (``wr``, None: cold) clipped to ``[rho_min, rho_max]``,
    ``QPSettings.rho`` where there is none or it is not finite."""
    rho = jnp.asarray(s.rho if wr is None else wr, dt)
    return jnp.where(jnp.isfinite(rho), jnp.clip(rho, s.rho_min, s.rho_max), s.rho)


def first_block(warm, s: QPSettings, iters: int):
    """() int32, the iterations before a solve's first convergence test (:class:`~wbc_jax.qp.QPSettings`
    ``warm_first_test``) from the warm tuple's iterations (``warm[4]``), at most ``max_iters``; None where the test
    comes after ``iters``: cold, the setting off, no extension, or a warm result without its iterations."""
    wk = None if warm is None else warm[4]
    if wk is None or s.warm_first_test < 0 or s.max_iters <= iters:
        return None
    blocks = (jnp.asarray(wk, jnp.int32) - s.warm_first_test - iters) // s.check_every
    return jnp.minimum(iters + jnp.clip(blocks, 0, FIRST_TEST_BLOCKS) * s.check_every, s.max_iters)


def active_rows(y, dt):
    """Rows active at a warm point, each block's ``y`` a bool array: a nonzero dual (ADMM's ``y`` is zero on rows
    inside their bounds up to the rounding of ``y - rho (y / rho)``, so "nonzero" is relative to ``||y||_inf``)."""
    floor = 100 * float(jnp.finfo(dt).eps) * amax(*y)
    return tuple(jnp.abs(v) > floor for v in y)


def finite_or_zero(v):
    """``v`` with its non-finite entries 0 (``v - v`` is 0 only where ``v`` is finite)."""
    return jnp.where(v - v == 0.0, v, 0.0)


def scaled_start(wx, wz, wy, D, E, c):
    """A warm point in the user's units, in the equilibrated problem: ``(x / D, z E, y c / E)``, non-finite entries 0;
    ``wx`` (n,), ``wz``, ``wy`` and the row scalings ``E`` tuples of the blocks of rows, ``D`` (n,), ``c`` ()."""
    return (finite_or_zero(wx / D), tuple(finite_or_zero(v * e) for v, e in zip(wz, E)),
            tuple(finite_or_zero(v * c / e) for v, e in zip(wy, E)))


def start_on_rows(z, y, ax, l, u, free):
    """The start's ``z`` and ``y`` made consistent with the rows (tuples of blocks): ``z`` in ``[l, u]``, and on
    rows without bounds (``free``) ``z = A x`` (``ax``) and ``y = 0``."""
    z = tuple(jnp.where(f, a, jnp.minimum(jnp.maximum(v, lo), hi)) for f, a, v, lo, hi in zip(free, ax, z, l, u))
    return z, tuple(jnp.where(f, 0.0, v) for f, v in zip(free, y))


def rel_residuals(ax, z, px, aty, q, offset):
    """Relative primal and dual residuals (inf-norms), rows in blocks (``ax``, ``z``: tuples).

    Returns:
        ``(prim, dual)``: ``||Ax - z|| / (offset + max(||Ax||, ||z||))`` and
        ``||Px + q + A'y|| / (offset + max(||Px||, ||A'y||, ||q||))``.
    """
    prim = amax(*(a - b for a, b in zip(ax, z))) / (offset + jnp.maximum(amax(*ax), amax(*z)))
    dual = amax(px + q + aty) / (offset + jnp.maximum(jnp.maximum(amax(px), amax(aty)), amax(q)))
    return prim, dual


def scaled_residuals(sp: Scaled, x, z, y, offset):
    """:func:`rel_residuals` of ``(x (n,), z (m,), y (m,))`` in the equilibrated problem ``sp`` (XLA path)."""
    return rel_residuals((mv(sp.A, x),), (z,), mv(sp.P, x), mv(sp.A.T, y), sp.q, offset)


def adapt_rho(rho, prim, dual, s: QPSettings):
    """OSQP's rho estimate ``adapt_bias rho sqrt(prim / dual)`` from relative residuals (:func:`rel_residuals` of
    the scaled problem), clipped to ``[rho_min, rho_max]``; rho changes only by more than ``adapt_tol``."""
    tiny = 1e-30
    est = jnp.clip(s.adapt_bias * rho * jnp.sqrt(prim / (dual + tiny)), s.rho_min, s.rho_max)
    change = (est > rho * s.adapt_tol) | (est < rho / s.adapt_tol)
    return jnp.where(change & (est - est == 0.0), est, rho)


def termination(ax, z, px, aty, q, s: QPSettings):
    """OSQP's test in the user's units, rows in blocks (``ax``, ``z``: tuples).

    Returns:
        ``(prim, dual, converged)``: ``||A x - z||_inf``, ``||P x + q + A'y||_inf`` and () bool, both within
        ``eps_abs + eps_rel * scale``.
    """
    prim, prim_ok = primal_test(ax, z, s)
    dual, dual_ok = dual_test(px, aty, q, s)
    return prim, dual, prim_ok & dual_ok


def primal_test(ax, z, s: QPSettings):
    """``(||A x - z||_inf, () bool: within eps_abs + eps_rel max(||A x||_inf, ||z||_inf))``, rows in blocks."""
    prim = amax(*(a - b for a, b in zip(ax, z)))
    return prim, prim <= s.eps_abs + s.eps_rel * jnp.maximum(amax(*ax), amax(*z))


def dual_test(px, aty, q, s: QPSettings):
    """``(||P x + q + A'y||_inf, () bool: within eps_abs + eps_rel max(||P x||, ||A'y||, ||q||)_inf)``."""
    dual = amax(px + q + aty)
    return dual, dual <= s.eps_abs + s.eps_rel * jnp.maximum(jnp.maximum(amax(px), amax(aty)), amax(q))


def primal_infeasible(l, u, dy, at, s: QPSettings):
    """OSQP's primal-infeasibility test on the last dual step, user's units, rows in blocks.

    Args:
        l, u, dy: tuples of each block's bounds (finite, ``+-BIG``) and last step in ``y``.
        at: ``A' dy`` as a function of the masked step (a tuple of blocks), (n,).
    """
    dy = tuple(jnp.where(((lb <= -BIG) & (d < 0)) | ((ub >= BIG) & (d > 0)), 0.0, d) for lb, ub, d in zip(l, u, dy))
    ndy = amax(*dy)
    supp = sum(jnp.sum(jnp.where(ub >= BIG, 0.0, ub) * jnp.maximum(d, 0.0)
                       + jnp.where(lb <= -BIG, 0.0, lb) * jnp.minimum(d, 0.0)) for lb, ub, d in zip(l, u, dy))
    return (ndy > 0) & (amax(at(dy)) <= s.eps_pinf * ndy) & (supp <= -s.eps_pinf * ndy)


def dual_infeasible(l, u, dx, adx, pdx, qdx, s: QPSettings):
    """OSQP's dual-infeasibility (unbounded objective) test on the last primal step ``dx`` (n,), user's units:
    ``adx`` the tuple of each block's ``A dx``, ``pdx`` (n,) ``P dx``, ``qdx`` () ``q' dx``."""
    ndx = amax(dx)
    tol = s.eps_dinf * ndx
    out = [jnp.where(ub >= BIG, 0.0, jnp.where(a <= tol, 0.0, 1.0)) + jnp.where(lb <= -BIG, 0.0,
           jnp.where(a >= -tol, 0.0, 1.0)) for lb, ub, a in zip(l, u, adx)]  # > 0: a row leaves the recession cone
    return (ndx > 0) & (amax(pdx) <= tol) & (qdx <= -tol) & (amax(*out) == 0.0)


def status(finite, empty, pinf, dinf, converged):
    """() the result's ``FLAG_*`` in order of precedence, as a float (the caller casts): non-finite, an empty box
    (primal infeasible), converged, then OSQP's certificates (primal, dual infeasible; OSQP tests them only where
    the residuals fail, so ``pinf`` and ``dinf`` are not read where ``converged``), else the cap. Arithmetic on the
    tests as 0/1 rather than ``where``: Pallas' Triton lowering types a scalar ``where``'s constant cases after its
    predicate (bool)."""
    nf, em, pi, di, cv = (jnp.asarray(b).astype(jnp.float32) for b in (~finite, empty, pinf, dinf, converged))
    cert = pi * FLAG_PRIMAL_INFEASIBLE + (1.0 - pi) * (di * FLAG_DUAL_INFEASIBLE + (1.0 - di) * FLAG_MAX_ITER)
    rest = cv * FLAG_SOLVED + (1.0 - cv) * cert
    return nf * FLAG_NONFINITE + (1.0 - nf) * (em * FLAG_PRIMAL_INFEASIBLE + (1.0 - em) * rest)


def clean(v, nan, big):
    """``v`` with NaN replaced by ``nan`` and +-inf by +-``big`` (in a Triton kernel: ``v`` a vector, see
    :func:`status`)."""
    return jnp.where(v - v == 0.0, v, jnp.where(v > 0, big, jnp.where(v < 0, -big, nan)))
