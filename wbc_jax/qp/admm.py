"""Fixed-iteration ADMM for dense convex QPs in OSQP form, batched with ``jax.vmap``.

Problem::

    minimize 1/2 x'Px + q'x   subject to   l <= Ax <= u

with ``P`` (n, n) positive semidefinite, ``A`` (m, n), ``l``/``u`` (m,) (``+-inf`` for a
missing bound, ``l == u`` for an equality). The algorithm is OSQP's (Stellato et al.
2020): Ruiz equilibration of the KKT matrix plus cost scaling, per-row step size rho
(equality rows ``rho * rho_eq_scale``, free rows ``rho_min``), sigma proximal term,
over-relaxation alpha, one dense Cholesky of ``P + sigma I + A' diag(rho) A`` per
segment, then a fixed number of iterations in ``lax.scan``. Rho adaptation fits the
fixed count: the iterations run in segments of ``adapt_every``; after each segment rho
is re-estimated from the residual ratio (OSQP's rule, biased toward feasibility) and
the matrix refactored (an O(n^2) update of a precomputed ``A' diag(w) A`` plus the
Cholesky). The x-update is written in residual form so that float32 rounding in the
Cholesky does not move the fixed point. There is no early exit, so a vmapped batch
costs exactly ``iters`` iterations per problem.

Robustness: every iterate is checked for finiteness and a non-finite step is rejected
(the last finite iterate is kept and the flag says so); ``+-inf`` bounds become
``+-1e20``; outputs are passed through ``nan_to_num`` as a last line of defence. An
empty box (``l > u``) or a primal-infeasibility certificate (OSQP's test on the last
dual step) gives ``FLAG_PRIMAL_INFEASIBLE``; the returned iterate is then the (finite)
last one, with ``y`` growing linearly in the iteration count.

Flags (``QPResult.flag``, int32):
    0 ``FLAG_SOLVED``: residuals within ``eps_abs + eps_rel * scale`` (OSQP's test).
    1 ``FLAG_MAX_ITER``: not within tolerance after ``iters`` iterations (the iterate is
      still the best the budget gives; check ``prim_res``/``dual_res``).
    2 ``FLAG_PRIMAL_INFEASIBLE``: ``l > u`` somewhere, or a certificate of primal
      infeasibility (contradictory constraints).
    3 ``FLAG_DUAL_INFEASIBLE``: certificate of an unbounded objective (P singular).
    4 ``FLAG_NONFINITE``: a non-finite value appeared (bad data, failed Cholesky); the
      output is the last finite iterate (or zeros).

Defaults and the evidence for them
----------------------------------
Measured on 200 problems from ``wbc_jax.bench.qp_problems.make_batch(0, 200)`` (100 generic,
100 with WBC structure and scales, entries spanning 6+ orders of magnitude; n = 68,
24 equality + 70 inequality rows), cold start, CPU. Each cell: fraction of generic /
WBC problems with rel. objective error <= 1e-4 and max violation (relative to
``max(1, ||Ax||_inf)``) <= 1e-5 against the constructed optimum (float32 rows:
1e-3 / 1e-4), at 50 / 75 / 100 / 150 iterations::

    default (float64)              .83/.86  1.0/.98  1.0/1.0  1.0/1.0
    cost_scaling="osqp"            .46/.00  1.0/.00  1.0/.09  1.0/.64
    cost_scaling="none"            .83/.86  1.0/.99  1.0/1.0  1.0/1.0
    adapt_bias=1 (OSQP's rule)     .80/.75  .99/.90  1.0/.98  1.0/1.0
    adapt_every=0 (fixed rho)      .30/.75  1.0/.89  1.0/.95  1.0/.98
    adapt_every=25, adapt_tol=5    .34/.76  1.0/.89  1.0/.97  1.0/.99
    ruiz_iters=0                   .99/.39  1.0/.81  1.0/.92  1.0/1.0
    ruiz_iters=10                  .82/.78  1.0/.97  1.0/1.0  1.0/1.0
    alpha=1.0                      .03/.29  .86/.83  1.0/.96  1.0/1.0
    rho_eq_scale=1e2               .84/.85  1.0/.98  1.0/1.0  1.0/1.0
    rho=0.1                        .97/.70  1.0/.98  1.0/1.0  1.0/1.0
    anderson=10                    .96/1.0  1.0/1.0  1.0/1.0  1.0/1.0
    default (float32)              .99/.99  1.0/1.0  1.0/1.0  1.0/1.0
    float32 residual_form=False    .08/.53  .05/.60  .02/.67  .12/.65
    float32 linsolve="inv"         1.0/.98  1.0/.99  1.0/1.0  1.0/1.0

Reading: OSQP's cost scaling (which includes ``||q||``) makes the scaled problem's
good rho ~1e-4 on WBC data and costs > 100 iterations; scaling the cost by ``P`` only
matches no scaling on these data and keeps the solver robust when the whole cost is
multiplied by a constant, as WBC gains do (WBC family at 100 / 150 iterations: x1e6
1.0 / 1.0, x1e3 1.0 / 1.0, x1e-3 .98 / 1.0, x1e-6 .77 / .95; no cost scaling at
x1e-3: .09 / .50). Weights far below the constraint scale still need more iterations. The residual form of the x-update is what makes float32
work (OSQP's form stalls at the Cholesky's rounding, ~1e-4 relative violation). The
rho-adaptation bias 2 (aim at primal residual 1/4 of OSQP's balance point) pays
because the acceptance is dominated by violation, not by objective error. Float64
reaches >= 99 % at 75 iterations; ``iters = 100`` leaves margin on other seeds.
Float32 needs ~50. Anderson acceleration (memory 10) saves ~20 % of the iterations
but costs +50-70 % per iteration on CPU (256-batch, 60 iterations: 225 ms -> 382 ms),
so it is off; ``bench.py`` times it on the device.

Warm start, from the default-count solution of the same problems with the data
perturbed by 1 % (``problems.perturb``: q, A, l, u entrywise, P -> S P S), float64,
200 problems, seeds 20240603 / 1 / 2. Cold needs 75 / 100 / 100 iterations for 99 %
on the grid 50, 60, 75, 100 (at 75: 1.0 / .985 / .985). Fraction meeting the criterion
at 25 / 37 / 50 iterations (seed 20240603, then the range over the three seeds; rows
marked * were measured with the old entrywise P perturbation, see below)::

    cold                                   -  / .30 / .84
    warm, rho reset (old default)         .14 / .66 / .94    37: .66-.73  50: .94-.95
    warm_rho="keep"                       .30 / .79 / .96    37: .79-.81  50: .96
    keep + warm_active_scale=3 (default)  .67 / .90 / .985   37: .90-.915 50: .975-.99
    keep + active x2 / x5                 .58 / .88 / .98 ;  .68 / .89 / .98
    keep + active x3 + anderson=10        .87(30) / .93 / .985
  * keep + active x3, inactive rows x0.3 .72 / .82 / .90 (x10 / x0.1: worse)
  * keep + active x3, adapt_every=0       .69 / .84 / .88
  * warm_rho="estimate"                   .10 / .50 / .87 (reset on the same data: .10 / .65 / .92)

So the default is to keep the warm result's rho and to give inequality rows that are
active at the warm point (nonzero dual) 3x rho. Per family at 37 iterations: generic
.99-1.0, WBC .81-.83 (cold, both: .30): for ADMM alone the issue's "acceptance at
half the cold count" holds on the generic family, not on the WBC family, which reaches 99 % at
~50-60 warm iterations. There ~8 of the 70 inequality rows change activity under a 1 %
perturbation (force multipliers with duals of ~1 next to costs of ~1e5) and the
remaining violation (~1e-5 on multiplier rows that are active at both points) decays at
ADMM's linear rate (~x3 per 10 iterations); larger active-row factors make inequality
rows chatter (y is reset whenever ``a x`` overshoots into the interval by more than
``|y| / rho``) and are worse even with the true active set. The scaling of the warm
point is consistent (x / D, z E, y c / E with the new problem's D, E, c; taking
z = A x instead of the old z changes nothing). For reference, OSQP 1.1 (adaptive rho
every 25 iterations, warm start with ``update`` + ``warm_start``, old perturbation) on
seed 20240603 needs 250 iterations cold and 200 warm for 99 % (at 50: cold .39, warm
.71): its warm start does not halve the count either.
The perturbation model matters: multiplying every entry of P by (1 + 0.01 N) makes ~13 %
of the WBC Hessians indefinite, and the identity shift that repairs them moves the
optimum by ~50 % (20-35 activity changes); those problems were the warm failures before
``perturb`` switched to the congruence S P S (optimum moves 2.7 % median, 8 % max).
Warm points solved further (400 instead of 100 iterations) do not help (.80 at 37: the
rho kept from a long solve is less suited).

Polishing (``polish=True``, off by default). After the iterations, primal-dual
active-set passes: guess the active rows from ``A x + y`` (OSQP's rule, scaled
problem), solve the equality-constrained KKT system on them (fixed shapes: inactive rows
masked; one n x n Cholesky of the regularized reduced system plus 3 refinement steps),
guess again from that solution and its raw multipliers, and keep the point with the
smallest KKT error (only finite, non-increasing ones replace the iterate, so polishing
cannot make a result worse, NaN or Inf; float32 stays finite, infeasible problems keep
their flags). Same 200 problems, float64, same settings for cold and warm (the warm
point is the polished default-count solve of the perturbed problems), seed 20240603,
fraction meeting the criterion (generic / WBC)::

    iterations                 5         6         8         9         10        15
    cold, 3 passes *           .14       -         .72       -         .885      .985
    cold, 6 passes (default)   .655      .795      .95       .98       .995      1.0
                               (.99/.32) (1.0/.59) (1.0/.90) (1.0/.96) (1.0/.99)
    warm, 6 passes             .995      .995      -         -         -         -
                               (1.0/.99)
    warm, 6 passes at 1* / 3 / 4 / 7: .945 / .985 / .99 / 1.0

(No polishing: cold .00 at 20, .295 at 37, .84 at 50, 1.0 at 75. Rows and cells marked
* were measured with the LU variant below, which gives the same fractions.)
With 3 passes cold needs 20 (.995), warm 15 (.995); with 4, cold 15 (.99), warm 7
(.99): no halving. With 6 passes (``polish_passes`` default) cold needs 10 and warm
meets the criterion at 5 (199 of 200; WBC 99 of 100), so the issue's line holds on this
benchmark, with a margin of one problem. On seeds 1 / 2 cold also needs 10, warm at 5
passes .98 / .985 and needs 7 / 6: the warm gain is real but the factor 2 is at the
edge. More passes do not help (10 passes: the same fractions at 1, 5 and 10
iterations): the remaining failures are WBC problems on which the active-set passes
diverge from the few-iteration iterate (6-30 wrong rows, singular guesses), and
a backtracking variant (flip only the half of the proposed rows with the largest
violation after a rejected pass) was worse. Cost on the CPU (200 problems, shared
2 cores): one pass ~55 ms, about 9 iterations; 75 plain iterations 547 ms, 10 iterations
+ 6 passes 494 ms, 5 + 6 passes 443 ms (a dense LU of the full (n + m) KKT matrix gives
the same fractions at twice the cost). So polishing meets the criterion at about the
time of the plain default count, warm start saves ~10 % of that, and it is kept off by
default (the default count already meets the criterion; the transport controller uses 20
iterations per step, the centroidal one 40).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

FLAG_SOLVED = 0
FLAG_MAX_ITER = 1
FLAG_PRIMAL_INFEASIBLE = 2
FLAG_DUAL_INFEASIBLE = 3
FLAG_NONFINITE = 4

BIG = 1e20  # stands for an infinite bound inside the solver
_MIN_SCALING = 1e-4
_MAX_SCALING = 1e4
_MIN_COST_SCALING = 1e-8  # wider than OSQP: keeps the cost scale-invariant over 1e-6..1e6
_MAX_COST_SCALING = 1e8
_EQ_TOL = 1e-4  # scaled |u - l| below this marks an equality row (OSQP's RHO_TOL)
_HI = lax.Precision.HIGHEST  # no TF32 on GPU: the iteration needs full float32


class QPSettings(NamedTuple):
    """Static solver settings (hashable: pass as a static argument under ``jit``).

    Attributes:
        iters: default iteration count, used when ``solve_qp(iters=None)``.
        rho: initial ADMM step size for inequality rows (scaled problem).
        sigma: proximal weight on x (keeps the matrix positive definite).
        alpha: over-relaxation in (0, 2).
        rho_eq_scale: equality rows use ``rho * rho_eq_scale``.
        rho_min: rho of free rows and lower clip of adapted rho.
        rho_max: upper clip of adapted rho.
        adapt_every: iterations per segment between rho re-estimates and refactors;
            0 disables adaptation (one Cholesky per solve).
        adapt_tol: rho changes only when the estimate differs by more than this factor.
        adapt_bias: factor on OSQP's estimate ``rho sqrt(prim_rel / dual_rel)`` (> 1
            favours primal feasibility).
        warm_rho: rho when warm-started: ``"reset"`` (``rho``), ``"keep"`` (the warm
            result's ``rho``, as OSQP does) or ``"estimate"`` (OSQP's estimate at the
            warm point).
        warm_active_scale: when warm-started, inequality rows with a nonzero dual at the
            warm point use this factor on rho (1 disables).
        ruiz_iters: Ruiz equilibration passes (0 disables scaling).
        cost_scaling: per Ruiz pass, scale the cost by the mean column norm of ``P``
            (``"P"``), by ``max(that, ||q||_inf)`` as OSQP does (``"osqp"``), or not
            (``"none"``).
        eps_abs: absolute tolerance, only used to set the flag.
        eps_rel: relative tolerance, only used to set the flag.
        eps_pinf: tolerance of the primal-infeasibility certificate.
        eps_dinf: tolerance of the dual-infeasibility certificate.
        linsolve: ``"chol"`` (two triangular solves per iteration) or ``"inv"`` (the
            explicit inverse from the Cholesky factor: matrix-vector products only,
            which may be faster on GPU for small n; as accurate thanks to the residual
            form), or ``"auto"``: ``"chol"`` on the CPU, ``"inv"`` on an accelerator
            (H100, WBC-sized problems, 50 iterations: 2.8x faster at batch 256 and 1.3x
            at 16384 than ``"chol"``; on the CPU the inverse is several times slower).
        residual_form: x-update as ``x - K^-1 (Px + q + A'(y + rho (Ax - z)))``, whose
            fixed point does not depend on the linear solve's rounding (False:
            OSQP's right-hand-side form, which stalls in float32).
        anderson: Anderson (type II) memory on the ADMM fixed-point map, reset at each
            refactor; 0 disables.
        aa_reg: Tikhonov weight (relative to the trace) in the Anderson least squares.
        aa_safeguard: an extrapolated point whose fixed-point residual grew by more
            than this factor is rejected (the plain step is taken instead).
        unroll: unroll factor of the iteration and equilibration loops (``lax.scan``'s
            ``unroll``; True: fully). Same arithmetic; on GPU fewer loop trips (each costs
            a device-host round trip) and more fusion, at a longer compile.
        kernel: ``"xla"`` (iterations as XLA ops in ``lax.scan``) or ``"pallas"`` (each
            segment's iterations in one Pallas kernel that keeps the matrices on chip,
            :mod:`wbc_jax.qp.fused`; needs ``linsolve="inv"``, ``residual_form`` and no
            Anderson; interpreted, hence slow, on the CPU), or ``"auto"``: ``"pallas"`` on a
            GPU where those hold, else ``"xla"``.
        num_warps: warps per problem of the Pallas kernel (GPU).
        polish: after the iterations, polish the solution (:func:`_polish`): guess
            the active set from the iterate, solve the KKT system on it, repeat from
            that solution (primal-dual active-set passes), keep the point with the
            smallest KKT error. Off by default: the criterion of the module docstring
            is met without it at the default count, and a control step cannot afford
            it (each pass costs about 9 iterations on the CPU).
        polish_passes: active-set passes (one n x n Cholesky each).
        polish_delta: regularization of the KKT system (scaled problem).
        polish_refine: iterative-refinement steps per pass.
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
    warm_rho: str = "keep"
    warm_active_scale: float = 3.0
    ruiz_iters: int = 5
    cost_scaling: str = "P"
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    eps_pinf: float = 1e-5
    eps_dinf: float = 1e-5
    linsolve: str = "chol"
    residual_form: bool = True
    anderson: int = 0
    aa_reg: float = 1e-8
    aa_safeguard: float = 1.0
    unroll: int | bool = 1
    kernel: str = "xla"
    num_warps: int = 8
    polish: bool = False
    polish_passes: int = 6
    polish_delta: float = 1e-6
    polish_refine: int = 3


class QPResult(NamedTuple):
    """Solution of one QP (fields get leading batch axes under ``vmap``).

    Attributes:
        x: (n,) primal solution.
        y: (m,) duals of the rows (> 0 at an active upper bound, < 0 at a lower one).
        z: (m,) ``A x`` projected onto ``[l, u]`` (ADMM's z iterate).
        prim_res: () ``||A x - z||_inf`` (units of the rows).
        dual_res: () ``||P x + q + A'y||_inf`` (units of the cost gradient).
        flag: () int32, ``FLAG_*`` (0 = converged to tolerance).
        iters: () int32, iterations run.
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


class _Scaled(NamedTuple):
    """Equilibrated problem: ``Pb = c D P D``, ``qb = c D q``, ``Ab = E A D``, ``lb = E l``."""

    P: jax.Array  # (n, n)
    q: jax.Array  # (n,)
    A: jax.Array  # (m, n)
    l: jax.Array  # (m,)
    u: jax.Array  # (m,)
    D: jax.Array  # (n,) column scaling
    E: jax.Array  # (m,) row scaling
    c: jax.Array  # () cost scaling


class _State(NamedTuple):
    x: jax.Array  # (n,) scaled
    z: jax.Array  # (m,)
    y: jax.Array  # (m,)
    dx: jax.Array  # (n,) last step in x (dual-infeasibility certificate)
    dy: jax.Array  # (m,) last step in y (primal-infeasibility certificate)
    bad: jax.Array  # () bool, a non-finite step was rejected


def _mv(M, v):
    return jnp.matmul(M, v, precision=_HI)


def _inf_norm(v):
    return jnp.max(jnp.abs(v), initial=0.0)


def _limit(v):
    """OSQP's ``limit_scaling``: tiny norms -> 1, huge -> clipped."""
    return jnp.where(v < _MIN_SCALING, 1.0, jnp.minimum(v, _MAX_SCALING))


def _equilibrate(P, q, A, l, u, s: QPSettings) -> _Scaled:
    """Ruiz equilibration of ``[[P, A'], [A, 0]]`` with cost scaling (OSQP's scheme)."""
    n, m = P.shape[0], A.shape[0]
    dt = P.dtype

    def one_pass(carry, _):
        P, q, A, D, E, c = carry
        col = jnp.maximum(jnp.max(jnp.abs(P), axis=0), jnp.max(jnp.abs(A), axis=0, initial=0.0))
        row = jnp.max(jnp.abs(A), axis=1, initial=0.0)
        d = lax.rsqrt(_limit(col))
        e = lax.rsqrt(_limit(row))
        P = d[:, None] * P * d[None, :]
        A = e[:, None] * A * d[None, :]
        q = d * q
        if s.cost_scaling in ("P", "osqp"):
            cp = jnp.mean(jnp.max(jnp.abs(P), axis=0))
            if s.cost_scaling == "osqp":
                cp = jnp.maximum(cp, _inf_norm(q))
            ct = 1.0 / jnp.clip(cp, _MIN_COST_SCALING, _MAX_COST_SCALING)
            P, q, c = ct * P, ct * q, ct * c
        return (P, q, A, D * d, E * e, c), None

    init = (P, q, A, jnp.ones(n, dt), jnp.ones(m, dt), jnp.ones((), dt))
    if s.ruiz_iters > 0:
        init, _ = lax.scan(one_pass, init, None, length=s.ruiz_iters, unroll=s.unroll)
    P, q, A, D, E, c = init
    P = 0.5 * (P + P.T)
    return _Scaled(P, q, A, E * l, E * u, D, E, c)


def _row_weights(eq, free, act, s: QPSettings):
    """(m,) per-row rho factors: equality rows ``rho_eq_scale``, inequality rows 1, free
    rows 0 (they use ``rho_min``); when warm (``act`` given), inequality rows active at
    the warm point (nonzero dual) ``warm_active_scale``."""
    w = jnp.where(eq, s.rho_eq_scale, 1.0)
    if act is not None:
        w = jnp.where(eq, w, jnp.where(act, s.warm_active_scale, 1.0))
    return jnp.where(free, 0.0, w)


def _rho_vec(rho, w, free, s: QPSettings):
    """(m,) per-row rho from the scalar rho."""
    return jnp.where(free, s.rho_min, rho * w)


def _gram(sp: _Scaled, w, free, s: QPSettings):
    """``(K0, G)`` with ``P + sigma I + A' diag(rho_vec(rho)) A = K0 + rho G``.

    Built once per solve (the O(m n^2) part), so a refactor for a new rho costs one
    O(n^2) update plus the Cholesky.
    """
    n = sp.P.shape[0]
    G = jnp.matmul(sp.A.T * w[None, :], sp.A, precision=_HI)
    Gf = jnp.matmul(sp.A.T * jnp.where(free, s.rho_min, 0.0)[None, :], sp.A, precision=_HI)
    K0 = sp.P + s.sigma * jnp.eye(n, dtype=sp.P.dtype) + Gf
    return K0, G


def _factor(K0, G, rho, s: QPSettings):
    """Linear solver for ``(K0 + rho G) x = b``: Cholesky factor or explicit inverse."""
    n = K0.shape[0]
    L = jnp.linalg.cholesky(K0 + rho * G)
    if s.linsolve == "inv":
        Li = jax.scipy.linalg.solve_triangular(L, jnp.eye(n, dtype=K0.dtype), lower=True)
        return jnp.matmul(Li.T, Li, precision=_HI)
    return L


def _solve(fac, b, s: QPSettings):
    if s.linsolve == "inv":
        return _mv(fac, b)
    return jax.scipy.linalg.cho_solve((fac, True), b)


def _all_finite(*vs):
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in vs]))


