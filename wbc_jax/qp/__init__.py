"""Batched fixed-iteration ADMM QP solver in OSQP form (``min 1/2 x'Px + q'x, l <= Ax <= u``).

Knows nothing about robots. Entry point :func:`solve_qp`; see :mod:`wbc_jax.qp.admm`.
"""

from wbc_jax.qp.admm import (
    FLAG_DUAL_INFEASIBLE,
    FLAG_MAX_ITER,
    FLAG_NONFINITE,
    FLAG_PRIMAL_INFEASIBLE,
    FLAG_SOLVED,
    QPResult,
    QPSettings,
    solve_qp,
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
