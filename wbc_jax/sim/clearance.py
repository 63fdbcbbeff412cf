"""Exact clearance between the robot's non-foot geoms and the scene's static geoms (issue 24), from the geoms' world
poses (``d.geom_xpos``, ``d.geom_xmat``, which both MJX backends fill) and the model's sizes.

Why not MJX's contact slots: the JAX backend's capsule-box collider reports the distance of its candidate contact
points, which is not the pair's distance when the box's closest feature is an edge and the pair does not touch
(a crouched shank 2.8 mm above block2's far edge reads 5.0 mm; 24.1 mm reads 27.8 mm), and a pair beyond the
collision margin reads 1 m; on Warp a pair's distance is reported only while it penetrates. The distances here
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
  points' depth: -19.0 mm for a shank into block2 where this reads -21.6 mm and MJX's slots -25.0 mm), so only
  the sign and the order of magnitude of a penetration compare; and for a segment that goes through a box MuJoCo
  C may report a positive distance (seen for shanks driven through a block from below, unphysical poses).
* **sphere / box**: the box SDF at the centre, minus the radius (exact, signed).
* **box / box** (trunk or tray vs a wall; trunk vs a block): separated, the smallest of each edge of the robot's
  box against the other box (the capsule/box candidates outside the box, 12 x 22) and each vertex of the other
  box against the robot's box (8): exact, since a closest pair is a point of an edge of one box or a vertex of
  the other against a face (face/face and face/edge closest sets end at vertices or on edges). Overlapping (no
  separating axis among the 15 of the separating-axis test): minus the smallest overlap over those axes, which is
  the exact penetration depth (minimum translation distance) of two boxes.

Which pairs (:func:`clearance_pairs`): every robot geom (not a foot, not the carried object) that the scene pairs
with the floor or the terrain, against the floor and every terrain block; and every robot geom that the scene pairs
with a wall part, against every wall part. A pair the scene does not list (e.g. a thigh against a block) is
measured too, at no physics cost (the clearance is not a contact). Sizes are the scene's (static); poses are per
run. Other geom types raise :class:`wbc_jax.errors.SceneError` when the pairs are built.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

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

# unit box: 8 corners, 12 edges (axis i from -1 to +1 at the 4 sign combinations of the other two)
_CORNERS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
_EDGES = np.array([[np.insert([s1, s2], i, -1.0), np.insert([s1, s2], i, 1.0)]
                   for i in range(3) for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)])  # (12, 2, 3)
_SIGNS = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
_AXIS_PAIRS = np.array([[0, 1], [0, 2], [1, 2]])
_EDGE_OTHER = np.array([[j for j in range(3) if j != i] for i in range(3) for _ in range(4)])  # (12, 2)
_EDGE_SIGNS = np.array([[s1, s2] for _ in range(3) for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)])  # (12, 2)


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
# primitives (one pair; vmapped over the pairs of a kind). Written per coordinate (no ``@``, no reductions over a
# last axis of 3, candidate points as x, y, z arrays): XLA on the CPU fuses that into a few loops; measured in a
# lax.scan at batch 4, 143 us per physics step for the 54 pairs of the course (36 capsule/box 31 us, 9 box/box
# 116 us: 12 x 22 candidate points per pair), against 304 us with 3-vector products and (..., 3) points.

def _dot(x, y):
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]


def _mul_t(X, M):
    """``X @ M.T`` for rows X (..., 3) and a 3x3 M."""
    return jnp.stack([X[..., 0] * M[i, 0] + X[..., 1] * M[i, 1] + X[..., 2] * M[i, 2] for i in range(3)], axis=-1)


def _mul(X, M):
    """``X @ M`` for rows X (..., 3) and a 3x3 M."""
    return jnp.stack([X[..., 0] * M[0, j] + X[..., 1] * M[1, j] + X[..., 2] * M[2, j] for j in range(3)], axis=-1)


def box_sdf(p, h):
    """Signed distance of point(s) ``p`` (..., 3) (box frame) to the box of half-sizes ``h`` (3,)."""
    return _sdf_xyz(p[..., 0], p[..., 1], p[..., 2], h)


def _sdf_xyz(x, y, z, h):
    """:func:`box_sdf` of points given by their coordinate arrays (elementwise only: XLA fuses it)."""
    qx, qy, qz = jnp.abs(x) - h[0], jnp.abs(y) - h[1], jnp.abs(z) - h[2]
    ox, oy, oz = jnp.maximum(qx, 0.0), jnp.maximum(qy, 0.0), jnp.maximum(qz, 0.0)
    return jnp.sqrt(ox * ox + oy * oy + oz * oz) + jnp.minimum(jnp.maximum(jnp.maximum(qx, qy), qz), 0.0)


def _pick(x, idx):
    """``x[..., idx]`` for a static index array, as static slices (a gather is a slow call on the CPU)."""
    idx = np.asarray(idx)
    return jnp.stack([x[..., int(k)] for k in idx.ravel()], axis=-1).reshape(*x.shape[:-1], *idx.shape)


def _ratio(num, den):
    """clip(num / den, 0, 1), 0 where den is 0."""
    ok = jnp.abs(den) > 1e-12
    return jnp.clip(jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0), 0.0, 1.0)


def _outside_candidates(a, D, h):
    """(22,) segment parameters that hold the minimum of the box SDF over the segment a + t D when it is positive:
    the ends, the segment's point nearest each box vertex (8) and nearest each edge's line (12: in the plane across
    the edge, a point-to-segment projection). A closest box feature is a vertex, an edge (the segment point nearest
    its line) or a face, whose minimum along the segment is at an end or where its projection leaves the face,
    i.e. at the point nearest that edge's line."""
    dd = _dot(D, D)
    tv = _ratio(_dot(jnp.asarray(_CORNERS) * h - a, D), dd)  # (8,)
    o = _EDGE_OTHER  # (12, 2) the two axes across each edge
    c = jnp.asarray(_EDGE_SIGNS) * _pick(h, o)  # (12, 2) the edge's coordinates on them
    Do = _pick(D, o)
    te = _ratio(jnp.sum((c - _pick(a, o)) * Do, axis=-1), jnp.sum(Do * Do, axis=-1))  # (12,)
    return jnp.concatenate([jnp.array([0.0, 1.0], a.dtype), tv, te])