def _step(sp: _Scaled, fac, rho_v, s: QPSettings, st: _State) -> _State:
    """One OSQP iteration in the scaled problem; rejects a non-finite result."""
    if s.residual_form:
        # x~ = x - K^-1 (P x + q + A'(y + rho (A x - z))): the same step in exact
        # arithmetic, but its fixed point does not depend on the solve's rounding.
        r = _mv(sp.P, st.x) + sp.q + _mv(sp.A.T, st.y + rho_v * (_mv(sp.A, st.x) - st.z))
        xt = st.x - _solve(fac, r, s)
    else:
        rhs = s.sigma * st.x - sp.q + _mv(sp.A.T, rho_v * st.z - st.y)
        xt = _solve(fac, rhs, s)
    zt = _mv(sp.A, xt)
    x = s.alpha * xt + (1.0 - s.alpha) * st.x
    zr = s.alpha * zt + (1.0 - s.alpha) * st.z
    z = jnp.clip(zr + st.y / rho_v, sp.l, sp.u)
    y = st.y + rho_v * (zr - z)
    ok = _all_finite(x, z, y)
    new = _State(x, z, y, x - st.x, y - st.y, st.bad)
    old = st._replace(bad=jnp.ones((), bool))
    return jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, old)


def _rel_residuals(sp: _Scaled, x, z, y, offset):
    """Relative primal and dual residuals in the scaled problem (inf-norms).

    Args:
        sp: scaled problem.
        x: (n,) primal point.
        z: (m,) row values.
        y: (m,) duals.
        offset: added to the denominators (tiny: OSQP's relative residuals; 1: also
            absolute near zero).

    Returns:
        ``(prim, dual)``: ``||Ax - z|| / (offset + max(||Ax||, ||z||))`` and
        ``||Px + q + A'y|| / (offset + max(||Px||, ||A'y||, ||q||))``.
    """
    ax, px, aty = _mv(sp.A, x), _mv(sp.P, x), _mv(sp.A.T, y)
    prim = _inf_norm(ax - z) / (offset + jnp.maximum(_inf_norm(ax), _inf_norm(z)))
    dual = _inf_norm(px + sp.q + aty) / (
        offset + jnp.maximum(jnp.maximum(_inf_norm(px), _inf_norm(aty)), _inf_norm(sp.q)))
    return prim, dual


