"""The MJCF contact sensors the Warp backend reads (:mod:`wbc_jax.physics.contacts` explains why).

Per object contact sphere its contact with the tray, per non-foot ground pair, and per wall (one per wall pair
where :func:`whole_wall_bodies` finds none): ``found``, contact-frame ``force``, ``dist`` (at :data:`DIST`), the same
fields for every sensor, so that all are of one stage (acceleration: the force needs it) and MuJoCo Warp matches and
sorts them in one pass a step instead of one per stage; added to the scene's spec before it is compiled. MuJoCo Warp
launches its matching, sorting and evaluation per run and sensor every physics step, so fewer sensors are less work.

The Warp scene also disables native CCD (``mjDSBL_NATIVECCD``): MuJoCo Warp then collides box-box pairs with its
``box_box`` primitive (up to 8 contacts, like MuJoCo C's ``mjc_BoxBox``) instead of its convex GJK/EPA kernel,
whose compile is a fresh machine's longest (the shipped scenes' box-box pairs: robot boxes vs the wall's). And it
disables the stages that compute only zeros for the scene (:func:`zero_stages`: passive forces, friction loss), whose
kernels MuJoCo Warp would otherwise launch every physics step; the physics is the same.

MuJoCo Warp matches each sensor against the contact list in slots of ``contact_sensor_maxmatch`` contacts per run
and sensor (64 by default, from the model's numeric of that name), filled and sorted every physics step. The scene
gets the most contacts one of its sensed pairs can produce instead (:func:`max_pair_contacts`): the same matches,
sorted in smaller slots. ``found`` counts every match, so a pair with more is detected
(:func:`wbc_jax.physics.contacts.match_overflow`). A wall body's sensor needs no slots of its own: its flag reads
``found`` alone (every contact it matches penetrates), so its pairs do not size the slots and an overflow there is
harmless.
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


@dataclass(frozen=True, eq=False)
class ContactSensors:
    """Addresses in ``sensordata`` of the contact sensors (see the module docstring); each sensor's values are
    ``found`` (number of matching contacts), force (3, contact frame, normal first) [N] (at :data:`FORCE`), dist [m]
    (at :data:`DIST`).

    Attributes:
        obj: (4,) per object contact sphere vs the tray.
        nonfoot: (k,) per non-foot robot part vs ground pair (``RobotIds.nonfoot_floor_pair`` order).
        nonfoot_geoms: (k, 2) the geom ids of each of those pairs.
        wall: (w,) per wall body of :func:`whole_wall_bodies`, then per other wall pair (``RobotIds.wall_pair``
            order); any of them with ``dist`` < 0 is the robot or the object in a wall.
        n_wall_bodies: how many of ``wall`` are whole bodies' (the first).
    """

    obj: np.ndarray
    nonfoot: np.ndarray
    nonfoot_geoms: np.ndarray
    wall: np.ndarray
    n_wall_bodies: int = 0

    @property
    def found(self) -> np.ndarray:
        """The ``found`` address of every sensor whose slots must hold all its matches (its nearest contact is
        read): the object's, the non-foot pairs', the wall pairs' not of a whole body, in that order."""
        return np.concatenate([self.obj, self.nonfoot, self.wall[self.n_wall_bodies:]])


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


