"""Signed distances between a robot geom and a scene geom, exact when positive, and lower bounds of them.

A robot geom is a capsule, a sphere or a box, a scene geom a plane or a box; :mod:`wbc_jax.physics.clearance`
measures a scene's pairs with these functions:

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

The primitives (:data:`PRIMITIVES`, by pair kind) and the bounds (:data:`BOUNDS`) take ``(pos, R, size, env_pos,
env_R, env_size)``: positions (3,), rotations (3, 3) (columns = axes) and sizes (3,) (capsule: radius, half-length;
sphere: radius; box: half-sizes; plane: unused) of one pair (:func:`over_pairs` maps them over a kind's pairs),
and return the signed distance [m] (a bound: at most the distance).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# unit box: 8 corners (index 4 (x > 0) + 2 (y > 0) + (z > 0)) and its 12 edges as (start, end) corner indices (the
# edges along x, then y, then z)
_CORNERS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
_EDGE_ENDS = np.array([(c, c | (4 >> i)) for i in range(3) for c in range(8) if not c & (4 >> i)])  # (12, 2)
_OTHER = ((1, 2), (0, 2), (0, 1))


# ---------------------------------------------------------------------------------------------------------------
# primitives (one pair; :func:`over_pairs` maps them over a kind's pairs). A point or vector is a 3-tuple of
# arrays (its components) and a box's half-sizes a 3-tuple too. Candidates that share one expression and differ by
# constants (a box's vertices, its edge lines' signs) are one array over a leading candidate axis (:func:`_lead`),
# reduced with a min: the program stays a few hundred operations per kind, which XLA traces and compiles quickly.

def _v(p):
    """The components of a (3,) array."""
    return (p[0], p[1], p[2])


def _lead(c, like):
    """A constant (k,) array of candidates shaped to lead ``like``'s axes ((k,) for a scalar component, (k, 1, ...)
    for a candidate array), so that it broadcasts against ``like`` and a reduction over axis 0 is over the
    candidates."""
    return np.reshape(c, (-1,) + (1,) * jnp.ndim(like))


def over_pairs(fn, args):
    """(n,) ``fn`` (a primitive or a bound) of ``n`` pairs at once: ``jax.vmap`` over the pairs on axis 0 of every
    argument."""
    return jax.vmap(fn)(*args)


def _col(M, j):
    """Column ``j`` of a 3x3 matrix, as components."""
    return (M[0, j], M[1, j], M[2, j])


def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _sub(p, o):
    return (p[0] - o[0], p[1] - o[1], p[2] - o[2])


def _add(p, o):
    return (p[0] + o[0], p[1] + o[1], p[2] + o[2])


def _cols(M):
    """The 3 columns of a 3x3 matrix, each as components."""
    return tuple(_col(M, j) for j in range(3))


def _in_frame(p, o, cols):
    """``(p - o) @ M``: point ``p`` in the frame of origin ``o`` and rotation M given by its columns (the axes,
    :func:`_cols`)."""
    d = _sub(p, o)
    return tuple(_dot(d, c) for c in cols)


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


def _signs(first, second, like):
    """Constant (4,) sign columns over a candidate axis leading ``like``'s axes (:func:`_lead`)."""
    return _lead(np.array(first), like), _lead(np.array(second), like)


def _edge_lines_t(a, D, h):
    """(12, ...) segment parameters of the points of segment a + t D nearest each of the box's 12 edge lines (in the
    plane across the edge, a point-to-segment projection), clipped to [0, 1]; the 4 lines along an axis at once."""
    ts = []
    for i in range(3):
        o1, o2 = _OTHER[i]
        s1, s2 = _signs((-1.0, -1.0, 1.0, 1.0), (-1.0, 1.0, -1.0, 1.0), a[o1])
        num = (s1 * h[o1] - a[o1]) * D[o1] + (s2 * h[o2] - a[o2]) * D[o2]
        ts.append(_ratio(num, D[o1] * D[o1] + D[o2] * D[o2]))
    return _cat(ts)


