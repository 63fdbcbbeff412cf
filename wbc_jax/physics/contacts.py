"""The contacts the rollout reads, on either physics backend.

The controller needs each foot's distance to the ground (touchdown), the metrics need the simulator's forces and
distances at the object's four contact spheres (R, object off the tray), and the monitors need every non-foot robot
part's and the wall's penetration (falls, grazes). The two MJX implementations keep contacts differently:

* **JAX** (``impl="jax"``): one fixed slot per candidate contact of every ``<pair>``, per run, with the distance
  filled in whether or not the pair touches, and its force (read through :mod:`wbc_jax.physics.backend`'s
  ``slot_*`` accessors). :func:`contact_slots` finds the slots of each role once per model.
* **Warp** (``impl="warp"``): one list of the contacts that exist, shared by all runs (``naconmax`` in total).
  The non-foot and wall distances are the smallest ``dist`` of each watched pair's listed contacts per run,
  reduced from the whole list at once (:func:`pair_minima`: one scatter over the list, each contact to its run's
  entry of its pair's role); every contact counts, so no pair can hold more contacts than a slot. The object's
  forces come from MJCF contact sensors, which MuJoCo evaluates per run into ``sensordata`` (as MJX's documentation
  and Playground do): :func:`wbc_jax.robot.sensors.with_contact_sensors` adds one per object sphere vs the tray
  (``found``, contact-frame ``force``, ``dist``). The pairs' margin is 0, so a listed contact is a penetrating one.
  The near-contact distances the rollout also needs (a foot within 1 mm of the ground, an object sphere more than
  1 mm off the tray) are computed from the geometry (:func:`sphere_distance`: sphere vs plane or box, as MuJoCo's
  collision functions do). Listing contacts up to 1 mm through ``margin = gap = 1 mm`` instead is not the same
  physics on Warp: MuJoCo Warp 1.18 does not subtract ``gap`` from the constraint's margin.

:class:`wbc_jax.rollout.config.Sim` holds the indices of both kinds in the same fields (``foot_slots``,
``obj_slots``, ``nonfoot_slots``, ``wall_slots``): contact slots on JAX; on Warp sensordata addresses (object),
pair ids (feet) and entries of :func:`pair_minima` (non-foot, wall); the readers below take a Sim and dispatch on
``sim.robot.backend`` (static). A distance that the backend does not
report (no contact listed) reads as ``+inf``.

The run's clearance (``wbc_jax.rollout.step.clearance``) does not read contacts: neither backend reports a
separated pair's distance exactly (JAX: a capsule/box slot reads its candidate points' distance, not the edge's;
a pair beyond the margin reads 1 m; Warp: penetrations only), so it is measured from the geoms' poses
(:mod:`wbc_jax.physics.clearance`). The non-foot and wall readers here serve the contact flags (dist < 0).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.physics import backend as physics
from wbc_jax.robot.sensors import FORCE as SENSOR_FORCE
from wbc_jax.runtime import aot

CONTACT_DIST = 1e-3  # [m] a foot closer than this to the floor or terrain counts as touching; an object sphere
#                      farther than this from the tray counts as off it

def contact_forces(m, d, slots) -> jax.Array:
    """Simulator forces at the given contact slots in their contact frames: (n, 3) [N], column 0 normal.

    Args:
        m: mjx.Model; d: mjx.Data after the constraint solve (``efc_force`` filled); slots: static (n,) ints.
    """
    if len(slots) == 0:
        return jnp.zeros((0, 3))
    return physics.slot_forces(m, d, slots)


class ContactIndices(NamedTuple):
    """Where the rollout reads each role's contacts: MJX contact slots (JAX); on Warp (:func:`sim_indices`) the
    object's contact-sensor addresses, the foot pairs' ids and entries of :func:`pair_minima`."""

    nonfoot: np.ndarray  # (k,) non-foot robot parts vs the floor or terrain
    wall: np.ndarray  # anything vs a wall part
    foot: np.ndarray  # (4, K) each foot vs the floor and terrain (Warp: (4, 1) pair ids)
    obj: np.ndarray  # the object's contact spheres vs the tray
    nonfoot_geoms: np.ndarray  # (k, 2) the geom ids of each non-foot entry's pair


def contact_slots(robot) -> ContactIndices:
    """JAX backend: the :class:`ContactIndices` of MJX's contact slots (MJX's layout, computed once per model and
    kept on disk: :func:`wbc_jax.runtime.aot.cached_value`)."""
    return aot.cached_value("slots", aot.describe(robot), lambda: _contact_slots(robot))


def compiled_contact_geoms(robot) -> np.ndarray:
    """(ncon, 2) geom ids of MJX's contact slots read from one compiled sensing pass (slow: a compile)."""
    d = jax.jit(physics.sense)(robot.mjx_model, physics.mjx.make_data(robot.mjx_model,
                                                                       device=jax.local_devices()[0]))
    return np.asarray(physics.slot_geoms(d)).astype(np.int64)


def _contact_slots(robot):
    m = robot.mj_model
    geom = physics.slot_geoms_static(robot.mjx_model)
    if geom is None:
        geom = compiled_contact_geoms(robot)
    pairs = {(int(m.pair_geom1[i]), int(m.pair_geom2[i])): i for i in range(m.npair)}
    slot_pair = np.array([pairs.get((int(a), int(b)), pairs.get((int(b), int(a)), -1)) for a, b in geom])
    foot = np.array([np.where(np.isin(slot_pair, fp))[0] for fp in robot.ids.foot_pair])
    nonfoot = np.where(np.isin(slot_pair, robot.ids.nonfoot_floor_pair))[0]
    return ContactIndices(nonfoot=nonfoot, wall=np.where(np.isin(slot_pair, robot.ids.wall_pair))[0], foot=foot,
                          obj=np.where(np.isin(slot_pair, robot.ids.obj_pair))[0],
                          nonfoot_geoms=geom[nonfoot].reshape(-1, 2).astype(np.int64))