def _adapt(sp: _Scaled, st: _State, rho, s: QPSettings):
    """OSQP's rho estimate ``rho sqrt(prim_rel / dual_rel)`` from scaled residuals."""
    tiny = 1e-30
    prim, dual = _rel_residuals(sp, st.x, st.z, st.y, tiny)
    est = jnp.clip(s.adapt_bias * rho * jnp.sqrt(prim / (dual + tiny)), s.rho_min, s.rho_max)
    change = (est > rho * s.adapt_tol) | (est < rho / s.adapt_tol)
    return jnp.where(change & jnp.isfinite(est), est, rho)


def _run(sp, st, rho, w, free, s: QPSettings, iters: int):
    """``iters`` iterations in segments of ``adapt_every`` with refactor in between."""
    k = s.adapt_every if 0 < s.adapt_every < iters else iters
    with jax.named_scope("qp_factor"):
        K0, G = _gram(sp, w, free, s)

    def segment(length):
        def seg(carry, _):
            st, rho = carry
            rho_v = _rho_vec(rho, w, free, s)
            with jax.named_scope("qp_factor"):
                fac = _factor(K0, G, rho, s)
            if s.kernel == "pallas":
                from wbc_jax.qp.fused import fused_segment

                x, z, y, dx, dy, bad = fused_segment(sp.P, sp.A, fac, sp.q, sp.l, sp.u, rho_v, st.x, st.z, st.y,
                                                     iters=length, alpha=s.alpha, num_warps=s.num_warps)
                st = _State(x, z, y, dx, dy, st.bad | bad)
            elif s.anderson > 0:
                st = _anderson_scan(sp, fac, rho_v, s, st, length)
            else:
                st, _ = lax.scan(lambda c, _: (_step(sp, fac, rho_v, s, c), None), st, None,
                                 length=length, unroll=s.unroll)
            if s.adapt_every > 0:
                rho = _adapt(sp, st, rho, s)
            return (st, rho), None
        return seg

    carry = (st, rho)
    n_full, rem = divmod(iters, k) if k > 0 else (0, 0)
    with jax.named_scope("qp_iterations"):
        if n_full > 0:
            carry, _ = lax.scan(segment(k), carry, None, length=n_full, unroll=s.unroll)
        if rem > 0:
            carry, _ = segment(rem)(carry, None)
    return carry