def whole_wall_bodies(model: mujoco.MjModel, wall_pair) -> dict[int, np.ndarray]:
    """The bodies of ``model`` that one contact sensor (object type body) can watch for all the wall pairs
    ``wall_pair`` (pair ids) they take part in: {body: (j,) those pairs}, chosen greedily, most pairs first, each
    pair once. A body qualifies where each contact MuJoCo can list for one of its geoms comes from a wall pair and
    penetrates: every pair of one of its geoms is a wall pair with margin <= 0 and gap 0 (a listed contact then
    has dist < 0; MuJoCo Warp's sensors match active contacts only), and its geoms have contype and conaffinity 0
    (no contacts outside the pairs); it has a name. The world body (0) never does."""
    g1, g2 = model.pair_geom1, model.pair_geom2
    wall = set(int(p) for p in np.asarray(wall_pair).ravel())
    pair_bodies = [(int(model.geom_bodyid[g1[p]]), int(model.geom_bodyid[g2[p]])) for p in range(model.npair)]
    candidates = {}
    for b in {b for p in wall for b in pair_bodies[p]} - {0}:
        pairs = [p for p in range(model.npair) if b in pair_bodies[p]]
        geoms = np.where(model.geom_bodyid == b)[0]
        penetrating = all(p in wall and pair_bodies[p].count(b) == 1 and model.pair_margin[p] <= 0
                          and model.pair_gap[p] == 0 for p in pairs)
        listed_only = not np.any(model.geom_contype[geoms]) and not np.any(model.geom_conaffinity[geoms])
        if model.body(b).name and penetrating and listed_only:
            candidates[b] = set(pairs)
    chosen, left = {}, set(wall)
    while candidates:
        b = max(sorted(candidates), key=lambda b: len(candidates[b] & left))
        if len(candidates[b] & left) < 2:  # a body of one pair: that pair's own sensor is the same work
            break
        chosen[b] = np.array(sorted(candidates.pop(b) & left), dtype=np.int64)
        left -= set(chosen[b].tolist())
    return chosen


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

    def geom_name(g) -> str:
        return base.geom(int(g)).name

    def add(name, objtype, objname, refname=None):
        s = spec.add_sensor(name=name, type=mujoco.mjtSensor.mjSENS_CONTACT, objtype=objtype, objname=objname)
        if refname is not None:  # same order as the pair, so the force's normal points as the pair's contact does
            s.reftype = mujoco.mjtObj.mjOBJ_GEOM
            s.refname = refname
        s.intprm[0] = sum(1 << f for f in (_FOUND, _FORCE, _DIST))
        s.intprm[1] = _MINDIST
        s.intprm[2] = 1
        return name

    def add_pair(name, p):
        return add(name, mujoco.mjtObj.mjOBJ_GEOM, geom_name(g1[p]), geom_name(g2[p]))

    bodies = whole_wall_bodies(base, ids.wall_pair)
    in_body = {int(p) for pairs in bodies.values() for p in pairs}
    wall_pairs = [int(p) for p in ids.wall_pair if int(p) not in in_body]
    names = {key: [add_pair(f"wbc_{key}{i}", p) for i, p in enumerate(pairs)]
             for key, pairs in (("obj", ids.obj_pair), ("nonfoot", ids.nonfoot_floor_pair))}
    names["wall"] = ([add(f"wbc_wall_body{b}", mujoco.mjtObj.mjOBJ_BODY, base.body(b).name) for b in bodies]
                     + [add_pair(f"wbc_wall{i}", p) for i, p in enumerate(wall_pairs)])
    sensed = np.concatenate([ids.obj_pair, ids.nonfoot_floor_pair, wall_pairs]).astype(int)
    maxmatch = max_pair_contacts(base, np.stack([g1[sensed], g2[sensed]], axis=1), primitive_boxes=True)
    if "contact_sensor_maxmatch" not in [n.name for n in spec.numerics]:
        spec.add_numeric(name="contact_sensor_maxmatch", data=[float(maxmatch)])
    m = spec.compile()
    if m.npair != base.npair or m.ngeom != base.ngeom:
        raise AssertionError("adding contact sensors changed the scene's pairs or geoms")

    def adr(key):
        return np.array([m.sensor_adr[m.sensor(n).id] for n in names[key]], dtype=np.int64)

    nf = ids.nonfoot_floor_pair.astype(int)
    return m, ContactSensors(obj=adr("obj"), nonfoot=adr("nonfoot"),
                             nonfoot_geoms=np.stack([g1[nf], g2[nf]], axis=1).astype(np.int64).reshape(-1, 2),
                             wall=adr("wall"), n_wall_bodies=len(bodies))
