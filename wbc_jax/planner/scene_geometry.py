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
    """Terrain and obstacle boxes of a :class:`wbc_jax.sim.model.Robot`'s scene."""
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


SHIN_SLOPE = 1.8  # [-] 1 / tan(30 deg): the shins slope up backwards from the feet at 30 deg or more (in the crouch
#                   over block2 they slope at 23 deg, but 1 / tan(20 deg) = 2.75 put the landing so far beyond the
#                   edge that 63 of 270 paper runs struck it during the swing: H100, 2026-11-25)


def clear_of_edges(terrain, xy, direction, clearance):
    """Move a foothold along ``direction`` away from the edges of terrain boxes that cross the walking
    direction.

    Every edge: the foot centre keeps ``clearance`` from it (a sphere foot landing on an edge rolls off).
    The far edge of a box (the one the robot steps down from), when the foot lands beyond it on the lower
    ground: ``clearance + SHIN_SLOPE * h`` for a box of height h, because the shin slopes up backwards from
    the foot and would strike the edge just stepped off (seen in the course with the robot crouched).

    Args:
        terrain: (nt, 2, 3) boxes; xy: (2,) nominal foothold [m]; direction: (2,) unit walking
            direction (axis-aligned); clearance: () [m], e.g. foot radius + margin.

    Returns:
        (2,) adjusted foothold: pushed onto the nearer safe side of each offending edge.
    """
    terrain = jnp.asarray(terrain)
    if terrain.shape[0] == 0:
        return xy
    u = jnp.asarray(direction)
    s = xy @ u
    across = jnp.array([-u[1], u[0]])
    c = xy @ across
    for b in range(terrain.shape[0]):
        lo, hi = terrain[b, 0, :2], terrain[b, 1, :2]
        e_in, e_out = jnp.sort(jnp.array([lo @ u, hi @ u]))
        c_lo, c_hi = jnp.sort(jnp.array([lo @ across, hi @ across]))
        in_lane = (c >= c_lo) & (c <= c_hi)
        near_in = in_lane & (jnp.abs(s - e_in) < clearance)
        s = jnp.where(near_in, jnp.where(s < e_in, e_in - clearance, e_in + clearance), s)
        beyond = clearance + SHIN_SLOPE * terrain[b, 1, 2]
        near_out = in_lane & (s > e_out - clearance) & (s < e_out + beyond)
        # nearer safe side: back on the box, or far enough beyond it
        s = jnp.where(near_out, jnp.where(s - (e_out - clearance) < (e_out + beyond) - s, e_out - clearance,
                                          e_out + beyond), s)
    return s * u + c * across
