"""The MJCF contact sensors the Warp backend reads: the object's contact forces (:mod:`wbc_jax.physics.contacts`).

Per object contact sphere its contact with the tray: ``found``, contact-frame ``force``, ``dist`` (at :data:`DIST`),
added to the scene's spec before it is compiled. The rollout's other contacts (a non-foot robot part in the floor or
the terrain, anything in a wall) need only distances, which it reads from MuJoCo Warp's contact list itself
(:func:`wbc_jax.physics.contacts.pair_minima`): MuJoCo Warp matches, sorts and evaluates its contact sensors per run
and sensor every physics step, so fewer sensors are less work.

The Warp scene also disables native CCD (``mjDSBL_NATIVECCD``): MuJoCo Warp then collides box-box pairs with its
``box_box`` primitive (up to 8 contacts, like MuJoCo C's ``mjc_BoxBox``) instead of its convex GJK/EPA kernel,
whose compile is a fresh machine's longest (the shipped scenes' box-box pairs: robot boxes vs the wall's). And it
disables the stages that compute only zeros for the scene (:func:`zero_stages`: passive forces, friction loss), whose
kernels MuJoCo Warp would otherwise launch every physics step; the physics is the same.

MuJoCo Warp matches each sensor against the contact list in slots of ``contact_sensor_maxmatch`` contacts per run
and sensor (64 by default, from the model's numeric of that name), filled and sorted every physics step. The scene
gets the most contacts one of its sensed pairs can produce instead (:func:`max_pair_contacts`; a sphere's pair 1),
at least :data:`MIN_SLOTS`: the same matches in smaller slots. ``found`` counts every match, so a pair with more is
detected (:func:`wbc_jax.physics.contacts.match_overflow`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from wbc_jax.errors import SceneError

_FOUND, _FORCE, _DIST = 0, 1, 3  # bits of mjtConDataField: found, force (3), dist
FORCE, DIST = 1, 4  # offsets of ``force`` (3 values) and ``dist`` in every contact sensor's values (found first)
_MINDIST = 1  # mjtConReduce: the nearest contact first
_NATIVECCD = int(mujoco.mjtDisableBit.mjDSBL_NATIVECCD)  # MuJoCo Warp: box-box pairs on the box_box primitive
_DIST_TYPES = (int(mujoco.mjtGeom.mjGEOM_SPHERE), int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_BOX))
_G = mujoco.mjtGeom
# the most contacts MuJoCo Warp's collision functions give one geom pair, by (unordered) geom types: sphere pairs 1;
# capsule vs plane or box 2 (the segment's ends); box vs plane 4 (its corners); box vs box 4 (the convex path's
# multicontact keeps at most 4 points; 8 from the box_box primitive, used where the model disables native CCD)
_PAIR_CONTACTS = {frozenset((_G.mjGEOM_SPHERE, _G.mjGEOM_PLANE)): 1, frozenset((_G.mjGEOM_SPHERE, _G.mjGEOM_BOX)): 1,
                  frozenset((_G.mjGEOM_SPHERE,)): 1, frozenset((_G.mjGEOM_CAPSULE, _G.mjGEOM_PLANE)): 2,
                  frozenset((_G.mjGEOM_CAPSULE, _G.mjGEOM_BOX)): 2, frozenset((_G.mjGEOM_BOX, _G.mjGEOM_PLANE)): 4,
                  frozenset((_G.mjGEOM_BOX,)): 4}
WARP_MAXMATCH = 64  # MuJoCo Warp's contact_sensor_maxmatch without the numeric
MIN_SLOTS = 2  # the fewest slots set: MuJoCo Warp sorts a sensor's slots with Warp's tile sort, tested from 2 keys


@dataclass(frozen=True, eq=False)
class ContactSensors:
    """Addresses in ``sensordata`` of the contact sensors (see the module docstring); each sensor's values are
    ``found`` (number of matching contacts), force (3, contact frame, normal first) [N] (at :data:`FORCE`), dist [m]
    (at :data:`DIST`).

    Attributes:
        obj: (4,) per object contact sphere vs the tray (``RobotIds.obj_pair`` order).
    """

    obj: np.ndarray

    @property
    def found(self) -> np.ndarray:
        """The ``found`` address of every sensor, whose slots must hold all its matches."""
        return self.obj


_SPRING_DAMPER_FIELDS = ("jnt_stiffness", "jnt_stiffnesspoly", "dof_damping", "dof_dampingpoly", "tendon_stiffness",
                         "tendon_stiffnesspoly", "tendon_damping", "tendon_dampingpoly", "body_gravcomp")


def zero_stages(model: mujoco.MjModel) -> int:
    """``mjtDisableBit`` flags of the stages that give only zeros for ``model``: springs and dampers (and with both
    off MuJoCo skips the passive stage, gravity compensation and fluid forces included) where no joint, dof or
    tendon has stiffness or damping (linear or polynomial), no body gravity compensation, no flex, and the
    medium no density or viscosity; friction loss where no dof or tendon has any. 0 where each stage has something
    to compute; a field this MuJoCo lacks counts as zero."""
    none = lambda *xs: all(not np.any(np.asarray(x)) for x in xs)  # noqa: E731
    bits = 0
    if (none(*(getattr(model, f, 0) for f in _SPRING_DAMPER_FIELDS), model.opt.density, model.opt.viscosity)
            and model.nflex == 0):
        bits |= int(mujoco.mjtDisableBit.mjDSBL_SPRING) | int(mujoco.mjtDisableBit.mjDSBL_DAMPER)
    if none(model.dof_frictionloss, model.tendon_frictionloss):
        bits |= int(mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS)
    return bits


def max_pair_contacts(model: mujoco.MjModel, pairs, primitive_boxes: bool | None = None) -> int:
    """The most contacts MuJoCo Warp gives any of the geom pairs ``pairs`` ((k, 2) geom ids of ``model``): 1 for a
    sphere, 2 for a capsule vs a plane or box, 4 for a box vs a plane or box (8 for two boxes on the box_box
    primitive: ``primitive_boxes``, None: where ``model`` disables native CCD); :data:`WARP_MAXMATCH` where a pair is
    of other types."""
    if primitive_boxes is None:
        primitive_boxes = bool(model.opt.disableflags & _NATIVECCD)

    def one(a, b):
        types = frozenset((_G(int(model.geom_type[a])), _G(int(model.geom_type[b]))))
        if primitive_boxes and types == frozenset((_G.mjGEOM_BOX,)):
            return 8
        return _PAIR_CONTACTS.get(types, WARP_MAXMATCH)
    return max((one(a, b) for a, b in np.asarray(pairs).reshape(-1, 2)), default=1)


def with_contact_sensors(path: Path, base: mujoco.MjModel, ids) -> tuple[mujoco.MjModel, ContactSensors]:
    """The scene at ``path`` compiled with the contact sensors the Warp backend reads (module docstring).

    Args:
        path: scene XML; base: the same scene compiled as is; ids: its ``RobotIds`` (pair and geom ids are the
            same in the returned model: sensors add no geoms or pairs).

    Returns:
        (MuJoCo model with the sensors, ContactSensors).
    """
    spec = mujoco.MjSpec.from_file(str(path))
    spec.option.disableflags |= _NATIVECCD  # box-box pairs on MuJoCo Warp's box_box primitive (module docstring)
    spec.option.disableflags |= zero_stages(base)  # no launches for stages that compute zeros (module docstring)
    g1, g2 = base.pair_geom1, base.pair_geom2
    for p in np.concatenate([ids.foot_pair.ravel(), ids.obj_pair]).astype(int):
        for g in (g1[p], g2[p]):
            if base.geom_type[g] not in _DIST_TYPES:
                raise SceneError(f"scene {path}: geom {base.geom(int(g)).name!r} of a foot or object pair is neither "
                                 "a sphere, a plane nor a box (the Warp backend measures those distances itself)")

    def add(name, p):  # geoms in the pair's order, so the force's normal points as the pair's contact does
        s = spec.add_sensor(name=name, type=mujoco.mjtSensor.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_GEOM,
                            objname=base.geom(int(g1[p])).name)
        s.reftype = mujoco.mjtObj.mjOBJ_GEOM
        s.refname = base.geom(int(g2[p])).name
        s.intprm[0] = sum(1 << f for f in (_FOUND, _FORCE, _DIST))
        s.intprm[1] = _MINDIST
        s.intprm[2] = 1
        return name

    sensed = ids.obj_pair.astype(int)
    names = [add(f"wbc_obj{i}", p) for i, p in enumerate(sensed)]
    maxmatch = max(max_pair_contacts(base, np.stack([g1[sensed], g2[sensed]], axis=1), primitive_boxes=True),
                   MIN_SLOTS)
    if "contact_sensor_maxmatch" not in [n.name for n in spec.numerics]:
        spec.add_numeric(name="contact_sensor_maxmatch", data=[float(maxmatch)])
    m = spec.compile()
    if m.npair != base.npair or m.ngeom != base.ngeom:
        raise AssertionError("adding contact sensors changed the scene's pairs or geoms")
    return m, ContactSensors(obj=np.array([m.sensor_adr[m.sensor(n).id] for n in names], dtype=np.int64))
