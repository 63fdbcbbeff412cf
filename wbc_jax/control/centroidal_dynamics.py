"""Centroidal dynamics terms (centroidal paper Sec. 2.2; Wensing and Orin's CMM from the mass matrix).

From the floating-base rows of MuJoCo's joint-space equations (:class:`~wbc_jax.physics.observe.DynTerms`):

    A_G     = X^T M[0:6, :]                           centroidal momentum matrix        (eq. 13)
    Adot v  = X^T h[0:6] - [0, 0, m g, 0, 0, 0]^T     bias with gravity removed          (eq. 14)
    I_G     = X^T M[0:6, 0:6] X = diag(m I3, Ibar_G)  centroidal composite inertia      (eq. 24)

``X`` (6, 6) maps the centroidal twist ``[v_G; omega]`` (world frame, v_G at the CoM) to the free joint's
generalized velocity (``qvel[0:3]`` world velocity of the trunk origin p, ``qvel[3:6]`` body-frame angular
velocity): ``X = [[I, -[p - c]x], [0, R^T]]``. ``X^T`` moves the free joint's generalized forces (world force,
body-frame torque about p) to a world-frame wrench about the CoM c. Momentum h_G = [l; k] is
[linear N s; angular about the CoM N m s], world frame, so ``h_G = A_G v`` and
``hdot_G = A_G vdot + Adot v = [m g_vec; 0] + sum of the contact wrenches about the CoM`` (eq. 12). Gravity
has no moment about the CoM, so ``Adot v = X^T h[0:6] - [0, 0, m g, 0, 0, 0]`` with the MuJoCo bias
``h = C v + g(q)`` (gravity enters ``X^T h[0:6]`` as ``+m g`` along z only).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.spatial import GRAVITY, skew
from wbc_jax.types import DynTerms


class CentroidalTerms(NamedTuple):
    """Centroidal quantities at one instant (nv_r = 24 robot dofs).

    Attributes:
        A: (6, nv_r) centroidal momentum matrix A_G (rows: linear [kg], angular [kg m]).
        Adv: (6,) Adot v [N, N m] (velocity-product part of hdot_G).
        I_G: (6, 6) centroidal composite-rigid-body inertia, block-diag(m I3, Ibar_G).
        Ibar: (3, 3) locked-robot rotational inertia about the CoM, world frame [kg m^2].
    """

    A: jax.Array
    Adv: jax.Array
    I_G: jax.Array
    Ibar: jax.Array


def com_transform_T(dyn: DynTerms):
    """(6, 6) X^T: free-joint generalized force (world force, body torque about the trunk origin) ->
    world wrench about the CoM."""
    XT = jnp.zeros((6, 6))
    XT = XT.at[0:3, 0:3].set(jnp.eye(3))
    XT = XT.at[3:6, 0:3].set(skew(dyn.p_base - dyn.com))
    return XT.at[3:6, 3:6].set(dyn.R_base)


def centroidal_terms(dyn: DynTerms) -> CentroidalTerms:
    """A_G, Adot v and the centroidal composite inertia from :class:`DynTerms` (eqs. 13, 14, 24).

    Works for any DynTerms, including a controller's mis-scaled model (M, h, mass scaled together).
    """
    XT = com_transform_T(dyn)  # (6, 6)
    A = XT @ dyn.M[0:6]  # (6, nv)
    Adv = XT @ dyn.h[0:6] - jnp.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]) * dyn.mass * GRAVITY
    X = jnp.zeros((6, 6)).at[0:3, 0:3].set(jnp.eye(3)).at[0:3, 3:6].set(-skew(dyn.p_base - dyn.com))
    X = X.at[3:6, 3:6].set(dyn.R_base.T)
    I_G = A[:, 0:6] @ X
    return CentroidalTerms(A=A, Adv=Adv, I_G=I_G, Ibar=I_G[3:6, 3:6])
