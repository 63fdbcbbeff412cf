"""Exact clearance between the robot's non-foot geoms and the scene's static geoms, from the geoms' world
poses (``d.geom_xpos``, ``d.geom_xmat``, which both MJX backends fill) and the model's sizes.

MJX's contact slots do not give a separated pair's distance (the JAX backend's capsule-box collider reports its
candidate points', a pair beyond the margin reads 1 m, and Warp lists penetrations only); the distances here
are the same on both backends and exact when positive:

* **capsule / plane** (and box / plane, sphere / plane): the lowest segment end (box vertex, sphere centre) along
  the plane normal, minus the radius: exact, signed (the plane is a half-space).
* **capsule / box**: the smallest signed distance (box SDF) of a point of the capsule's segment, minus the radius.
  The SDF along the segment is convex, and its minimum is at one of 37 closed-form candidate points, all
  evaluated at once (no iteration). Outside the box (22): the two ends, the segment's point nearest each box
  vertex (8) and nearest each edge's line (12): the closest box feature is a vertex, an edge, or a face, whose
  minimum along the segment is at an end or where the segment's projection leaves the face, which is the
  segment's point nearest that edge's line. Inside (15): the SDF is max_i(|p_i| - h_i), piecewise linear, with
  its breakpoints where a coordinate crosses 0 (3) or two face terms are equal (3 axis pairs x 4 signs). Exact
  when positive; when the segment enters the box it is the depth of the segment's deepest point below the
  nearest face, minus the radius. MuJoCo C's capsule-box depth is another measure of a penetration (its contact
  points' depth), so only the sign and the order of magnitude of a penetration compare; and for a segment that
  goes through a box MuJoCo C may report a positive distance.
* **sphere / box**: the box SDF at the centre, minus the radius (exact, signed).
* **box / box** (trunk or tray vs a wall; trunk vs a block): separated, the smallest of each box's vertices against
  the other box (8 + 8 box SDFs) and each edge of the robot's box at its point nearest each edge line of the other
  box (12 x 12): exact, since a closest pair is a vertex of one box against the other box, or an interior point
  of an edge of each (non-parallel edges: the first edge's point nearest the second's line); a closest set that
  involves a face or two parallel edges is a segment or a face whose ends reach a vertex or an edge. Overlapping (no
  separating axis among the 15 of the separating-axis test): minus the smallest overlap over those axes, which is
  the exact penetration depth (minimum translation distance) of two boxes.

Which pairs (:func:`clearance_pairs`): every robot geom (not a foot, not the carried object) that the scene pairs
with the floor or the terrain, against the floor and every terrain block; and every robot geom that the scene pairs
with a wall part, against every wall part. A pair the scene does not list (e.g. a thigh against a block) is
measured too, at no physics cost (the clearance is not a contact). Sizes are the scene's (static); poses are per
run. Other geom types raise :class:`wbc_jax.errors.SceneError` when the pairs are built.

Broad phase (:func:`bounded_min_clearance`, which :func:`min_clearance` uses): capsule/box and box/box pairs first
get a cheap lower bound of their distance (the robot geom's extent along the scene box's axes); only the few with
the smallest bounds (:data:`CANDIDATES`, a fixed count, so shapes stay static) get the exact distance. The minimum is
the exact one whenever it lies below the smallest bound left out, which the call returns.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.errors import SceneError

_PLANE, _SPHERE, _CAPSULE, _BOX = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_SPHERE),
                                   int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_BOX))
_ROBOT_TYPES = {_SPHERE: "sphere", _CAPSULE: "capsule", _BOX: "box"}
_ENV_TYPES = {_PLANE: "plane", _BOX: "box"}
KINDS = ("capsule_plane", "capsule_box", "sphere_plane", "sphere_box", "box_plane", "box_box")  # pair order

# unit box: 8 corners (index 4 (x > 0) + 2 (y > 0) + (z > 0)), its 12 edges as (start, end) corner indices (the
# edges along x, then y, then z), and the 12 edges as (axis, sign on the first other axis, sign on the second)
_CORNERS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
_EDGE_ENDS = np.array([(c, c | (4 >> i)) for i in range(3) for c in range(8) if not c & (4 >> i)])  # (12, 2)
_EDGE_LINES = [(i, s1, s2) for i in range(3) for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)]
_OTHER = ((1, 2), (0, 2), (0, 1))


@dataclass(frozen=True, eq=False)
class ClearancePairs:
    """The measured pairs of a scene, in :data:`KINDS` order (a pair's index is its position here).

    Attributes:
        robot, env: (n,) geom ids of each pair's robot geom and scene geom.
        kind: (n,) index into :data:`KINDS`.
        size: (n, 3) the robot geom's size (capsule: radius, half-length; sphere: radius; box: half-sizes).
        env_size: (n, 3) the scene geom's size (box: half-sizes; plane: unused).
    """

    robot: np.ndarray
    env: np.ndarray
    kind: np.ndarray
    size: np.ndarray
    env_size: np.ndarray

    def __len__(self) -> int:
        return int(self.robot.size)


_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def clearance_pairs(robot) -> ClearancePairs:
    """The pairs measured for ``robot``'s scene (module docstring; computed once per Robot)."""
    if robot not in _CACHE:
        _CACHE[robot] = _build_pairs(robot.mj_model, robot.ids)
    return _CACHE[robot]


def _build_pairs(m: mujoco.MjModel, ids) -> ClearancePairs:
    g1, g2 = np.asarray(m.pair_geom1), np.asarray(m.pair_geom2)
    fp = np.asarray(ids.foot_pair, int).ravel()
    ground = np.unique(np.concatenate([[ids.floor_geom], np.where(np.isin(g1[fp], ids.foot_geom), g2[fp], g1[fp])]))
    wall = np.array([i for i in range(m.ngeom) if (m.geom(i).name or "").startswith("wall")], int)

    def robot_side(pairs, env):
        p = np.asarray(pairs, int)
        r = np.where(np.isin(g1[p], env), g2[p], g1[p])
        keep = ~np.isin(r, ids.foot_geom) & (m.geom_bodyid[r] != ids.obj_body) & (m.geom_bodyid[r] != 0)
        return np.unique(r[keep])

    cand = [(r, e) for r in robot_side(ids.nonfoot_floor_pair, ground) for e in ground]
    cand += [(r, e) for r in robot_side(ids.wall_pair, wall) for e in wall]
    rows = []
    for r, e in cand:
        tr, te = int(m.geom_type[r]), int(m.geom_type[e])
        if tr not in _ROBOT_TYPES or te not in _ENV_TYPES:
            raise SceneError(f"clearance: geom pair {m.geom(int(r)).name!r} ({tr}) / {m.geom(int(e)).name!r} ({te}): "
                             "robot geoms must be capsules, spheres or boxes, scene geoms planes or boxes")
        rows.append((KINDS.index(f"{_ROBOT_TYPES[tr]}_{_ENV_TYPES[te]}"), int(r), int(e)))
    rows.sort(key=lambda x: x[0])  # stable: pairs keep their order within a kind
    k = np.array([x[0] for x in rows], int).reshape(-1)
    r = np.array([x[1] for x in rows], int).reshape(-1)
    e = np.array([x[2] for x in rows], int).reshape(-1)
    return ClearancePairs(robot=r, env=e, kind=k, size=np.asarray(m.geom_size[r], float).reshape(-1, 3),
                          env_size=np.asarray(m.geom_size[e], float).reshape(-1, 3))


# ---------------------------------------------------------------------------------------------------------------
# primitives (one pair, or the pairs of a kind at once: :func:`_over_pairs`). A point or vector is a 3-tuple of
# arrays (its components) and a box's half-sizes a 3-tuple too, every candidate point is its own expression and
# minima are taken pairwise, so a kind's whole distance is elementwise arithmetic that XLA fuses into one GPU kernel
# (no stacked candidates, no concatenation, no reduction over a short axis).

def _v(p):
    """The components of a (3,) array (or of the leading axis of a (3, ...) array)."""
    return (p[0], p[1], p[2])


def _lead(c, like):
    """A constant (k,) array of candidates shaped to lead ``like``'s axes: (k, 1, ...), so that it broadcasts against
    a batch of pairs (their components' shape) and a reduction over axis 0 is over the candidates."""
    return np.reshape(c, (-1,) + (1,) * jnp.ndim(like))


def _over_pairs(fn, args):
    """(n,) ``fn`` (a primitive) of ``n`` pairs at once: ``args`` with the pairs on axis 0 (as
    :func:`_kind_inputs` gives them) moved to the last axis, so that a component ``p[0]`` or ``M[i, j]`` holds every
    pair's. The same elementwise arithmetic as ``jax.vmap(fn)``, traced without a batching level."""
    return fn(*(jnp.moveaxis(a, 0, -1) for a in args))


def _col(M, j):
    """Column ``j`` of a 3x3 matrix, as components."""
    return (M[0, j], M[1, j], M[2, j])


def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _sub(p, o):
    return (p[0] - o[0], p[1] - o[1], p[2] - o[2])


def _add(p, o):
    return (p[0] + o[0], p[1] + o[1], p[2] + o[2])


def _in_frame(p, o, M):
    """``(p - o) @ M``: point ``p`` in the frame of origin ``o`` and rotation ``M`` (3x3 array, columns = axes)."""
    d = _sub(p, o)
    return tuple(_dot(d, _col(M, j)) for j in range(3))


def box_sdf(p, h):
    """Signed distance of point ``p`` (box frame) to the box of half-sizes ``h`` (components, any shapes)."""
    qx, qy, qz = jnp.abs(p[0]) - h[0], jnp.abs(p[1]) - h[1], jnp.abs(p[2]) - h[2]
    ox, oy, oz = jnp.maximum(qx, 0.0), jnp.maximum(qy, 0.0), jnp.maximum(qz, 0.0)
    return jnp.sqrt(ox * ox + oy * oy + oz * oz) + jnp.minimum(jnp.maximum(jnp.maximum(qx, qy), qz), 0.0)


def _ratio(num, den):
    """clip(num / den, 0, 1), 0 where den is 0."""
    ok = jnp.abs(den) > 1e-12
    return jnp.clip(jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0), 0.0, 1.0)


