"""The XLA path of :func:`wbc_jax.qp.solve_qp`: OSQP's ADMM on one dense problem as XLA ops (``vmap`` batches it).

One solve: Ruiz equilibration (:func:`wbc_jax.qp.scaling.equilibrate`), the scaled warm start, then ``iters``
iterations in segments of ``adapt_every``, each segment with one factorization of
``K = P + sigma I + A' diag(rho) A`` and rho re-estimated after it (:func:`wbc_jax.qp.rules.adapt_rho`); then, with
``max_iters > iters``, blocks of ``check_every`` iterations with the last factorization while OSQP's termination
test fails, up to ``max_iters`` (a ``while_loop``: under ``vmap`` the batch runs until its slowest problem has
converged); optional polishing (:mod:`wbc_jax.qp.polish`); the result unscaled with its residuals, certificates and
flag. One iteration (:func:`_step`; Stellato et al. 2020, Algorithm 1, steps 3-6), in the scaled problem::

    x~ = x - K^-1 (P x + q + A'(y + rho (A x - z)))        step 3, residual form
    z~ = A x~
    x+ = alpha x~ + (1 - alpha) x                           step 4
    z+ = clip(alpha z~ + (1 - alpha) z + y / rho, l, u)     step 5
    y+ = y + rho (alpha z~ + (1 - alpha) z - z+)            step 6

Step 3 in residual form is OSQP's step in exact arithmetic, but its fixed point does not depend on the
factorization's rounding, which float32 needs. Rows with ``l == u`` among the first ``eq_rows`` are held exactly:
step 3 solves the KKT system ``[[K, Ae'], [Ae, 0]]`` through the Schur complement and ``y`` on them is the KKT
multiplier. Rows without bounds carry ``z = A x``, ``y = 0``. A non-finite step is rejected: the last finite
iterate is kept and the flag says so.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from wbc_jax.qp import rules
from wbc_jax.qp.polish import polish
from wbc_jax.qp.scaling import Scaled, all_finite, equilibrate, factor, mv, regularize_schur, solve
from wbc_jax.qp.settings import BIG, FIRST_TEST_BLOCKS, QPResult, QPSettings


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


class Unscaled(NamedTuple):
    """An iterate in the user's units with OSQP's convergence test (:func:`wbc_jax.qp.rules.termination`)."""

    x: jax.Array  # (n,)
    z: jax.Array  # (m,)
    y: jax.Array  # (m,)
    prim: jax.Array  # () ||A x - z||_inf
    dual: jax.Array  # () ||P x + q + A'y||_inf
    converged: jax.Array  # () bool, both within eps_abs + eps_rel * scale


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
    O(n^2) update plus the factorization.
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
    """One OSQP iteration in the scaled problem (module docstring); rejects a non-finite result.

    With exact rows (``ex``, rho 0, ``y`` their multiplier) the step ``(dx, dnu)`` solves
    ``[[K, Ae'], [Ae, 0]] [dx; dnu] = [-r; b - Ae x]`` (Schur complement), so ``Ae x~ = b``.
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
    # rows without bounds carry no constraint: z = A x exactly (the relaxed z would lag behind A x by a factor
    # |1 - alpha| per iteration after a row turns free, e.g. a foot lifting off), y = 0
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


def _run(sp, st, rho, w, free, ex, s: QPSettings, iters: int, first=None):
    """``iters`` iterations in segments of ``adapt_every`` with a refactorization in between; with ``first`` (()
    int32, one factorization per solve) ``first`` iterations instead (:func:`wbc_jax.qp.rules.first_block`).

    Returns:
        ``(st, rho, cont)``: the iterate, the (adapted) rho for the next solve, and ``cont(st, length, active)``,
        which runs ``active`` (<= ``length``) more iterations with the last segment's factorization (for the
        convergence-checked extension, :func:`_extend`).
    """
    k = s.adapt_every if 0 < s.adapt_every < iters else iters
    ne = min(s.eq_rows, sp.A.shape[0])
    K0, G, Ae = _factor_parts(sp, w, free, ex, s, ne)

    def make_kkt(rho):  # w = 0 on exact rows
        with jax.named_scope("qp_factor"):
            return _kkt_factor(K0 + rho * G, Ae, ex[:ne], s.linsolve), rules.rho_vec(rho, w, free, s)

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
            if first is None:
                st = iterate(st, kkt, rho_v, iters)
            else:
                st = iterate(st, kkt, rho_v, iters + FIRST_TEST_BLOCKS * s.check_every, first)
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


def _extend(P, q, A, sp: Scaled, st: State, cont, s: QPSettings, iters: int, first=None):
    """The convergence-checked extension (``QPSettings.max_iters``): blocks of ``check_every`` iterations
    (``cont`` from :func:`_run`) while outside tolerance, the last block cut at ``max_iters``; ``first``: the
    iterations run before it when not ``iters``.

    Returns:
        ``(st, n_it)``: the iterate and () int32 the iterations run in all.
    """
    n_it = jnp.asarray(iters if first is None else first, jnp.int32)
    if s.max_iters <= iters:
        return st, n_it

    def unconverged(c):
        st, k = c
        return (k < s.max_iters) & ~_unscaled(P, q, A, sp, st, s).converged & ~st.bad

    def more(c):
        st, k = c
        active = jnp.minimum(s.check_every, s.max_iters - k)
        return cont(st, s.check_every, active), k + active

    with jax.named_scope("qp_iterations"):
        return lax.while_loop(unconverged, more, (st, n_it))


def _unscaled(P, q, A, sp: Scaled, st: State, s: QPSettings) -> Unscaled:
    """The iterate in the user's units and OSQP's convergence test there."""
    x = sp.D * st.x
    z = st.z / sp.E
    y = sp.E * st.y / sp.c
    return Unscaled(x, z, y, *rules.termination((mv(A, x),), (z,), mv(P, x), mv(A.T, y), q, s))


def _start(sp: Scaled, warm, eq, free, ex, s: QPSettings, dt):
    """``(State, w)``: the start in the scaled problem (``x = xb / D``, ``z = zb E``, ``y = yb c / E``; zeros cold;
    consistent with the rows, :func:`wbc_jax.qp.rules.start_on_rows`) and the per-row rho weights."""
    n, m = sp.P.shape[0], sp.A.shape[0]
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
    return State(xb, zb, yb, jnp.zeros(n, dt), jnp.zeros(m, dt), jnp.zeros((), bool)), w


def _result(P, q, A, l, u, sp: Scaled, st: State, rho, empty, n_it, s: QPSettings) -> QPResult:
    """The final iterate in the user's units with its residuals, infeasibility certificates and flag (non-finite
    entries cleaned: NaN to 0, residuals to the dtype's max)."""
    dt = P.dtype
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


def row_kinds(sp: Scaled, l, u, s: QPSettings):
    """``(free, eq, ex)``, bool (m,) each: the rows without bounds (``l``, ``u`` the user's, ``+-BIG`` for none),
    the equality rows of the scaled problem ``sp``, and those among the first ``eq_rows`` held exactly in the
    x-update."""
    free = (l <= -BIG) & (u >= BIG)
    eq = jnp.abs(sp.u - sp.l) < rules.EQ_TOL
    return free, eq, (jnp.arange(l.shape[0]) < s.eq_rows) & eq & ~free


def solve_xla(P, q, A, l, u, warm, s: QPSettings, iters: int) -> QPResult:
    """One problem (in one floating dtype, bounds finite: ``+-BIG`` for none) by the XLA path (module docstring).

    Args:
        P: (n, n), q: (n,), A: (m, n), l, u: (m,) the problem.
        warm: None (cold) or ``(x, z, y, rho or None, iters or None)`` in the user's units.
        s: the settings (``"auto"`` choices made); iters: the fixed iterations.
    """
    dt = P.dtype
    P = 0.5 * (P + P.T)  # the problem solved and tested (an asymmetric P's dual residual has a floor)
    empty = jnp.any(l > u)
    with jax.named_scope("qp_equilibrate"):
        sp = equilibrate(P, q, A, l, u, s.ruiz_iters, s.unroll)
    free, eq, ex = row_kinds(sp, l, u, s)
    rho = rules.warm_rho(None if warm is None else warm[3], s, dt)
    st, w = _start(sp, warm, eq, free, ex, s, dt)
    first = rules.first_block(warm, s, iters)
    st, rho, cont = _run(sp, st, rho, w, free, ex, s, iters, first)
    st, n_it = _extend(P, q, A, sp, st, cont, s, iters, first)
    if s.polish:
        x, z, y = polish(sp, st.x, st.z, st.y, eq, free, s)
        st = st._replace(x=x, z=z, y=y)
    with jax.named_scope("qp_residuals"):
        return _result(P, q, A, l, u, sp, st, rho, empty, n_it, s)
