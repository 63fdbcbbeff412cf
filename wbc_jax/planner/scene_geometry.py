"""What the planner knows about the scene, read from the compiled MJCF (never hand-placed numbers).

Two kinds of static geometry, both as world-frame axis-aligned boxes ``(lo (3,), hi (3,))``:

* **terrain**: box geoms the feet may stand on (the other side of a foot contact pair, e.g. the blocks);
  :func:`terrain_height` gives the ground height under a point, for footholds and swing references;
* **obstacles**: geoms named ``wall*`` (pillars and lintel), which the object path must avoid
  (:mod:`wbc_jax.planner.apf`).

Moving or resizing a block or the wall in the scene file moves the footholds and the dip with it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.planner.gait import FOOT_NAMES


class SceneGeometry(NamedTuple):
    """Static scene boxes (numpy, host side).

    Attributes:
        terrain: (nt, 2, 3) lo/hi corners of standable boxes [m] (may be empty).
        obstacles: (no, 2, 3) lo/hi corners of obstacle boxes [m] (may be empty).
    """

    terrain: np.ndarray
    obstacles: np.ndarray

    @property
    def is_course(self) -> bool:
        """The scene has terrain or obstacles (planned with ``course_plan``, crouch allowed)."""
        return bool(self.terrain.shape[0] or self.obstacles.shape[0])


def _aabb(m: mujoco.MjModel, d: mujoco.MjData, g: int) -> np.ndarray:
    """(2, 3) world AABB of box geom g (rotated boxes get their enclosing box)."""
    if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_BOX:
        raise ValueError(f"geom {m.geom(g).name!r}: only box terrain/obstacles are supported")
    R = d.geom_xmat[g].reshape(3, 3)
    half = np.abs(R) @ m.geom_size[g]
    return np.stack([d.geom_xpos[g] - half, d.geom_xpos[g] + half])


def scene_geometry(robot) -> SceneGeometry:
    """Terrain and obstacle boxes of a :class:`wbc_jax.robot.model.Robot`'s scene."""
    m, ids = robot.mj_model, robot.ids
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    feet = set(int(g) for g in ids.foot_geom)
    other = set()
    for p in np.asarray(ids.foot_pair).ravel():
        for g in (int(m.pair_geom1[p]), int(m.pair_geom2[p])):
            if g not in feet and m.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE:
                other.add(g)
    terrain = [_aabb(m, d, g) for g in sorted(other)]
    walls = [_aabb(m, d, g) for g in range(m.ngeom) if (m.geom(g).name or "").startswith("wall")]
    empty = np.zeros((0, 2, 3))
    return SceneGeometry(terrain=np.array(terrain) if terrain else empty,
                         obstacles=np.array(walls) if walls else empty)


def terrain_height(terrain, xy):
    """Ground height under a point [m] (jax; the floor is z = 0).

    Args:
        terrain: (nt, 2, 3) terrain boxes (static count).
        xy: (..., 2) query points [m].

    Returns:
        (...,) the top of the highest box containing the point, else 0.
    """
    terrain = jnp.asarray(terrain)
    if terrain.shape[0] == 0:
        return jnp.zeros(jnp.shape(xy)[:-1])
    x, y = xy[..., None, 0], xy[..., None, 1]
    inside = (x >= terrain[:, 0, 0]) & (x <= terrain[:, 1, 0]) & (y >= terrain[:, 0, 1]) & (y <= terrain[:, 1, 1])
    return jnp.max(jnp.where(inside, terrain[:, 1, 2], 0.0), axis=-1)


SHIN_MARGIN = 0.010  # [m] clearance kept between a shank capsule and a box's far edge at touchdown
HIP_DROP = 0.07  # [m] the stepping leg's hip is checked this much below its planned height (the trunk sags and
#                  pitches towards the stepping leg after a step down in the crouch)
CANDIDATE_STEP = 0.005  # [m] spacing of the landing candidates searched beyond a far edge
CANDIDATE_SPAN = 0.40  # [m] how far beyond a far edge they go (at least a shank's length: :func:`leg_geometry`)


class LegGeometry(NamedTuple):
    """Sagittal-plane leg lengths [m] (every leg alike): hip pitch axis -> knee (``thigh``), knee -> foot centre
    (``shank``), the shank capsule (from the knee over ``shank_len`` along the shank, radius ``shank_r``) and the
    thigh capsule (hip to knee, radius ``thigh_r``). The knee bends backwards (it lies behind the hip-foot line,
    opposite to the walking direction)."""

    thigh: float
    shank: float
    shank_len: float
    shank_r: float
    thigh_r: float