def _at(a, D, h, t):
    """Box SDF (half-sizes ``h``) at the segment point a + t D."""
    return box_sdf((a[0] + t * D[0], a[1] + t * D[1], a[2] + t * D[2]), h)


def _edge_lines_min(a, D, h):
    """Smallest box SDF at the segment's points nearest each of the box's 12 edge lines (in the plane across the
    edge, a point-to-segment projection)."""
    best = None
    for i, s1, s2 in _EDGE_LINES:
        o1, o2 = _OTHER[i]
        num = (s1 * h[o1] - a[o1]) * D[o1] + (s2 * h[o2] - a[o2]) * D[o2]
        v = _at(a, D, h, _ratio(num, D[o1] * D[o1] + D[o2] * D[o2]))
        best = v if best is None else jnp.minimum(best, v)
    return best


def segment_box(a, b, h):
    """Smallest box SDF over the segment a-b (box frame, components; half-sizes ``h``), exact (module docstring).

    Candidates (segment parameters): the ends; the segment's point nearest each box vertex (8) and nearest each
    edge's line (12), which hold the minimum when it is positive; and the breakpoints of max_i(|a_i + t D_i| - h_i),
    the SDF inside the box: a coordinate crossing 0 (3), two face terms equal (3 axis pairs x 4 signs). Every
    candidate is a point of the segment, so a minimum over more candidates stays exact when positive."""
    D = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
    dd = _dot(D, D)
    best = jnp.minimum(jnp.minimum(box_sdf(a, h), box_sdf(b, h)), _edge_lines_min(a, D, h))
    for c in _CORNERS:
        best = jnp.minimum(best, _at(a, D, h, _ratio(sum((c[k] * h[k] - a[k]) * D[k] for k in range(3)), dd)))
    for i in range(3):
        best = jnp.minimum(best, _at(a, D, h, _ratio(-a[i], D[i])))
    for i, j in ((0, 1), (0, 2), (1, 2)):  # s_i (a_i + t D_i) - h_i = s_j (a_j + t D_j) - h_j
        for si, sj in ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)):
            best = jnp.minimum(best, _at(a, D, h, _ratio(h[i] - h[j] - si * a[i] + sj * a[j], si * D[i] - sj * D[j])))
    return best


