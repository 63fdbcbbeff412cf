"""The contacts the rollout reads, on either physics backend.

The controller needs each foot's distance to the ground (touchdown), the metrics need the simulator's forces and
distances at the object's four contact spheres (R, object off the tray), and the monitors need every non-foot robot
part's and the wall's penetration (falls, grazes). The two MJX implementations keep contacts differently:

* **JAX** (``impl="jax"``): one fixed slot per candidate contact of every ``<pair>``, per run, with the distance
  filled in whether or not the pair touches (``d._impl.contact.dist``); forces through
  ``mujoco.mjx._src.support.contact_force``. :func:`contact_slots` finds the slots of each role once per model.
* **Warp** (``impl="warp"``): one list of the contacts that exist, shared by all runs (``naconmax`` in total), so a
  run's contacts are read through MJCF contact sensors, which MuJoCo evaluates per run into ``sensordata``
  (as MJX's documentation and Playground do). :func:`with_contact_sensors` adds them: per object sphere its contact
  with the tray (``found``, contact-frame ``force``, ``dist``), per non-foot ground pair and per wall pair ``found``
  and ``dist``. The pairs' margin is 0, so a listed contact is a penetrating one. The near-contact distances the
  rollout also needs (a foot within 1 mm of the ground, an object sphere more than 1 mm off the tray) are computed
  from the geometry (:func:`sphere_distance`: sphere vs plane or box, as MuJoCo's collision functions do). Listing
  contacts up to 1 mm through ``margin = gap = 1 mm`` instead is not the same physics on Warp: MuJoCo Warp 1.18
  does not subtract ``gap`` from the constraint's margin (measured: the object's normal forces rose from 0.74 N to
  18 N per sphere at rest).

:class:`wbc_jax.sim.rollout.Sim` holds the indices of both kinds in the same fields (``foot_slots``,
``obj_slots``, ``nonfoot_slots``, ``wall_slots``): contact slots on JAX, sensordata addresses on Warp; the
readers below take a Sim and dispatch on ``sim.robot.backend`` (static). A distance that the backend does not
report (no contact listed) reads as ``+inf``.

The run's clearance (``wbc_jax.sim.rollout.clearance``) does not read contacts: neither backend reports a
separated pair's distance exactly (JAX: a capsule/box slot reads its candidate points' distance, not the edge's;
a pair beyond the margin reads 1 m; Warp: penetrations only), so it is measured from the geoms' poses
(:mod:`wbc_jax.sim.clearance`). The non-foot and wall readers here serve the contact flags (dist < 0).
"""

from __future__ import annotations

from dataclasses import dataclass

from wbc_jax.errors import SceneError
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

CONTACT_DIST = 1e-3  # [m] a foot closer than this to the floor or terrain counts as touching; an object sphere
#                      farther than this from the tray counts as off it

_FOUND, _FORCE, _DIST = 0, 1, 3  # bits of mjtConDataField: found, force (3), dist
_MINDIST = 1  # mjtConReduce: the nearest contact first
_DIST_TYPES = (int(mujoco.mjtGeom.mjGEOM_SPHERE), int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_BOX))


@dataclass(frozen=True, eq=False)
class ContactSensors:
    """Addresses in ``sensordata`` of the contact sensors (see the module docstring); each sensor's values start
    with ``found`` (number of matching contacts), then its fields in MuJoCo's order (force (3), dist).

    Attributes:
        obj: (4,) per object contact sphere vs the tray: found, force (3, contact frame, normal first) [N], dist.
        nonfoot: (k,) per non-foot robot part vs ground pair (``RobotIds.nonfoot_floor_pair`` order): found, dist.
        nonfoot_geoms: (k, 2) the geom ids of each of those pairs.
        wall: (w,) per wall pair (``RobotIds.wall_pair`` order): found, dist.
    """

    obj: np.ndarray
    nonfoot: np.ndarray
    nonfoot_geoms: np.ndarray
    wall: np.ndarray