class StartPose(NamedTuple):
    """The robot and the object at a configuration (MuJoCo C kinematics), world frame."""

    p_obj: np.ndarray  # (3,) object position [m]
    com: np.ndarray  # (3,) the robot's centre of mass [m]
    feet: np.ndarray  # (4, 3) foot centres [m]
    R_obj: np.ndarray  # (3, 3) object orientation
    R_base: np.ndarray  # (3, 3) trunk orientation
    hips: np.ndarray  # (4, 3) hip pitch axes (the thigh bodies' origins) [m]


def start_pose(robot, qpos0) -> StartPose:
    """The :class:`StartPose` of a :class:`wbc_jax.robot.model.Robot` at configuration ``qpos0`` (nq,)."""
    m, ids = robot.mj_model, robot.ids
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    hips = np.stack([d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"{leg}_thigh")] for leg in FOOT_NAMES])
    return StartPose(p_obj=d.xpos[ids.obj_body].copy(), com=d.subtree_com[ids.trunk_body].copy(),
                     feet=d.site_xpos[ids.foot_site].copy(), R_obj=d.xmat[ids.obj_body].reshape(3, 3).copy(),
                     R_base=d.xmat[ids.trunk_body].reshape(3, 3).copy(), hips=hips.copy())


def leg_geometry(robot, leg: str = "FR") -> LegGeometry:
    """The :class:`LegGeometry` of a :class:`wbc_jax.robot.model.Robot`, read from the MJCF (bodies ``{leg}_thigh``
    and ``{leg}_calf``, geoms ``{leg}_shank`` (a capsule) and ``{leg}_foot``)."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    body = lambda n: d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)]  # noqa: E731
    gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    g, gt = gid(f"{leg}_shank"), gid(f"{leg}_thigh")
    if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE or m.geom_type[gt] != mujoco.mjtGeom.mjGEOM_CAPSULE:
        raise ValueError(f"geoms {leg}_shank, {leg}_thigh: capsules are expected")
    knee = body(f"{leg}_calf")
    axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
    far_end = d.geom_xpos[g] + axis * m.geom_size[g, 1]
    near_end = d.geom_xpos[g] - axis * m.geom_size[g, 1]
    tip = far_end if np.linalg.norm(far_end - knee) > np.linalg.norm(near_end - knee) else near_end
    out = LegGeometry(thigh=float(np.linalg.norm(knee - body(f"{leg}_thigh"))),
                      shank=float(np.linalg.norm(d.geom_xpos[gid(f"{leg}_foot")] - knee)),
                      shank_len=float(np.linalg.norm(tip - knee)), shank_r=float(m.geom_size[g, 0]),
                      thigh_r=float(m.geom_size[gt, 0]))
    if out.shank_len + out.shank_r > CANDIDATE_SPAN:
        raise ValueError(f"shank of {out.shank_len + out.shank_r:.3f} m: longer than CANDIDATE_SPAN")
    return out


def knee_position(hip, foot, leg):
    """Knee of a planar two-link leg (jax): ``hip`` and ``foot`` (..., 2) as (s along the walking direction, z) [m];
    the knee behind (smaller s). A foot out of reach gets the stretched leg's knee (on the hip-foot line)."""
    d = foot - hip
    r = jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
    u = d / r
    a = (leg[0] ** 2 - leg[1] ** 2 + r ** 2) / (2.0 * r)
    hh = jnp.sqrt(jnp.maximum(leg[0] ** 2 - a ** 2, 0.0))
    n = jnp.stack([-u[..., 1], u[..., 0]], axis=-1)  # u turned +90 deg
    k1, k2 = hip + a * u + hh * n, hip + a * u - hh * n
    return jnp.where(k1[..., :1] <= k2[..., :1], k1, k2)


def _segment_distance(p, a, b):
    """Distance from points p to segments a-b (all (..., 2))."""
    w = b - a
    t = jnp.clip(jnp.sum((p - a) * w, -1) / jnp.maximum(jnp.sum(w * w, -1), 1e-12), 0.0, 1.0)
    return jnp.linalg.norm(p - (a + t[..., None] * w), axis=-1)


def shin_clearance(hip, foot, edge, leg):
    """Distance [m] from a box edge to the leg's capsules (shank and thigh) of a planar leg standing on ``foot``
    with its hip at ``hip`` (jax; all points (..., 2) as (s, z)); negative: a capsule crosses the edge; -1 m: the
    foot is out of reach.

    Args:
        leg: (thigh, shank, shank_len, shank_r, thigh_r) (:class:`LegGeometry`).
    """
    reach = jnp.linalg.norm(foot - hip, axis=-1) <= leg[0] + leg[1]
    knee = knee_position(hip, foot, leg)
    tip = knee + leg[2] * (foot - knee) / leg[1]  # end of the shank capsule
    shank = _segment_distance(edge, knee, tip) - leg[3]
    thigh = _segment_distance(edge, hip, knee) - leg[4]
    return jnp.where(reach, jnp.minimum(shank, thigh), -1.0)