def _capsule_ends(pos, R, half):
    axis = tuple(R[k, 2] * half for k in range(3))
    return _sub(pos, axis), _add(pos, axis)


def capsule_plane(pos, R, size, ppos, pR, _):
    a, b = _capsule_ends(pos, R, size[1])
    n = _col(pR, 2)
    return jnp.minimum(_dot(n, _sub(a, ppos)), _dot(n, _sub(b, ppos))) - size[0]


def capsule_box(pos, R, size, bpos, bR, bsize):
    a, b = _capsule_ends(pos, R, size[1])
    o = _v(bpos)
    return segment_box(_in_frame(a, o, bR), _in_frame(b, o, bR), _v(bsize)) - size[0]


def sphere_plane(pos, R, size, ppos, pR, _):
    return _dot(_col(pR, 2), _sub(pos, ppos)) - size[0]


def sphere_box(pos, R, size, bpos, bR, bsize):
    return box_sdf(_in_frame(_v(pos), _v(bpos), bR), _v(bsize)) - size[0]


def box_plane(pos, R, size, ppos, pR, _):
    """The lowest vertex along the plane's normal n: centre height minus sum_j |size_j (R[:, j] . n)|."""
    n = _col(pR, 2)
    return (_dot(n, _sub(pos, ppos))
            - sum(jnp.abs(size[j] * _dot(_col(R, j), n)) for j in range(3)))


