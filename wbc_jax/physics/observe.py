"""What the controllers observe of the simulated state: :func:`observe` (mjx.Data ->
:class:`wbc_jax.types.Observation`).

All quantities come from one sensing pass (:func:`wbc_jax.physics.backend.sense`: MJX ``fwd_position`` +
``fwd_velocity`` on the JAX backend, ``forward`` on Warp) and are restricted to the robot's ``nv_r = 24`` dofs (the
object is a separate kinematic tree, so its dofs never couple into the robot's mass matrix or Jacobians).
Frames: forces, positions and Jacobians are in the world frame; ``qvel[3:6]`` is MuJoCo's
body-frame angular velocity of the trunk, which the Jacobians already account for.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.physics.backend import mjx, motion_cross
from wbc_jax.spatial import full_precision
from wbc_jax.types import DynTerms, ObjectState, Observation, RobotIds


def chain_dofs(m, body: int) -> np.ndarray:
    """(nv,) bool, static: the dofs whose motion moves ``body`` (its own joints' and its ancestors'), from the model's
    tree (``body_parentid``, ``dof_bodyid``: numpy on both backends). MJX's ``jac`` finds the same mask at run time
    by a scan over the tree with the body id traced."""
    parent, chain, b = np.asarray(m.body_parentid), {int(body)}, int(body)
    while b > 0:
        b = int(parent[b])
        chain.add(b)
    return np.isin(np.asarray(m.dof_bodyid), sorted(chain))


class PointJacobians(NamedTuple):
    """Jacobians of k points on the robot's ``nv_r`` dofs and their Jdot v."""

    Jp: jax.Array  # (k, 3, nv_r) translational
    Jr: jax.Array  # (k, 3, nv_r) rotational
    Jdv_p: jax.Array  # (k, 3) translational Jdot v
    Jdv_r: jax.Array  # (k, 3) rotational Jdot v


def point_jacobians(m, d, ids: RobotIds, points, bodies) -> PointJacobians:
    """Translational and rotational Jacobians of points fixed to bodies, and their Jdot v.

    MJX's ``jac`` and ``jac_dot`` (its support module), the same arithmetic, with the bodies static: each
    body's dof mask (:func:`chain_dofs`), root and velocity are constants of the program, so no scan over the body
    tree and no gather by a traced id runs in the control step (few, large XLA ops: at small batches each op's launch
    dominates).

    Args:
        points: (k, 3) world points [m]; bodies: (k,) body ids (static ints).

    Returns:
        :class:`PointJacobians`.
    """
    nvr = ids.nv_robot
    bodies = [int(b) for b in np.asarray(bodies).reshape(-1)]
    mask = np.stack([chain_dofs(m, b) for b in bodies]).astype(np.float32)[:, :, None]  # (k, nv, 1)
    dof_body = np.asarray(m.dof_bodyid)
    jnt_type, dof_adr = np.asarray(m.jnt_type)[m.dof_jntid], np.asarray(m.jnt_dofadr)[m.dof_jntid]
    is_quat = (jnt_type == int(mujoco.mjtJoint.mjJNT_BALL)) | (
        (jnt_type == int(mujoco.mjtJoint.mjJNT_FREE)) & (np.arange(m.nv) >= dof_adr + 3))
    offset = points - d.subtree_com[np.asarray(m.body_rootid)[bodies]]  # (k, 3)
    cvel = d.cvel[np.asarray(bodies)]  # (k, 6) [angular; linear]
    cdof = d.cdof  # (nv, 6)
    cross = lambda a, b: jnp.cross(a, b, axis=-1)  # noqa: E731
    # the points' Jacobians (k, nv, 3): v = cdof_lin + cdof_ang x offset, masked to the body's chain
    jacp = (cdof[None, :, 3:] + cross(cdof[None, :, :3], offset[:, None])) * mask
    jacr = cdof[None, :, :3] * mask
    # their time derivatives; a ball or free joint's rotational cdof_dot from the body's own velocity, as MJX does
    cdof_dot = jnp.where(is_quat[:, None], jax.vmap(motion_cross)(d.cvel[dof_body], cdof), d.cdof_dot)
    pvel_lin = cvel[:, 3:] - cross(offset, cvel[:, :3])  # (k, 3)
    jdp = (cdof_dot[None, :, 3:] + cross(cdof_dot[None, :, :3], offset[:, None])
           + cross(cdof[None, :, :3], pvel_lin[:, None])) * mask
    jdr = cdof_dot[None, :, :3] * mask
    T = lambda j: jnp.swapaxes(j, 1, 2)  # noqa: E731  (k, nv, 3) -> (k, 3, nv)
    return PointJacobians(T(jacp)[:, :, :nvr], T(jacr)[:, :, :nvr], T(jdp) @ d.qvel, T(jdr) @ d.qvel)


