"""Batched dense convex QP solver in OSQP form (``min 1/2 x'Px + q'x  s.t.  l <= Ax <= u``); knows nothing about
robots.

Entry point :func:`solve_qp` (:mod:`wbc_jax.qp.api`: the problem, the algorithm, the two implementations);
settings, result and flags in :mod:`wbc_jax.qp.settings`; equilibration in :mod:`wbc_jax.qp.scaling`; OSQP's rho
rules, termination test and certificates in :mod:`wbc_jax.qp.rules`; the XLA path in :mod:`wbc_jax.qp.admm`; the
GPU path in :mod:`wbc_jax.qp.fused` and its kernels (``kernel_*``); active-set polishing in :mod:`wbc_jax.qp.polish`.
"""

from wbc_jax.qp.api import empty_factors, last_usable, solve_qp
from wbc_jax.qp.settings import (
    FLAG_DIVERGED,
    FLAG_DUAL_INFEASIBLE,
    FLAG_MAX_ITER,
    FLAG_NONFINITE,
    FLAG_PRIMAL_INFEASIBLE,
    FLAG_SOLVED,
    QPResult,
    QPSettings,
    unusable,
)

__all__ = [
    "FLAG_DIVERGED",
    "FLAG_DUAL_INFEASIBLE",
    "FLAG_MAX_ITER",
    "FLAG_NONFINITE",
    "FLAG_PRIMAL_INFEASIBLE",
    "FLAG_SOLVED",
    "QPResult",
    "QPSettings",
    "empty_factors",
    "last_usable",
    "solve_qp",
    "unusable",
]