def box_box(pos, R, size, bpos, bR, bsize):
    """Signed distance of box (pos, R, size) to box (bpos, bR, bsize) (module docstring)."""
    Rab = [[_dot(_col(bR, i), _col(R, j)) for j in range(3)] for i in range(3)]  # bR.T @ R: A's axes in B's frame
    axes = [(Rab[0][j], Rab[1][j], Rab[2][j]) for j in range(3)]  # A's axes a_j (Rab's columns)
    t = _in_frame(_v(pos), _v(bpos), bR)  # A's centre in B's frame
    s, h = _v(size), _v(bsize)

    def in_b(C):  # Rab (C * s) for the rows of a constant (k, 3) array C of unit-box points: (k, ...) components
        return tuple(sum(Rab[i][j] * (_lead(C[:, j], s[j]) * s[j]) for j in range(3)) for i in range(3))

    # separated (module docstring): A's vertices against B, B's vertices against A, and each edge of A at its
    # points nearest B's 12 edge lines (A's 8 vertices and 12 edges as axes of length 8 and 12)
    e0, e1 = _CORNERS[_EDGE_ENDS[:, 0]], _CORNERS[_EDGE_ENDS[:, 1]]  # (12, 3) each
    d = _sub(tuple(_lead(_CORNERS[:, i], h[i]) * h[i] for i in range(3)), t)  # B's vertices - A's centre (B's frame)
    vb = tuple(_dot(d, a) for a in axes)  # in A's frame
    sep = jnp.minimum(jnp.minimum(jnp.min(box_sdf(_add(t, in_b(_CORNERS)), h), axis=0),
                                  jnp.min(box_sdf(vb, s), axis=0)),
                      jnp.min(_edge_lines_min(_add(t, in_b(e0)), in_b(e1 - e0), h), axis=0))

    def gap(L):  # separating-axis gap along L (B's frame), times |L|
        return (jnp.abs(_dot(L, t)) - sum(jnp.abs(L[i]) * h[i] for i in range(3))
                - sum(jnp.abs(_dot(L, a)) * s[j] for j, a in enumerate(axes)))

    # separating-axis test in B's frame: B's axes, A's axes, their 9 cross products;
    # gap(L) = |L.t| - sum_i |L_i| h_i - sum_j |L.a_j| s_j, divided by |L|
    g = [jnp.abs(t[i]) - h[i] - sum(jnp.abs(Rab[i][j]) * s[j] for j in range(3)) for i in range(3)]
    g += [gap(a) for a in axes]  # unit: columns of a rotation
    for i in range(3):
        for a in axes:  # e_i x a
            L = [(0.0, -a[2], a[1]), (a[2], 0.0, -a[0]), (-a[1], a[0], 0.0)][i]
            n = jnp.sqrt(_dot(L, L))
            ok = n > 1e-6
            g.append(jnp.where(ok, gap(L) / jnp.where(ok, n, 1.0), -jnp.inf))
    worst = g[0]
    for x in g[1:]:
        worst = jnp.maximum(worst, x)
    return jnp.where(worst < 0.0, worst, sep)