def with_contact_sensors(path: Path, base: mujoco.MjModel, ids) -> tuple[mujoco.MjModel, ContactSensors]:
    """The scene at ``path`` compiled with the contact sensors the Warp backend reads (module docstring).

    Args:
        path: scene XML; base: the same scene compiled as is; ids: its ``RobotIds`` (pair and geom ids are the
            same in the returned model: sensors add no geoms or pairs).

    Returns:
        (MuJoCo model with the sensors, ContactSensors).
    """
    spec = mujoco.MjSpec.from_file(str(path))
    g1, g2 = base.pair_geom1, base.pair_geom2
    for p in np.concatenate([ids.foot_pair.ravel(), ids.obj_pair]).astype(int):
        for g in (g1[p], g2[p]):
            if base.geom_type[g] not in _DIST_TYPES:
                raise SceneError(f"scene {path}: geom {base.geom(int(g)).name!r} of a foot or object pair is neither "
                                 "a sphere, a plane nor a box (the Warp backend measures those distances itself)")

    def geom_name(g) -> str:
        return base.geom(int(g)).name

    def add(name, fields, geom1, geom2=None):
        s = spec.add_sensor(name=name, type=mujoco.mjtSensor.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_GEOM,
                            objname=geom_name(geom1))
        if geom2 is not None:  # same order as the pair, so the force's normal points as the pair's contact does
            s.reftype = mujoco.mjtObj.mjOBJ_GEOM
            s.refname = geom_name(geom2)
        s.intprm[0] = sum(1 << f for f in (_FOUND, *fields))
        s.intprm[1] = _MINDIST
        s.intprm[2] = 1
        return name

    names = {"obj": [add(f"wbc_obj{i}", (_FORCE, _DIST), g1[p], g2[p]) for i, p in enumerate(ids.obj_pair)],
             "nonfoot": [add(f"wbc_nonfoot{i}", (_DIST,), g1[p], g2[p]) for i, p in enumerate(ids.nonfoot_floor_pair)],
             "wall": [add(f"wbc_wall{i}", (_DIST,), g1[p], g2[p]) for i, p in enumerate(ids.wall_pair)]}
    m = spec.compile()
    if m.npair != base.npair or m.ngeom != base.ngeom:
        raise AssertionError("adding contact sensors changed the scene's pairs or geoms")

    def adr(key):
        return np.array([m.sensor_adr[m.sensor(n).id] for n in names[key]], dtype=np.int64)

    nf = ids.nonfoot_floor_pair.astype(int)
    return m, ContactSensors(obj=adr("obj"), nonfoot=adr("nonfoot"),
                             nonfoot_geoms=np.stack([g1[nf], g2[nf]], axis=1).astype(np.int64).reshape(-1, 2),
                             wall=adr("wall"))


def contact_slots(robot):
    """JAX backend: indices of MJX contact slots: non-foot parts vs floor or terrain, anything vs a wall, (4, K) each
    foot vs floor and terrain, the object's contact spheres vs the tray; then the (k, 2) geom ids of the non-foot
    slots (MJX's layout, computed once per model and kept on disk: :func:`wbc_jax.sim.aot.cached_value`)."""
    from wbc_jax.sim import aot

    return aot.cached_value("slots", aot.describe(robot), lambda: _contact_slots(robot))


def contact_geoms_static(mjx_model) -> np.ndarray | None:
    """(ncon, 2) geom ids of MJX's contact slots (JAX backend), from the model alone: MJX's collision driver runs one
    collision function per group of geom pairs (``collision_driver._geom_groups``: by geom types, mesh and condim),
    repeats each group's rows by the function's contact count and concatenates the groups by ascending condim, in
    the groups' order. None where that layout is not static (a broad phase: ``max_geom_pairs`` or
    ``max_contact_points`` set) or does not add up to the model's contact count; :func:`compiled_contact_geoms`
    reads it from a compiled step instead (a test compares the two)."""
    from mujoco.mjx._src import collision_driver as cd

    if cd._numeric(mjx_model, "max_geom_pairs") > -1 or cd._numeric(mjx_model, "max_contact_points") > -1:
        return None
    by_condim: dict[int, list[np.ndarray]] = {}
    for key, ids in cd._geom_groups(mjx_model).items():
        func = cd._COLLISION_FUNC.get(key.types)
        if func is None:  # SDF and other groups whose count is not the function's
            return None
        geom = np.asarray(ids, dtype=np.int64)[:, :2]
        by_condim.setdefault(int(key.condim), []).append(np.repeat(geom, func.ncon, axis=0))
    if not by_condim:
        return None
    dims = np.concatenate([np.full(len(g), c) for c in sorted(by_condim) for g in by_condim[c]])
    if not np.array_equal(dims, cd.make_condim(mjx_model)):  # MJX's own count of the slots and their dims
        return None
    return np.concatenate([g for c in sorted(by_condim) for g in by_condim[c]])


def compiled_contact_geoms(robot) -> np.ndarray:
    """(ncon, 2) geom ids of MJX's contact slots read from one compiled sensing pass (25-40 s of compile on a CPU)."""
    from wbc_jax.sim import physics
    from wbc_jax.sim.model import mjx

    d = jax.jit(physics.sense)(robot.mjx_model, mjx.make_data(robot.mjx_model, device=jax.local_devices()[0]))
    return np.asarray(d._impl.contact.geom).astype(np.int64)


def _contact_slots(robot):
    m = robot.mj_model
    geom = contact_geoms_static(robot.mjx_model)
    if geom is None:
        geom = compiled_contact_geoms(robot)
    pairs = {(int(m.pair_geom1[i]), int(m.pair_geom2[i])): i for i in range(m.npair)}
    slot_pair = np.array([pairs.get((int(a), int(b)), pairs.get((int(b), int(a)), -1)) for a, b in geom])
    foot = np.array([np.where(np.isin(slot_pair, fp))[0] for fp in robot.ids.foot_pair])
    nonfoot = np.where(np.isin(slot_pair, robot.ids.nonfoot_floor_pair))[0]
    return (nonfoot, np.where(np.isin(slot_pair, robot.ids.wall_pair))[0], foot,
            np.where(np.isin(slot_pair, robot.ids.obj_pair))[0], geom[nonfoot].reshape(-1, 2).astype(np.int64))


