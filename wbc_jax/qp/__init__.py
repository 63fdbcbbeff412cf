"""Batched fixed-iteration ADMM QP solver in OSQP form (``min 1/2 x'Px + q'x, l <= Ax <= u``).

Knows nothing about robots. Entry point :func:`solve_qp` (:mod:`wbc_jax.qp.admm`, the algorithm and its evidence);
settings, result and flags in :mod:`wbc_jax.qp.settings`, equilibration in :mod:`wbc_jax.qp.scaling`, OSQP's rho
rules, termination test and infeasibility certificates in :mod:`wbc_jax.qp.rules`, the GPU kernels in
:mod:`wbc_jax.qp.fused`, active-set polishing in :mod:`wbc_jax.qp.polish`.
"""

from wbc_jax.qp.admm import solve_qp
from wbc_jax.qp.settings import (
    FLAG_DUAL_INFEASIBLE,
    FLAG_MAX_ITER,
    FLAG_NONFINITE,
    FLAG_PRIMAL_INFEASIBLE,
    FLAG_SOLVED,
    QPResult,
    QPSettings,
)

__all__ = [
    "FLAG_DUAL_INFEASIBLE",
    "FLAG_MAX_ITER",
    "FLAG_NONFINITE",
    "FLAG_PRIMAL_INFEASIBLE",
    "FLAG_SOLVED",
    "QPResult",
    "QPSettings",
    "solve_qp",
]
