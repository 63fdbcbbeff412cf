"""Batched dense convex QPs in OSQP form, solved by a warm-startable ADMM with a fixed iteration count.

Problem::

    minimize    1/2 x'Px + q'x
    subject to  l <= Ax <= u

with ``P`` (n, n) positive semidefinite (symmetrized), ``A`` (m, n), ``l``, ``u`` (m,); ``-inf`` / ``+inf`` for a
missing bound, ``l == u`` for an equality. Leading batch axes shared by every array are vmapped.

Algorithm: OSQP's ADMM (Stellato, Banjac, Goulart, Bemporad, Boyd, "OSQP: an operator splitting solver for quadratic
programs", Math. Prog. Comp. 2020): Ruiz equilibration with cost scaling, per-row step sizes rho (equality rows
``rho * rho_eq_scale``, rows without bounds ``rho_min``), proximal weight ``sigma``, over-relaxation ``alpha``, rho
re-estimated from the residual ratio, OSQP's termination test and infeasibility certificates. ``iters`` iterations
always run; with ``max_iters > iters``, blocks of ``check_every`` more while the residuals are outside tolerance.
A warm start reuses the previous result's ``x``, ``z``, ``y`` and rho. Every setting with its default and meaning:
:class:`~wbc_jax.qp.settings.QPSettings`; the result and its flags: :class:`~wbc_jax.qp.settings.QPResult`.

The same arithmetic has two implementations (``QPSettings.kernel``): XLA ops (:mod:`wbc_jax.qp.admm`, any device)
and three Pallas kernels of one program per problem (:mod:`wbc_jax.qp.fused`, GPU, float32).

Provenance: written for this project after OSQP's algorithm, with the x-update in residual form and equality rows
held exactly in the x-update, so that float32 converges on whole-body-control problems.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from wbc_jax.qp.admm import solve_xla
from wbc_jax.qp.settings import (
    BIG,
    DIVERGED_RATIO,
    FLAG_DIVERGED,
    FLAG_MAX_ITER,
    KERNELS,
    LAUNCH_ORDERS,
    LINSOLVES,
    QPResult,
    QPSettings,
    unusable,
)


def _dtype(P, q, A):
    """The problem's floating dtype: ``P``'s, ``q``'s and ``A``'s common type, the default float for integers."""
    dt = jnp.result_type(P, q, A)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def _inputs(P, q, A, l, u):
    """The problem in one floating dtype (:func:`_dtype`), missing bounds as ``+-BIG``: ``(P, q, A, l, u)``."""
    dt = _dtype(P, q, A)
    P, q, A, l, u = (jnp.asarray(a, dt) for a in (P, q, A, l, u))
    big = jnp.asarray(BIG, dt)
    l = jnp.clip(jnp.nan_to_num(l, nan=-BIG, neginf=-BIG), -big, big)
    u = jnp.clip(jnp.nan_to_num(u, nan=BIG, posinf=BIG), -big, big)
    return P, q, A, l, u


def _solve_one(P, q, A, l, u, warm, s: QPSettings, iters: int) -> QPResult:
    P, q, A, l, u = _inputs(P, q, A, l, u)
    if s.kernel == "fused":
        from wbc_jax.qp.fused import solve_fused  # Pallas' Triton modules load only where the kernels run

        return solve_fused(P, q, A, l, u, warm, s, iters)
    return solve_xla(P, q, A, l, u, warm, s, iters)


def empty_factors(n: int, m: int, s: QPSettings, dtype=jnp.float32):
    """A warm result's ``factors`` before any solve made them (``QPSettings.reuse_factors``: the first solve
    factors), for a problem of ``n`` variables and ``m`` rows under ``s`` (its ``eq_rows`` and ``box_rows``):
    :func:`wbc_jax.qp.fused.empty_factors`."""
    from wbc_jax.qp.fused import empty_factors as empty  # Pallas' Triton modules load only where the kernels run

    return empty(n, m, s, dtype)


def _warm_tuple(warm: Any, s: QPSettings):
    """``(x, z, y, rho or None, iters or None, factors or None)`` of a warm result (None: cold); ``iters`` only
    where ``s.warm_first_test`` uses it, ``factors`` where ``s.reuse_factors`` does. An :func:`unusable` result
    (``FLAG_NONFINITE``, ``FLAG_DIVERGED``) starts the solve from zero with ``s.rho``, tested after the fixed
    iterations and its factors not kept, so that it cannot poison the next."""
    if warm is None:
        return None
    iters = getattr(warm, "iters", None) if s.warm_first_test >= 0 else None
    factors = getattr(warm, "factors", None) if s.reuse_factors else None
    x, z, y, rho = warm.x, warm.z, warm.y, getattr(warm, "rho", None)
    flag = getattr(warm, "flag", None)
    if flag is not None:
        bad = unusable(jnp.asarray(flag))
        x, z, y = (jnp.where(bad[..., None], jnp.zeros_like(v), v) for v in (x, z, y))  # bad: the batch's shape
        rho = None if rho is None else jnp.where(bad, jnp.nan, rho)  # rules.warm_rho: s.rho where not finite
        iters = None if iters is None else jnp.where(bad, 0, iters)
        factors = None if factors is None else factors._replace(fresh=factors.fresh & ~bad)
    return (x, z, y, rho, iters, factors)


def _batched(fn, n_axes: int):
    for _ in range(n_axes):
        fn = jax.vmap(fn)
    return fn


@jax.jit(static_argnames=("iters", "settings"))
def _solve_jit(P, q, A, l, u, warm, iters: int, settings: QPSettings) -> QPResult:
    fn = lambda P, q, A, l, u, w: _solve_one(P, q, A, l, u, w, settings, iters)  # noqa: E731
    return _batched(fn, P.ndim - 2)(P, q, A, l, u, warm)


def resolve_settings(s: QPSettings, iters: int, dtype, backend: str) -> QPSettings:
    """``s`` with its ``"auto"`` choices made for this solve, checked (ValueError naming the setting).

    ``linsolve="auto"``: Cholesky on a CPU, the explicit inverse elsewhere. ``kernel="auto"``: the fused Pallas
    kernels on a GPU for float32 problems with one factorization per solve and no polishing, else XLA (and then
    ``reuse_factors`` off). The kernels
    are built for float32 (Triton's lowering fails in float64), so ``kernel="fused"`` with float64 data is refused
    off the CPU (Pallas' interpreter runs it).

    Args:
        s: the settings; iters: the fixed iterations; dtype: the problem's floating dtype; backend: JAX's
            default backend (``"cpu"``, ``"gpu"``, ...).
    """
    if s.linsolve == "auto":
        s = s._replace(linsolve="chol" if backend == "cpu" else "inv")
    if s.linsolve not in LINSOLVES:
        raise ValueError(f"QPSettings.linsolve must be one of {LINSOLVES}, not {s.linsolve!r}")
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    if s.kernel not in KERNELS:
        raise ValueError(f"QPSettings.kernel must be one of {KERNELS}, not {s.kernel!r}")
    if s.launch_order not in LAUNCH_ORDERS:
        raise ValueError(f"QPSettings.launch_order must be one of {LAUNCH_ORDERS}, not {s.launch_order!r}")
    one_factor = s.adapt_every == 0 or s.adapt_every >= iters
    f32 = jnp.dtype(dtype) == jnp.float32
    auto_kernel = s.kernel == "auto"
    if auto_kernel:
        s = s._replace(kernel="fused" if backend != "cpu" and one_factor and not s.polish and f32 else "xla")
    if s.kernel == "fused" and (not one_factor or s.polish):
        raise ValueError(f"QPSettings.kernel='fused' needs one factorization per solve (adapt_every 0 or >= iters) "
                         f"and polish=False, got adapt_every={s.adapt_every}, iters={iters}, polish={s.polish}")
    if s.warm_first_test < -1 or (s.warm_first_test >= 0 and not one_factor):
        raise ValueError(f"QPSettings.warm_first_test must be -1 or >= 0 with one factorization per solve "
                         f"(adapt_every 0 or >= iters), got {s.warm_first_test} with adapt_every={s.adapt_every}")
    if s.reuse_factors and s.kernel != "fused":
        if auto_kernel:  # the XLA path factors every solve
            s = s._replace(reuse_factors=False)
        else:
            raise ValueError(f"QPSettings.reuse_factors needs kernel='fused' or 'auto' (the XLA path factors every "
                             f"solve), got kernel={s.kernel!r}")
    if s.kernel == "fused" and backend != "cpu" and not f32:
        raise ValueError(f"QPSettings.kernel='fused' runs float32 problems on a {backend.upper()} (its Triton "
                         f"kernels), got {jnp.dtype(dtype).name}; use kernel='auto' or 'xla'")
    return s


def _check_rows(s: QPSettings, it: int, m: int, n: int) -> None:
    """ValueError naming the setting where ``box_rows`` or ``check_every`` do not fit the problem."""
    nb_max = min(n, m - max(min(s.eq_rows, m), 1))
    if not 0 <= s.box_rows <= nb_max:
        raise ValueError(f"QPSettings.box_rows must be in [0, {nb_max}] (bounds on the last variables, after the "
                         f"eq_rows rows, or at least one other row), got {s.box_rows}")
    if s.max_iters > it and s.check_every < 1:
        raise ValueError(f"QPSettings.check_every must be >= 1 with max_iters > iters, got {s.check_every}")


def solve_qp(P, q, A, l, u, *, iters: int | None = None, warm: Any = None,
             settings: QPSettings | None = None) -> QPResult:
    """Solve ``min 1/2 x'Px + q'x  s.t.  l <= Ax <= u`` (module docstring).

    Jit-able and vmap-able; leading batch axes ``(B..., )`` shared by all arrays are also handled directly.

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

    Raises:
        ValueError: a setting out of range for this problem (the message names it).
    """
    s = QPSettings() if settings is None else settings
    it = int(s.iters if iters is None else iters)
    s = resolve_settings(s, it, _dtype(P, q, A), jax.default_backend())
    m, n = jnp.shape(A)[-2:]
    _check_rows(s, it, m, n)
    P = jnp.asarray(P)
    return _mark_diverged(_solve_jit(P, q, A, l, u, _warm_tuple(warm, s), iters=it, settings=s), warm, s)


def last_usable(res: QPResult, warm: QPResult) -> QPResult:
    """``res`` with ``x`` the warm result's where ``res`` is :func:`unusable` (a control loop's step applies that,
    and carries it as the next warm result, whose flag makes the next solve start from zero); flags, residuals
    and ``z``, ``y`` stay ``res``'s. Shapes: ``res.x``, ``warm.x`` (..., n), flags (...,)."""
    return res._replace(x=jnp.where(unusable(res.flag)[..., None], warm.x, res.x))


def _mark_diverged(res: QPResult, warm: Any, s: QPSettings) -> QPResult:
    """``res`` flagged ``FLAG_DIVERGED`` where it is ``FLAG_MAX_ITER`` with a primal residual above
    ``DIVERGED_RATIO`` times ``max(warm.prim_res, s.eps_abs)``; not after an :func:`unusable` warm result (that
    solve started from zero) nor without a warm result carrying ``prim_res`` and ``flag``."""
    prev, flag = getattr(warm, "prim_res", None), getattr(warm, "flag", None)
    if prev is None or flag is None:
        return res
    bound = jnp.where(unusable(jnp.asarray(flag)), jnp.inf, DIVERGED_RATIO * jnp.maximum(prev, s.eps_abs))
    diverged = (res.flag == FLAG_MAX_ITER) & (res.prim_res > bound)
    return res._replace(flag=jnp.where(diverged, FLAG_DIVERGED, res.flag).astype(res.flag.dtype))