def clear_of_edges(terrain, xy, direction, clearance, hip=None, foot_z=None, leg=None,
                   margin: float = SHIN_MARGIN, hip_drop: float = HIP_DROP):
    """Move a foothold along ``direction`` away from the edges of terrain boxes that cross the walking
    direction.

    Every edge: the foot centre keeps ``clearance`` from it (a sphere foot landing on an edge rolls off).
    The far edge of a box (the one the robot steps down from): the shin slopes up backwards from the foot to the
    knee and passes over that edge, at an angle set by where the hip is: low and flat in a crouch, and flatter
    the further the foot lands ahead of the hip. With ``hip`` and ``leg`` given, a landing beyond a far edge is
    kept only where the shank capsule of the planar leg (:func:`shin_clearance`, the hip at its planned height,
    ``hip_drop / 2`` and ``hip_drop`` below it) clears the edge by ``margin``; otherwise the nearest such landing
    beyond the edge (candidates every ``CANDIDATE_STEP`` out to one shank length) or, if nearer or none exists,
    the foot stays on the box (``clearance`` before its edge) and steps down at a later step, when the hip is
    further past the edge.
    Without ``hip``: every edge, far ones included, only keeps ``clearance``.

    Args:
        terrain: (nt, 2, 3) boxes; xy: (2,) nominal foothold [m]; direction: (2,) unit walking
            direction (axis-aligned); clearance: () [m], e.g. foot radius + margin.
        hip: (3,) the leg's hip pitch axis at touchdown (planned) [m]; foot_z: () foot centre height above the
            ground [m]; leg: (5,) :class:`LegGeometry` values.

    Returns:
        (2,) adjusted foothold.
    """
    terrain = jnp.asarray(terrain)
    if terrain.shape[0] == 0:
        return xy
    u = jnp.asarray(direction)
    s = xy @ u
    across = jnp.array([-u[1], u[0]])
    c = xy @ across
    if hip is not None:
        leg = jnp.asarray(leg)
        # the hip anywhere between its plan and hip_drop below (the clearance is not monotone in the drop: a lower
        # hip bends the knee more): checked at the plan, half-way and the full drop
        # (3, 1, 2): the three hips on a leading axis, broadcast against the landings checked at once
        hips_sz = jnp.stack([jnp.stack([hip[:2] @ u, hip[2] - f * hip_drop]) for f in (0.0, 0.5, 1.0)])[:, None]
    for b in range(terrain.shape[0]):
        lo, hi = terrain[b, 0, :2], terrain[b, 1, :2]
        e_in, e_out = jnp.sort(jnp.array([lo @ u, hi @ u]))
        c_lo, c_hi = jnp.sort(jnp.array([lo @ across, hi @ across]))
        in_lane = (c >= c_lo) & (c <= c_hi)
        near_in = in_lane & (jnp.abs(s - e_in) < clearance)
        s = jnp.where(near_in, jnp.where(s < e_in, e_in - clearance, e_in + clearance), s)
        if hip is None:
            near_out = in_lane & (jnp.abs(s - e_out) < clearance)
            s = jnp.where(near_out, jnp.where(s < e_out, e_out - clearance, e_out + clearance), s)
            continue
        edge = jnp.stack([e_out, terrain[b, 1, 2]])
        box_side = e_out - clearance

        def ok(sc, edge=edge, e_out=e_out):
            """Landing at sc (beyond the edge) clears it with the shin."""
            ground = terrain_height(terrain, sc[..., None] * u + c * across)
            foot = jnp.stack([sc, ground + foot_z], axis=-1)
            worst = jnp.min(shin_clearance(hips_sz, foot, edge, leg), axis=0)  # over the three hips
            return (sc >= e_out + clearance) & (worst >= margin)

        reach_out = e_out + leg[2] + leg[3]  # beyond this the shank cannot be over the edge
        considered = in_lane & (s > box_side) & (s < reach_out)
        cand = e_out + clearance + CANDIDATE_STEP * jnp.arange(int(np.ceil(CANDIDATE_SPAN / CANDIDATE_STEP)))
        ok_cand_s = ok(jnp.concatenate([cand, s[None]]))  # the candidates and the foothold itself, at once
        good = ok_cand_s[:-1] & (cand < reach_out)
        gap = jnp.where(good, jnp.abs(cand - s), jnp.inf)
        best = cand[jnp.argmin(gap)]
        best_gap = jnp.min(gap)
        moved = jnp.where(best_gap < s - box_side, best, box_side)
        s = jnp.where(considered & ~ok_cand_s[-1], moved, s)
    return s * u + c * across
