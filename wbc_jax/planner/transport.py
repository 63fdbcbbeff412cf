"""Transport-paper motion planner: object path -> CoM reference -> trot footholds and swing refs.

The CoM reference is the object reference plus the constant initial offset (Sec. IV-B,
q_r,d = q_b,ref + q_b,r), the trunk keeps its initial orientation, feet follow a time-based trot
and land at their nominal offset from the CoM reference at mid-stance.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.control.transport import Reference
from wbc_jax.planner.gait import GaitParams, foot_stance_time, gait_phase
from wbc_jax.planner.spline import CubicPath, eval_path, path_end_time, straight_path
from wbc_jax.planner.swing import swing_reference


class TransportPlan(NamedTuple):
    """Per-run plan (pytree; leaves may carry a batch axis).

    Attributes:
        obj_path: object position path (CubicPath).
        com_offset: (3,) CoM minus object position at t = 0 [m].
        R_obj: (3, 3) object orientation reference (initial orientation).
        R_base: (3, 3) trunk orientation reference (initial orientation).
        foot_offset: (4, 3) nominal foot centre minus CoM in xy; z is the absolute foot-centre height [m].
        gait: GaitParams.
        swing_height: () swing apex above the higher end point [m].
        t_ramp: () duration of the load ramps before liftoff and after touchdown [s].
    """

    obj_path: CubicPath
    com_offset: jax.Array
    R_obj: jax.Array
    R_base: jax.Array
    foot_offset: jax.Array
    gait: GaitParams
    swing_height: jax.Array
    t_ramp: jax.Array


def straight_plan(robot, qpos0: np.ndarray, distance: float = 3.4, speed: float = 0.13, ramp: float = 1.0,
                  gait: GaitParams = GaitParams(), swing_height: float = 0.05, t_ramp: float = 0.06,
                  direction=(0.0, -1.0, 0.0)) -> TransportPlan:
    """Plan a straight transport of ``distance`` metres along ``direction`` at ``speed`` (flat ground).

    Args:
        robot: wbc_jax.model.Robot; qpos0: (nq,) initial configuration (object on the tray).
    """
    m, ids = robot.mj_model, robot.ids
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    p_obj = d.xpos[ids.obj_body].copy()
    com = d.subtree_com[ids.trunk_body].copy()
    feet = d.site_xpos[ids.foot_site].copy()
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    path = straight_path(jnp.asarray(p_obj), jnp.asarray(p_obj + distance * u), speed, t0=gait.t_start, ramp=ramp)
    t_end = float(path_end_time(path))
    gait = gait._replace(t_stop=t_end)
    foot_off = feet.copy()
    foot_off[:, :2] -= com[:2]
    return TransportPlan(
        obj_path=path, com_offset=jnp.asarray(com - p_obj), R_obj=jnp.asarray(d.xmat[ids.obj_body].reshape(3, 3)),
        R_base=jnp.asarray(d.xmat[ids.trunk_body].reshape(3, 3)), foot_offset=jnp.asarray(foot_off),
        gait=GaitParams(*(jnp.asarray(x, float) for x in gait)), swing_height=jnp.asarray(swing_height),
        t_ramp=jnp.asarray(t_ramp),
    )


def plan_duration(plan: TransportPlan) -> float:
    """End time of the object path [s] (host-side)."""
    return float(np.max(np.asarray(plan.obj_path.t_knots)[..., -1]))


def reference(plan: TransportPlan, t, p_lift) -> Reference:
    """References at time t.

    Args:
        plan: TransportPlan; t: () time [s]; p_lift: (4, 3) each foot's position at its last liftoff [m].
    """
    p_o, v_o, a_o = eval_path(plan.obj_path, t)
    p_c, v_c, a_c = p_o + plan.com_offset, v_o, a_o
    g = gait_phase(plan.gait, t)
    t_mid = t + g.t_to_touchdown + 0.5 * foot_stance_time(plan.gait)  # (4,) mid-stance after touchdown
    t_mid = jnp.where(jnp.isfinite(t_mid), t_mid, t)
    com_mid = jax.vmap(lambda tt: eval_path(plan.obj_path, tt)[0])(t_mid) + plan.com_offset
    p_land = jnp.concatenate([com_mid[:, :2] + plan.foot_offset[:, :2], plan.foot_offset[:, 2:]], axis=1)
    # quintic pieces: the acceleration is continuous at liftoff, apex and touchdown (cubic pieces jump by
    # ~200 m/s^2 at the apex for a 0.06 m step in 0.115 s, a jolt the whole body and the tray feel)
    swing_fn = functools.partial(swing_reference, kind="quintic")
    p_sw, v_sw, a_sw = jax.vmap(swing_fn, in_axes=(0, 0, 0, None, None))(
        p_lift, p_land, g.swing_phase, plan.gait.t_swing, plan.swing_height)
    t_since_td = foot_stance_time(plan.gait) - g.t_to_liftoff  # valid while stepping
    ramp_td = jnp.where(jnp.isfinite(g.t_to_liftoff) & g.stepping, t_since_td, jnp.inf)
    load = jnp.clip(jnp.minimum(g.t_to_liftoff, ramp_td) / plan.t_ramp, 0.02, 1.0)
    return Reference(p_obj=p_o, v_obj=v_o, a_obj=a_o, R_obj=plan.R_obj, p_com=p_c, v_com=v_c, a_com=a_c,
                     R_base=plan.R_base, swing=g.swing, p_sw=p_sw, v_sw=v_sw, a_sw=a_sw, load=load)
