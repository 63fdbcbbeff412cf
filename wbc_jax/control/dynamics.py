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
import numpy as np

from wbc_jax.sim.model import RobotIds, mjx

from mujoco.mjx._src.support import jac_dot as _jac_dot  # noqa: E402  (not re-exported by mjx)

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


def point_jacobians(m, d, ids: RobotIds, points, bodies):
    """Translational and rotational Jacobians of points fixed to bodies, and their Jdot v.

    Args:
        points: (k, 3) world points [m]; bodies: (k,) body ids (static or traced ints).

    Returns:
        (Jp (k, 3, nv_r), Jr (k, 3, nv_r), Jdv_p (k, 3), Jdv_r (k, 3)).
    """
    nvr = ids.nv_robot

    def one(p, b):
        jp, jr = mjx.jac(m, d, p, b)
        jdp, jdr = _jac_dot(m, d, p, b)
        return jp.T[:, :nvr], jr.T[:, :nvr], jdp.T @ d.qvel, jdr.T @ d.qvel

    return jax.vmap(one)(points, jnp.asarray(bodies))


def mass_matrix(m, d) -> jax.Array:
    """(nv, nv) dense joint-space mass matrix of either backend.

    MJX's JAX implementation keeps M dense for small models (``mjx.full_m`` returns it); MuJoCo Warp keeps its
    lower triangle in MuJoCo's CSR layout (``M_rownnz`` / ``M_rowadr`` / ``M_colind``, ``nC`` values), which
    ``mjx.full_m`` returns unchanged for small models: scatter it and mirror the strict lower triangle.
    """
    M = mjx.full_m(m, d)
    if M.ndim == 2:
        return M
    rows = np.repeat(np.arange(m.nv), m.M_rownnz)
    L = jnp.zeros((m.nv, m.nv), M.dtype).at[rows, np.asarray(m.M_colind)].set(M)
    return L + jnp.tril(L, -1).T


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


def wrench_map(points, about):
    """(3k, 6)^T map: stacked point forces (k, 3) -> wrench [sum f; sum (p - about) x f] as (6, 3k)."""
    k = points.shape[0]
    top = jnp.tile(jnp.eye(3), (1, k))
    bot = jnp.concatenate([skew(p - about) for p in points], axis=1) if k else jnp.zeros((3, 0))
    return jnp.concatenate([top, bot], axis=0)


def rot_error(R_ref, R):
    """Exponential coordinates of R_ref R^T (world frame) [rad], via the unit quaternion."""
    E = R_ref @ R.T
    w = 0.5 * jnp.sqrt(jnp.maximum(1.0 + jnp.trace(E), 1e-12))
    vec = jnp.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]]) / (4.0 * w)
    s = jnp.linalg.norm(vec)
    ang = 2.0 * jnp.arctan2(s, w)
    return jnp.where(s > 1e-9, vec * ang / jnp.maximum(s, 1e-9), 2.0 * vec)