def _inside_candidates(a, D, h):
    """(15,) breakpoints of max_i(|a_i + t D_i| - h_i) (the SDF inside the box): a coordinate crossing 0 (3), two
    face terms equal (3 axis pairs x 4 signs)."""
    i, j = _AXIS_PAIRS[:, 0], _AXIS_PAIRS[:, 1]
    si, sj = _SIGNS[:, None, 0], _SIGNS[:, None, 1]  # (4, 1)
    # s_i (a_i + t D_i) - h_i = s_j (a_j + t D_j) - h_j
    t_face = _ratio(_pick(h, i) - _pick(h, j) - si * _pick(a, i) + sj * _pick(a, j),
                    si * _pick(D, i) - sj * _pick(D, j)).ravel()  # (12,)
    return jnp.concatenate([_ratio(-a, D), t_face])


def segment_box(a, b, h, inside: bool = True):
    """Smallest box SDF over the segment a-b (box frame; box half-sizes ``h``), exact (module docstring);
    ``inside`` False: exact only when positive (the penetrating candidates left out)."""
    D = b - a
    t = _outside_candidates(a, D, h)
    if inside:
        t = jnp.concatenate([t, _inside_candidates(a, D, h)])
    return jnp.min(_sdf_xyz(a[0] + t * D[0], a[1] + t * D[1], a[2] + t * D[2], h))


def _capsule_ends(pos, R, half):
    axis = R[:, 2] * half
    return pos - axis, pos + axis


def capsule_plane(pos, R, size, ppos, pR, _):
    a, b = _capsule_ends(pos, R, size[1])
    n = pR[:, 2]
    return jnp.minimum(_dot(n, a - ppos), _dot(n, b - ppos)) - size[0]


