"""Rigid-body and friction-cone arithmetic shared by the controllers, the metrics and the robot model (pure JAX)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

GRAVITY = 9.81  # [m/s^2]


def full_precision(fn):
    """``fn`` traced with float32 matrix products at full precision.

    On Ampere and later GPUs JAX's default float32 matmul rounds its inputs to TF32 (about 1e-3 relative): the
    controller's QP data would then carry errors of that size, and ``H' Q H`` would not even be symmetric, so a
    QP residual could not go below ~1e-3 of its scale. Same results on the CPU.
    """
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)
    return wrapped


def cube_inertia(m, d):
    """Principal moment of inertia of a solid cube about its centre, m d^2 / 6 [kg m^2]."""
    return m * d**2 / 6.0


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
    point forces times ``block_diag(E_1, ..., E_k)``, without building either matrix (whose concatenations of
    blocks would be separate kernels).

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