def _cat(ts):
    """Candidate arrays (k_i, ...) concatenated on their candidate axis, their other axes broadcast."""
    rest = jnp.broadcast_shapes(*(jnp.shape(t)[1:] for t in ts))
    return jnp.concatenate([jnp.broadcast_to(t, jnp.shape(t)[:1] + rest) for t in ts])


def segment_box(a, b, h):
    """Smallest box SDF over the segment a-b (box frame, components; half-sizes ``h``), exact (module docstring).

    Candidates (segment parameters): the ends; the segment's point nearest each box vertex (8) and nearest each
    edge's line (12), which hold the minimum when it is positive; and the breakpoints of max_i(|a_i + t D_i| - h_i),
    the SDF inside the box: a coordinate crossing 0 (3), two face terms equal (3 axis pairs x 4 signs). Every
    candidate is a point of the segment, so a minimum over more candidates stays exact when positive."""
    D = _sub(b, a)
    like = a[0] * D[0] * h[0]  # the components' broadcast shape
    vert = _ratio(sum((_lead(_CORNERS[:, k], like) * h[k] - a[k]) * D[k] for k in range(3)), _dot(D, D))
    ts = [vert, _edge_lines_t(a, D, h)] + [_ratio(-a[i], D[i])[None] for i in range(3)]
    for i, j in ((0, 1), (0, 2), (1, 2)):  # s_i (a_i + t D_i) - h_i = s_j (a_j + t D_j) - h_j
        si, sj = _signs((1.0, 1.0, -1.0, -1.0), (1.0, -1.0, 1.0, -1.0), like)
        ts.append(_ratio(h[i] - h[j] - si * a[i] + sj * a[j], si * D[i] - sj * D[j]))
    inner = jnp.min(_at(a, D, h, _cat(ts)), axis=0)
    return jnp.minimum(jnp.minimum(box_sdf(a, h), box_sdf(b, h)), inner)


def _capsule_ends(pos, R, half):
    axis = tuple(R[k, 2] * half for k in range(3))
    return _sub(pos, axis), _add(pos, axis)


def capsule_plane(pos, R, size, ppos, pR, _):
    a, b = _capsule_ends(pos, R, size[1])
    n = _col(pR, 2)
    return jnp.minimum(_dot(n, _sub(a, ppos)), _dot(n, _sub(b, ppos))) - size[0]


def capsule_box(pos, R, size, bpos, bR, bsize):
    a, b = _capsule_ends(pos, R, size[1])
    o, axes = _v(bpos), _cols(bR)
    return segment_box(_in_frame(a, o, axes), _in_frame(b, o, axes), _v(bsize)) - size[0]


def sphere_plane(pos, R, size, ppos, pR, _):
    return _dot(_col(pR, 2), _sub(pos, ppos)) - size[0]


def sphere_box(pos, R, size, bpos, bR, bsize):
    return box_sdf(_in_frame(_v(pos), _v(bpos), _cols(bR)), _v(bsize)) - size[0]


def box_plane(pos, R, size, ppos, pR, _):
    """The lowest vertex along the plane's normal n: centre height minus sum_j |size_j (R[:, j] . n)|."""
    n = _col(pR, 2)
    return (_dot(n, _sub(pos, ppos))
            - sum(jnp.abs(size[j] * _dot(_col(R, j), n)) for j in range(3)))