class _AA(NamedTuple):
    """Anderson (type II) memory over the ADMM fixed-point state ``v = (x, z + y/rho)``."""

    v: jax.Array  # (N,) current point, N = n + m
    f_prev: jax.Array  # (N,) F(previous point)
    g_prev: jax.Array  # (N,) F(prev) - prev
    ng_prev: jax.Array  # () ||g_prev||
    dF: jax.Array  # (M, N) differences of F values
    dG: jax.Array  # (M, N) differences of residuals
    idx: jax.Array  # () int32 ring position
    have_prev: jax.Array  # () bool
    was_aa: jax.Array  # () bool, current point came from an extrapolation
    st: _State  # last plain ADMM state (for dx, dy, bad)


def _anderson_scan(sp: _Scaled, fac, rho_v, s: QPSettings, st: _State, length: int) -> _State:
    """``length`` ADMM steps with safeguarded Anderson acceleration (fixed cost per step).

    The ADMM map is a fixed-point map on ``v = (x, w)``, ``w = z + y / rho``
    (``z = clip(w, l, u)``, ``y = rho (w - z)``). Each step evaluates it once; an
    extrapolated point whose residual grows by more than ``aa_safeguard`` is replaced by
    the plain step from the previous point and the memory is cleared.
    """
    n = st.x.shape[0]
    M = s.anderson
    dt = st.x.dtype

    def split(v):
        x, w = v[:n], v[n:]
        z = jnp.clip(w, sp.l, sp.u)
        return x, z, rho_v * (w - z)

    def join(x, z, y):
        return jnp.concatenate([x, z + y / rho_v])

    def body(a: _AA, _):
        x, z, y = split(a.v)
        st1 = _step(sp, fac, rho_v, s, a.st._replace(x=x, z=z, y=y))
        f = join(st1.x, st1.z, st1.y)
        g = f - a.v
        ng = jnp.sqrt(jnp.sum(g * g))
        reject = a.was_aa & ~(ng <= s.aa_safeguard * a.ng_prev)
        # Memory update with the newest differences.
        dF = a.dF.at[a.idx].set(jnp.where(a.have_prev, f - a.f_prev, 0.0))
        dG = a.dG.at[a.idx].set(jnp.where(a.have_prev, g - a.g_prev, 0.0))
        gram = jnp.matmul(dG, dG.T, precision=_HI)
        lam = s.aa_reg * jnp.trace(gram) + jnp.finfo(dt).tiny
        gamma = jnp.linalg.solve(gram + lam * jnp.eye(M, dtype=dt), _mv(dG, g))
        v_aa = f - jnp.matmul(gamma, dF, precision=_HI)
        ok = _all_finite(v_aa) & ~reject
        v_next = jnp.where(reject, a.f_prev, jnp.where(ok, v_aa, f))
        keep = ~reject
        zeros = jnp.zeros_like(a.dF)
        return _AA(
            v=v_next,
            f_prev=jnp.where(keep, f, a.f_prev),
            g_prev=jnp.where(keep, g, a.g_prev),
            ng_prev=jnp.where(keep, ng, a.ng_prev),
            dF=jnp.where(keep, dF, zeros),
            dG=jnp.where(keep, dG, zeros),
            idx=jnp.where(keep & a.have_prev, (a.idx + 1) % M, 0).astype(jnp.int32),
            have_prev=keep,
            was_aa=keep & ok & a.have_prev,
            st=st1,
        ), None

    v0 = join(st.x, st.z, st.y)
    N = v0.shape[0]
    a0 = _AA(v0, v0, jnp.zeros(N, dt), jnp.asarray(jnp.inf, dt), jnp.zeros((M, N), dt),
             jnp.zeros((M, N), dt), jnp.zeros((), jnp.int32), jnp.zeros((), bool),
             jnp.zeros((), bool), st)
    a, _ = lax.scan(body, a0, None, length=length)
    x, z, y = split(a.v)
    return a.st._replace(x=x, z=z, y=y)


