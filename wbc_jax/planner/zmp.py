"""CoM replanning helpers: cubic segments, cart-table ZMP, support-polygon margin.

The transport paper replans the CoM at the start of every footstep with a cubic so that
the ZMP stays inside the support polygon (Sec. IV-B). The pieces here are fixed-shape and
jit/vmap-able: a footstep's CoM segment is :func:`cubic_hermite` (re-exported from
:mod:`.spline`), its ZMP is :func:`zmp_xy`, and :func:`support_margin` /
:func:`clamp_to_support` measure and enforce "inside the support polygon" for the convex
hull of the stance feet (up to four, chosen by a boolean mask; the hull is found by
testing all foot pairs, so no sorting or data-dependent shapes are involved).

Margins are signed distances [m]: positive inside the hull (distance to its boundary),
negative outside (minus the distance to the hull). When the stance feet are collinear or
fewer than three (a trot's diagonal pair) the hull has no interior and the margin is
minus the distance to the segment (or point): at most 0.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .spline import cubic_hermite, eval_cubic

__all__ = [
    "cubic_hermite",
    "eval_cubic",
    "zmp_xy",
    "support_margin",
    "clamp_to_support",
    "min_zmp_margin",
    "replan_com",
    "preview_com_xy",
]

_TOL = 1e-6  # [m] collinearity tolerance
_TOL_FEAS = 1e-5  # [m] feasibility tolerance of projection candidates
_TINY = 1e-12


class _Local(NamedTuple):
    """A point and the feet relative to the stance centroid ``origin`` (world frame, [m])."""

    q: jax.Array  # (2,)
    feet: jax.Array  # (4, 2)
    stance: jax.Array  # (4,) bool
    origin: jax.Array  # (2,)


def _local(point_xy, feet_xy, stance) -> _Local:
    """float32 care: express point and feet relative to the stance centroid (metres from
    the robot rather than from the world origin, which may be several metres away)."""
    dtype = jnp.result_type(float)
    q = jnp.asarray(point_xy, dtype=dtype)
    feet = jnp.asarray(feet_xy, dtype=dtype)
    stance = jnp.asarray(stance, dtype=bool)
    n_st = jnp.maximum(jnp.sum(stance), 1)
    origin = jnp.sum(jnp.where(stance[:, None], feet, 0.0), axis=0) / n_st  # (2,)
    return _Local(q - origin, feet - origin, stance, origin)


def zmp_xy(p_com, a_com, g=9.81, z_ground=0.0):
    """Cart-table (point-mass) ZMP on a horizontal ground plane.

    ``zmp = p_xy - (p_z - z_ground) a_xy / (a_z + g)``

    Args:
        p_com: (3,) CoM position [m].
        a_com: (3,) CoM acceleration [m/s^2].
        g: gravity [m/s^2].
        z_ground: ground height [m].

    Returns:
        (2,) ZMP [m]. ``a_z + g`` is floored at 1e-3 g (free fall has no ZMP).
    """
    dtype = jnp.result_type(float)
    p, a = jnp.asarray(p_com, dtype=dtype), jnp.asarray(a_com, dtype=dtype)
    g = jnp.asarray(g, dtype=dtype)
    den = jnp.maximum(a[2] + g, 1e-3 * g)
    return p[:2] - (p[2] - z_ground) * a[:2] / den


# foot pairs: the 6 unordered pairs i < j (candidate hull edges) then the 4 single feet
_PI = (0, 0, 0, 1, 1, 2, 0, 1, 2, 3)
_PJ = (1, 2, 3, 2, 3, 3, 0, 1, 2, 3)
_N_LINES = 6


def _pairs(feet_xy, stance):
    """Foot pairs (10 rows, see _PI/_PJ): start points, directions, both-in-stance mask."""
    fi = feet_xy[jnp.asarray(_PI)]  # (10, 2)
    fj = feet_xy[jnp.asarray(_PJ)]
    both = stance[jnp.asarray(_PI)] & stance[jnp.asarray(_PJ)]  # (10,)
    return fi, fj - fi, both


def _seg_closest(q, a, d):
    """Closest points on segments a + s d (s in [0, 1]) to q; a, d (n, 2)."""
    s = jnp.clip(jnp.sum((q - a) * d, -1) / jnp.maximum(jnp.sum(d * d, -1), _TINY), 0.0, 1.0)
    return a + s[:, None] * d


def _hull_edges(feet_xy, stance):
    """Supporting lines of the stance hull: inward unit normals n (6, 2), offsets c (6,)
    with n . x >= c inside, and a mask of the pairs that are hull edges."""
    fi, d, both = (x[:_N_LINES] for x in _pairs(feet_xy, stance))
    length = jnp.linalg.norm(d, axis=-1)
    n = jnp.stack([-d[:, 1], d[:, 0]], -1) / jnp.maximum(length, _TINY)[:, None]  # left normal
    side = jnp.einsum("pk,pqk->pq", n, feet_xy[None, :, :] - fi[:, None, :])  # (6, 4)
    side = jnp.where(stance[None, :], side, 0.0)
    all_left = jnp.all(side >= -_TOL, axis=1)
    all_right = jnp.all(side <= _TOL, axis=1)
    some_off = jnp.any(jnp.abs(side) > _TOL, axis=1)  # the hull has area on one side
    edge = both & (length > _TOL) & (all_left | all_right) & some_off
    n = jnp.where(all_left[:, None], n, -n)
    c = jnp.sum(n * fi, -1)
    return n, c, edge


def support_margin(point_xy, feet_xy, stance):
    """Signed distance of a point to the convex hull of the stance feet.

    Args:
        point_xy: (2,) point (e.g. the ZMP) [m].
        feet_xy: (4, 2) foot positions (FL, FR, BL, BR) [m].
        stance: (4,) bool, feet in contact.

    Returns:
        () margin [m]: > 0 inside (distance to the boundary), < 0 outside (minus the
        distance to the hull); for hulls without interior (<= 2 feet or collinear feet)
        minus the distance to the segment/point; -inf with no stance foot.
    """
    q, feet, stance, _ = _local(point_xy, feet_xy, stance)
    fi, d, both = _pairs(feet, stance)
    dist = jnp.linalg.norm(_seg_closest(q, fi, d) - q, axis=-1)
    dist_hull = jnp.min(jnp.where(both, dist, jnp.inf))
    n, c, edge = _hull_edges(feet, stance)
    inner = jnp.min(jnp.where(edge, n @ q - c, jnp.inf))
    inside = jnp.any(edge) & (inner >= 0.0)
    return jnp.where(inside, inner, -dist_hull)


def clamp_to_support(point_xy, feet_xy, stance, margin=0.0):
    """Closest point of the stance hull shrunk by ``margin``.

    For a hull with interior the shrunken region is ``{x: support_margin(x) >= margin}``
    (each edge moved inward by ``margin``); the point is projected on it exactly (best of
    the point itself, its projections on the edge lines and the pairwise line
    intersections that satisfy every edge). If the shrunken region is empty (margin too
    large), the centroid of the stance feet is returned. For a segment (two feet, or
    collinear feet) both ends are pulled in by ``margin`` (to the midpoint if shorter than
    ``2 margin``) and the point is projected on it; for one foot, the foot.

    Args:
        point_xy: (2,) point [m].
        feet_xy: (4, 2) foot positions [m].
        stance: (4,) bool.
        margin: () required inner margin [m], >= 0.

    Returns:
        (2,) clamped point [m] (the input point when no foot is in stance).
    """
    q, feet, stance, origin = _local(point_xy, feet_xy, stance)
    m = jnp.asarray(margin, dtype=q.dtype)

    # --- degenerate hull: closest point on the (shortened) pair segments
    fi, d, both = _pairs(feet, stance)
    length = jnp.linalg.norm(d, axis=-1)
    u = d / jnp.maximum(length, _TINY)[:, None]
    cut = jnp.minimum(m, 0.5 * length)
    a = fi + cut[:, None] * u
    dd = d - 2.0 * cut[:, None] * u
    cand = _seg_closest(q, a, dd)  # (10, 2)
    real = both & (length > _TOL)  # single feet only count when no real segment exists
    use = jnp.where(jnp.any(real), real, both)
    dist = jnp.where(use, jnp.linalg.norm(cand - q, axis=-1), jnp.inf)
    seg_point = cand[jnp.argmin(dist)]

    # --- polygon: project on {n . x >= c + m} for the hull edges
    n, c, edge = _hull_edges(feet, stance)
    c = c + m

    def feasible(x):  # x (..., 2)
        return jnp.all(jnp.where(edge, x @ n.T - c >= -_TOL_FEAS, True), axis=-1)

    L = _N_LINES
    proj = q - (n @ q - c)[:, None] * n  # (6, 2) projections on each line
    ni, nj = jnp.repeat(n, L, axis=0), jnp.tile(n, (L, 1))  # (36, 2) line pairs
    ci, cj = jnp.repeat(c, L), jnp.tile(c, L)
    det = ni[:, 0] * nj[:, 1] - ni[:, 1] * nj[:, 0]
    ok_det = jnp.abs(det) > 1e-9
    det_s = jnp.where(ok_det, det, 1.0)
    cross = jnp.stack([(ci * nj[:, 1] - cj * ni[:, 1]) / det_s, (ni[:, 0] * cj - nj[:, 0] * ci) / det_s], -1)
    pair_edge = jnp.repeat(edge, L) & jnp.tile(edge, L) & ok_det
    cands = jnp.concatenate([q[None], proj, cross], axis=0)  # (43, 2)
    valid = jnp.concatenate([jnp.ones((1,), bool), edge, pair_edge]) & feasible(cands)
    cd = jnp.where(valid, jnp.linalg.norm(cands - q, axis=-1), jnp.inf)
    poly_point = jnp.where(jnp.any(valid), cands[jnp.argmin(cd)], 0.0)  # else the centroid

    out = jnp.where(jnp.any(edge), poly_point, seg_point)
    return jnp.where(jnp.any(stance), out, q) + origin


def min_zmp_margin(coef, T, feet_xy, stance, n: int = 16, g=9.81, z_ground=0.0, tau0=0.0):
    """Smallest support margin of the ZMP along a cubic CoM segment (fixed samples).

    Args:
        coef: (4, 3) CoM segment from :func:`cubic_hermite` (time since segment start).
        T: () end of the checked interval [s] (since the segment start).
        feet_xy: (4, 2) foot positions [m].
        stance: (4,) bool stance mask (held over the interval).
        n: number of samples, including both ends; static.
        g: gravity [m/s^2].
        z_ground: ground height [m].
        tau0: () start of the checked interval [s] (e.g. ``t_stance`` to check only the
            swing part of a footstep with the diagonal-pair mask).

    Returns:
        () min over the samples of ``support_margin(zmp_xy(p, a))`` [m].
    """
    taus = tau0 + jnp.linspace(0.0, 1.0, n) * (T - tau0)

    def one(tau):
        p, _, a = eval_cubic(coef, tau)
        return support_margin(zmp_xy(p, a, g, z_ground), feet_xy, stance)

    return jnp.min(jax.vmap(one)(taus))


def replan_com(p0, v0, p_goal, v_goal, T, feet_xy, stance, margin=0.0, g=9.81, z_ground=0.0):
    """One footstep of CoM reference (the transport paper's replanning at each footstep).

    A cubic from the current CoM reference state ``(p0, v0)`` to the desired CoM state at
    the end of the footstep ``(p_goal, v_goal)`` (e.g. the object path plus the initial
    offset, evaluated at ``t + T``), with the goal's horizontal position moved to the
    closest point of the support region of ``stance`` shrunk by ``margin``
    (:func:`clamp_to_support`; a no-op when the goal is already there). Pass the stance
    mask of the footstep's swing phase (the diagonal pair for a trot) so the CoM ends
    over the support line. The goal velocity and height are kept. The ZMP margin along
    the whole segment is returned so callers can monitor it.

    Args:
        p0: (3,) CoM reference position at the footstep start [m].
        v0: (3,) CoM reference velocity at the footstep start [m/s].
        p_goal: (3,) desired CoM position at the footstep end [m].
        v_goal: (3,) desired CoM velocity at the footstep end [m/s].
        T: () footstep duration [s].
        feet_xy: (4, 2) foot positions (swing feet: their planned landing points) [m].
        stance: (4,) bool support mask the goal is clamped to.
        margin: () inner margin for the goal [m].
        g: gravity [m/s^2].
        z_ground: ground height [m].

    Returns:
        (coef, zmp_margin): coef (4, 3) for :func:`eval_cubic` on tau in [0, T];
        zmp_margin () min ZMP support margin of the segment w.r.t. ``stance`` [m].
    """
    p_goal = jnp.asarray(p_goal, dtype=jnp.result_type(float))
    goal_xy = clamp_to_support(p_goal[:2], feet_xy, stance, margin)
    coef = cubic_hermite(p0, v0, p_goal.at[:2].set(goal_xy), v_goal, T)
    return coef, min_zmp_margin(coef, T, feet_xy, stance, g=g, z_ground=z_ground)


# ----------------------------------------------------------------------------- per-footstep replanning (setup time)


class _PhaseRows(NamedTuple):
    """Rows mapping (state at the phase start (3,), the phase's jerk) to p, a at local times tau (n,)."""

    p_x: np.ndarray  # (n, 3) position on (p, v, a) at the phase start
    p_j: np.ndarray  # (n,) position on the jerk
    a_x: np.ndarray  # (n, 3) acceleration on the state
    a_j: np.ndarray  # (n,) acceleration on the jerk


def _phase_rows(tau) -> _PhaseRows:
    """The :class:`_PhaseRows` at local times ``tau`` (n,) [s]."""
    one, zero = np.ones_like(tau), np.zeros_like(tau)
    p_x = np.stack([one, tau, 0.5 * tau**2], 1)
    a_x = np.stack([zero, zero, one], 1)
    return _PhaseRows(p_x, tau**3 / 6.0, a_x, tau)


def _propagate(T):
    """Triple integrator over T: x' = F x + G j, x = (p, v, a)."""
    F = np.array([[1.0, T, 0.5 * T**2], [0.0, 1.0, T], [0.0, 0.0, 1.0]])
    return F, np.array([T**3 / 6.0, 0.5 * T**2, T])


def _solve_window(x0, T, c_des, kz, line_n, line_c, two_foot, tau, w_track, w_zmp, w_jerk, x_end=None):
    """Jerks (n, 2) of the phases of one preview window (see :func:`preview_com_xy`)."""
    n = len(T)
    # Phi[i] (3, 3) and Gam[i] (3, n): state at the start of phase i = Phi x0 + Gam j (per axis)
    Phi, Gam = [np.eye(3)], [np.zeros((3, n))]
    for i in range(n):
        F, G = _propagate(T[i])
        g = F @ Gam[-1]
        g[:, i] += G
        Phi.append(F @ Phi[-1])
        Gam.append(g)
    rows, rhs = [], []
    for i in range(n):
        p_x, p_j, a_x, a_j = _phase_rows(tau[i])
        w = T[i] / len(tau[i])  # quadrature weight of one sample [s]
        P = p_x @ Gam[i]  # (ns, n) position rows on the jerks
        P[:, i] += p_j
        A = a_x @ Gam[i]
        A[:, i] += a_j
        p0 = p_x @ Phi[i] @ x0  # (ns, 2) position from the initial state
        a0 = a_x @ Phi[i] @ x0
        s = np.sqrt(w_track * w)
        for ax in range(2):  # tracking of the desired CoM, per axis
            r = np.zeros((len(tau[i]), 2 * n))
            r[:, ax * n:(ax + 1) * n] = s * P
            rows.append(r)
            rhs.append(s * (c_des[i][:, ax] - p0[:, ax]))
        if two_foot[i]:  # the ZMP's distance from the support line
            s = np.sqrt(w_zmp * w)
            Z = P - kz[i][:, None] * A  # (ns, n)
            z0 = p0 - kz[i][:, None] * a0
            r = s * np.concatenate([line_n[i, 0] * Z, line_n[i, 1] * Z], axis=1)
            rows.append(r)
            rhs.append(s * (line_c[i] - z0 @ line_n[i]))
        r = np.zeros((2, 2 * n))
        r[0, i] = r[1, n + i] = np.sqrt(w_jerk * T[i])
        rows.append(r)
        rhs.append(np.zeros(2))
    A_ls, b_ls = np.concatenate(rows), np.concatenate(rhs)
    if x_end is None:
        u = np.linalg.lstsq(A_ls, b_ls, rcond=None)[0]
    else:  # the last state held: KKT of min |A u - b|^2 s.t. E u = e
        E = np.zeros((6, 2 * n))
        E[0:3, :n] = E[3:6, n:] = Gam[n]
        e = np.concatenate([x_end[:, ax] - Phi[n] @ x0[:, ax] for ax in range(2)])
        K = np.block([[A_ls.T @ A_ls, E.T], [E, np.zeros((6, 6))]])
        u = np.linalg.lstsq(K, np.concatenate([A_ls.T @ b_ls, e]), rcond=None)[0][:2 * n]
    return np.stack([u[:n], u[n:]], 1)


def preview_com_xy(x0, T, c_des, kz, line_n, line_c, two_foot, tau, per_step=2, horizon=3, w_track=1.0,
                   w_zmp=1e3, w_jerk=1e-7, x_end=None):
    """Horizontal CoM reference replanned at the start of every footstep (numpy, setup time).

    The CoM moves with piecewise constant jerk, one cubic per support phase, continuous in position, velocity
    and acceleration. At the start of each footstep (``per_step`` phases) the jerks of the next ``horizon``
    footsteps are chosen by least squares from the reference state reached so far, and the first footstep's
    are kept (a receding preview): the cost is the integral of ``w_track |c - c_des|^2`` over every phase,
    ``w_zmp (n . zmp - c)^2`` over the phases with a support line (two-foot support: the ZMP of the
    cart-table model, ``zmp = c - kz c''``, on the stance feet's line ``n . x = c``) and ``w_jerk |j|^2``.
    The last window also ends at ``x_end`` exactly (a hard constraint).

    Args:
        x0: (3, 2) position, velocity, acceleration at the first phase's start [m, m/s, m/s^2].
        T: (M,) phase durations [s], M a multiple of ``per_step``.
        c_des: M arrays (n_i, 2) desired CoM at the samples [m].
        kz: M arrays (n_i,) cart-table factor (CoM height above the ground) / (g + a_z) at the samples [s^2].
        line_n: (M, 2) unit normal of each phase's support line; line_c: (M,) its offset [m].
        two_foot: (M,) bool, the phase has a support line (its ZMP term is used).
        tau: M arrays (n_i,) sample times since each phase's start [s].
        per_step: phases per footstep; horizon: footsteps per preview window.
        w_track [1/(m^2 s)], w_zmp [1/(m^2 s)], w_jerk [s^5/m^2 / s]: weights.
        x_end: (3, 2) state at the end of the last phase (None: free).

    Returns:
        (M, 4, 2) power-basis coefficients of each phase's cubic in its local time (``coef[i, j]`` multiplies
        ``tau**j``), for :class:`.spline.CubicPath`.
    """
    T = np.asarray(T, float)
    M = len(T)
    x = np.asarray(x0, float).copy()
    coef = np.empty((M, 4, 2))
    i = 0
    while i < M:
        stop = min(i + horizon * per_step, M)
        last = stop == M
        sl = slice(i, stop)
        jerk = _solve_window(x, T[sl], c_des[sl], kz[sl], line_n[sl], line_c[sl], two_foot[sl], tau[sl],
                             w_track, w_zmp, w_jerk, x_end if last else None)
        keep = stop - i if last else per_step
        for k in range(keep):
            coef[i + k] = np.stack([x[0], x[1], 0.5 * x[2], jerk[k] / 6.0])
            F, G = _propagate(T[i + k])
            x = F @ x + G[:, None] * jerk[k][None, :]
        i += keep
    return coef
