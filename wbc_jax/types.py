"""The data that crosses the package's layers: static robot ids, what the controller observes, what the planner
plans, what the controller knows of the object. Pytrees (NamedTuples) and one frozen dataclass; no logic.

Frames: world frame unless a field says otherwise; ``nv_r`` = 24 robot dofs (free joint, 12 leg joints, 6 arm joints).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import numpy as np


@dataclass(frozen=True, eq=False)
class RobotIds:
    """Static indices into a compiled scene (all numpy / int; never traced).

    Attributes:
        trunk_body: trunk body id.
        foot_geom: (4,) foot sphere geom ids (FL, FR, BL, BR).
        foot_site: (4,) foot-centre site ids.
        foot_body: (4,) calf body ids (the bodies carrying the feet).
        foot_radius: foot sphere radius [m].
        tray_body, tray_geom, tray_site: tray body, its box geom, its top-surface-centre site.
        tray_half: (3,) tray box half-sizes [m].
        obj_body: object body id (-1 when the scene has no object).
        obj_box_geom: object box geom id.
        obj_contact_geom: (4,) object contact-sphere geom ids.
        obj_pair: (4,) explicit contact pair ids object-sphere vs tray.
        obj_sphere_radius: contact-sphere radius [m].
        obj_qpos_adr, obj_dof_adr: start of the object's free joint in qpos / qvel.
        act_dof: (18,) dof index driven by each actuator (actuator order).
        act_qpos: (18,) qpos index of each actuated joint.
        tau_max: (18,) actuator torque limits [N m] (symmetric).
        nv_robot: number of robot dofs (24).
        floor_geom: floor plane geom id.
        nonfoot_floor_pair: ids of pairs robot-part (not foot) vs floor or terrain (what the feet stand on).
        foot_pair: (4, K) pair ids of each foot vs floor and blocks (K surfaces).
        wall_pair: ids of pairs anything vs a wall geom (may be empty).
        key_home: id of the 'home' keyframe.
    """

    trunk_body: int
    foot_geom: np.ndarray
    foot_site: np.ndarray
    foot_body: np.ndarray
    foot_radius: float
    tray_body: int
    tray_geom: int
    tray_site: int
    tray_half: np.ndarray
    obj_body: int
    obj_box_geom: int
    obj_contact_geom: np.ndarray
    obj_pair: np.ndarray
    obj_sphere_radius: float
    obj_qpos_adr: int
    obj_dof_adr: int
    act_dof: np.ndarray
    act_qpos: np.ndarray
    tau_max: np.ndarray
    nv_robot: int
    floor_geom: int
    nonfoot_floor_pair: np.ndarray
    foot_pair: np.ndarray
    wall_pair: np.ndarray
    key_home: int

    @property
    def has_object(self) -> bool:
        return self.obj_body >= 0


class DynTerms(NamedTuple):
    """Robot dynamics and kinematics at one instant (nv_r = 24).

    Attributes:
        M: (nv_r, nv_r) joint-space mass matrix (armature included).
        h: (nv_r,) bias forces C(q, v) v + g(q) [N, N m].
        q: (nq_r,) robot generalized position (free joint first).
        v: (nv_r,) robot generalized velocity.
        R_base: (3, 3) trunk orientation (world from body).
        p_base: (3,) trunk origin [m].
        omega_base: (3,) trunk angular velocity, world frame [rad/s].
        com: (3,) robot CoM [m].
        com_vel: (3,) robot CoM velocity [m/s].
        h_G: (6,) centroidal momentum [linear N s; angular about the CoM N m s], world frame.
        mass: () total robot mass [kg].
        p_foot: (4, 3) foot-centre positions [m].
        J_foot: (4, 3, nv_r) foot-centre translational Jacobians.
        Jdv_foot: (4, 3) Jdot v of the foot centres [m/s^2].
        v_foot: (4, 3) foot-centre velocities [m/s].
        R_tray: (3, 3) tray orientation.
        p_tray: (3,) tray top-surface centre [m].
    """

    M: jax.Array
    h: jax.Array
    q: jax.Array
    v: jax.Array
    R_base: jax.Array
    p_base: jax.Array
    omega_base: jax.Array
    com: jax.Array
    com_vel: jax.Array
    h_G: jax.Array
    mass: jax.Array
    p_foot: jax.Array
    J_foot: jax.Array
    Jdv_foot: jax.Array
    v_foot: jax.Array
    R_tray: jax.Array
    p_tray: jax.Array


class ObjectModel(NamedTuple):
    """What the controller knows about the object (assumptions A1, A2, A5), per run.

    Attributes:
        mass: () [kg]; side: () cube side d [m]; mu: () tray friction [-];
        inset: () horizontal inset of the contact points from the cube's edges [m].
    """

    mass: jax.Array
    side: jax.Array
    mu: jax.Array
    inset: jax.Array


class ObjectState(NamedTuple):
    """Measured object state: p (3,) [m], R (3, 3), v (3,) [m/s], omega (3,) world [rad/s]."""

    p: jax.Array
    R: jax.Array
    v: jax.Array
    omega: jax.Array


class Reference(NamedTuple):
    """Planner output at one instant (world frame).

    Attributes:
        p_obj, v_obj, a_obj: (3,) object reference; R_obj: (3, 3) object orientation reference.
        p_com, v_com, a_com: (3,) CoM reference; R_base: (3, 3) trunk orientation reference.
        swing: (4,) bool swing mask; p_sw, v_sw, a_sw: (4, 3) swing-foot references.
        load: (4,) in [0, 1], fraction of the normal-force cap a stance foot may carry (ramps to 0
            before liftoff and back up after touchdown so the force distribution changes smoothly).
    """

    p_obj: jax.Array
    v_obj: jax.Array
    a_obj: jax.Array
    R_obj: jax.Array
    p_com: jax.Array
    v_com: jax.Array
    a_com: jax.Array
    R_base: jax.Array
    swing: jax.Array
    p_sw: jax.Array
    v_sw: jax.Array
    a_sw: jax.Array
    load: jax.Array


class Observation(NamedTuple):
    """What a controller reads of the simulated state at one control step (:func:`wbc_jax.physics.observe.observe`).

    Attributes:
        robot: the robot's dynamics and kinematics (:class:`DynTerms`).
        obj: the object's measured state (:class:`ObjectState`; zeros when the scene has no object).
        J_tray_obj: (6, nv_r) Jacobian [translation; rotation] of the tray body at the object's CoM.
        Jdv_tray_obj: (6,) its Jdot v [m/s^2, rad/s^2].
        J_tray_top: (3, nv_r) translational Jacobian of the tray body at its top-surface centre.
        qpos: (nq,) the full generalized position (robot, then object).
        armature: (nv_r,) joint armature of the robot's dofs [kg m^2] (a model constant the controller may use).
    """

    robot: DynTerms
    obj: ObjectState
    J_tray_obj: jax.Array
    Jdv_tray_obj: jax.Array
    J_tray_top: jax.Array
    qpos: jax.Array
    armature: jax.Array
