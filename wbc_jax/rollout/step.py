"""One control step of one run: sense -> observation and reference -> controller -> physics period -> metrics.

A control step (period ``Sim.dt_control`` = ``Sim.n_substeps`` physics steps of ``Sim.dt_physics``):
:func:`wbc_jax.physics.backend.sense` (kinematics, M, bias) -> planner reference -> the controller (the plug-in
``Sim.controller``, :mod:`wbc_jax.rollout.controllers`) -> torques ->
:func:`physics_period`: :func:`wbc_jax.physics.backend.finish` (rest of the forward pass + integration), then
``n_substeps - 1`` further ``mjx.step`` calls with the torques (and any push force) held, as a ``lax.scan``.

Monitors run at two rates. *Physics rate* (after every physics step, :func:`substep_monitors`): the paper's
integrands 1/H and ||object acceleration|| (dt = the physics step), non-foot/floor and wall contact, object off the
tray, clearance; so a contact or an acceleration spike inside a control period is not missed and the integrals do
not depend on the control period. *Control rate* (from the sensed state, once per control step): the controller's
sample (``Controller.record``; the transport's: trunk height, slip and lift on the tray, tracking error, torque
ratios, QP residuals and flags) and the log. Both fold into the run's :class:`wbc_jax.metrics.accumulate.Accum`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.metrics import paper
from wbc_jax.metrics.accumulate import (
    Accum,
    SubstepMonitors,
    fold_control_step,
    fold_physics_step,
    in_window,
    mark_failure,
)
from wbc_jax.physics import backend as physics
from wbc_jax.physics import clearance as geom_clearance
from wbc_jax.physics import contacts
from wbc_jax.physics.contacts import CONTACT_DIST
from wbc_jax.physics.observe import observe
from wbc_jax.planner.scene_geometry import scene_geometry
from wbc_jax.robot.model import mjx
from wbc_jax.rollout.config import Sim
from wbc_jax.rollout.controllers.base import keep_where
from wbc_jax.rollout.packed import pack
from wbc_jax.rollout.state import Push, RunState
from wbc_jax.types import ObjectModel, Observation


def seen_qvel(sim: Sim, d, push: Push, step):
    """The generalized velocities the controller sees: None (the true ones) or (``sim.sensor_noise``) ``d.qvel``
    plus the run's white noise of control step ``step``."""
    if not sim.sensor_noise:
        return None
    key = jax.random.fold_in(push.key, step)
    return d.qvel + push.qvel_noise_std * jax.random.normal(key, d.qvel.shape, d.qvel.dtype)


class ControllerInputs(NamedTuple):
    """What one control step computes before the controller."""

    d: mjx.Data  # the sensed state
    obs: Observation  # the controller's observation of it (with the run's velocity noise)
    ref: object  # the planner's reference (Controller.reference; with foot contacts from the simulator)
    mu_feet: jax.Array  # (4,) each foot pyramid's friction: that of the ground surface the foot is nearest to (floor
    #                     or a block), capped by the run's mu_ground (the scene's floor friction, or the campaign's
    #                     ground_mu, which the physics then also uses for every foot pair)


def controller_inputs(sim: Sim, m, run_state: RunState, plan, push: Push, mu_ground) -> ControllerInputs:
    """The sensed state, the controller's observation and the reference of one control step
    (:class:`ControllerInputs`)."""
    with jax.named_scope("sense"):
        step = run_state.acc.n_steps
        if sim.sensing == "delayed":  # the state the derived fields belong to: no physics call
            qpos, qvel, time = run_state.prev
            d = run_state.d.replace(qpos=qpos, qvel=qvel, time=time)
            qvel_seen = seen_qvel(sim, d, push, step)
            d_ctl = d if qvel_seen is None else d.replace(qvel=qvel_seen)
        else:
            d, d_ctl = physics.sense_with_view(m, run_state.d, seen_qvel(sim, run_state.d, push, step))
    with jax.named_scope("dynamics_reference"):
        obs = observe(m, d_ctl, sim.robot.ids)
        dist, mu_feet = contacts.foot_ground(sim, m, d)  # (4,), (4,)
        ref = sim.controller.reference(plan, d.time, obs, run_state.p_lift, dist < CONTACT_DIST)
    return ControllerInputs(d, obs, ref, jnp.minimum(mu_ground, mu_feet))


