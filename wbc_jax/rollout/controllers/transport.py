"""The transport controller as a rollout plug-in: the transport paper's planner, WBC and metrics (R, T, S)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.transport import TransportConfig, default_gains, init_control_state, transport_control
from wbc_jax.metrics import paper
from wbc_jax.metrics.accumulate import ControlSample
from wbc_jax.planner.spline import pad_path
from wbc_jax.planner.transport import course_plan, plan_duration, reference, straight_plan
from wbc_jax.rollout.controllers.base import Controller, Record, keep_but_warm_start, object_in_tray
from wbc_jax.runtime import aot
from wbc_jax.runtime.static import ByValue


class Log(NamedTuple):
    """Logged every ``log_every`` steps (per run): time, object and CoM actual vs reference, QP residual,
    torques, and the full configuration qpos (nq,) for replay and video."""

    t: jax.Array
    p_obj: jax.Array
    p_obj_ref: jax.Array
    com: jax.Array
    com_ref: jax.Array
    slip: jax.Array
    trunk_z: jax.Array
    prim_res: jax.Array
    tau: jax.Array
    qpos: jax.Array


@dataclass(frozen=True, eq=False)
class TransportController(Controller, ByValue):
    """The transport WBC (:func:`wbc_jax.control.transport.transport_control`) on the object-path plans of
    :mod:`wbc_jax.planner.transport`; metrics: :mod:`wbc_jax.metrics.paper`."""

    cfg: TransportConfig
    name = "transport"

    @classmethod
    def default(cls, dt: float) -> "TransportController":
        """Default settings with control period ``dt`` [s]."""
        return cls(TransportConfig(dt=dt))

    def default_gains(self):
        return default_gains()

    def batched(self, gains) -> bool:
        """``gains`` has a leading run axis."""
        return jnp.ndim(gains.kp_obj) > 0

    def init_state(self, robot, d, dyn):
        return init_control_state(self.cfg, dyn, robot.ids)

    def freeze(self, frozen, new, old):
        """The base rule, but the QP's warm start (solution, multipliers, rho, carried factors) follows ``new``
        (:func:`wbc_jax.rollout.controllers.base.keep_but_warm_start`)."""
        return keep_but_warm_start(frozen, new, old)

    def variant(self, cs):
        """The ablation switches (:class:`wbc_jax.control.variants.Variant`) of the controller state ``cs``."""
        return cs.variant

    def with_variant(self, cs, switches):
        """``cs`` with its ablation switches replaced by ``switches``."""
        return cs._replace(variant=switches)

    def make_plan(self, robot, course: bool, qpos0, kw: dict):
        """One plan (:func:`course_plan` when ``course``, else :func:`straight_plan`, with keyword arguments ``kw``)
        and numpy leaves, kept on disk like a compiled program (:func:`wbc_jax.runtime.aot.cached_value`: keyed by
        the model's bytes, the start pose, ``kw``, the package's sources and the versions; off with
        ``WBC_JAX_CACHE=off``): computing the course's is most of a warm campaign's setup."""
        def compute():
            p = course_plan(robot, qpos0, **kw) if course else straight_plan(robot, qpos0, **kw)
            return jax.tree_util.tree_map(np.asarray, p)

        static = aot.describe(robot, np.asarray(qpos0, float), "course" if course else "straight",
                              *(f"{k}={aot.describe(v)}" for k, v in sorted(kw.items())))
        return aot.cached_value("plan", static, compute)

    def align_plans(self, plans: list) -> list:
        """Per-footstep CoM paths and landing tables padded to the longest plan's."""
        if plans[0].com_xy is not None:
            n = max(len(p.com_xy.t_knots) for p in plans)
            plans = [p._replace(com_xy=pad_path(p.com_xy, n)) for p in plans]
        n = max(len(p.landing) for p in plans)
        return [p._replace(landing=np.pad(np.asarray(p.landing), ((0, n - len(p.landing)), (0, 0), (0, 0)),
                                          mode="edge")) for p in plans]

    def plan_end(self, plan) -> np.ndarray:
        """(B,) end of each run's object path [s] (host)."""
        return np.asarray(plan.obj_path.t_knots)[:, -1]

    def planned_s(self, plan) -> float:
        return plan_duration(plan)

    def reference(self, plan, t, obs, p_lift, foot_contact):
        return reference(plan, t, p_lift, foot_contact, obs.robot.p_foot)

    def control(self, obs, ref, obj_model, gains, state, ids, mu):
        return transport_control(obs, ref, obj_model, gains, state, ids, self.cfg, mu)

    def record(self, sim, d, obs, ref, tau, diag, rel0, obj_model, metrics, plan) -> Record:
        """The paper's control-rate sample (trunk height, slip and lift on the tray, tracking error, torque ratio,
        QP diagnostics) and the log row, from the sensed state ``d`` at time t."""
        ids, dyn = sim.robot.ids, obs.robot
        rel = object_in_tray(d, ids)
        slip = jnp.linalg.norm(rel[:2] - rel0[:2])
        p_obj = d.xpos[ids.obj_body]
        sample = ControlSample(trunk_z=dyn.p_base[2], slip=slip, lift=rel[2] - rel0[2],
                               tau_ratio=jnp.max(jnp.abs(tau) / jnp.asarray(ids.tau_max)),
                               track_err=jnp.linalg.norm(ref.p_obj - p_obj), qp=diag, obj_mu=obj_model.mu)
        log = Log(t=d.time, p_obj=p_obj, p_obj_ref=ref.p_obj, com=dyn.com, com_ref=ref.p_com, slip=slip,
                  trunk_z=dyn.p_base[2], prim_res=diag.prim_res, tau=tau, qpos=d.qpos)
        return Record(sample, metrics, log)

    def empty_log(self, d, nu: int) -> Log:
        """A Log of zeros shaped like one run's (``d``: that run's mjx.Data; ``nu``: actuators)."""
        z, z3 = jnp.zeros_like(d.time), jnp.zeros(3, d.qpos.dtype)
        return Log(t=z, p_obj=z3, p_obj_ref=z3, com=z3, com_ref=z3, slip=z, trunk_z=z, prim_res=z,
                   tau=jnp.zeros(nu, d.qpos.dtype), qpos=jnp.zeros_like(d.qpos))

    def failed(self, acc, course: bool):
        return paper.run_failed(acc, course)

    def final_input(self, logs):
        """(B, 3) the object's goal: the reference's last logged point [m]."""
        return logs.p_obj_ref[:, -1]

    def finalize(self, sim, acc, state, p_goal, mu, n, course: bool) -> dict:
        """:func:`wbc_jax.metrics.paper.finalize` of a batch's final ``state`` (``acc``: its Accum on the host,
        first ``n`` runs), ``p_goal`` (B, 3) the object's goal [m], ``mu`` (n or B,) tray friction."""
        p_obj = np.asarray(state.d.xpos)[:, sim.robot.ids.obj_body]
        p_goal = np.asarray(p_goal)
        if n is not None:
            p_obj, p_goal = p_obj[:n], p_goal[:n]
        return paper.finalize(acc, sim.dt_control, mu, course=course,
                              final_err=np.linalg.norm(p_obj - p_goal, axis=1), substeps=sim.n_substeps)