def sim_indices(robot) -> ContactIndices:
    """The :class:`ContactIndices` of ``robot``'s backend: contact slots (JAX); on Warp the object's sensordata
    addresses, the foot pairs' ids and the non-foot and wall entries of :func:`pair_minima`."""
    s = robot.sensors
    if s is None:
        return contact_slots(robot)
    m, ids = robot.mj_model, robot.ids
    nf = np.asarray(ids.nonfoot_floor_pair, int).reshape(-1)
    return ContactIndices(nonfoot=np.arange(nf.size), wall=np.arange(nf.size, nf.size + (len(ids.wall_pair) > 0)),
                          foot=np.asarray(ids.foot_pair), obj=s.obj,
                          nonfoot_geoms=np.stack([m.pair_geom1[nf], m.pair_geom2[nf]], axis=1).astype(np.int64))


def pair_minima(sim, d) -> jax.Array:
    """Warp: (k + 1,) the smallest ``dist`` [m] of this run's listed contacts (:func:`physics.contact_list
    <wbc_jax.physics.backend.contact_list>`) of each non-foot ground pair (``RobotIds.nonfoot_floor_pair`` order),
    then of all wall pairs together; +inf where none is listed. Called per run under the vmap over runs (one level:
    MuJoCo Warp's world index is the run's index in it), it reduces the shared list once for the whole batch (a
    ``custom_vmap`` rule: one ``segment_min``); the same values as a contact sensor per pair whose slots hold all its
    contacts."""
    dist, geom, world, listed = physics.contact_list(d)
    return _minima_reader(sim.robot)(dist, geom, world, listed, d.time)


@functools.cache
def _minima_reader(robot):
    """The ``custom_vmap`` function of :func:`pair_minima` for ``robot``'s pairs: a role per geom pair (its
    non-foot pair's index, k for a wall pair, -1 for the others) looked up from a static (ngeom, ngeom) table."""
    m, ids = robot.mj_model, robot.ids
    nf, wall = (np.asarray(p, int).reshape(-1) for p in (ids.nonfoot_floor_pair, ids.wall_pair))
    table = np.full((m.ngeom, m.ngeom), -1, np.int32)
    for role, pairs in [(k, [p]) for k, p in enumerate(nf)] + [(nf.size, wall)]:
        for p in pairs:
            table[m.pair_geom1[p], m.pair_geom2[p]] = table[m.pair_geom2[p], m.pair_geom1[p]] = role
    n_roles = nf.size + 1

    def minima(dist, geom, world, listed, n_runs: int):  # (n_runs, n_roles)
        role = jnp.asarray(table)[geom[:, 0], geom[:, 1]]
        ok = listed & (role >= 0) & (world >= 0) & (world < n_runs)
        seg = jnp.where(ok, world * n_roles + role, n_runs * n_roles)  # the others out of bounds: dropped, not
        #                                                                   written (no atomics on one address)
        out = jax.ops.segment_min(dist, seg, num_segments=n_runs * n_roles, mode="drop")
        return out.reshape(n_runs, n_roles)

    @jax.custom_batching.custom_vmap
    def reader(dist, geom, world, listed, anchor):  # one run, not vmapped: world 0
        del anchor
        return minima(dist, geom, world, listed, 1)[0]

    @reader.def_vmap
    def _(axis_size, in_batched, dist, geom, world, listed, anchor):  # anchor: a per-run leaf, so the rule runs
        if any(in_batched[:4]):
            raise ValueError("pair_minima: MuJoCo Warp's contact list is batched (more than one vmap over runs?)")
        return minima(dist, geom, world, listed, axis_size), True

    return reader


def _slot_dist(d, slots):
    return physics.slot_dist(d, slots)


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
        mu = physics.slot_friction(d, sim.foot_slots)
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
        f = jnp.stack([sd[a + SENSOR_FORCE + k] for k in range(3)], axis=1)
        return jnp.where(found[:, None], f, 0.0), _pair_distances(sim, m, d, sim.robot.ids.obj_pair)

    return contact_forces(m, d, sim.obj_slots), _slot_dist(d, sim.obj_slots)


def penetrations(sim, d) -> tuple[jax.Array, jax.Array]:
    """(k,) distance [m] of each non-foot ground slot (JAX) or pair (Warp), and (w,) of each wall slot (JAX) or of
    all wall pairs (Warp, w = 1); < 0 is penetration, +inf where nothing is listed (Warp)."""
    if sim.robot.backend == "warp":
        minima = pair_minima(sim, d)
        return minima[sim.nonfoot_slots], minima[sim.wall_slots]
    return _slot_dist(d, sim.nonfoot_slots), _slot_dist(d, sim.wall_slots)


def match_overflow(sim, m, d) -> jax.Array:
    """() bool: a contact sensor (the object's) matched more contacts than the model ``m``'s slots per sensor hold
    (:func:`wbc_jax.physics.backend.contact_sensor_slots`; its nearest contact may then be missed:
    :mod:`wbc_jax.robot.sensors`), read from the sensors' ``found`` (every match counted); always False on JAX."""
    sensors, slots = sim.robot.sensors, physics.contact_sensor_slots(m)
    if sensors is None or slots is None:
        return jnp.bool_(False)
    return jnp.any(d.sensordata[sensors.found] > slots)