_FNS = {"capsule_plane": capsule_plane, "capsule_box": capsule_box, "sphere_plane": sphere_plane,
        "sphere_box": sphere_box, "box_plane": box_plane, "box_box": box_box}


def _kind_inputs(pairs: ClearancePairs, d, sel):
    """The primitives' arguments for pairs ``sel`` (indices of one kind): robot geom pose and size, scene geom pose
    and size, each with the pairs on axis 0."""
    r, e = pairs.robot[sel], pairs.env[sel]
    dt = d.geom_xpos.dtype
    return (d.geom_xpos[r], d.geom_xmat[r].reshape(-1, 3, 3), jnp.asarray(pairs.size[sel], dt), d.geom_xpos[e],
            d.geom_xmat[e].reshape(-1, 3, 3), jnp.asarray(pairs.env_size[sel], dt))


def pair_distances(pairs: ClearancePairs, d) -> jax.Array:
    """(len(pairs),) signed distance [m] of each pair at the geom poses of ``d`` (one run; vmap for a batch)."""
    out = []
    for k, name in enumerate(KINDS):
        sel = np.where(pairs.kind == k)[0]
        if sel.size:
            out.append(_over_pairs(_FNS[name], _kind_inputs(pairs, d, sel)))
    if not out:
        return jnp.zeros((0,))
    return jnp.concatenate(out)


# ---------------------------------------------------------------------------------------------------------------
# broad phase: a lower bound of each expensive pair's distance from the geoms' extents along the scene box's axes

def _extent_bound(c, e, h):
    """Lower bound of the signed distance between a box of half-sizes ``h`` (its frame) and a set that lies within
    |p_i - c_i| <= e_i (components). Clear of the box along an axis (g_i = |c_i| - e_i - h_i > 0): every point of the
    set is outside with |p_i| - h_i >= g_i, so the box SDF formula over max(g, 0) bounds it; otherwise max_i g_i, a
    separating-axis gap, which bounds minus the penetration depth."""
    g = [jnp.abs(c[i]) - e[i] - h[i] for i in range(3)]
    out = [jnp.maximum(x, 0.0) for x in g]
    return jnp.sqrt(_dot(out, out)) + jnp.minimum(jnp.maximum(jnp.maximum(g[0], g[1]), g[2]), 0.0)


def capsule_box_bound(pos, R, size, bpos, bR, bsize):
    """A lower bound of :func:`capsule_box`: the segment's extent along the box's axes, minus the radius."""
    axis = tuple(_dot(_col(R, 2), _col(bR, j)) * size[1] for j in range(3))
    c = _in_frame(_v(pos), _v(bpos), bR)
    return _extent_bound(c, tuple(jnp.abs(a) for a in axis), _v(bsize)) - size[0]


