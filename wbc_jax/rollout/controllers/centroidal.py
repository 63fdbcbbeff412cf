"""The centroidal controller as a rollout plug-in: the centroidal paper's capture-point trot (Sec. 2.3.1) and
centroidal-momentum WBC (:func:`wbc_jax.control.centroidal.centroidal_control`), with the trot's metrics
(:mod:`wbc_jax.rollout.controllers.trot_metrics`).

A run's plan (:class:`TrotPlan`) is a straight trot along the trunk's forward axis from the run's start pose:
``n_steps`` half-cycles of ``step_time`` [s] (``four_foot`` of them four-foot support) after ``t_start`` [s] of
standing, the virtual leg advancing ``speed`` x ``step_time`` per step. The controller's parameters are
:class:`wbc_jax.control.centroidal.CentroidalGains` (``mass_scale``: the model mass error of the paper's Fig. 12;
``load_mass``: the payload it assumes on the tray). It plans its ground forces with its own friction coefficient
(``gains.mu``), not the run's ground friction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.control.centroidal import (
    CentroidalConfig,
    CentroidalRef,
    centroidal_control,
    centroidal_qp_settings,
    default_gains,
    init_state,
)
from wbc_jax.metrics import paper
from wbc_jax.metrics.accumulate import ControlSample
from wbc_jax.planner.capture_point import CPWalkPlan, cp_walk_plan, cp_walk_reference
from wbc_jax.planner.gait import GaitParams
from wbc_jax.rollout.controllers import trot_metrics
from wbc_jax.rollout.controllers.base import Controller, Record, keep_but_warm_start, object_in_tray
from wbc_jax.rollout.controllers.trot_metrics import TrotLog, trunk_rpy
from wbc_jax.runtime.static import ByValue

SWING_HEIGHT = 0.06  # [m] swing apex above the higher end point


class TrotPlan(NamedTuple):
    """One run's walking pattern: the capture-point plan, the trunk's orientation at the start (its attitude
    reference, (3, 3)) and the stride () [m] (virtual-leg advance per step)."""

    walk: CPWalkPlan
    R0: jax.Array
    stride: jax.Array


class TrotReference(NamedTuple):
    """The planner's output at one instant: the WBC's reference, the desired CP xi_d (2,) [m] and the current
    virtual leg P (2,) [m]."""

    wbc: CentroidalRef
    xi_d: jax.Array
    P: jax.Array

    @property
    def swing(self):
        """(4,) bool swing mask."""
        return self.wbc.swing


class QPHealth(NamedTuple):
    """The centroidal QP's health in the fields the shared accumulators read (no object forces are planned)."""

    tau_excess: jax.Array
    prim_res: jax.Array
    flag: jax.Array
    iters: jax.Array
    obj_forces: jax.Array


def walk_plan(robot, qpos0, stride: float, step_time: float, t_four: float, n_steps: int, t_start: float = 0.5,
              swing_height: float = SWING_HEIGHT) -> TrotPlan:
    """Walking pattern along the trunk's forward axis from ``qpos0`` (numpy leaves).

    Args:
        stride: virtual-leg advance per step [m]; step_time: half-cycle [s]; t_four: its four-foot part [s];
        n_steps: half-cycles (>= 2); t_start: standing time before the first [s]; swing_height: [m].
    """
    m, ids = robot.mj_model, robot.ids
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    R0 = d.xmat[ids.trunk_body].reshape(3, 3).copy()
    heading = float(np.arctan2(R0[1, 0], R0[0, 0]))
    gait = GaitParams(t_stance=t_four, t_swing=step_time - t_four, t_start=t_start)
    plan = cp_walk_plan(d.site_xpos[ids.foot_site].copy(), d.subtree_com[ids.trunk_body].copy(), heading, stride,
                        n_steps, gait, swing_height)
    return jax.tree_util.tree_map(np.asarray, TrotPlan(plan, R0, np.asarray(stride, float)))


