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
    5 ``FLAG_DIVERGED``: not within tolerance, and the primal residual above ``DIVERGED_RATIO`` times that of
      the (usable) warm start's result: the iterations diverged (a kept factorization's step can,
      :mod:`wbc_jax.qp.fused`); the output is that iterate.
Results flagged 4 or 5 are :func:`unusable`: not to be applied, nor to warm-start a solve.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax

FLAG_SOLVED = 0
FLAG_MAX_ITER = 1
FLAG_PRIMAL_INFEASIBLE = 2
FLAG_DUAL_INFEASIBLE = 3
FLAG_NONFINITE = 4
FLAG_DIVERGED = 5
DIVERGED_RATIO = 1e6  # an unconverged solve's primal residual over its warm start's that marks it diverged

BIG = 1e20  # stands for an infinite bound inside the solver
FIRST_TEST_BLOCKS = 3  # QPSettings.warm_first_test: the first block at most iters + this many blocks

LINSOLVES = ("chol", "inv", "auto")
KERNELS = ("xla", "fused", "auto")
LAUNCH_ORDERS = ("batch", "predicted")


def unusable(flag):
    """Where a result's iterate is not to be applied nor to warm-start a solve: ``flag`` (int array) is
    ``FLAG_NONFINITE`` or ``FLAG_DIVERGED``. Returns a bool array of ``flag``'s shape."""
    return (flag == FLAG_NONFINITE) | (flag == FLAG_DIVERGED)


class QPSettings(NamedTuple):
    """Static solver settings (hashable: pass as a static argument under ``jit``). Rho values are those of the
    equilibrated problem.

    Attributes:
        iters: iterations when ``solve_qp(iters=None)`` (default 100).
        rho: initial ADMM step size of inequality rows (default 1.0); a warm start keeps the warm result's rho.
        sigma: proximal weight on x, keeps the x-update's matrix positive definite (default 1e-6).
        alpha: over-relaxation, in (0, 2) (default 1.6).
        rho_eq_scale: factor on rho of equality rows not held exactly (default 1e3).
        rho_min: rho of rows without bounds and lower clip of an adapted rho (default 1e-6).
        rho_max: upper clip of an adapted rho (default 1e6).
        adapt_every: iterations per segment between rho re-estimates and refactorizations (default 10); 0: rho
            fixed, one factorization per solve; ``>= iters``: one factorization per solve and rho re-estimated
            after the iterations, for the next warm-started solve.
        adapt_tol: rho changes only when the estimate differs by more than this factor (default 1.5).
        adapt_bias: factor on OSQP's estimate ``rho sqrt(prim_rel / dual_rel)``; > 1 favours primal feasibility
            (default 2.0).
        warm_active_scale: factor on rho of inequality rows with a nonzero dual at the warm point; 1 disables
            (default 3.0).
        ruiz_iters: Ruiz equilibration passes; 0 disables scaling (default 5).
        eps_abs: absolute tolerance of the termination test (flag and extension only) (default 1e-5).
        eps_rel: relative tolerance of the termination test (default 1e-5).
        eps_pinf: tolerance of the primal-infeasibility certificate (default 1e-5).
        eps_dinf: tolerance of the dual-infeasibility certificate (default 1e-5).
        linsolve: the x-update's solve: ``"chol"`` (triangular solves), ``"inv"`` (the explicit inverse from the
            Cholesky factor: matrix-vector products only, as accurate with the residual-form step) or ``"auto"``
            (``"chol"`` on a CPU, ``"inv"`` on an accelerator) (default ``"chol"``).
        unroll: ``lax.scan``'s unroll of the iteration and equilibration loops; True: fully (default 1).
        polish: polish the solution by active-set passes (:mod:`wbc_jax.qp.polish`) (default False).
        polish_passes: active-set passes, one n x n Cholesky each (default 6).
        polish_delta: regularization of the polishing KKT system (default 1e-6).
        polish_refine: iterative-refinement steps per pass (default 3).
        eq_rows: the first ``eq_rows`` rows are held exactly in every x-update instead of through rho: those with
            ``l == u`` enter the x-update's KKT system (Schur complement of the equality block) and their ``y`` is
            the KKT multiplier; those without bounds are ignored; any other stays an ADMM row. 0: OSQP's scheme
            for every row (default 0).
        box_rows: the last ``box_rows`` rows of ``A`` bound the last ``box_rows`` variables one each (row
            ``m - box_rows + i`` is zero except at column ``n - box_rows + i``). The solver trusts this structure:
            the fused kernels store those rows as a diagonal; the XLA path treats them as dense rows (default 0).
        max_iters: 0: exactly ``iters`` iterations. Larger: after ``iters``, blocks of ``check_every`` more
            iterations (same factorization) while the residuals are outside tolerance, up to ``max_iters``; under
            ``vmap`` the XLA path runs the blocks until the batch's slowest problem has converged, converged
            problems keeping their result (default 0).
        check_every: iterations per block of the extension, one convergence test each (default 10).
        warm_first_test: with ``max_iters > iters``, a warm start that carries its solve's iterations (a
            ``QPResult``) and ``>= 0``: the first test comes after that count minus ``warm_first_test``, in whole
            blocks of ``check_every`` from ``iters``, at least ``iters``, at most ``iters`` plus
            :data:`FIRST_TEST_BLOCKS` blocks, the first block one projection and its iterations; a solve near its
            predecessor (a control loop's) needs about as many iterations, so fewer tests run (a saving of the
            fused kernels, which stop per problem; the XLA path runs the longest first block, masked). -1: the first
            test after ``iters`` (default -1).
        kernel: ``"xla"`` (XLA ops, :mod:`wbc_jax.qp.admm`), ``"fused"`` (three Pallas kernels of one program per
            problem, :mod:`wbc_jax.qp.fused`; needs one factorization per solve and no polishing; rho is then
            re-estimated from the final iterate) or ``"auto"`` (fused on a GPU for float32 where that holds, else
            XLA) (default ``"xla"``).
        reuse_factors: fused kernels only: a solve warm-started from a result that carries its factors
            (``QPResult.factors``, made by a solve that factored) reuses them with their scaling and rho instead of
            equilibrating and factoring again, where no row changed kind (free, equality, held) since; the next
            solve then factors again, so every other solve of a control loop factors. The step is residual-based
            (the factors precondition it), so the solution and the convergence test are the current problem's,
            but it can diverge where the problem moved far from theirs (``FLAG_DIVERGED``) (default False).
        launch_order: fused kernels under ``vmap``, warm-started: the order the iterations kernel's programs (one
            per problem) start in. ``"batch"``: the batch's; ``"predicted"``: the problems predicted longest first
            (:func:`wbc_jax.qp.kernel_order.predicted_length`), so that a long solve does not start last and hold
            up the batch (docs/performance.md: the launch order); a batch that the device runs in one wave
            (:func:`~wbc_jax.qp.kernel_order.one_wave`) keeps the batch's. Each problem's arithmetic is the same in
            any order (in Pallas' CPU interpreter equal to float rounding, as its XLA compiles the reads through
            views with other kernels) (default ``"batch"``).
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
    warm_first_test: int = -1
    kernel: str = "xla"
    reuse_factors: bool = False
    launch_order: str = "batch"


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
        factors: the fused kernels' factors and what they were made from
            (:class:`wbc_jax.qp.kernel_layout.Factors`) where ``QPSettings.reuse_factors``, else None.
    """

    x: jax.Array
    y: jax.Array
    z: jax.Array
    prim_res: jax.Array
    dual_res: jax.Array
    flag: jax.Array
    iters: jax.Array
    rho: jax.Array
    factors: Any = None