def _kkt_error(sp: _Scaled, x, z, y):
    """Relative KKT error ``max(prim, dual)`` of ``(x, z, y)`` (:func:`_rel_residuals`
    with offset 1) in the scaled problem; ``z`` in ``[l, u]`` and ``y`` in its normal
    cone are assumed. Returns ()."""
    return jnp.maximum(*_rel_residuals(sp, x, z, y, 1.0))


def _guess_active(sp: _Scaled, ax, y, eq, free):
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


def _kkt_solve(sp: _Scaled, lo, up, eq, s: QPSettings):
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
    gram = jnp.matmul(sp.A.T * (a * e_inv)[None, :], sp.A, precision=_HI)
    L = jnp.linalg.cholesky(sp.P + s.polish_delta * jnp.eye(n, dtype=dt) + gram)

    def solve(r):
        x = jax.scipy.linalg.cho_solve((L, True), r[:n] + _mv(Aa.T, e_inv * r[n:]))
        return jnp.concatenate([x, e_inv * (_mv(Aa, x) - r[n:])])

    v = solve(rhs)
    for _ in range(s.polish_refine):
        v = v + solve(rhs - _mv(K, v))
    return v[:n], jnp.where(act, v[n:], 0.0)


def _polish(sp: _Scaled, st: _State, eq, free, s: QPSettings) -> _State:
    """Solution polishing by primal-dual active-set passes, keeping the best point.

    Pass k guesses the active set from ``(A x, y)`` of the previous point (the ADMM
    iterate for the first pass, then the last pass's solution with its raw
    multipliers), solves the KKT system on it (:func:`_kkt_solve`) and projects the
    multipliers onto the normal cone (wrong signs dropped). A pass's point replaces the
    current best only when it is finite and its KKT error (:func:`_kkt_error`) is not
    larger, so polishing never makes the result worse or non-finite.

    Args:
        sp: scaled problem.
        st: ADMM state after the iterations.
        eq, free: (m,) bool, equality / unbounded rows.
        s: settings (``polish_passes``, ``polish_delta``, ``polish_refine``).

    Returns:
        ``st`` with ``x``, ``z``, ``y`` replaced by the best point found.
    """
    def one_pass(carry, _):
        best, err, ax, y = carry
        lo, up = _guess_active(sp, ax, y, eq, free)
        x, y = _kkt_solve(sp, lo, up, eq, s)
        ax = _mv(sp.A, x)
        y_cone = jnp.where(lo, jnp.minimum(y, 0.0), jnp.where(up, jnp.maximum(y, 0.0), y))
        cand = (x, jnp.clip(ax, sp.l, sp.u), y_cone)
        e = _kkt_error(sp, *cand)
        ok = _all_finite(*cand, e) & (e <= err)
        best = tuple(jnp.where(ok, c, b) for c, b in zip(cand, best))
        return (best, jnp.where(ok, e, err), jnp.nan_to_num(ax), jnp.nan_to_num(y)), None

    best = (st.x, st.z, st.y)
    carry = (best, _kkt_error(sp, *best), _mv(sp.A, st.x), st.y)
    (best, _, _, _), _ = lax.scan(one_pass, carry, None, length=s.polish_passes)
    return st._replace(x=best[0], z=best[1], y=best[2])