def mass_matrix(m, d) -> jax.Array:
    """(nv, nv) dense joint-space mass matrix of either backend.

    MJX's JAX implementation keeps M dense for small models (``mjx.full_m`` returns it); MuJoCo Warp keeps its
    lower triangle in MuJoCo's CSR layout (``M_rownnz`` / ``M_rowadr`` / ``M_colind``, ``nC`` values), which
    ``mjx.full_m`` returns unchanged for small models: each dense entry is then read from its CSR value (or its
    mirror's) through a static index, one gather.
    """
    M = mjx.full_m(m, d)
    if M.ndim == 2:
        return M
    nv, nc = m.nv, M.shape[-1]
    rows = np.repeat(np.arange(nv), m.M_rownnz)
    idx = np.full((nv, nv), nc)  # entries outside the sparsity pattern read the appended zero
    idx[rows, np.asarray(m.M_colind)] = np.arange(nc)
    idx[np.asarray(m.M_colind), rows] = np.arange(nc)
    return jnp.concatenate([M, jnp.zeros((1,), M.dtype)])[idx]


@full_precision
def dyn_terms(m, d, ids: RobotIds) -> DynTerms:
    """Gather :class:`DynTerms` from sensed MJX data (:func:`wbc_jax.physics.backend.sense`)."""
    nvr = ids.nv_robot
    M = mass_matrix(m, d)[:nvr, :nvr]
    v = d.qvel[:nvr]
    R = d.xmat[ids.trunk_body]
    p_base = d.xpos[ids.trunk_body]
    mass = m.body_subtreemass[ids.trunk_body]
    com = d.subtree_com[ids.trunk_body]
    Mv = M @ v
    lin = Mv[0:3]  # free joint: world-frame translation -> total linear momentum
    ang_origin = R @ Mv[3:6]  # body-frame rotation -> angular momentum about the trunk origin
    ang_G = ang_origin - jnp.cross(com - p_base, lin)
    p_foot = d.site_xpos[ids.foot_site]
    Jp, _, Jdv, _ = point_jacobians(m, d, ids, p_foot, ids.foot_body)
    return DynTerms(
        M=M, h=d.qfrc_bias[:nvr], q=d.qpos[: nvr + 1], v=v, R_base=R, p_base=p_base, omega_base=R @ v[3:6], com=com,
        com_vel=lin / mass, h_G=jnp.concatenate([lin, ang_G]), mass=mass, p_foot=p_foot, J_foot=Jp,
        Jdv_foot=Jdv, v_foot=Jp @ v, R_tray=d.site_xmat[ids.tray_site], p_tray=d.site_xpos[ids.tray_site],
    )


def object_state(d, ids: RobotIds) -> ObjectState:
    """The object's measured state from mjx.Data (zeros when the scene has no object)."""
    if not ids.has_object:
        z3 = jnp.zeros(3, d.qpos.dtype)
        return ObjectState(p=z3, R=jnp.eye(3, dtype=d.qpos.dtype), v=z3, omega=z3)
    a = ids.obj_dof_adr
    R = d.xmat[ids.obj_body]
    return ObjectState(p=d.xpos[ids.obj_body], R=R, v=d.qvel[a : a + 3], omega=R @ d.qvel[a + 3 : a + 6])


@full_precision
def observe(m, d, ids: RobotIds) -> Observation:
    """The :class:`~wbc_jax.types.Observation` of sensed MJX data ``d`` (:func:`wbc_jax.physics.backend.sense`).

    Args:
        m: mjx.Model (one run's); d: sensed mjx.Data; ids: the scene's static ids.
    """
    robot = dyn_terms(m, d, ids)
    obj = object_state(d, ids)
    Jp, Jr, Jdp, Jdr = point_jacobians(m, d, ids, obj.p[None], [ids.tray_body])
    J_top = point_jacobians(m, d, ids, robot.p_tray[None], [ids.tray_body]).Jp[0]
    return Observation(robot=robot, obj=obj, J_tray_obj=jnp.concatenate([Jp[0], Jr[0]]),
                       Jdv_tray_obj=jnp.concatenate([Jdp[0], Jdr[0]]), J_tray_top=J_top, qpos=d.qpos,
                       armature=m.dof_armature[: ids.nv_robot])
