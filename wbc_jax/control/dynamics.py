"""Dynamics terms shared by the transport and centroidal controllers.

All quantities come from one sensing pass (:func:`wbc_jax.sim.physics.sense`: MJX ``fwd_position`` +
``fwd_velocity`` on the JAX backend, ``forward`` on Warp) and are restricted to the robot's ``nv_r = 24`` dofs (the object
is a separate kinematic tree, so its dofs never couple into the robot's mass matrix or Jacobians).
Frames: forces, positions and Jacobians are in the world frame; ``qvel[3:6]`` is MuJoCo's
body-frame angular velocity of the trunk, which the Jacobians already account for.
"""

from __future__ import annotations

import functools

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.sim.model import RobotIds, mjx

from mujoco.mjx._src.math import motion_cross as _motion_cross  # noqa: E402  (not re-exported by mjx)

GRAVITY = 9.81  # [m/s^2]


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


def chain_dofs(m, body: int) -> np.ndarray:
    """(nv,) bool, static: the dofs whose motion moves ``body`` (its own joints' and its ancestors'), from the model's
    tree (``body_parentid``, ``dof_bodyid``: numpy on both backends). MJX's ``jac`` finds the same mask at run time
    by a scan over the tree with the body id traced."""
    parent, chain, b = np.asarray(m.body_parentid), {int(body)}, int(body)
    while b > 0:
        b = int(parent[b])
        chain.add(b)
    return np.isin(np.asarray(m.dof_bodyid), sorted(chain))


def point_jacobians(m, d, ids: RobotIds, points, bodies):
    """Translational and rotational Jacobians of points fixed to bodies, and their Jdot v.

    MJX's ``jac`` and ``jac_dot`` (``mujoco.mjx._src.support``), the same arithmetic, with the bodies static: each
    body's dof mask (:func:`chain_dofs`), root and velocity are constants of the program, so no scan over the body
    tree and no gather by a traced id runs in the control step (issue 22: at batch 270 every XLA op costs ~1 us).

    Args:
        points: (k, 3) world points [m]; bodies: (k,) body ids (static ints).

    Returns:
        (Jp (k, 3, nv_r), Jr (k, 3, nv_r), Jdv_p (k, 3), Jdv_r (k, 3)).
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
    cdof_dot = jnp.where(is_quat[:, None], jax.vmap(_motion_cross)(d.cvel[dof_body], cdof), d.cdof_dot)
    pvel_lin = cvel[:, 3:] - cross(offset, cvel[:, :3])  # (k, 3)
    jdp = (cdof_dot[None, :, 3:] + cross(cdof_dot[None, :, :3], offset[:, None])
           + cross(cdof[None, :, :3], pvel_lin[:, None])) * mask
    jdr = cdof_dot[None, :, :3] * mask
    T = lambda j: jnp.swapaxes(j, 1, 2)  # noqa: E731  (k, nv, 3) -> (k, 3, nv)
    return T(jacp)[:, :, :nvr], T(jacr)[:, :, :nvr], T(jdp) @ d.qvel, T(jdr) @ d.qvel


def mass_matrix(m, d) -> jax.Array:
    """(nv, nv) dense joint-space mass matrix of either backend.

    MJX's JAX implementation keeps M dense for small models (``mjx.full_m`` returns it); MuJoCo Warp keeps its
    lower triangle in MuJoCo's CSR layout (``M_rownnz`` / ``M_rowadr`` / ``M_colind``, ``nC`` values), which
    ``mjx.full_m`` returns unchanged for small models: each dense entry is then read from its CSR value (or its
    mirror's) through a static index, one gather (a scatter and a transpose before, issue 22).
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


def full_precision(fn):
    """``fn`` traced with float32 matrix products at full precision.

    On Ampere and later GPUs JAX's default float32 matmul rounds its inputs to TF32 (about 1e-3 relative): the
    controller's QP data would then carry errors of that size, and ``H' Q H`` would not even be symmetric, so a
    QP residual could not go below ~1e-3 of its scale (issue 22: on an H100 27 % of the control steps ran into the
    iteration cap at tolerance 1e-4, 0 % on the CPU). Same results on the CPU.
    """
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)
    return wrapped


@full_precision
def dyn_terms(m, d, ids: RobotIds) -> DynTerms:
    """Gather :class:`DynTerms` from sensed MJX data (:func:`wbc_jax.sim.physics.sense`)."""
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


def cone_edges(mu, k: int, R=None):
    """Unit edges of the inscribed friction pyramid, edge j = Rz(2 pi j / k) Ry(atan mu) z.

    Args:
        mu: () friction coefficient; k: number of edges (static); R: optional (3, 3) contact frame
            (its z axis is the normal), identity if None.

    Returns:
        (3, k) edge directions in world frame.
    """
    th = jnp.arctan(mu)
    a = 2 * jnp.pi * jnp.arange(1, k + 1) / k
    e = jnp.stack([jnp.sin(th) * jnp.cos(a), jnp.sin(th) * jnp.sin(a), jnp.cos(th) * jnp.ones(k)])
    return e if R is None else R @ e


def skew(w):
    """(3,) -> (3, 3) cross-product matrix."""
    return jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def edge_wrenches(points, about, edges):
    """(6, k e): the wrench about ``about`` of a unit force along each friction-pyramid edge of each point, column
    ``i e + j`` for point i's edge j: ``[E_ij; (p_i - about) x E_ij]``. The same as the wrench map of the stacked
    point forces times ``block_diag(E_1, ..., E_k)``, without building either matrix (their concatenations of
    blocks were separate kernels, ~15 us per control step at batch 270 on an H100: issue 22).

    Args:
        points: (k, 3) [m]; about: (3,) [m]; edges: (k, 3, e) each point's edge directions (world frame).
    """
    r = jnp.broadcast_to((points - about)[:, :, None], edges.shape)
    w = jnp.concatenate([edges, jnp.cross(r, edges, axis=1)], axis=1)  # (k, 6, e)
    return jnp.swapaxes(w, 0, 1).reshape(6, -1)


def rot_error(R_ref, R):
    """Exponential coordinates of R_ref R^T (world frame) [rad], via the unit quaternion."""
    E = R_ref @ R.T
    w = 0.5 * jnp.sqrt(jnp.maximum(1.0 + jnp.trace(E), 1e-12))
    vec = jnp.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]]) / (4.0 * w)
    s = jnp.linalg.norm(vec)
    ang = 2.0 * jnp.arctan2(s, w)
    return jnp.where(s > 1e-9, vec * ang / jnp.maximum(s, 1e-9), 2.0 * vec)