def box_box(pos, R, size, bpos, bR, bsize):
    """Signed distance of box (pos, R, size) to box (bpos, bR, bsize) (module docstring)."""
    bc, rc = _cols(bR), _cols(R)
    Rab = [[_dot(bc[i], rc[j]) for j in range(3)] for i in range(3)]  # bR.T @ R: A's axes in B's frame
    axes = [(Rab[0][j], Rab[1][j], Rab[2][j]) for j in range(3)]  # A's axes a_j (Rab's columns)
    t = _in_frame(_v(pos), _v(bpos), bc)  # A's centre in B's frame
    s, h = _v(size), _v(bsize)

    def in_b(C):  # Rab (C * s) for the rows of a constant (k, 3) array C of unit-box points: (k, ...) components
        return tuple(sum(Rab[i][j] * (_lead(C[:, j], s[j]) * s[j]) for j in range(3)) for i in range(3))

    # separated (module docstring): A's vertices against B, B's vertices against A, and each edge of A at its
    # points nearest B's 12 edge lines (A's 8 vertices and 12 edges as axes of length 8 and 12)
    e0, e1 = _CORNERS[_EDGE_ENDS[:, 0]], _CORNERS[_EDGE_ENDS[:, 1]]  # (12, 3) each
    d = _sub(tuple(_lead(_CORNERS[:, i], h[i]) * h[i] for i in range(3)), t)  # B's vertices - A's centre (B's frame)
    vb = tuple(_dot(d, a) for a in axes)  # in A's frame
    a0, D0 = _add(t, in_b(e0)), in_b(e1 - e0)  # A's edges (12, ...): starts and directions
    sep = jnp.minimum(jnp.minimum(jnp.min(box_sdf(_add(t, in_b(_CORNERS)), h), axis=0),
                                  jnp.min(box_sdf(vb, s), axis=0)),
                      jnp.min(_at(a0, D0, h, _edge_lines_t(a0, D0, h)), axis=(0, 1)))

    def gap(L):  # separating-axis gap along L (B's frame), times |L|
        return (jnp.abs(_dot(L, t)) - sum(jnp.abs(L[i]) * h[i] for i in range(3))
                - sum(jnp.abs(_dot(L, a)) * s[j] for j, a in enumerate(axes)))

    # separating-axis test in B's frame: B's axes, A's axes, their 9 cross products;
    # gap(L) = |L.t| - sum_i |L_i| h_i - sum_j |L.a_j| s_j, divided by |L|
    g = [jnp.abs(t[i]) - h[i] - sum(jnp.abs(Rab[i][j]) * s[j] for j in range(3)) for i in range(3)]
    A = tuple(jnp.stack(jnp.broadcast_arrays(*(a[k] for a in axes))) for k in range(3))  # A's axes (3, ...)
    g.append(jnp.max(gap(A), axis=0))  # unit: columns of a rotation
    zero = jnp.zeros_like(A[0])
    for i in range(3):  # e_i x a_j for A's 3 axes a_j at once
        L = [(zero, -A[2], A[1]), (A[2], zero, -A[0]), (-A[1], A[0], zero)][i]
        n = jnp.sqrt(_dot(L, L))
        ok = n > 1e-6
        g.append(jnp.max(jnp.where(ok, gap(L) / jnp.where(ok, n, 1.0), -jnp.inf), axis=0))
    worst = g[0]
    for x in g[1:]:
        worst = jnp.maximum(worst, x)
    return jnp.where(worst < 0.0, worst, sep)


PRIMITIVES = {"capsule_plane": capsule_plane, "capsule_box": capsule_box, "sphere_plane": sphere_plane,
              "sphere_box": sphere_box, "box_plane": box_plane, "box_box": box_box}


# ---------------------------------------------------------------------------------------------------------------
# lower bounds (a broad phase's): the robot geom's extent along the scene box's axes

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
    bc, z = _cols(bR), _col(R, 2)
    axis = tuple(_dot(z, bc[j]) * size[1] for j in range(3))
    c = _in_frame(_v(pos), _v(bpos), bc)
    return _extent_bound(c, tuple(jnp.abs(a) for a in axis), _v(bsize)) - size[0]


def box_box_bound(pos, R, size, bpos, bR, bsize):
    """A lower bound of :func:`box_box`: the robot box's extent along the scene box's axes."""
    bc, rc = _cols(bR), _cols(R)
    e = tuple(sum(jnp.abs(_dot(bc[i], rc[j])) * size[j] for j in range(3)) for i in range(3))
    return _extent_bound(_in_frame(_v(pos), _v(bpos), bc), e, _v(bsize))


BOUNDS = {"capsule_box": capsule_box_bound, "box_box": box_box_bound}
