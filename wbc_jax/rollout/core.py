"""Batched closed-loop rollout: MJX physics + transport WBC, lax.scan over time, vmap over runs.

One control step (period ``Sim.dt_control`` = ``Sim.n_substeps`` physics steps of ``Sim.dt_physics``):
:func:`wbc_jax.physics.backend.sense` (kinematics, M, bias) -> planner reference -> QP build -> ADMM (warm-started) ->
torques -> :func:`physics_period`: :func:`wbc_jax.physics.backend.finish` (rest of the forward pass + integration), then
``n_substeps - 1`` further ``mjx.step`` calls with the torques (and any push force) held, as a ``lax.scan``.

Monitors run at two rates. *Physics rate* (after every physics step, :func:`substep_monitors`): the paper's
integrands 1/H and ||object acceleration|| (``wbc_jax.metrics.paper``, dt = the physics step), non-foot/floor and wall
contact, object off the tray; so a contact or an acceleration spike inside a control period is not missed and
the integrals do not depend on the control period. *Control rate* (from the sensed state, once per control
step): trunk height, slip and lift on the tray, tracking error, torque ratios, QP residuals and flags, and the
log. Long runs are executed in chunks (one jit call per chunk) so progress can be shown and finished chunks
kept. Per-step quantities are reduced online (max, min, sums; :class:`Accum`) and logged once every
``log_every`` control steps.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.transport import (
    ControlState,
    TransportConfig,
    TransportGains,
    init_control_state,
    transport_control,
)
from wbc_jax.control.variants import Variant
from wbc_jax.metrics import paper as metrics
from wbc_jax.physics import backend as physics
from wbc_jax.physics import contacts
from wbc_jax.physics.contacts import CONTACT_DIST, contact_slots  # noqa: F401  (re-exported: tests, trot study)
from wbc_jax.physics.observe import dyn_terms, observe
from wbc_jax.planner.transport import TransportPlan, reference
from wbc_jax.robot.model import Robot, mjx
from wbc_jax.rollout.packed import Packed, pack, placed_like
from wbc_jax.types import ObjectModel


class Push(NamedTuple):
    """Per-run disturbances: an external force on the trunk and noise on the state the controller sees.

    Attributes:
        force: (3,) world-frame force on the trunk [N], applied for t in [t0, t0 + duration).
        t0, duration: () [s].
        qvel_noise_std: () std of white Gaussian noise added, every control step, to every generalized velocity
            the controller reads (robot and object; [m/s] for translations, [rad/s] for rotations). The physics
            integrates the true state; only the controller's view (its Jacobian-dot terms, CoM and foot
            velocities, observer momentum, object velocity) is noisy. Used only when ``Sim.sensor_noise``.
        key: (2,) uint32 raw PRNG key of the run's noise; step k draws from ``fold_in(key, k)``.
    """

    force: jax.Array
    t0: jax.Array
    duration: jax.Array
    qvel_noise_std: jax.Array
    key: jax.Array


def make_push(force, t0, duration, qvel_noise_std=0.0, seed=0) -> Push:
    """A Push from plain values (one run; or arrays with a leading run axis: ``seed`` (B,) then gives (B, 2) keys)."""
    seed = np.asarray(seed, dtype=np.uint64)
    key = np.stack([np.zeros_like(seed), seed], axis=-1).astype(np.uint32)
    return Push(jnp.asarray(force, dtype=float), jnp.asarray(t0, dtype=float), jnp.asarray(duration, dtype=float),
                jnp.asarray(qvel_noise_std, dtype=float), jnp.asarray(key))


def no_push() -> Push:
    return make_push(np.zeros(3), 0.0, 0.0)


class Accum(NamedTuple):
    """Online reductions since the start of the run (per run). Fields marked (physics rate) are updated after
    every physics step (:func:`substep_monitors`), the others once per control step. Carried in ``RunState.acc``
    packed into two arrays (:mod:`wbc_jax.rollout.packed`), which reads like this NamedTuple (``acc.max_slip``)."""

    min_trunk_z: jax.Array  # [m]
    max_slip: jax.Array  # [m] object displacement on the tray, tray frame, xy
    max_lift: jax.Array  # [m] object bottom above the tray surface
    nonfoot_floor: jax.Array  # bool, a non-foot robot part touched the floor (physics rate)
    wall_contact: jax.Array  # bool (physics rate)
    max_tau_ratio: jax.Array  # max |tau| / limit of the applied torques
    max_tau_excess: jax.Array  # [N m] largest unclipped-torque excess over the limit
    sum_prim_res: jax.Array
    n_flag: jax.Array  # steps whose QP was flagged
    sum_qp_iters: jax.Array  # int32, ADMM iterations over the control steps (QPSettings.max_iters: varies per step)
    max_qp_iters: jax.Array  # int32, most iterations one control step took
    n_steps: jax.Array  # int32, control steps
    sum_track: jax.Array  # integral of ||p_obj,ref - p_obj|| [m s]
    nonfinite: jax.Array  # bool (physics rate)
    off_steps: jax.Array  # int32, consecutive physics steps (up to now) with the object touching nothing on the tray
    max_off_s: jax.Array  # [s] longest such spell (physics steps x dt_physics)
    sum_invH: jax.Array  # integral of 1/H (the paper's robustness integrand, wbc_jax.metrics.paper) [rad^2 s] (physics rate)
    sum_acc: jax.Array  # integral of ||object CoM linear acceleration|| [m/s] (physics rate)
    n_boundary: jax.Array  # int32, physics steps with 1/H = 0 (a contact unloaded or on/outside its cone)
    first_contact_t: jax.Array  # [s] start of the physics step whose contacts first had a non-foot robot part
    #                             penetrating the floor or terrain; NaN if none yet (physics rate)
    first_contact_k: jax.Array  # int32, index into Sim.nonfoot_slots of that step's deepest such contact; -1 if none
    overflow: jax.Array  # bool, a physics step's contacts or constraint rows may not all have fit (Warp's capacity,
    #                      wbc_jax.physics.backend.overflow; the run is failed) (physics rate)
    t_end: jax.Array  # [s] end of the run's metric window [0, t_end) (input, not a reduction: :func:`with_metric_window`;
    #                   +inf: the whole simulation). sum_invH, sum_acc, n_boundary, sum_track and n_win count only
    #                   the control periods whose midpoint lies in the window; the flags and extremes count all
    n_win: jax.Array  # int32, control steps inside the metric window (the duration of R, T, S)
    min_clear: jax.Array  # [m] smallest signed distance of a non-foot robot geom to the floor, terrain or a wall
    #                       over the run (:func:`clearance`, exact geometry; +inf: no such pair) (physics rate)
    min_clear_t: jax.Array  # [s] start of the physics step of min_clear (the contacts' time); NaN if none
    min_clear_k: jax.Array  # int32, its pair: index into wbc_jax.physics.clearance.clearance_pairs(robot)
    #                         (:func:`clearance_name`); -1 if none
    n_boundary_cone: jax.Array  # int32, the part of n_boundary with every contact loaded and a force on/outside
    #                             the circular cone (physics rate)
    sum_invH_plan: jax.Array  # integral of 1/H of the QP's planned object forces [rad^2 s] (control rate,
    #                           :func:`wbc_jax.metrics.paper.planned_inv_H`)
    n_boundary_plan: jax.Array  # int32, control steps with that 1/H = 0 (the boundary rule)
    n_boundary_plan_cone: jax.Array  # int32, the part of n_boundary_plan with a loaded planned force on/outside the cone
    n_solver_cap: jax.Array  # int32, physics steps whose constraint solve stopped at opt.iterations, not at its
    #                          tolerance (wbc_jax.physics.backend.solver_capped) (physics rate)


class RunState(NamedTuple):
    """Carried state of one run: MJX data, controller memory, swing bookkeeping, accumulators."""

    d: mjx.Data
    cs: ControlState
    p_lift: jax.Array  # (4, 3)
    rel0: jax.Array  # (3,) object position in the tray frame at t = 0
    acc: Packed  # the Accum, packed (wbc_jax.rollout.packed: reads like it, e.g. acc.max_slip; acc.unpack() is the Accum)
    prev: Any = None  # Sim.sensing "delayed": (qpos (nq,), qvel (nv,), time ()) of the state d's derived fields
    #                   (kinematics, M, contacts, sensors) belong to, the start of the last physics step; else None


def state_axes(sim: "Sim", state: RunState) -> RunState:
    """The run axes of a batched RunState: 0 on every leaf but the Warp data's shared contact list (None:
    :func:`wbc_jax.physics.backend.data_axes`). The ``in_axes`` of the state in ``vmap``, sharding and row selection
    (``wbc_jax.rollout.runs``)."""
    zeros = jax.tree_util.tree_map(lambda _: 0, state)
    return zeros._replace(d=physics.data_axes(sim.robot, state.d))


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


def empty_log(d, nu: int) -> Log:
    """A Log of zeros shaped like one run's (``d``: that run's mjx.Data; ``nu``: actuators): the inner loop's
    initial carry, which the first control step overwrites."""
    z, z3 = jnp.zeros_like(d.time), jnp.zeros(3, d.qpos.dtype)
    return Log(t=z, p_obj=z3, p_obj_ref=z3, com=z3, com_ref=z3, slip=z, trunk_z=z, prim_res=z,
               tau=jnp.zeros(nu, d.qpos.dtype), qpos=jnp.zeros_like(d.qpos))


SENSING = ("auto", "exact", "delayed")
"""What the controller reads on the Warp backend (:func:`resolve_sensing`; "auto": "delayed" on Warp with one
physics step per control step, else "exact"). "exact": a ``forward`` call (Warp) computes the kinematics, mass
matrix, bias forces, contacts and sensors of the current state before the controller acts (two Warp calls per
control step). "delayed": no such call; the controller reads the fields Warp's ``step`` left, which belong to the
state at the start of that step, so the controller sees the state one physics step (1 ms) old and its torques act
on the current one; control-rate metrics and the log are taken at that (consistent) older state; with sensor noise,
the noise reaches the velocities the controller reads but not its bias forces (computed by the step with the true
velocities). Measured on the course: docs/performance.md."""


def resolve_sensing(sensing: str, backend: str, n_substeps: int = 1) -> str:
    """``sensing`` (:data:`SENSING`) for a resolved physics ``backend``: "auto" -> "delayed" on Warp with one
    physics step per control step (H100, paper campaign: the same outcome and statistics, 103.0 s vs 125.2 s),
    else "exact". Raises ValueError for an unknown value or "delayed" where it saves nothing."""
    if sensing not in SENSING:
        raise ValueError(f"sensing = {sensing!r}: expected one of {', '.join(SENSING)}")
    if sensing == "auto":
        return "delayed" if backend == "warp" and n_substeps == 1 else "exact"
    if sensing == "delayed" and (backend != "warp" or n_substeps != 1):
        raise ValueError(f"sensing = 'delayed' needs the Warp backend and one physics step per control step (got "
                         f"backend {backend!r}, {n_substeps} substeps): it drops Warp's forward call, which the "
                         f"JAX backend does not make")
    return sensing


@dataclass(frozen=True)
class Sim:
    """Static rollout structure: the robot, controller config, physics substeps and contact indices.

    The ``*_slots`` fields index MJX contact slots on the JAX backend and contact-sensor addresses in ``sensordata``
    on Warp (``wbc_jax.physics.contacts``, whose readers take the Sim); ``nonfoot_geoms`` names each non-foot entry.
    """

    robot: Robot
    cfg: TransportConfig
    n_substeps: int
    log_every: int
    nonfoot_slots: np.ndarray
    nonfoot_geoms: np.ndarray  # (len(nonfoot_slots), 2) geom ids of each non-foot slot's pair (robot part, ground)
    wall_slots: np.ndarray
    foot_slots: np.ndarray
    obj_slots: np.ndarray
    sensor_noise: bool = False  # the controller sees qvel + noise (Push.qvel_noise_std); costs a velocity pass
    sensing: str = "exact"  # "exact" (Warp: a forward call for the controller) or "delayed" (:data:`SENSING`)

    @property
    def dt_control(self) -> float:
        """Control period [s] (= n_substeps x dt_physics)."""
        return self.cfg.dt

    @property
    def dt_physics(self) -> float:
        """Physics timestep [s] (the model's ``opt.timestep``)."""
        return float(self.robot.mj_model.opt.timestep)


def make_sim(robot: Robot, cfg: TransportConfig | None = None, n_substeps: int = 1, log_every: int = 20,
             sensor_noise: bool = False, sensing: str = "exact") -> Sim:
    """The Sim of ``robot``. ``cfg.dt`` (the controller's period) must equal ``n_substeps`` x the model's
    timestep; ``cfg`` None: default controller settings with that period. ``sensing``: :data:`SENSING`
    (:func:`resolve_sensing`)."""
    h = float(robot.mj_model.opt.timestep)
    n_substeps = int(n_substeps)
    if n_substeps < 1:
        raise ValueError(f"n_substeps = {n_substeps}: expected >= 1")
    sensing = resolve_sensing(sensing, robot.backend, n_substeps)
    cfg = cfg or TransportConfig(dt=h * n_substeps)
    if abs(cfg.dt - h * n_substeps) > 1e-9 * h:
        raise ValueError(f"control period cfg.dt = {cfg.dt} s != n_substeps ({n_substeps}) x the model's timestep "
                         f"({h} s)")
    nf, wl, ft, ob, nfg = contacts.sim_indices(robot)
    return Sim(robot=robot, cfg=cfg, n_substeps=n_substeps, log_every=log_every, nonfoot_slots=nf, nonfoot_geoms=nfg,
               wall_slots=wl, foot_slots=ft, obj_slots=ob, sensor_noise=sensor_noise, sensing=sensing)


def seen_qvel(sim: Sim, d, push: Push, step):
    """The generalized velocities the controller sees: None (the true ones) or (``sim.sensor_noise``) ``d.qvel``
    plus the run's white noise of control step ``step``."""
    if not sim.sensor_noise:
        return None
    key = jax.random.fold_in(push.key, step)
    return d.qvel + push.qvel_noise_std * jax.random.normal(key, d.qvel.shape, d.qvel.dtype)


def _tray_rel(d, ids):
    R = d.site_xmat[ids.tray_site]
    return R.T @ (d.xpos[ids.obj_body] - d.site_xpos[ids.tray_site])


def init_state(sim: Sim, m, qpos0, qvel0=None, n_runs: int = 1) -> RunState:
    """Initial RunState of one run (vmappable over m, qpos0 and qvel0; qvel0 None: at rest). ``n_runs``: the size
    of the batch it is vmapped over (sizes the Warp backend's shared contact list)."""
    ids = sim.robot.ids
    d = physics.make_data(sim.robot, n_runs).replace(qpos=qpos0)
    if qvel0 is not None:
        d = d.replace(qvel=qvel0)
    d = physics.sense(m, d)
    dyn = dyn_terms(m, d, ids)
    z = jnp.zeros(())
    acc = Accum(min_trunk_z=dyn.p_base[2], max_slip=z, max_lift=z, nonfoot_floor=jnp.bool_(False),
                wall_contact=jnp.bool_(False), max_tau_ratio=z, max_tau_excess=jnp.full((), -jnp.inf, z.dtype), sum_prim_res=z,
                n_flag=jnp.zeros((), jnp.int32), sum_qp_iters=jnp.zeros((), jnp.int32),
                max_qp_iters=jnp.zeros((), jnp.int32), n_steps=jnp.zeros((), jnp.int32), sum_track=z,
                nonfinite=jnp.bool_(False), off_steps=jnp.zeros((), jnp.int32), max_off_s=z,
                sum_invH=z, sum_acc=z, n_boundary=jnp.zeros((), jnp.int32), first_contact_t=jnp.full((), jnp.nan, z.dtype),
                first_contact_k=jnp.full((), -1, jnp.int32), overflow=jnp.bool_(False),
                t_end=jnp.full((), jnp.inf, z.dtype), n_win=jnp.zeros((), jnp.int32),
                min_clear=jnp.full((), jnp.inf, z.dtype), min_clear_t=jnp.full((), jnp.nan, z.dtype),
                min_clear_k=jnp.full((), -1, jnp.int32), n_boundary_cone=jnp.zeros((), jnp.int32), sum_invH_plan=z,
                n_boundary_plan=jnp.zeros((), jnp.int32), n_boundary_plan_cone=jnp.zeros((), jnp.int32),
                n_solver_cap=jnp.zeros((), jnp.int32))
    prev = (d.qpos, d.qvel, d.time) if sim.sensing == "delayed" else None
    return RunState(d=d, cs=init_control_state(sim.cfg, dyn, ids), p_lift=dyn.p_foot, rel0=_tray_rel(d, ids),
                    acc=pack(acc), prev=prev)


def controller_inputs(sim: Sim, m, rs: RunState, plan: TransportPlan, push: Push, mu_ground):
    """What one control step computes before the controller: the sensed state, the controller's observation of it
    (with the run's velocity noise) and the reference (with foot contacts from the simulator).

    Returns:
        (d sensed mjx.Data, the controller's Observation, Reference, (4,) the friction
        coefficient of each foot's pyramid: that of the ground surface the foot is nearest to (floor or a block),
        capped by the run's ``mu_ground`` (the scene's floor friction, or the campaign's ``ground_mu``, which the
        physics then also uses for every foot pair)).
    """
    with jax.named_scope("sense"):
        if sim.sensing == "delayed":  # the state the derived fields belong to: no physics call
            d = rs.d.replace(qpos=rs.prev[0], qvel=rs.prev[1], time=rs.prev[2])
            qvel_seen = seen_qvel(sim, d, push, rs.acc.n_steps)
            d_ctl = d if qvel_seen is None else d.replace(qvel=qvel_seen)
        else:
            d, d_ctl = physics.sense_with_view(m, rs.d, seen_qvel(sim, rs.d, push, rs.acc.n_steps))
    with jax.named_scope("dynamics_reference"):
        obs = observe(m, d_ctl, sim.robot.ids)
        dist, mu_feet = contacts.foot_ground(sim, m, d)  # (4,), (4,)
        ref = reference(plan, d.time, rs.p_lift, dist < CONTACT_DIST, obs.robot.p_foot)
    return d, obs, ref, jnp.minimum(mu_ground, mu_feet)


class SubstepMonitors(NamedTuple):
    """Physics-rate monitor values of one physics step of one run (each a scalar), from the data before and after
    the step. Contacts and constraint forces are those of the step's start (``wbc_jax.physics.backend`` docstring)."""

    inv_h: jax.Array  # 1/H of the simulator's forces on the object's contact slots [rad^2]; 0 if not finite
    cone: jax.Array  # bool, those forces all loaded and one on/outside the circular cone (boundary rule, 2nd case)
    acc: jax.Array  # ||object CoM linear acceleration|| over the step, (v_after - v_before) / dt_physics [m/s^2]
    nonfoot_floor: jax.Array  # bool, a non-foot robot part penetrates the floor or terrain (dist < 0)
    nonfoot_k: jax.Array  # int32, index into Sim.nonfoot_slots of the deepest such contact (-1: none)
    t: jax.Array  # [s] time at the step's start (the contacts' time)
    wall: jax.Array  # bool, anything penetrates a wall (dist < 0)
    off: jax.Array  # bool, every object contact sphere farther than CONTACT_DIST from the tray
    finite: jax.Array  # bool, positions after the step and the held torques are finite
    overflow: jax.Array  # bool, the step's contacts or constraint rows may not all have fit (Warp)
    solver_cap: jax.Array  # bool, the step's constraint solve stopped at opt.iterations
    clear: jax.Array  # [m] :func:`clearance` after the step (+inf: no such pair)
    clear_k: jax.Array  # int32, its pair (Accum.min_clear_k numbering; -1: none)


def substep_monitors(sim: Sim, m, om: ObjectModel, tau, d, d_after) -> SubstepMonitors:
    """Monitor values of the physics step ``d`` -> ``d_after`` taken with torques ``tau`` (nu,) [N m]."""
    finite = jnp.all(jnp.isfinite(d_after.qpos)) & jnp.all(jnp.isfinite(tau))
    if sim.obj_slots.size:  # paper metrics: forces of this step's constraint solve, object acceleration
        oa = sim.robot.ids.obj_dof_adr
        f_obj, obj_dist = contacts.object_contacts(sim, m, d_after)
        inv_h, acc_norm = metrics.step_integrands(f_obj, om.mu, d.qvel[oa:oa + 3], d_after.qvel[oa:oa + 3],
                                                  sim.dt_physics)
        inv_h, acc_norm = jnp.where(finite, inv_h, 0.0), jnp.where(finite, acc_norm, 0.0)
        cone = finite & metrics.at_cone(*metrics.cone_angle(f_obj), om.mu)
        off = jnp.all(obj_dist > CONTACT_DIST)
    else:
        inv_h = acc_norm = jnp.zeros(())
        off = cone = jnp.bool_(False)
    wall_d = contacts.wall_dist(sim, d_after) if sim.wall_slots.size else None
    nf_dist = contacts.nonfoot_dist(sim, d_after) if sim.nonfoot_slots.size else None
    wall = jnp.any(wall_d < 0.0) if wall_d is not None else jnp.bool_(False)
    if nf_dist is not None:
        nonfoot = jnp.any(nf_dist < 0.0)
        nonfoot_k = jnp.where(nonfoot, jnp.argmin(nf_dist), -1).astype(jnp.int32)
    else:
        nonfoot, nonfoot_k = jnp.bool_(False), jnp.full((), -1, jnp.int32)
    clear, clear_k = clearance(sim, d_after)
    return SubstepMonitors(inv_h=inv_h, cone=cone, acc=acc_norm, nonfoot_floor=nonfoot, nonfoot_k=nonfoot_k, t=d.time,
                           wall=wall, off=off, finite=finite, overflow=physics.overflow(d_after),
                           solver_cap=physics.solver_capped(m, d_after), clear=clear, clear_k=clear_k)


def clearance(sim: Sim, d):
    """Smallest signed distance [m] between a non-foot robot geom and the floor, the terrain blocks or a wall, and
    its pair, at the geom poses of ``d`` (after a physics step: those of the step's start, like its contacts).

    Exact geometry (:mod:`wbc_jax.physics.clearance`), not the contact slots: every robot geom (not a foot, not the
    object) that the scene pairs with the floor or terrain against the floor and every block, and every robot geom
    it pairs with a wall part against every wall part (:func:`wbc_jax.physics.clearance.clearance_pairs`).
    Capsule/plane, box/plane, capsule/box and box/box distances are exact when positive (MuJoCo C's
    ``mj_geomDistance``); a penetration is the depth of the robot geom's deepest point (capsule/box: of its
    segment, minus the radius; box/box: the separating-axis depth), which may differ from MuJoCo's contact depth.
    The same on both backends (it reads ``d.geom_xpos`` and ``d.geom_xmat`` only).

    Returns:
        (() distance [m], +inf when the scene has no such pair; () int32 pair: index into
        ``clearance_pairs(sim.robot)`` (:func:`clearance_name`); -1 when the distance is not finite).
    """
    from wbc_jax.physics import clearance as _clearance

    return _clearance.min_clearance(_clearance.clearance_pairs(sim.robot), d)


def physics_substep(sim: Sim, m, om: ObjectModel, tau, d):
    """One held-torque physics step (``mjx.step``, ``d.ctrl`` = ``tau``) -> (data after, its SubstepMonitors)."""
    d_after = mjx.step(m, d)
    return d_after, substep_monitors(sim, m, om, tau, d, d_after)


def in_window(sim: Sim, a: Accum) -> jax.Array:
    """() bool: the control period now starting (index ``a.n_steps``) counts in the metric window: its midpoint
    (n_steps + 1/2) x dt_control is before ``a.t_end`` (from the step counter, not the float time, so no drift)."""
    return (a.n_steps.astype(a.t_end.dtype) + 0.5) * sim.dt_control < a.t_end


def _like(old, value):
    """``value`` broadcast to the shape and dtype of the leaf ``old`` and placed like it (a leaf committed
    elsewhere would change the chunk function's input shardings)."""
    return placed_like(old, np.array(np.broadcast_to(np.asarray(value, old.dtype), old.shape)))


def with_metric_window(state: RunState, t_end) -> RunState:
    """``state`` (batched or not) with its metric window set to [0, ``t_end``) [s] (scalar or (B,) per run)."""
    return state._replace(acc=state.acc._replace(t_end=t_end))


def with_variant(state: RunState, variant: Variant) -> RunState:
    """``state`` (batched or not) with the controller's ablation switches set (:mod:`wbc_jax.control.variants`;
    each field 0/1, scalar or (B,) per run)."""
    cs = state.cs
    return state._replace(cs=cs._replace(variant=Variant(*(_like(o, v) for o, v in zip(cs.variant, variant)))))


def _fold(sim: Sim, a: Accum, s: SubstepMonitors, w) -> Accum:
    """Accum with one physics step's monitors added (integrals: value x dt_physics, only while ``w`` (the period
    is in the metric window); flags OR'ed and extremes over every step)."""
    h = sim.dt_physics
    off_steps = jnp.where(s.off, a.off_steps + 1, 0)
    first = s.nonfoot_floor & ~a.nonfoot_floor
    closer = s.clear < a.min_clear
    return a._replace(
        min_clear=jnp.where(closer, s.clear, a.min_clear),
        min_clear_t=jnp.where(closer, s.t, a.min_clear_t),
        min_clear_k=jnp.where(closer, s.clear_k, a.min_clear_k),
        nonfoot_floor=a.nonfoot_floor | s.nonfoot_floor,
        first_contact_t=jnp.where(first, s.t, a.first_contact_t),
        first_contact_k=jnp.where(first, s.nonfoot_k, a.first_contact_k),
        wall_contact=a.wall_contact | s.wall,
        nonfinite=a.nonfinite | ~s.finite,
        overflow=a.overflow | s.overflow,
        n_solver_cap=a.n_solver_cap + s.solver_cap.astype(jnp.int32),
        off_steps=off_steps,
        max_off_s=jnp.maximum(a.max_off_s, off_steps * h),
        sum_invH=a.sum_invH + jnp.where(w, s.inv_h * h, 0.0),
        sum_acc=a.sum_acc + jnp.where(w, s.acc * h, 0.0),
        n_boundary=a.n_boundary + (w & (s.inv_h <= 0.0)).astype(jnp.int32),
        n_boundary_cone=a.n_boundary_cone + (w & (s.inv_h <= 0.0) & s.cone).astype(jnp.int32),
    )


def physics_period(sim: Sim, m, om: ObjectModel, d, tau, acc: Accum):
    """The physics of one control period with its physics-rate monitors.

    :func:`wbc_jax.physics.backend.finish` on the sensed ``d``, then ``sim.n_substeps - 1`` :func:`physics_substep`
    calls in a ``lax.scan`` (torques and ``d.xfrc_applied`` held); :func:`substep_monitors` of every step folded
    into ``acc``.

    Args:
        d: sensed mjx.Data (``wbc_jax.physics.backend.sense``) with the period's ``xfrc_applied``; tau: (nu,) [N m];
        acc: the run's Accum before the period.

    Returns:
        (mjx.Data n_substeps physics steps later, Accum with the physics-rate fields updated, () bool: every step
        of the period finite).
    """
    d1 = physics.finish(m, d, tau)
    s = substep_monitors(sim, m, om, tau, d, d1)
    w = in_window(sim, acc)  # the whole period is in the window or out of it
    carry = (d1, _fold(sim, acc, s, w), s.finite)
    if sim.n_substeps > 1:
        def body(carry, _):
            d, a, finite = carry
            d, s = physics_substep(sim, m, om, tau, d)
            return (d, _fold(sim, a, s, w), finite & s.finite), None

        carry = jax.lax.scan(body, carry, None, length=sim.n_substeps - 1)[0]
    return carry


def control_step(sim: Sim, m, rs: RunState, plan: TransportPlan, om: ObjectModel, gains: TransportGains,
                 push: Push, mu_ground):
    """One control period of one run. Returns (new RunState, per-step values for the log)."""
    ids = sim.robot.ids
    d, obs, ref, mu = controller_inputs(sim, m, rs, plan, push, mu_ground)
    dyn = obs.robot
    t = d.time
    tau, cs, qd = transport_control(obs, ref, om, gains, rs.cs, ids, sim.cfg, mu)
    d_phys = rs.d if sim.sensing == "delayed" else d  # delayed: d is one physics step old, the torques act now
    on = (d_phys.time >= push.t0) & (d_phys.time < push.t0 + push.duration)
    xfrc = jnp.zeros_like(d.xfrc_applied).at[ids.trunk_body, 0:3].set(jnp.where(on, push.force, 0.0))
    with jax.named_scope("physics"):
        d_next, a, finite = physics_period(sim, m, om, d_phys.replace(xfrc_applied=xfrc), tau, rs.acc.unpack())
    p_lift = jnp.where(ref.swing[:, None], rs.p_lift, dyn.p_foot)

    # control-rate metrics (from the sensed state d at time t)
    rel = _tray_rel(d, ids)
    slip = jnp.linalg.norm(rel[:2] - rs.rel0[:2])
    lift = rel[2] - rs.rel0[2]
    p_obj = d.xpos[ids.obj_body]
    w = in_window(sim, a)  # a.n_steps is still this period's index
    inv_h_plan, cone_plan = metrics.planned_inv_H(qd.obj_forces, om.mu)  # the QP's planned forces
    acc = a._replace(
        min_trunk_z=jnp.minimum(a.min_trunk_z, dyn.p_base[2]),
        max_slip=jnp.maximum(a.max_slip, slip),
        max_lift=jnp.maximum(a.max_lift, lift),
        max_tau_ratio=jnp.maximum(a.max_tau_ratio, jnp.max(jnp.abs(tau) / jnp.asarray(ids.tau_max))),
        max_tau_excess=jnp.maximum(a.max_tau_excess, qd.tau_excess),
        sum_prim_res=a.sum_prim_res + qd.prim_res,
        n_flag=a.n_flag + (qd.flag != 0).astype(jnp.int32),
        sum_qp_iters=a.sum_qp_iters + qd.iters,
        max_qp_iters=jnp.maximum(a.max_qp_iters, qd.iters),
        n_steps=a.n_steps + 1,
        n_win=a.n_win + w.astype(jnp.int32),
        sum_track=a.sum_track + jnp.where(w, jnp.linalg.norm(ref.p_obj - p_obj) * sim.dt_control, 0.0),
        sum_invH_plan=a.sum_invH_plan + jnp.where(w, inv_h_plan * sim.dt_control, 0.0),
        n_boundary_plan=a.n_boundary_plan + (w & (inv_h_plan <= 0.0)).astype(jnp.int32),
        n_boundary_plan_cone=a.n_boundary_plan_cone + (w & (inv_h_plan <= 0.0) & cone_plan).astype(jnp.int32),
    )
    # a run that went non-finite is frozen (its state no longer advances) so it cannot poison others
    d_next = physics.freeze(finite, d_next, rs.d)
    # delayed: d_next's derived fields belong to the state the step started from (a frozen run's too: it keeps that
    # state)
    prev = (d_phys.qpos, d_phys.qvel, d_phys.time) if sim.sensing == "delayed" else None
    log = Log(t=t, p_obj=p_obj, p_obj_ref=ref.p_obj, com=dyn.com, com_ref=ref.p_com, slip=slip,
              trunk_z=dyn.p_base[2], prim_res=qd.prim_res, tau=tau, qpos=d.qpos)
    return RunState(d=d_next, cs=cs, p_lift=p_lift, rel0=rs.rel0, acc=pack(acc, rs.acc.layout), prev=prev), log


def final_results(sim: Sim, state: RunState, p_goal, mu, n: int | None = None) -> dict[str, np.ndarray]:
    """:func:`wbc_jax.metrics.paper.finalize` of a batch's final state.

    Args:
        state: batched RunState at the end of the runs; p_goal: (B, 3) the object's goal position [m] (the
            reference's last point); mu: (n or B,) tray friction of each run.
        n: keep the first n runs (drops the padding of a sharded batch); None: all.
    """
    from wbc_jax.planner.scene_geometry import scene_geometry

    acc = jax.device_get(state.acc)
    p_obj = np.asarray(state.d.xpos[:, sim.robot.ids.obj_body])
    p_goal = np.asarray(p_goal)
    if n is not None:
        acc = jax.tree_util.tree_map(lambda x: np.asarray(x)[:n], acc)
        p_obj, p_goal = p_obj[:n], p_goal[:n]
    out = metrics.finalize(acc, sim.dt_control, mu, course=scene_geometry(sim.robot).is_course,
                           final_err=np.linalg.norm(p_obj - p_goal, axis=1), substeps=sim.n_substeps)
    if not physics.reports_solver_cap(sim.robot):  # MJX's JAX solver does not report its iteration count
        out["solver_cap_fraction"] = np.full(len(out["success"]), np.nan)
    out["first_contact_s"] = np.asarray(acc.first_contact_t, float)
    out["first_contact"] = np.array([contact_name(sim, k) for k in np.asarray(acc.first_contact_k)], dtype=object)
    out["min_clearance_pair"] = np.array([clearance_name(sim, k) for k in np.asarray(acc.min_clear_k)], dtype=object)
    return out


def _pair_name(sim: Sim, g1, g2) -> str:
    """``"robot geom (body B) / scene geom"``: the geom not on the world body (floor, blocks, walls) first."""
    m = sim.robot.mj_model

    def name(g):
        return m.geom(int(g)).name or f"geom{int(g)}"

    robot_g, env_g = (g1, g2) if int(m.geom_bodyid[g1]) != 0 else (g2, g1)
    return f"{name(robot_g)} (body {m.body(int(m.geom_bodyid[robot_g])).name}) / {name(env_g)}"


def clearance_name(sim: Sim, k: int) -> str:
    """Readable pair of clearance index ``k`` (Accum.min_clear_k, an index into
    ``wbc_jax.physics.clearance.clearance_pairs(sim.robot)``; -1: ""), e.g. ``"FL_shank (body FL_calf) / block3"``."""
    if k < 0:
        return ""
    from wbc_jax.physics.clearance import clearance_pairs

    p = clearance_pairs(sim.robot)
    return _pair_name(sim, p.robot[int(k)], p.env[int(k)])


def contact_name(sim: Sim, k: int) -> str:
    """Readable pair of non-foot slot ``k`` (index into ``sim.nonfoot_slots``; -1: "" ), e.g.
    ``"BR_shank (body BR_calf) / block3"``: the robot geom with its body, then the floor or terrain geom."""
    if k < 0:
        return ""
    g1, g2 = sim.nonfoot_geoms[int(k)]
    return _pair_name(sim, g1, g2)


def make_chunk_fn(sim: Sim, n_logs: int, model_axes):
    """One chunk of every run: ``n_logs`` x ``log_every`` control steps, the runs batched inside each step.

    Returns f(batched model, state, plan, om, gains, push, mu_ground) -> (state, Log with axes (run, log)), for
    ``jax.jit``; every argument after the model has the runs on its axis 0, the model on ``model_axes``
    (``Batch.in_axes``).

    The step is vmapped inside the scans (``scan(vmap(step))``), not the scans over one run's step
    (``vmap(scan(step))``). With vmap outside, JAX traces the step into a jaxpr and then runs that jaxpr again
    under the scans' batching rules; here the step is traced once, batched. Measured on the CPU (course scene, JAX
    physics, 2 runs; the two forms alternated twice, caches cleared): tracing 7.01 / 6.60 s before, 5.33 / 5.17 s
    now; the compiled programs have the same op counts (36,440 ops, 852 copies, 1,562 fusions) and the outputs are
    equal bit for bit (flat scene).
    """
    nu = sim.robot.mj_model.nu
    step = jax.vmap(functools.partial(control_step, sim), in_axes=(model_axes, 0, 0, 0, 0, 0, 0))

    def chunk(m, rs, plan, om, gains, push, mu_ground):
        # the log of the period's last step rides in the carry (overwritten every step) rather than as the inner
        # scan's stacked output, of which only the last row was kept
        log0 = jax.vmap(lambda d: empty_log(d, nu))(rs.d)

        def inner(carry, _):
            return step(m, carry[0], plan, om, gains, push, mu_ground), None

        def outer(rs, _):
            return jax.lax.scan(inner, (rs, log0), None, length=sim.log_every)[0]

        rs, logs = jax.lax.scan(outer, rs, None, length=n_logs)
        return rs, jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), logs)  # (log, run) -> (run, log)

    return chunk


_CHUNK_FNS: dict = {}


def simulate(sim: Sim, bmodel, in_axes, state: RunState, plan, om, gains, push, mu_ground, seconds: float,
             chunk_seconds: float = 2.0, progress=None):
    """Run ``seconds`` of simulated time in chunks; returns (final state, Log with time axis 1)."""
    steps_per_log = sim.log_every
    dt = sim.dt_control
    logs_per_chunk = max(1, int(round(chunk_seconds / (dt * steps_per_log))))
    n_logs_total = int(np.ceil(seconds / (dt * steps_per_log)))
    out_logs = []
    done = 0
    while done < n_logs_total:
        n = min(logs_per_chunk, n_logs_total - done)
        key = (id(sim), n)
        if key not in _CHUNK_FNS:  # one compiled function per (sim, chunk length), reused across calls
            _CHUNK_FNS[key] = jax.jit(make_chunk_fn(sim, n, in_axes))
        state, logs = _CHUNK_FNS[key](bmodel, state, plan, om, gains, push, mu_ground)
        out_logs.append(jax.device_get(logs))
        done += n
        if progress is not None:
            progress(done * steps_per_log * dt)
    logs = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *out_logs)
    return state, logs