def capsule_box(pos, R, size, bpos, bR, bsize):
    a, b = _capsule_ends(pos, R, size[1])
    return segment_box(_mul(a - bpos, bR), _mul(b - bpos, bR), bsize) - size[0]


def sphere_plane(pos, R, size, ppos, pR, _):
    return _dot(pR[:, 2], pos - ppos) - size[0]


def sphere_box(pos, R, size, bpos, bR, bsize):
    return box_sdf(_mul(pos - bpos, bR), bsize) - size[0]


def box_plane(pos, R, size, ppos, pR, _):
    v = pos + _mul_t(jnp.asarray(_CORNERS) * size, R)  # (8, 3)
    return jnp.min(_dot(v - ppos, pR[:, 2]))


def box_box(pos, R, size, bpos, bR, bsize):
    """Signed distance of box (pos, R, size) to box (bpos, bR, bsize) (module docstring)."""
    Rab = _mul(bR.T, R)  # bR.T @ R: A's axes in B's frame (columns)
    t = _mul(pos - bpos, bR)  # A's centre in B's frame
    vb = _mul(jnp.asarray(_CORNERS) * bsize - t, Rab)  # B's vertices in A's frame
    ea = t + _mul_t(jnp.asarray(_EDGES) * size, Rab)  # (12, 2, 3) A's edges in B's frame
    # separated: a closest pair is a point of an edge of A against B (each edge's exact distance to B) or a vertex
    # of B against a face of A (face/face and face/edge closest sets end at vertices or on edges)
    e_d = jax.vmap(lambda e: segment_box(e[0], e[1], bsize, inside=False))(ea)
    sep = jnp.minimum(jnp.min(e_d), jnp.min(box_sdf(vb, size)))
    # separating-axis test in B's frame: B's axes, A's axes, their 9 cross products
    eye = jnp.eye(3, dtype=t.dtype)
    cross = jnp.cross(eye[:, None, :], Rab.T[None, :, :]).reshape(9, 3)
    L = jnp.concatenate([eye, Rab.T, cross])  # (15, 3)
    n = jnp.linalg.norm(L, axis=1)
    ok = n > 1e-6
    L = L / jnp.where(ok, n, 1.0)[:, None]
    gap = jnp.abs(_dot(L, t)) - _dot(jnp.abs(L), bsize) - _dot(jnp.abs(_mul(L, Rab)), size)
    gap = jnp.max(jnp.where(ok, gap, -jnp.inf))
    return jnp.where(gap < 0.0, gap, sep)


_FNS = {"capsule_plane": capsule_plane, "capsule_box": capsule_box, "sphere_plane": sphere_plane,
        "sphere_box": sphere_box, "box_plane": box_plane, "box_box": box_box}


def pair_distances(pairs: ClearancePairs, d) -> jax.Array:
    """(len(pairs),) signed distance [m] of each pair at the geom poses of ``d`` (one run; vmap for a batch)."""
    out = []
    for k, name in enumerate(KINDS):
        sel = np.where(pairs.kind == k)[0]
        if sel.size == 0:
            continue
        r, e = pairs.robot[sel], pairs.env[sel]
        dt = d.geom_xpos.dtype
        out.append(jax.vmap(_FNS[name])(d.geom_xpos[r], d.geom_xmat[r].reshape(-1, 3, 3),
                                        jnp.asarray(pairs.size[sel], dt), d.geom_xpos[e],
                                        d.geom_xmat[e].reshape(-1, 3, 3), jnp.asarray(pairs.env_size[sel], dt)))
    if not out:
        return jnp.zeros((0,))
    return jnp.concatenate(out)


def min_clearance(pairs: ClearancePairs, d):
    """(() smallest signed distance [m] over ``pairs`` (+inf: no pairs), () int32 its pair index (-1: none or
    not finite))."""
    if len(pairs) == 0:
        return jnp.full((), jnp.inf), jnp.full((), -1, jnp.int32)
    dist = pair_distances(pairs, d)
    k = jnp.argmin(dist)
    return dist[k], jnp.where(jnp.isfinite(dist[k]), k, -1).astype(jnp.int32)