def _certificates(P, q, A, l, u, dx, dy, s: QPSettings):
    """OSQP's primal/dual infeasibility tests on the last steps (unscaled)."""
    lo_inf = l <= -BIG
    up_inf = u >= BIG
    dy = jnp.where((lo_inf & (dy < 0)) | (up_inf & (dy > 0)), 0.0, dy)
    ndy = _inf_norm(dy)
    lf = jnp.where(lo_inf, 0.0, l)
    uf = jnp.where(up_inf, 0.0, u)
    supp = jnp.sum(uf * jnp.maximum(dy, 0.0) + lf * jnp.minimum(dy, 0.0))
    pinf = (ndy > 0) & (_inf_norm(_mv(A.T, dy)) <= s.eps_pinf * ndy) & (supp <= -s.eps_pinf * ndy)
    ndx = _inf_norm(dx)
    adx = _mv(A, dx)
    tol = s.eps_dinf * ndx
    in_cone = jnp.all(jnp.where(up_inf, True, adx <= tol) & jnp.where(lo_inf, True, adx >= -tol))
    dinf = (ndx > 0) & (_inf_norm(_mv(P, dx)) <= tol) & (jnp.dot(q, dx, precision=_HI) <= -tol) & in_cone
    return pinf, dinf


def _solve_one(P, q, A, l, u, warm, s: QPSettings, iters: int) -> QPResult:
    dt = jnp.result_type(P, q, A)
    if not jnp.issubdtype(dt, jnp.floating):
        dt = jnp.result_type(float)
    P, q, A, l, u = (jnp.asarray(a, dt) for a in (P, q, A, l, u))
    n, m = P.shape[-1], A.shape[0]
    big = jnp.asarray(BIG, dt)
    l = jnp.clip(jnp.nan_to_num(l, nan=-BIG, neginf=-BIG), -big, big)
    u = jnp.clip(jnp.nan_to_num(u, nan=BIG, posinf=BIG), -big, big)
    empty = jnp.any(l > u)
    with jax.named_scope("qp_equilibrate"):
        sp = _equilibrate(P, q, A, l, u, s)
    free = (l <= -BIG) & (u >= BIG)
    eq = jnp.abs(sp.u - sp.l) < _EQ_TOL
    # Scaled start: x = D xb, z = zb / E, y = E yb / c.
    if warm is None:
        xb, zb, yb = jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros(m, dt)
        rho = jnp.asarray(s.rho, dt)
    else:
        wx, wz, wy, wr = warm
        xb = jnp.asarray(wx, dt) / sp.D
        zb = jnp.asarray(wz, dt) * sp.E
        yb = jnp.asarray(wy, dt) * sp.c / sp.E
        rho = jnp.asarray(s.rho if (wr is None or s.warm_rho != "keep") else wr, dt)
        rho = jnp.where(jnp.isfinite(rho), jnp.clip(rho, s.rho_min, s.rho_max), s.rho)
        xb, zb, yb = (jnp.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for v in (xb, zb, yb))
    act = None
    if warm is not None and s.warm_active_scale != 1.0:
        # ADMM's y is zero on rows inside their bounds up to rounding of y - rho (y / rho).
        act = jnp.abs(yb) > 100 * jnp.finfo(dt).eps * _inf_norm(yb)
    w = _row_weights(eq, free, act, s)
    zb = jnp.clip(zb, sp.l, sp.u)
    st = _State(xb, zb, yb, jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros((), bool))
    if warm is not None and s.warm_rho == "estimate" and s.adapt_every > 0:
        rho = _adapt(sp, st, rho, s)
    st, rho = _run(sp, st, rho, w, free, s, iters)
    if s.polish:
        st = _polish(sp, st, eq, free, s)
    with jax.named_scope("qp_residuals"):
        # Unscale and evaluate in the user's units.
        x = sp.D * st.x
        z = st.z / sp.E
        y = sp.E * st.y / sp.c
        dx = sp.D * st.dx
        dy = sp.E * st.dy / sp.c
        ax, px, aty = _mv(A, x), _mv(P, x), _mv(A.T, y)
        prim = _inf_norm(ax - z)
        dual = _inf_norm(px + q + aty)
        prim_tol = s.eps_abs + s.eps_rel * jnp.maximum(_inf_norm(ax), _inf_norm(z))
        dual_tol = s.eps_abs + s.eps_rel * jnp.maximum(jnp.maximum(_inf_norm(px), _inf_norm(aty)),
                                                       _inf_norm(q))
        pinf, dinf = _certificates(P, q, A, l, u, dx, dy, s)
        finite = _all_finite(x, y, z, prim, dual) & ~st.bad
        converged = (prim <= prim_tol) & (dual <= dual_tol)
        flag = jnp.where(~finite, FLAG_NONFINITE,
                         jnp.where(empty | pinf, FLAG_PRIMAL_INFEASIBLE,
                                   jnp.where(dinf, FLAG_DUAL_INFEASIBLE,
                                             jnp.where(converged, FLAG_SOLVED, FLAG_MAX_ITER))))
        fmax = jnp.finfo(dt).max
        clean = lambda v: jnp.nan_to_num(v, nan=0.0, posinf=fmax, neginf=-fmax)  # noqa: E731
        res_clean = lambda v: jnp.nan_to_num(v, nan=fmax, posinf=fmax)  # noqa: E731
        return QPResult(
            x=clean(x), y=clean(y), z=clean(z),
            prim_res=res_clean(prim), dual_res=res_clean(dual),
            flag=flag.astype(jnp.int32), iters=jnp.asarray(iters, jnp.int32),
            rho=jnp.nan_to_num(rho, nan=s.rho).astype(dt))