@dataclass(frozen=True, eq=False)
class CentroidalController(Controller, ByValue):
    """The centroidal WBC on the capture-point trot (module docstring)."""

    cfg: CentroidalConfig
    name = "centroidal"

    @classmethod
    def default(cls, dt: float) -> "CentroidalController":
        """Default settings with control period ``dt`` [s]."""
        return cls(CentroidalConfig(qp=centroidal_qp_settings(), dt=dt))

    @classmethod
    def with_iters(cls, dt: float, iters: int) -> "CentroidalController":
        """Settings with control period ``dt`` [s] and ``iters`` ADMM iterations per control step."""
        return cls(CentroidalConfig(qp=centroidal_qp_settings(iters), dt=dt))

    def default_gains(self):
        return default_gains()

    def batched(self, gains) -> bool:
        """``gains`` has a leading run axis."""
        return jnp.ndim(gains.kp_z) > 0

    def init_state(self, robot, d, dyn):
        return init_state(self.cfg, d.qpos, robot.ids)

    def init_metrics(self, robot, d, dyn):
        return trot_metrics.init_metrics(dyn, robot.mj_model.nu)

    def freeze(self, frozen, new, old):
        """The base rule, but the QP's warm start follows ``new`` (:func:`keep_but_warm_start`)."""
        return keep_but_warm_start(frozen, new, old)

    def make_plan(self, robot, course: bool, qpos0, kw: dict) -> TrotPlan:
        """:func:`walk_plan` from ``kw``: speed [m/s], step_time [s], four_foot [s], n_steps, t_start [s] (the
        stride is speed x step_time; other keys are ignored)."""
        return walk_plan(robot, qpos0, kw["speed"] * kw["step_time"], kw["step_time"], kw["four_foot"],
                         int(kw["n_steps"]), kw.get("t_start", 0.5))

    def align_plans(self, plans: list) -> list:
        return plans  # one step count for every run: the same shapes

    def plan_end(self, plan) -> np.ndarray:
        """(B,) end of each run's walk [s] (host)."""
        return np.asarray(plan.walk.gait.t_stop).reshape(-1)

    def planned_s(self, plan) -> float:
        return float(np.max(self.plan_end(plan)))

    def reference(self, plan: TrotPlan, t, obs, p_lift, foot_contact) -> TrotReference:
        """Desired CP, CoM velocity (eq. 19) and swing references at time t (:func:`cp_walk_reference`); the
        trot is time-based (``foot_contact`` is not used)."""
        dyn = obs.robot
        wr = cp_walk_reference(plan.walk, t, dyn.com[:2], p_lift)
        wbc = CentroidalRef(v_xy=wr.v_xy, z=plan.walk.z0, R_base=plan.R0, heading=plan.walk.heading, swing=wr.swing,
                            p_sw=wr.p_sw, v_sw=wr.v_sw, a_sw=wr.a_sw)
        return TrotReference(wbc, wr.cp.xi, wr.cp.P)

    def control(self, obs, ref: TrotReference, obj_model, gains, state, ids, mu):
        return centroidal_control(obs, ref.wbc, gains, state, ids, self.cfg)

    def record(self, sim, d, obs, ref: TrotReference, tau, diag, rel0, obj_model, metrics, plan: TrotPlan) -> Record:
        """The shared sample (trunk height, the object's slip and lift on the tray, the CP error as the tracking
        error, torque ratio, QP health), the trot's online reductions and the log row, at the sensed state ``d``."""
        ids, dyn = sim.robot.ids, obs.robot
        rel = object_in_tray(d, ids)
        rpy = trunk_rpy(plan.R0, dyn.R_base)
        step = trot_metrics.step_values(plan, ref, dyn, rpy, d.time)
        health = QPHealth(diag.tau_excess, diag.prim_res, diag.flag, diag.iters, jnp.zeros((4, 3), tau.dtype))
        sample = ControlSample(trunk_z=dyn.p_base[2], slip=jnp.linalg.norm(rel[:2] - rel0[:2]), lift=rel[2] - rel0[2],
                               tau_ratio=jnp.max(jnp.abs(tau) / jnp.asarray(ids.tau_max)),
                               track_err=jnp.linalg.norm(step.e_cp), qp=health, obj_mu=obj_model.mu)
        legs_v, legs_q = jnp.asarray(ids.act_dof[:12]), jnp.asarray(ids.act_qpos[:12])
        log = TrotLog(t=d.time, com=dyn.com, com_vel=dyn.com_vel, xi_d=ref.xi_d, P=ref.P, v_des=ref.wbc.v_xy, rpy=rpy,
                      trunk_z=dyn.p_base[2], tau=tau, tau_grf=diag.tau_grf, q_leg=d.qpos[legs_q],
                      qd_leg=d.qvel[legs_v], swing=ref.swing, prim_res=diag.prim_res, qpos=d.qpos)
        return Record(sample, trot_metrics.fold(metrics, step, ref.swing, dyn.p_foot, tau), log)

    def empty_log(self, d, nu: int) -> TrotLog:
        z, z2, z3 = jnp.zeros_like(d.time), jnp.zeros(2, d.qpos.dtype), jnp.zeros(3, d.qpos.dtype)
        return TrotLog(t=z, com=z3, com_vel=z3, xi_d=z2, P=z2, v_des=z2, rpy=z3, trunk_z=z,
                       tau=jnp.zeros(nu, d.qpos.dtype), tau_grf=jnp.zeros(nu, d.qpos.dtype),
                       q_leg=jnp.zeros(12, d.qpos.dtype), qd_leg=jnp.zeros(12, d.qpos.dtype),
                       swing=jnp.zeros(4, bool), prim_res=z, qpos=jnp.zeros_like(d.qpos))

    def failed(self, acc, course: bool):
        """Trunk below the fall height, a non-foot part on the floor or terrain, a non-finite state or Warp's
        capacity overflow (the object on the tray may slide or drop: not a failure of the trot)."""
        fall_z = paper.FALL_Z_COURSE if course else paper.FALL_Z_FLAT
        return (acc.min_trunk_z < fall_z) | acc.nonfoot_floor | acc.nonfinite | acc.overflow

    def final_input(self, logs):
        """(B, 1) the last logged time [s] (finalization needs nothing else of the logs)."""
        return logs.t[:, -1:]

    def finalize(self, sim, acc, state, final_input, mu, n, course: bool) -> dict:
        """:func:`wbc_jax.rollout.controllers.trot_metrics.finalize` of the batch's final state."""
        metrics = jax.device_get(state.metrics)
        if n is not None:
            metrics = jax.tree_util.tree_map(lambda x: np.asarray(x)[:n], metrics)
        return trot_metrics.finalize(acc, metrics, sim.robot.ids, course, sim.n_substeps)