def box_box_bound(pos, R, size, bpos, bR, bsize):
    """A lower bound of :func:`box_box`: the robot box's extent along the scene box's axes."""
    e = tuple(sum(jnp.abs(_dot(_col(bR, i), _col(R, j))) * size[j] for j in range(3)) for i in range(3))
    return _extent_bound(_in_frame(_v(pos), _v(bpos), bR), e, _v(bsize))


_BOUNDS = {"capsule_box": capsule_box_bound, "box_box": box_box_bound}
CANDIDATES = {"capsule_box": 8, "box_box": 3}
"""Pairs of each bounded kind whose exact distance is computed at every pose: those with the smallest bounds."""
BOUND_ROUNDING = 1e-5  # [m] taken off the reported bound: a float32 bound can exceed the exact distance by rounding


class Clearance(NamedTuple):
    """The smallest clearance over a scene's pairs at one pose (:func:`bounded_min_clearance`)."""

    distance: jax.Array  # () [m] the smallest exact distance over the candidate pairs (+inf: no pairs)
    pair: jax.Array  # () int32 its pair index (-1: none or not finite)
    bound: jax.Array  # () [m] every pair left out is at least this far (+inf: none left out)


def bounded_min_clearance(pairs: ClearancePairs, d) -> Clearance:
    """The smallest signed distance over ``pairs`` at the geom poses of ``d`` (one run), with a broad phase.

    Planes and spheres are exact for every pair; of each kind in :data:`CANDIDATES` only that many pairs, those with
    the smallest lower bounds (:func:`capsule_box_bound`, :func:`box_box_bound`), get their exact distance. The
    distance equals the minimum of :func:`pair_distances` (same value, same pair, ties to the lowest index) whenever
    it is below ``bound``, the smallest bound of a pair left out; otherwise it is the exact distance of a pair and at
    least that minimum. Non-finite poses give NaN and -1 as the exact minimum does."""
    dist, index, bounds, bad = [], [], [], jnp.bool_(False)
    for k, name in enumerate(KINDS):
        sel = np.where(pairs.kind == k)[0]
        if sel.size == 0:
            continue
        args, idx = _kind_inputs(pairs, d, sel), jnp.asarray(sel, jnp.int32)
        n_exact = CANDIDATES.get(name, sel.size)
        if n_exact < sel.size:
            lower = _over_pairs(_BOUNDS[name], args)
            neg, pick = jax.lax.top_k(-lower, n_exact + 1)
            bounds.append(-neg[n_exact])
            bad = bad | jnp.any(jnp.isnan(lower))
            args, idx = tuple(a[pick[:n_exact]] for a in args), idx[pick[:n_exact]]
        dist.append(_over_pairs(_FNS[name], args))
        index.append(idx)
    if not dist:
        return Clearance(jnp.full((), jnp.inf), jnp.full((), -1, jnp.int32), jnp.full((), jnp.inf))
    dist, index = jnp.concatenate(dist), jnp.concatenate(index)
    best = jnp.where(bad, jnp.nan, jnp.min(dist))
    k = jnp.min(jnp.where(dist == best, index, len(pairs)))
    bound = jnp.min(jnp.stack(bounds)) - BOUND_ROUNDING if bounds else jnp.full((), jnp.inf, best.dtype)
    return Clearance(best, jnp.where(jnp.isfinite(best), k, -1).astype(jnp.int32), bound)


def min_clearance(pairs: ClearancePairs, d):
    """(() smallest signed distance [m] over ``pairs`` (+inf: no pairs), () int32 its pair index (-1: none or
    not finite)), by :func:`bounded_min_clearance`: exact below its bound."""
    out = bounded_min_clearance(pairs, d)
    return out.distance, out.pair