def sim_indices(robot):
    """(nonfoot, wall, foot, obj, nonfoot_geoms) indices of ``robot``'s backend: contact slots (JAX; foot (4, K))
    or sensordata addresses (Warp; foot (4, 1))."""
    s = robot.sensors
    if s is None:
        return contact_slots(robot)
    return s.nonfoot, s.wall, np.asarray(robot.ids.foot_pair), s.obj, s.nonfoot_geoms


def _sensor_dist(d, adr):
    """Distance field of contact sensors whose values are (found, dist): +inf where nothing was found."""
    sd = d.sensordata
    return jnp.where(sd[adr] > 0, sd[adr + 1], jnp.inf)


def _slot_dist(d, slots):
    return d._impl.contact.dist[slots]


def sphere_distance(m, d, sphere: int, other: int) -> jax.Array:
    """() signed distance [m] between sphere geom ``sphere`` and geom ``other`` (plane or box; static ids), from
    the geoms' world poses (``geom_xpos``, ``geom_xmat``) and sizes, as MuJoCo's sphere-plane and sphere-box
    collision functions measure it (negative: penetration)."""
    c, r = d.geom_xpos[sphere], m.geom_size[sphere][0]
    pos, R = d.geom_xpos[other], d.geom_xmat[other]
    if int(m.geom_type[other]) == int(mujoco.mjtGeom.mjGEOM_PLANE):
        return jnp.dot(c - pos, R[:, 2]) - r
    p = R.T @ (c - pos)  # sphere centre in the box frame
    q = jnp.abs(p) - m.geom_size[other]
    outside = jnp.linalg.norm(jnp.maximum(q, 0.0))
    return outside + jnp.minimum(jnp.max(q), 0.0) - r


def _pair_distances(sim, m, d, pairs) -> jax.Array:
    """Distances of sphere pairs (any shape of pair ids) on the Warp backend, same shape."""
    g1, g2 = sim.robot.mj_model.pair_geom1, sim.robot.mj_model.pair_geom2
    sphere = int(mujoco.mjtGeom.mjGEOM_SPHERE)

    def one(p):
        a, b = int(g1[p]), int(g2[p])
        if int(m.geom_type[a]) != sphere:
            a, b = b, a
        return sphere_distance(m, d, a, b)

    flat = np.asarray(pairs).ravel()
    return jnp.stack([one(p) for p in flat]).reshape(np.shape(pairs))


def foot_ground(sim, m, d) -> tuple[jax.Array, jax.Array]:
    """Each foot's nearest ground surface (floor or a terrain block): (4,) distance [m] and (4,) its sliding
    friction coefficient (the contact pair's, from the model: per run where the batch varies it)."""
    if sim.robot.backend == "warp":
        dist = _pair_distances(sim, m, d, sim.foot_slots)  # (4, K) over ids.foot_pair
        mu = m.pair_friction[jnp.asarray(sim.foot_slots), 0]
    else:
        dist = _slot_dist(d, sim.foot_slots)  # (4, K) MJX slots
        mu = d._impl.contact.friction[sim.foot_slots, 0]
    k = jnp.argmin(dist, axis=1)[:, None]
    return jnp.take_along_axis(dist, k, 1)[:, 0], jnp.take_along_axis(mu, k, 1)[:, 0]


def foot_dist(sim, m, d) -> jax.Array:
    """(4,) each foot's distance to the nearest ground surface [m]."""
    return foot_ground(sim, m, d)[0]


def object_contacts(sim, m, d) -> tuple[jax.Array, jax.Array]:
    """Simulator forces (4, 3) [N] (contact frame, normal first) and distances (4,) [m] at the object's contact
    spheres (zero force where nothing touches)."""
    if sim.robot.backend == "warp":
        sd, a = d.sensordata, sim.obj_slots
        found = sd[a] > 0
        f = jnp.stack([sd[a + 1], sd[a + 2], sd[a + 3]], axis=1)
        return jnp.where(found[:, None], f, 0.0), _pair_distances(sim, m, d, sim.robot.ids.obj_pair)
    from wbc_jax.sim.metrics import contact_forces

    return contact_forces(m, d, sim.obj_slots), _slot_dist(d, sim.obj_slots)


def nonfoot_dist(sim, d) -> jax.Array:
    """(k,) distance of each non-foot ground slot (JAX) or pair (Warp) [m]; < 0 is penetration."""
    if sim.robot.backend == "warp":
        return _sensor_dist(d, sim.nonfoot_slots)
    return _slot_dist(d, sim.nonfoot_slots)


def wall_dist(sim, d) -> jax.Array:
    """(w,) distance of each wall slot (JAX) or pair (Warp) [m]; < 0 is penetration."""
    if sim.robot.backend == "warp":
        return _sensor_dist(d, sim.wall_slots)
    return _slot_dist(d, sim.wall_slots)
