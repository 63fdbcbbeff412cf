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

The control loop's settings (warm start, one factorization per step, rho fixed at 3, 4 iterations then blocks of
4 to tolerance 1e-4) and their closed-loop evidence on the course (issue 22) are in
:func:`wbc_jax.control.transport.control_qp_settings`. On a GPU the iterations and the extension run in one Pallas
kernel per problem (``QPSettings.kernel``, :mod:`wbc_jax.qp.fused`; H100, course, Warp physics: paper campaign
171.0 s -> 133.2 s, physics + WBC at batch 16384 431,605 -> 530,978 env-steps/s, docs/performance.md), now preceded by
a Pallas factorization kernel (physics + WBC at 16384: 906,038 -> 1,058,577 env-steps/s against XLA's) and a Pallas
preparation kernel (equilibration, warm start; the residuals and flag moved into the iterations kernel: 1,035,444 ->
1,256,437 at 16384, 196,113 -> 244,058 at 270).

Removed settings (git has them), each measured without an advantage for the product:
Anderson acceleration (above: -20 % iterations at +50-70 % per iteration), the x-update
in OSQP's right-hand-side form (``residual_form=False``, stalls in float32), OSQP's and
no cost scaling (:mod:`wbc_jax.qp.scaling`), rho reset / re-estimated on a warm start
(table above), and an earlier fused kernel of fixed-length segments (+12 % env-steps/s
at batch 16384 on an H100 but a slower paper campaign, 192.6 s vs 175.0 s, from its
compile), and the x-update's factorization inside the iterations kernel (commit 9dfbbbf; with the rows in blocks
again in 2026-11-26: 214,204 / 899,189 env-steps/s at batch 270 / 16384 against 219,705 / 1,058,577 for the separate
factorization kernel, :mod:`wbc_jax.qp.fused`). Polishing is in :mod:`wbc_jax.qp.polish`, scaling in
:mod:`wbc_jax.qp.scaling`, settings, result and flags in :mod:`wbc_jax.qp.settings`.
"""


from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from wbc_jax.qp import rules
from wbc_jax.qp.polish import polish
from wbc_jax.qp.scaling import Scaled, all_finite, equilibrate, factor, mv, regularize_schur, solve
from wbc_jax.qp.settings import BIG, KERNELS, LINSOLVES, QPResult, QPSettings


class State(NamedTuple):
    """ADMM iterate in the scaled problem."""

    x: jax.Array  # (n,)
    z: jax.Array  # (m,)
    y: jax.Array  # (m,)
    dx: jax.Array  # (n,) last step in x (dual-infeasibility certificate)
    dy: jax.Array  # (m,) last step in y (primal-infeasibility certificate)
    bad: jax.Array  # () bool, a non-finite step was rejected


class KKT(NamedTuple):
    """The x-update's linear operator (one per segment).

    ``fac`` factors ``K = P + sigma I + A' diag(rho) A`` (ADMM rows only); with exact rows
    (``QPSettings.eq_rows > 0``) also ``Ae`` (ne, n) their rows (zero for rows not held),
    ``W = K^-1 Ae'`` (n, ne) and ``Sf``, the factor of the Schur complement ``S = Ae W``
    (ne, ne; identity on rows not held, so their multiplier stays 0)."""

    fac: Any
    Ae: Any = None
    W: Any = None
    Sf: Any = None


def _kkt_factor(K, Ae, ex_e, linsolve: str) -> KKT:
    """Factor the x-update's KKT system ``[[K, Ae'], [Ae, 0]]`` (:class:`KKT`).

    ``S`` is regularized on the held rows (:func:`wbc_jax.qp.scaling.regularize_schur`).
    """
    fac = factor(K, linsolve)
    if Ae is None:
        return KKT(fac)
    W = solve(fac, Ae.T, linsolve)
    return KKT(fac, Ae, W, factor(regularize_schur(mv(Ae, W), ex_e), linsolve))


def _gram(sp: Scaled, w, free, s: QPSettings):
    """``(K0, G)`` with ``P + sigma I + A' diag(rho_vec(rho)) A = K0 + rho G``.

    Built once per solve (the O(m n^2) part), so a refactor for a new rho costs one
    O(n^2) update plus the Cholesky.
    """
    n = sp.P.shape[0]
    G = mv(sp.A.T * w[None, :], sp.A)
    Gf = mv(sp.A.T * jnp.where(free, s.rho_min, 0.0)[None, :], sp.A)
    K0 = sp.P + s.sigma * jnp.eye(n, dtype=sp.P.dtype) + Gf
    return K0, G


def _exact_gap(sp: Scaled, ex, ae_x):
    """(ne,) ``b - Ae x`` of the exact rows (``ae_x`` their ``A x``, ``b = l = u``), 0 on rows not held."""
    ne = ae_x.shape[0]
    return jnp.where(ex[:ne], sp.l[:ne] - ae_x, 0.0)


def _step(sp: Scaled, kkt: KKT, rho_v, ex, free, s: QPSettings, st: State) -> State:
    """One OSQP iteration in the scaled problem; rejects a non-finite result.

    The x-update is ``x~ = x - K^-1 (P x + q + A'(y + rho (A x - z)))``: OSQP's step in
    exact arithmetic, but its fixed point does not depend on the solve's rounding.
    With exact rows (``ex``, rho 0, ``y`` their multiplier) the step ``(dx, dnu)`` solves
    ``[[K, Ae'], [Ae, 0]] [dx; dnu] = [-r; b - Ae x]`` (Schur complement), so ``Ae x~ = b``
    and the fixed point is again independent of the factors' rounding.
    """
    ax = mv(sp.A, st.x)
    r = mv(sp.P, st.x) + sp.q + mv(sp.A.T, st.y + rho_v * (ax - st.z))
    t = solve(kkt.fac, r, s.linsolve)
    if kkt.Ae is not None:
        ne = kkt.Ae.shape[0]
        dnu = -solve(kkt.Sf, _exact_gap(sp, ex, ax[:ne]) + mv(kkt.Ae, t), s.linsolve)
        xt = st.x - t - mv(kkt.W, dnu)
    else:
        xt = st.x - t
    zt = mv(sp.A, xt)
    x = s.alpha * xt + (1.0 - s.alpha) * st.x
    zr = s.alpha * zt + (1.0 - s.alpha) * st.z
    z = jnp.clip(zr + st.y / jnp.where(ex, 1.0, rho_v), sp.l, sp.u)  # exact rows: l == u
    y = st.y + rho_v * (zr - z)
    # rows without bounds carry no constraint: z = A x exactly (not the relaxed z, which would lag behind A x by
    # a factor |1 - alpha| per iteration after a row turns free, e.g. a foot lifting off), y = 0
    z = jnp.where(free, s.alpha * zt + (1.0 - s.alpha) * ax, z)
    y = jnp.where(free, 0.0, y)
    if kkt.Ae is not None:
        y = y.at[:ne].add(jnp.where(ex[:ne], dnu, 0.0))
    ok = all_finite(x, z, y)
    new = State(x, z, y, x - st.x, y - st.y, st.bad)
    old = st._replace(bad=jnp.ones((), bool))
    return jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, old)


def _project(sp: Scaled, kkt: KKT, ex, st: State, linsolve: str) -> State:
    """Move ``x`` onto the exact rows (``Ae x = b``) by the smallest correction in ``K``'s norm.

    Over-relaxation keeps an affine constraint only when both points satisfy it, so a warm point that violates
    a row just turned into an equality (a foot touching down) would otherwise see its error shrink only by a
    factor ``|1 - alpha|`` per iteration. No-op without exact rows.
    """
    if kkt.Ae is None:
        return st
    x = st.x + mv(kkt.W, solve(kkt.Sf, _exact_gap(sp, ex, mv(kkt.Ae, st.x)), linsolve))
    return st._replace(x=jnp.where(all_finite(x), x, st.x))


def _adapt(sp: Scaled, st: State, rho, s: QPSettings):
    """OSQP's rho estimate from the scaled residuals (:func:`wbc_jax.qp.rules.adapt_rho`)."""
    return rules.adapt_rho(rho, *rules.scaled_residuals(sp, st.x, st.z, st.y, 1e-30), s)


def _factor_parts(sp: Scaled, w, free, ex, s: QPSettings, ne: int):
    """``(K0, G, Ae)``: :func:`_gram`'s parts of the x-update's matrix and the exact rows ``Ae`` (ne, n), the first
    ``ne`` rows of ``A`` masked by ``ex`` (None for ``ne = 0``)."""
    with jax.named_scope("qp_factor"):
        K0, G = _gram(sp, w, free, s)
        return K0, G, (sp.A[:ne] * ex[:ne, None] if ne > 0 else None)


def _run(sp, st, rho, w, free, ex, s: QPSettings, iters: int):
    """``iters`` iterations in segments of ``adapt_every`` with refactor in between.

    Returns:
        ``(st, rho, cont)``: the iterate, the (adapted) rho for the next solve, and ``cont(st, length, active)``,
        which runs ``active`` (<= ``length``) more iterations with the last segment's factorization (for the
        convergence-checked extension, :func:`_extend`).
    """
    k = s.adapt_every if 0 < s.adapt_every < iters else iters
    ne = min(s.eq_rows, sp.A.shape[0])
    K0, G, Ae = _factor_parts(sp, w, free, ex, s, ne)

    def make_kkt(rho):
        with jax.named_scope("qp_factor"):
            return _kkt_factor(K0 + rho * G, Ae, ex[:ne], s.linsolve), rules.rho_vec(rho, w, free, s)  # w = 0 on exact rows

    def iterate(st, kkt, rho_v, length, active=None):
        # active: () int, run only the first `active` of the `length` iterations (the extension's last block)
        st = _project(sp, kkt, ex, st, s.linsolve)

        def body(c, i):
            nxt = _step(sp, kkt, rho_v, ex, free, s, c)
            if active is None:
                return nxt, None
            return jax.tree_util.tree_map(lambda a, b: jnp.where(i < active, a, b), nxt, c), None

        st, _ = lax.scan(body, st, jnp.arange(length), unroll=s.unroll)
        return st

    with jax.named_scope("qp_iterations"):
        if k == iters:  # one factorization per solve (the control loops' setting)
            kkt, rho_v = make_kkt(rho)
            st = iterate(st, kkt, rho_v, iters)
            if s.adapt_every > 0:
                rho = _adapt(sp, st, rho, s)
            return st, rho, lambda st, length, active: iterate(st, kkt, rho_v, length, active)

        def seg(carry, _, length=k):
            st, rho = carry
            st = iterate(st, *make_kkt(rho), length)
            return (st, _adapt(sp, st, rho, s)), None

        n_full, rem = divmod(iters, k)
        carry, _ = lax.scan(seg, (st, rho), None, length=n_full, unroll=s.unroll)
        if rem > 0:
            carry, _ = seg(carry, None, rem)
        st, rho = carry
        return st, rho, lambda st, length, active: iterate(st, *make_kkt(rho), length, active)


def _extend(P, q, A, sp: Scaled, st: State, cont, s: QPSettings, iters: int):
    """The convergence-checked extension (``QPSettings.max_iters``): blocks of ``check_every`` iterations
    (``cont`` from :func:`_run`) while outside tolerance, the last block cut at ``max_iters``.

    Returns:
        ``(st, n_it)``: the iterate and () int32 the iterations run in all.
    """
    n_it = jnp.asarray(iters, jnp.int32)
    if s.max_iters <= iters:
        return st, n_it

    def unconverged(c):
        st, k = c
        return (k < s.max_iters) & ~_unscaled(P, q, A, sp, st, s)[5] & ~st.bad

    def more(c):
        st, k = c
        active = jnp.minimum(s.check_every, s.max_iters - k)
        return cont(st, s.check_every, active), k + active

    with jax.named_scope("qp_iterations"):
        return lax.while_loop(unconverged, more, (st, n_it))


def _unscaled(P, q, A, sp: Scaled, st: State, s: QPSettings):
    """The iterate in the user's units and OSQP's convergence test (:func:`wbc_jax.qp.rules.termination`).

    Returns:
        ``(x, z, y, prim, dual, converged)``: (n,), (m,), (m,), ``||A x - z||_inf``, ``||P x + q + A'y||_inf``
        and () bool, both within ``eps_abs + eps_rel * scale``.
    """
    x = sp.D * st.x
    z = st.z / sp.E
    y = sp.E * st.y / sp.c
    return (x, z, y) + rules.termination((mv(A, x),), (z,), mv(P, x), mv(A.T, y), q, s)


def _dtype(P, q, A):
    """The problem's floating dtype: ``P``'s, ``q``'s and ``A``'s common type, the default float for integers."""
    dt = jnp.result_type(P, q, A)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def _inputs(P, q, A, l, u):
    """The problem in one floating dtype (:func:`_dtype`), missing bounds as ``+-BIG``: ``(dt, P, q, A, l, u)``."""
    dt = _dtype(P, q, A)
    P, q, A, l, u = (jnp.asarray(a, dt) for a in (P, q, A, l, u))
    big = jnp.asarray(BIG, dt)
    l = jnp.clip(jnp.nan_to_num(l, nan=-BIG, neginf=-BIG), -big, big)
    u = jnp.clip(jnp.nan_to_num(u, nan=BIG, posinf=BIG), -big, big)
    return dt, P, q, A, l, u


def _solve_fused(P, q, A, l, u, warm, s: QPSettings, iters: int) -> QPResult:
    """The whole solve in the Pallas kernels of :mod:`wbc_jax.qp.fused` (equilibration, warm start, iterations with
    the extension, residuals, certificates, flag); here only the rows split into the kernels' blocks: the first
    ``ne`` (exact), the last ``box_rows`` (a diagonal), the dense rows between (split inside the kernels)."""
    from wbc_jax.qp.fused import fused_solve

    dt, P, q, A, l, u = _inputs(P, q, A, l, u)
    m, n = A.shape
    nb = s.box_rows
    ne = max(min(s.eq_rows, m - nb), 1)  # one exact-block row that is not held stands for none
    if warm is None:
        wx, wz, wy = jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros(m, dt)
    else:
        wx, wz, wy = (jnp.asarray(v, dt) for v in warm[:3])
    rho = rules.warm_rho(None if warm is None else warm[3], s, dt)
    return fused_solve(P, A, q, l, u, wx, wz, wy, rho, s=s, iters=iters, warm=warm is not None, ne=ne)


def _solve_one(P, q, A, l, u, warm, s: QPSettings, iters: int) -> QPResult:
    if s.kernel == "fused":
        return _solve_fused(P, q, A, l, u, warm, s, iters)
    dt, P, q, A, l, u = _inputs(P, q, A, l, u)
    P = 0.5 * (P + P.T)  # the problem solved and tested (an asymmetric P's dual residual has a floor)
    n, m = P.shape[-1], A.shape[0]
    empty = jnp.any(l > u)
    with jax.named_scope("qp_equilibrate"):
        sp = equilibrate(P, q, A, l, u, s.ruiz_iters, s.unroll)
    free = (l <= -BIG) & (u >= BIG)
    eq = jnp.abs(sp.u - sp.l) < rules.EQ_TOL
    ex = (jnp.arange(m) < s.eq_rows) & eq & ~free  # held exactly in the x-update
    # Scaled start: x = D xb, z = zb / E, y = E yb / c.
    rho = rules.warm_rho(None if warm is None else warm[3], s, dt)
    if warm is None:
        xb, zb, yb = jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros(m, dt)
    else:
        wx, wz, wy = (jnp.asarray(v, dt) for v in warm[:3])
        xb, (zb,), (yb,) = rules.scaled_start(wx, (wz,), (wy,), sp.D, (sp.E,), sp.c)
    act = None
    if warm is not None and s.warm_active_scale != 1.0:
        (act,) = rules.active_rows((yb,), dt)
    w = rules.row_weights(eq, free, ex, act, s)
    (zb,), (yb,) = rules.start_on_rows((zb,), (yb,), (mv(sp.A, xb),), (sp.l,), (sp.u,), (free,))
    st = State(xb, zb, yb, jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros((), bool))
    st, rho, cont = _run(sp, st, rho, w, free, ex, s, iters)
    st, n_it = _extend(P, q, A, sp, st, cont, s, iters)
    if s.polish:
        x, z, y = polish(sp, st.x, st.z, st.y, eq, free, s)
        st = st._replace(x=x, z=z, y=y)
    with jax.named_scope("qp_residuals"):
        # Unscale and evaluate in the user's units.
        x, z, y, prim, dual, converged = _unscaled(P, q, A, sp, st, s)
        dx = sp.D * st.dx
        dy = sp.E * st.dy / sp.c
        pinf = rules.primal_infeasible((l,), (u,), (dy,), lambda v: mv(A.T, v[0]), s)
        dinf = rules.dual_infeasible((l,), (u,), dx, (mv(A, dx),), mv(P, dx), mv(q, dx), s)
        finite = all_finite(x, y, z, prim, dual) & ~st.bad
        fmax = jnp.finfo(dt).max
        return QPResult(
            x=rules.clean(x, 0.0, fmax), y=rules.clean(y, 0.0, fmax), z=rules.clean(z, 0.0, fmax),
            prim_res=rules.clean(prim, fmax, fmax), dual_res=rules.clean(dual, fmax, fmax),
            flag=rules.status(finite, empty, pinf, dinf, converged).astype(jnp.int32), iters=n_it,
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


def resolve_settings(s: QPSettings, iters: int, dtype, backend: str) -> QPSettings:
    """``s`` with its ``"auto"`` choices made for this solve (``dtype``: the problem's floating dtype, :func:`_dtype`),
    checked (ValueError naming the setting).

    ``linsolve="auto"``: Cholesky on a CPU, the explicit inverse elsewhere. ``kernel="auto"``: the fused Pallas
    kernels on a GPU for float32 problems with one factorization per solve and no polishing, else XLA. The kernels
    are built and measured in float32: in float64 Triton's lowering fails (an f32 / f64 comparison, H100,
    2026-11-26), so ``kernel="fused"`` with float64 data is refused off the CPU (Pallas' interpreter runs it).
    """
    if s.linsolve == "auto":
        s = s._replace(linsolve="chol" if backend == "cpu" else "inv")
    if s.linsolve not in LINSOLVES:
        raise ValueError(f"QPSettings.linsolve must be one of {LINSOLVES}, not {s.linsolve!r}")
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    if s.kernel not in KERNELS:
        raise ValueError(f"QPSettings.kernel must be one of {KERNELS}, not {s.kernel!r}")
    one_factor = s.adapt_every == 0 or s.adapt_every >= iters
    f32 = jnp.dtype(dtype) == jnp.float32
    if s.kernel == "auto":
        s = s._replace(kernel="fused" if backend != "cpu" and one_factor and not s.polish and f32 else "xla")
    if s.kernel == "fused" and (not one_factor or s.polish):
        raise ValueError(f"QPSettings.kernel='fused' needs one factorization per solve (adapt_every 0 or >= iters) "
                         f"and polish=False, got adapt_every={s.adapt_every}, iters={iters}, polish={s.polish}")
    if s.kernel == "fused" and backend != "cpu" and not f32:
        raise ValueError(f"QPSettings.kernel='fused' runs float32 problems on a {backend.upper()} (its Triton "
                         f"kernels), got {jnp.dtype(dtype).name}; use kernel='auto' or 'xla'")
    return s


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
    it = int(s.iters if iters is None else iters)
    s = resolve_settings(s, it, _dtype(P, q, A), jax.default_backend())
    m, n = jnp.shape(A)[-2:]
    nb_max = min(n, m - max(min(s.eq_rows, m), 1))
    if not 0 <= s.box_rows <= nb_max:
        raise ValueError(f"QPSettings.box_rows must be in [0, {nb_max}] (bounds on the last variables, after the "
                         f"eq_rows rows, or at least one other row), got {s.box_rows}")
    if s.max_iters > it and s.check_every < 1:
        raise ValueError(f"QPSettings.check_every must be >= 1 with max_iters > iters, got {s.check_every}")
    P = jnp.asarray(P)
    return _solve_jit(P, q, A, l, u, _warm_tuple(warm), iters=it, settings=s)