def clearance(sim: Sim, d):
    """Smallest signed distance [m] between a non-foot robot geom and the floor, the terrain blocks or a wall, and
    its pair, at the geom poses of ``d`` (after a physics step: those of the step's start, like its contacts).

    Exact geometry (:func:`wbc_jax.physics.clearance.min_clearance` over
    :func:`~wbc_jax.physics.clearance.clearance_pairs`), not the contact slots; the same on both backends.

    Returns:
        (() distance [m], +inf when the scene has no such pair; () int32 pair: index into
        ``clearance_pairs(sim.robot)`` (:func:`wbc_jax.rollout.results.clearance_name`); -1 when the distance is
        not finite).
    """
    return geom_clearance.min_clearance(geom_clearance.clearance_pairs(sim.robot), d)


class ObjectMonitors(NamedTuple):
    """The object's monitors of one physics step (:class:`wbc_jax.metrics.accumulate.SubstepMonitors` fields)."""

    inv_h: jax.Array
    acc: jax.Array
    cone: jax.Array
    off: jax.Array


def _object_monitors(sim: Sim, m, obj_model: ObjectModel, d, d_after, finite) -> ObjectMonitors:
    """1/H, ||object acceleration||, cone and off-the-tray of one physics step (module docstring)."""
    if not sim.obj_slots.size:
        return ObjectMonitors(jnp.zeros(()), jnp.zeros(()), jnp.bool_(False), jnp.bool_(False))
    adr = sim.robot.ids.obj_dof_adr
    f_obj, obj_dist = contacts.object_contacts(sim, m, d_after)
    inv_h, acc_norm = paper.step_integrands(f_obj, obj_model.mu, d.qvel[adr:adr + 3], d_after.qvel[adr:adr + 3],
                                            sim.dt_physics)
    inv_h, acc_norm = jnp.where(finite, inv_h, 0.0), jnp.where(finite, acc_norm, 0.0)
    cone = finite & paper.at_cone(*paper.cone_angle(f_obj), obj_model.mu)
    return ObjectMonitors(inv_h, acc_norm, cone, jnp.all(obj_dist > CONTACT_DIST))


def substep_monitors(sim: Sim, m, obj_model: ObjectModel, tau, d, d_after) -> SubstepMonitors:
    """Monitor values of the physics step ``d`` -> ``d_after`` taken with torques ``tau`` (nu,) [N m]."""
    finite = jnp.all(jnp.isfinite(d_after.qpos)) & jnp.all(jnp.isfinite(tau))
    inv_h, acc_norm, cone, off = _object_monitors(sim, m, obj_model, d, d_after, finite)
    nonfoot_dist, wall_dist = contacts.penetrations(sim, d_after)
    wall = jnp.any(wall_dist < 0.0)
    if nonfoot_dist.size:
        nonfoot = jnp.any(nonfoot_dist < 0.0)
        nonfoot_k = jnp.where(nonfoot, jnp.argmin(nonfoot_dist), -1).astype(jnp.int32)
    else:
        nonfoot, nonfoot_k = jnp.bool_(False), jnp.full((), -1, jnp.int32)
    clear, clear_k = clearance(sim, d_after)
    if sim.monitors == "no_clearance":  # (Sim.monitors) the computation drops out of the program
        clear, clear_k = jnp.full_like(clear, jnp.inf), jnp.full_like(clear_k, -1)
    overflow = physics.overflow(d_after) | contacts.match_overflow(sim, m, d_after)
    out = SubstepMonitors(inv_h=inv_h, cone=cone, acc=acc_norm, nonfoot_floor=nonfoot, nonfoot_k=nonfoot_k, t=d.time,
                          wall=wall, off=off, finite=finite, overflow=overflow,
                          solver_cap=physics.solver_capped(m, d_after), clear=clear, clear_k=clear_k)
    if sim.monitors == "finite_only":
        out = SubstepMonitors(**{k: v if k in ("finite", "t") else jnp.zeros_like(v) for k, v in out._asdict().items()})
    return out


def fold_control(sim: Sim, acc: Accum, sample, dt_control: float) -> Accum:
    """``acc`` with the control step's ``sample`` folded (:func:`wbc_jax.metrics.accumulate.fold_control_step`);
    with ``sim.monitors == "finite_only"`` only the step counted (it indexes the velocity noise and the metric
    window)."""
    if sim.monitors == "finite_only":
        return acc._replace(n_steps=acc.n_steps + 1)
    return fold_control_step(acc, sample, dt_control)


def physics_substep(sim: Sim, m, obj_model: ObjectModel, tau, d):
    """One held-torque physics step (``mjx.step``, ``d.ctrl`` = ``tau``) -> (data after, its SubstepMonitors)."""
    d_after = mjx.step(m, d)
    return d_after, substep_monitors(sim, m, obj_model, tau, d, d_after)


