"""The QP solver's static settings, its result and its flags.

Flags (``QPResult.flag``, int32):
    0 ``FLAG_SOLVED``: residuals within ``eps_abs + eps_rel * scale`` (OSQP's test).
    1 ``FLAG_MAX_ITER``: not within tolerance after ``iters`` iterations (the iterate is
      still the best the budget gives; check ``prim_res``/``dual_res``).
    2 ``FLAG_PRIMAL_INFEASIBLE``: ``l > u`` somewhere, or a certificate of primal
      infeasibility (contradictory constraints).
    3 ``FLAG_DUAL_INFEASIBLE``: certificate of an unbounded objective (P singular).
    4 ``FLAG_NONFINITE``: a non-finite value appeared (bad data, failed Cholesky); the
      output is the last finite iterate (or zeros).
"""

from __future__ import annotations

from typing import NamedTuple

import jax

FLAG_SOLVED = 0
FLAG_MAX_ITER = 1
FLAG_PRIMAL_INFEASIBLE = 2
FLAG_DUAL_INFEASIBLE = 3
FLAG_NONFINITE = 4

BIG = 1e20  # stands for an infinite bound inside the solver

LINSOLVES = ("chol", "inv", "auto")
KERNELS = ("xla", "fused", "auto")


class QPSettings(NamedTuple):
    """Static solver settings (hashable: pass as a static argument under ``jit``).

    Attributes:
        iters: default iteration count, used when ``solve_qp(iters=None)``.
        rho: initial ADMM step size for inequality rows (scaled problem); a warm start
            keeps the warm result's rho (OSQP's choice, the best of those measured).
        sigma: proximal weight on x (keeps the matrix positive definite).
        alpha: over-relaxation in (0, 2).
        rho_eq_scale: equality rows use ``rho * rho_eq_scale``.
        rho_min: rho of free rows and lower clip of adapted rho.
        rho_max: upper clip of adapted rho.
        adapt_every: iterations per segment between rho re-estimates and refactors;
            0 disables adaptation (one Cholesky per solve, rho stays the initial or warm
            one). ``>= iters``: one Cholesky per solve and rho re-estimated after the
            iterations, for the next warm-started solve (cross-step adaptation: the
            control loop's choice, see :func:`wbc_jax.control.transport.control_qp_settings`).
        adapt_tol: rho changes only when the estimate differs by more than this factor.
        adapt_bias: factor on OSQP's estimate ``rho sqrt(prim_rel / dual_rel)`` (> 1
            favours primal feasibility).
        warm_active_scale: when warm-started, inequality rows with a nonzero dual at the
            warm point use this factor on rho (1 disables).
        ruiz_iters: Ruiz equilibration passes (0 disables scaling); the cost is scaled
            by the mean column norm of ``P`` in each pass.
        eps_abs: absolute tolerance, only used to set the flag.
        eps_rel: relative tolerance, only used to set the flag.
        eps_pinf: tolerance of the primal-infeasibility certificate.
        eps_dinf: tolerance of the dual-infeasibility certificate.
        linsolve: ``"chol"`` (two triangular solves per iteration) or ``"inv"`` (the
            explicit inverse from the Cholesky factor: matrix-vector products only,
            as accurate thanks to the residual form of the x-update), or ``"auto"``:
            ``"chol"`` on the CPU, ``"inv"`` on an accelerator (H100, WBC-sized
            problems, 50 iterations: 2.8x faster at batch 256 and 1.3x at 16384 than
            ``"chol"``; on the CPU the inverse is several times slower).
        unroll: unroll factor of the iteration and equilibration loops (``lax.scan``'s
            ``unroll``; True: fully). Same arithmetic; on GPU fewer loop trips and more
            fusion, at a longer compile.
        polish: after the iterations, polish the solution
            (:func:`wbc_jax.qp.polish.polish`): guess the active set from the iterate,
            solve the KKT system on it, repeat from that solution (primal-dual
            active-set passes), keep the point with the smallest KKT error.
        polish_passes: active-set passes (one n x n Cholesky each).
        polish_delta: regularization of the KKT system (scaled problem).
        polish_refine: iterative-refinement steps per pass.
        eq_rows: the first ``eq_rows`` rows are held exactly in every x-update instead of through ADMM's
            rho: those of them with ``l == u`` (equalities) enter the x-update's KKT system, solved through the
            Schur complement of the equality block (:func:`wbc_jax.qp.admm._kkt_factor`); those with no bound
            (free, e.g. a swing foot's stance row) are ignored; any other of them stays an ADMM row. Their
            ``y`` is the KKT multiplier. 0: OSQP's scheme for every row (equalities through
            ``rho * rho_eq_scale``).
        box_rows: the last ``box_rows`` rows of ``A`` bound the last ``box_rows`` variables one each (row
            ``m - box_rows + i`` is zero except at column ``n - box_rows + i``; e.g. a force multiplier's
            ``lambda >= 0``). The solver trusts this structure: the fused kernel stores those rows as a diagonal
            (:mod:`wbc_jax.qp.fused`, a smaller kernel: more problems at once on a GPU); the XLA path treats them
            as dense rows. 0: no such rows.
        max_iters: 0: exactly ``iters`` iterations. Larger: after ``iters``, blocks of ``check_every`` more
            iterations (same factorization) while the residuals are outside tolerance, up to ``max_iters``.
            Under ``vmap`` the block loop runs until the batch's slowest problem converges (converged problems
            keep their result), so its cost is paid only at steps where some problem needs it (contact events).
        check_every: iterations per block of the extension (one convergence test each).
        kernel: ``"xla"`` (the solve as XLA ops), ``"fused"`` (the whole solve in Pallas kernels of one program
            per problem, :mod:`wbc_jax.qp.fused`; needs one factorization per solve, ``adapt_every`` 0 or
            ``>= iters``, and no polishing; rho is then re-estimated from the final iterate) or ``"auto"`` (fused
            on a GPU where that holds, else XLA).
    """

    iters: int = 100
    rho: float = 1.0
    sigma: float = 1e-6
    alpha: float = 1.6
    rho_eq_scale: float = 1e3
    rho_min: float = 1e-6
    rho_max: float = 1e6
    adapt_every: int = 10
    adapt_tol: float = 1.5
    adapt_bias: float = 2.0
    warm_active_scale: float = 3.0
    ruiz_iters: int = 5
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    eps_pinf: float = 1e-5
    eps_dinf: float = 1e-5
    linsolve: str = "chol"
    unroll: int | bool = 1
    polish: bool = False
    polish_passes: int = 6
    polish_delta: float = 1e-6
    polish_refine: int = 3
    eq_rows: int = 0
    box_rows: int = 0
    max_iters: int = 0
    check_every: int = 10
    kernel: str = "xla"


class QPResult(NamedTuple):
    """Solution of one QP (fields get leading batch axes under ``vmap``).

    Attributes:
        x: (n,) primal solution.
        y: (m,) duals of the rows (> 0 at an active upper bound, < 0 at a lower one).
        z: (m,) ``A x`` projected onto ``[l, u]`` (ADMM's z iterate).
        prim_res: () ``||A x - z||_inf`` (units of the rows).
        dual_res: () ``||P x + q + A'y||_inf`` (units of the cost gradient).
        flag: () int32, ``FLAG_*`` (0 = converged to tolerance).
        iters: () int32, iterations run (``iters`` plus the extension's, ``QPSettings.max_iters``).
        rho: () final (adapted) rho of the scaled problem; a warm start reuses it.
    """

    x: jax.Array
    y: jax.Array
    z: jax.Array
    prim_res: jax.Array
    dual_res: jax.Array
    flag: jax.Array
    iters: jax.Array
    rho: jax.Array
