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
is re-estimated from the residual ratio (OSQP's rule) and the matrix refactored. There
is no early exit, so a vmapped batch costs exactly ``iters`` iterations per problem.

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
Measured with ``wbc_jax.qp.problems`` (half generic, half WBC-structured problems with
entries spanning 6+ orders of magnitude; n = 68, 24 equality + 70 inequality rows),
float64, cold start, fraction of problems reaching rel. objective error <= 1e-4 and
max violation <= 1e-5 against the constructed optimum (see ``bench.py`` for more):

(measurements being finalized; see bench.py)
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
        ruiz_iters: Ruiz equilibration passes (0 disables scaling).
        cost_scaling: also scale the cost (OSQP's ``c``) in each Ruiz pass.
        eps_abs: absolute tolerance, only used to set the flag.
        eps_rel: relative tolerance, only used to set the flag.
        eps_pinf: tolerance of the primal-infeasibility certificate.
        eps_dinf: tolerance of the dual-infeasibility certificate.
        linsolve: ``"chol"`` (two triangular solves per iteration) or ``"inv"`` (the
            explicit inverse from the Cholesky factor: matrix-vector products only,
            which may be faster on GPU for small n).
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
    warm_rho: str = "reset"
    ruiz_iters: int = 5
    cost_scaling: str = "P"
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    eps_pinf: float = 1e-5
    eps_dinf: float = 1e-5
    linsolve: str = "chol"
    residual_form: bool = True


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
            ct = 1.0 / _limit(cp)
            P, q, c = ct * P, ct * q, ct * c
        return (P, q, A, D * d, E * e, c), None

    init = (P, q, A, jnp.ones(n, dt), jnp.ones(m, dt), jnp.ones((), dt))
    if s.ruiz_iters > 0:
        init, _ = lax.scan(one_pass, init, None, length=s.ruiz_iters)
    P, q, A, D, E, c = init
    P = 0.5 * (P + P.T)
    return _Scaled(P, q, A, E * l, E * u, D, E, c)


def _rho_vec(rho, eq, free, s: QPSettings):
    """(m,) per-row rho from the scalar rho."""
    return jnp.where(free, s.rho_min, jnp.where(eq, rho * s.rho_eq_scale, rho))


def _gram(sp: _Scaled, eq, free, s: QPSettings):
    """``(K0, G)`` with ``P + sigma I + A' diag(rho_vec(rho)) A = K0 + rho G``.

    Built once per solve (the O(m n^2) part), so a refactor for a new rho costs one
    O(n^2) update plus the Cholesky.
    """
    n = sp.P.shape[0]
    w = jnp.where(free, 0.0, jnp.where(eq, s.rho_eq_scale, 1.0))
    G = jnp.matmul(sp.A.T * w[None, :], sp.A, precision=_HI)
    Gf = jnp.matmul(sp.A.T * jnp.where(free, s.rho_min, 0.0)[None, :], sp.A, precision=_HI)
    K0 = sp.P + s.sigma * jnp.eye(n, dtype=sp.P.dtype) + Gf
    return K0, G


def _factor(K0, G, rho, s: QPSettings):
    """Linear solver for ``(K0 + rho G) x = b``: Cholesky factor or explicit inverse."""
    n = K0.shape[0]
    L = jnp.linalg.cholesky(K0 + rho * G)
    if s.linsolve == "inv":
        return jax.scipy.linalg.cho_solve((L, True), jnp.eye(n, dtype=K0.dtype))
    if s.linsolve != "chol":
        raise ValueError(f"QPSettings.linsolve must be 'chol' or 'inv', not {s.linsolve!r}")
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


def _adapt(sp: _Scaled, st: _State, rho, s: QPSettings):
    """OSQP's rho estimate ``rho sqrt(prim_rel / dual_rel)`` from scaled residuals."""
    tiny = 1e-30
    ax = _mv(sp.A, st.x)
    px = _mv(sp.P, st.x)
    aty = _mv(sp.A.T, st.y)
    prim = _inf_norm(ax - st.z) / (jnp.maximum(_inf_norm(ax), _inf_norm(st.z)) + tiny)
    dual = _inf_norm(px + sp.q + aty) / (
        jnp.maximum(jnp.maximum(_inf_norm(px), _inf_norm(aty)), _inf_norm(sp.q)) + tiny)
    est = jnp.clip(s.adapt_bias * rho * jnp.sqrt(prim / (dual + tiny)), s.rho_min, s.rho_max)
    change = (est > rho * s.adapt_tol) | (est < rho / s.adapt_tol)
    return jnp.where(change & jnp.isfinite(est), est, rho)


def _run(sp, st, rho, eq, free, s: QPSettings, iters: int):
    """``iters`` iterations in segments of ``adapt_every`` with refactor in between."""
    k = s.adapt_every if 0 < s.adapt_every < iters else iters
    K0, G = _gram(sp, eq, free, s)

    def segment(length):
        def seg(carry, _):
            st, rho = carry
            rho_v = _rho_vec(rho, eq, free, s)
            fac = _factor(K0, G, rho, s)
            st, _ = lax.scan(lambda c, _: (_step(sp, fac, rho_v, s, c), None), st, None,
                             length=length)
            if s.adapt_every > 0:
                rho = _adapt(sp, st, rho, s)
            return (st, rho), None
        return seg

    carry = (st, rho)
    n_full, rem = divmod(iters, k) if k > 0 else (0, 0)
    if n_full > 0:
        carry, _ = lax.scan(segment(k), carry, None, length=n_full)
    if rem > 0:
        carry, _ = segment(rem)(carry, None)
    return carry


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
    zb = jnp.clip(zb, sp.l, sp.u)
    st = _State(xb, zb, yb, jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros((), bool))
    if warm is not None and s.warm_rho == "estimate" and s.adapt_every > 0:
        rho = _adapt(sp, st, rho, s)
    st, rho = _run(sp, st, rho, eq, free, s, iters)
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
    it = int(s.iters if iters is None else iters)
    if it < 1:
        raise ValueError(f"iters must be >= 1, got {it}")
    P = jnp.asarray(P)
    return _solve_jit(P, q, A, l, u, _warm_tuple(warm), iters=it, settings=s)