def physics_period(sim: Sim, m, obj_model: ObjectModel, d, tau, acc: Accum):
    """The physics of one control period with its physics-rate monitors.

    :func:`wbc_jax.physics.backend.finish` on the sensed ``d``, then ``sim.n_substeps - 1`` :func:`physics_substep`
    calls in a ``lax.scan`` (torques and ``d.xfrc_applied`` held); :func:`substep_monitors` of every step folded
    into ``acc``.

    Args:
        d: sensed mjx.Data (``wbc_jax.physics.backend.sense``; with delayed sensing the run's last state) with the
            period's ``xfrc_applied``; tau: (nu,) [N m]; acc: the run's Accum before the period.

    Returns:
        (mjx.Data n_substeps physics steps later, Accum with the physics-rate fields updated, () bool: every step
        of the period finite).
    """
    d1 = physics.finish(m, d, tau, sensed=sim.sensing != "delayed")
    monitors = substep_monitors(sim, m, obj_model, tau, d, d1)
    in_win = in_window(acc, sim.dt_control)  # the whole period is in the window or out of it
    carry = (d1, fold_physics_step(acc, monitors, in_win, sim.dt_physics), monitors.finite)
    if sim.n_substeps > 1:
        def body(carry, _):
            d, a, finite = carry
            d, s = physics_substep(sim, m, obj_model, tau, d)
            return (d, fold_physics_step(a, s, in_win, sim.dt_physics), finite & s.finite), None

        carry = jax.lax.scan(body, carry, None, length=sim.n_substeps - 1)[0]
    return carry


def _push_force(d, push: Push, trunk_body: int):
    """``d.xfrc_applied`` with the push's force on the trunk while the push is on at ``d.time``, else zero."""
    on = (d.time >= push.t0) & (d.time < push.t0 + push.duration)
    return jnp.zeros_like(d.xfrc_applied).at[trunk_body, 0:3].set(jnp.where(on, push.force, 0.0))


def control_step(sim: Sim, m, run_state: RunState, plan, obj_model: ObjectModel, gains, push: Push, mu_ground):
    """One control period of one run. Returns (new RunState, the controller's log row).

    ``plan``, ``gains``: the run's plan and parameters of ``sim.controller``; ``obj_model``: the object on the
    tray; ``mu_ground``: () the run's foot/ground friction.
    """
    ids, controller = sim.robot.ids, sim.controller
    d, obs, ref, mu = controller_inputs(sim, m, run_state, plan, push, mu_ground)
    dyn = obs.robot
    tau, control_state, diag = controller.control(obs, ref, obj_model, gains, run_state.cs, ids, mu)
    d_phys = run_state.d if sim.sensing == "delayed" else d  # delayed: d is one physics step old, torques act now
    d_phys = d_phys.replace(xfrc_applied=_push_force(d_phys, push, ids.trunk_body))
    with jax.named_scope("physics"):
        d_next, acc, finite = physics_period(sim, m, obj_model, d_phys, tau, run_state.acc.unpack())
    p_lift = jnp.where(ref.swing[:, None], run_state.p_lift, dyn.p_foot)

    # control-rate metrics (from the sensed state d at time t)
    record = controller.record(sim, d, obs, ref, tau, diag, run_state.rel0, obj_model, run_state.metrics, plan)
    acc = fold_control(sim, acc, record.sample, sim.dt_control)
    acc = mark_failure(acc, controller.failed(acc, scene_geometry(sim.robot).is_course), d.time)
    # a failed run (by an earlier step) is frozen: nothing of this step is kept, so its state, its metrics and its
    # failure stay as they were at its failure; a step that went non-finite keeps its last finite state
    frozen = run_state.acc.failed
    d_next = physics.freeze(finite & ~frozen, d_next, run_state.d)
    # delayed: d_next's derived fields belong to the state the step started from (a frozen run's too)
    prev = (d_phys.qpos, d_phys.qvel, d_phys.time) if sim.sensing == "delayed" else None
    stepped = RunState(d=d_next, cs=control_state, p_lift=p_lift, rel0=run_state.rel0,
                       acc=pack(acc, run_state.acc.layout), prev=prev, metrics=record.metrics)
    kept = keep_where(frozen, stepped._replace(d=None, cs=None), run_state._replace(d=None, cs=None))
    return kept._replace(d=d_next, cs=controller.freeze(frozen, control_state, run_state.cs)), record.log
