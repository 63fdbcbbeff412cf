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

import jax
import jax.numpy as jnp

from .spline import cubic_hermite, eval_cubic

__all__ = [
    "cubic_hermite",
    "eval_cubic",
    "zmp_xy",
    "support_margin",
    "clamp_to_support",
    "min_zmp_margin",
    "replan_com",
]

_TOL = 1e-6  # [m] collinearity tolerance
_TOL_FEAS = 1e-5  # [m] feasibility tolerance of projection candidates
_TINY = 1e-12


def _local(point_xy, feet_xy, stance):
    """float32 care: express point and feet relative to the stance centroid (metres from
    the robot rather than from the world origin, which may be several metres away)."""
    dtype = jnp.result_type(float)
    q = jnp.asarray(point_xy, dtype=dtype)
    feet = jnp.asarray(feet_xy, dtype=dtype)
    stance = jnp.asarray(stance, dtype=bool)
    n_st = jnp.maximum(jnp.sum(stance), 1)
    origin = jnp.sum(jnp.where(stance[:, None], feet, 0.0), axis=0) / n_st  # (2,)
    return q - origin, feet - origin, stance, origin


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
