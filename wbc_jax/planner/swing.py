"""Swing-foot references and footholds.

:func:`swing_reference` follows the transport paper (Sec. IV-B, its ref. [33]): the foot
height comes from two splines, a lift spline and a lower spline, each lasting
``0.5 T_sw`` and each starting and ending at rest; the horizontal motion is one rest-to-rest
curve over the whole swing. With ``kind="cubic"`` (default) every curve is the cubic
smoothstep ``3 s^2 - 2 s^3``, which is the unique cubic with zero end velocities, so the
horizontal curve is itself two cubic splines joined at mid-swing. ``kind="quintic"`` uses
``10 s^3 - 15 s^4 + 6 s^5`` (zero end velocities and accelerations), the centroidal paper's
quintic swing trajectories.

Phases come from :func:`wbc_jax.planner.gait.gait_phase` (``swing_phase``); outputs are in
the world frame, time derivatives in world units per second (chain rule through ``t_swing``).
"""

from __future__ import annotations

import jax.numpy as jnp

_KINDS = ("cubic", "quintic")


def _blend(s, kind: str):
    """Rest-to-rest blend f(s) on s in [0, 1] with f', f'' (s is clipped by the caller)."""
    if kind == "cubic":
        return s * s * (3.0 - 2.0 * s), 6.0 * s * (1.0 - s), 6.0 - 12.0 * s
    if kind == "quintic":
        s2 = s * s
        return (
            s2 * s * (10.0 + s * (-15.0 + 6.0 * s)),
            30.0 * s2 * (1.0 - s) ** 2,
            60.0 * s * (1.0 - s) * (1.0 - 2.0 * s),
        )
    raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")


def quintic(p0, p1, T, t):
    """Rest-to-rest quintic from p0 (t = 0) to p1 (t = T), zero end velocity and acceleration.

    Args:
        p0: start value, any shape (broadcast with p1) [m or rad].
        p1: end value, same trailing shape [m or rad].
        T: () duration [s], > 0.
        t: () time since the start [s]; clamped to [0, T] (constant outside, v = a = 0).

    Returns:
        (p, v, a): each of the broadcast shape of p0 and p1; units of p0 per s^0, s^1, s^2.
    """
    dtype = jnp.result_type(float)
    p0, p1, T, t = (jnp.asarray(x, dtype=dtype) for x in (p0, p1, T, t))
    f, df, ddf = _blend(jnp.clip(t / T, 0.0, 1.0), "quintic")
    d = p1 - p0
    return p0 + d * f, d * (df / T), d * (ddf / T**2)


def swing_reference(p_lift, p_land, phase, t_swing, height, kind: str = "cubic"):
    """Swing-foot position, velocity and acceleration references (world frame).

    Horizontal (x, y): rest-to-rest from ``p_lift`` to ``p_land`` over the whole swing.
    Vertical: lift spline ``z_lift -> z_apex`` on phase [0, 0.5], lower spline
    ``z_apex -> z_land`` on [0.5, 1], both with zero end velocities, where
    ``z_apex = max(z_lift, z_land) + height``.

    Args:
        p_lift: (3,) foot position at liftoff [m].
        p_land: (3,) touchdown target [m].
        phase: () swing progress in [0, 1] (e.g. ``GaitState.swing_phase[i]``). Outside
            [0, 1] the position is clamped and v = a = 0.
        t_swing: () swing duration T_sw [s], > 0.
        height: () step height above the higher end point [m].
        kind: "cubic" (transport paper) or "quintic" (centroidal paper); static.

    Returns:
        (p, v, a): each (3,) [m], [m/s], [m/s^2].
    """
    dtype = jnp.result_type(float)
    p_lift, p_land, phase, T, height = (
        jnp.asarray(x, dtype=dtype) for x in (p_lift, p_land, phase, t_swing, height)
    )
    inside = (phase >= 0.0) & (phase <= 1.0)
    phi = jnp.clip(phase, 0.0, 1.0)

    f, df, ddf = _blend(phi, kind)
    d = p_land - p_lift
    p = p_lift + d * f
    v = d * (df / T)
    a = d * (ddf / T**2)

    z_lift, z_land = p_lift[2], p_land[2]
    z_apex = jnp.maximum(z_lift, z_land) + height
    first = phi < 0.5
    s = jnp.where(first, 2.0 * phi, 2.0 * phi - 1.0)
    z0 = jnp.where(first, z_lift, z_apex)
    dz = jnp.where(first, z_apex - z_lift, z_land - z_apex)
    g, dg, ddg = _blend(s, kind)
    Th = 0.5 * T  # duration of each vertical spline [s]
    p = p.at[2].set(z0 + dz * g)
    v = v.at[2].set(dz * dg / Th)
    a = a.at[2].set(dz * ddg / Th**2)
    return p, jnp.where(inside, v, 0.0), jnp.where(inside, a, 0.0)


def raibert_foothold(hip_xy, v_xy, v_ref_xy, t_stance_total, k_v=0.2, t_to_touchdown=0.0):
    """Capture-style (Raibert) foothold in the horizontal plane.

    ``p = hip + v_ref t_to_touchdown + v_ref T_st / 2 + k_v (v - v_ref)``: the hip
    (advanced to touchdown along the reference velocity when ``t_to_touchdown`` is given)
    plus half the stance travel, plus a velocity-error correction.

    Args:
        hip_xy: (2,) hip position projected on the ground now [m].
        v_xy: (2,) measured horizontal base/CoM velocity [m/s].
        v_ref_xy: (2,) reference horizontal velocity [m/s].
        t_stance_total: () stance time of the foot per cycle [s] (for the trot
            ``gait.foot_stance_time(params)``).
        k_v: () velocity-feedback gain [s]; about sqrt(z0 / g) (0.2 s at z0 = 0.4 m).
        t_to_touchdown: () time until the foot lands [s]; 0 when ``hip_xy`` is already
            the hip at touchdown.

    Returns:
        (2,) foothold [m].
    """
    dtype = jnp.result_type(float)
    hip_xy, v_xy, v_ref_xy, T, k_v, t_td = (
        jnp.asarray(x, dtype=dtype) for x in (hip_xy, v_xy, v_ref_xy, t_stance_total, k_v, t_to_touchdown)
    )
    return hip_xy + v_ref_xy * (t_td + 0.5 * T) + k_v * (v_xy - v_ref_xy)