def _warm_tuple(warm: Any):
    if warm is None:
        return None
    return (warm.x, warm.z, warm.y, getattr(warm, "rho", None))


def _batched(fn, nb: int):
    for _ in range(nb):
        fn = jax.vmap(fn)
    return fn


@jax.jit(static_argnames=("iters", "settings"))
def _solve_jit(P, q, A, l, u, warm, iters: int, settings: QPSettings) -> QPResult:
    nb = P.ndim - 2
    fn = lambda P, q, A, l, u, w: _solve_one(P, q, A, l, u, w, settings, iters)  # noqa: E731
    return _batched(fn, nb)(P, q, A, l, u, warm)


def solve_qp(P, q, A, l, u, *, iters: int | None = None, warm: Any = None,
             settings: QPSettings | None = None) -> QPResult:
    """Solve ``min 1/2 x'Px + q'x  s.t.  l <= Ax <= u`` with a fixed number of ADMM steps.

    Jit-able and vmap-able; leading batch axes ``(B..., )`` shared by all arrays are
    also handled directly (vmapped inside).

    Args:
        P: (..., n, n) positive semidefinite cost Hessian (symmetrized internally).
        q: (..., n) linear cost.
        A: (..., m, n) constraint matrix.
        l: (..., m) lower bounds, ``-inf`` allowed.
        u: (..., m) upper bounds, ``+inf`` allowed; ``l == u`` marks an equality.
        iters: iteration count (static); ``None`` uses ``settings.iters``.
        warm: previous ``QPResult`` (or any object with ``x``, ``z``, ``y`` of matching
            shapes; ``rho`` is reused when present) to start from.
        settings: ``QPSettings`` (static); ``None`` uses the defaults.

    Returns:
        QPResult with fields of shape (..., n), (..., m) or (...,).
    """
    s = QPSettings() if settings is None else settings
    if s.linsolve == "auto":
        s = s._replace(linsolve="chol" if jax.default_backend() == "cpu" else "inv")
    if s.kernel == "auto":
        fusable = jax.default_backend() == "gpu" and s.linsolve == "inv" and s.residual_form and s.anderson == 0
        s = s._replace(kernel="pallas" if fusable else "xla")
    for name, allowed in (("linsolve", ("chol", "inv")), ("warm_rho", ("reset", "keep", "estimate")),
                          ("cost_scaling", ("P", "osqp", "none")), ("kernel", ("xla", "pallas"))):
        if getattr(s, name) not in allowed:
            raise ValueError(f"QPSettings.{name} must be one of {allowed}, not {getattr(s, name)!r}")
    if s.kernel == "pallas" and (s.linsolve != "inv" or not s.residual_form or s.anderson > 0):
        raise ValueError('QPSettings.kernel="pallas" needs linsolve="inv", residual_form=True and anderson=0')
    it = int(s.iters if iters is None else iters)
    if it < 1:
        raise ValueError(f"iters must be >= 1, got {it}")
    P = jnp.asarray(P)
    return _solve_jit(P, q, A, l, u, _warm_tuple(warm), iters=it, settings=s)
