"""The rollout's online metric reductions: one :class:`Accum` per run, folded after every physics step
(:func:`fold_physics_step`) and every control step (:func:`fold_control_step`); :func:`wbc_jax.metrics.paper.finalize`
turns the final Accum into R, T, S and the flags."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.metrics import paper


class Accum(NamedTuple):
    """Online reductions since the start of the run (per run, each a scalar). Fields marked (physics rate) are
    updated after every physics step, the others once per control step."""

    min_trunk_z: jax.Array  # [m]
    max_slip: jax.Array  # [m] object displacement on the tray, tray frame, xy
    max_lift: jax.Array  # [m] object bottom above the tray surface
    nonfoot_floor: jax.Array  # bool, a non-foot robot part touched the floor (physics rate)
    wall_contact: jax.Array  # bool (physics rate)
    max_tau_ratio: jax.Array  # max |tau| / limit of the applied torques
    max_tau_excess: jax.Array  # [N m] largest unclipped-torque excess over the limit
    sum_prim_res: jax.Array
    n_flag: jax.Array  # steps whose QP was flagged
    sum_qp_iters: jax.Array  # int32, ADMM iterations over the control steps
    max_qp_iters: jax.Array  # int32, most iterations one control step took
    n_steps: jax.Array  # int32, control steps
    sum_track: jax.Array  # integral of ||p_obj,ref - p_obj|| [m s]
    nonfinite: jax.Array  # bool (physics rate)
    off_steps: jax.Array  # int32, consecutive physics steps (up to now) with the object touching nothing on the tray
    max_off_s: jax.Array  # [s] longest such spell (physics steps x dt_physics)
    sum_invH: jax.Array  # integral of 1/H, the paper's robustness integrand [rad^2 s] (physics rate)
    sum_acc: jax.Array  # integral of ||object CoM linear acceleration|| [m/s] (physics rate)
    n_boundary: jax.Array  # int32, physics steps with 1/H = 0 (a contact unloaded or on/outside its cone)
    first_contact_t: jax.Array  # [s] start of the physics step whose contacts first had a non-foot robot part
    #                             penetrating the floor or terrain; NaN if none yet (physics rate)
    first_contact_k: jax.Array  # int32, index into Sim.nonfoot_slots of that step's deepest such contact; -1 if none
    overflow: jax.Array  # bool, a physics step's contacts or constraint rows may not all have fit (Warp's capacity;
    #                      the run is failed) (physics rate)
    t_end: jax.Array  # [s] end of the run's metric window [0, t_end) (an input, not a reduction; +inf: the whole
    #                   simulation). sum_invH, sum_acc, n_boundary, sum_track and n_win count only the control
    #                   periods whose midpoint lies in the window; the flags and extremes count all
    n_win: jax.Array  # int32, control steps inside the metric window (the duration of R, T, S)
    min_clear: jax.Array  # [m] smallest signed distance of a non-foot robot geom to the floor, terrain or a wall
    #                       over the run (exact geometry; +inf: no such pair) (physics rate)
    min_clear_t: jax.Array  # [s] start of the physics step of min_clear (the contacts' time); NaN if none
    min_clear_k: jax.Array  # int32, its pair: index into wbc_jax.physics.clearance.clearance_pairs(robot); -1 if none
    n_boundary_cone: jax.Array  # int32, the part of n_boundary with every contact loaded and a force on/outside
    #                             the circular cone (physics rate)
    sum_invH_plan: jax.Array  # integral of 1/H of the QP's planned object forces [rad^2 s] (control rate,
    #                           :func:`wbc_jax.metrics.paper.planned_inv_H`)
    n_boundary_plan: jax.Array  # int32, control steps with that 1/H = 0 (the boundary rule)
    n_boundary_plan_cone: jax.Array  # int32, the part of n_boundary_plan with a loaded planned force on/outside
    #                                  the cone
    n_solver_cap: jax.Array  # int32, physics steps whose constraint solve stopped at opt.iterations, not at its
    #                          tolerance (physics rate)
    failed: jax.Array  # bool, the run has failed (:func:`wbc_jax.metrics.paper.run_failed`); from the next control
    #                    step on, the rollout keeps its state (and this Accum) as they were: a failed run is frozen
    fail_t: jax.Array  # [s] start of the control step at which the run failed; NaN while it has not


class SubstepMonitors(NamedTuple):
    """Physics-rate monitor values of one physics step of one run (each a scalar), from the data before and after
    the step. Contacts and constraint forces are those of the step's start."""

    inv_h: jax.Array  # 1/H of the simulator's forces on the object's contact slots [rad^2]; 0 if not finite
    cone: jax.Array  # bool, those forces all loaded and one on/outside the circular cone (boundary rule, 2nd case)
    acc: jax.Array  # ||object CoM linear acceleration|| over the step, (v_after - v_before) / dt_physics [m/s^2]
    nonfoot_floor: jax.Array  # bool, a non-foot robot part penetrates the floor or terrain (dist < 0)
    nonfoot_k: jax.Array  # int32, index into Sim.nonfoot_slots of the deepest such contact (-1: none)
    t: jax.Array  # [s] time at the step's start (the contacts' time)
    wall: jax.Array  # bool, anything penetrates a wall (dist < 0)
    off: jax.Array  # bool, every object contact sphere farther than CONTACT_DIST from the tray
    finite: jax.Array  # bool, positions after the step and the held torques are finite
    overflow: jax.Array  # bool, the step's contacts, constraint rows or contact-sensor matches may not all fit (Warp)
    solver_cap: jax.Array  # bool, the step's constraint solve stopped at opt.iterations
    clear: jax.Array  # [m] clearance after the step (+inf: no such pair)
    clear_k: jax.Array  # int32, its pair (Accum.min_clear_k numbering; -1: none)


class ControlSample(NamedTuple):
    """Control-rate values of one control step of one run, taken at the sensed state."""

    trunk_z: jax.Array  # () [m] trunk height
    slip: jax.Array  # () [m] object displacement on the tray since t = 0, tray frame, xy
    lift: jax.Array  # () [m] object height change on the tray since t = 0
    tau_ratio: jax.Array  # () max |tau| / limit of the applied torques
    track_err: jax.Array  # () [m] ||p_obj,ref - p_obj||
    qp: NamedTuple  # the controller's QPDiag (tau_excess, prim_res, flag, iters, obj_forces (4, 3) [N])
    obj_mu: jax.Array  # () tray friction coefficient


def init_accum(min_trunk_z: jax.Array) -> Accum:
    """The Accum of a run at t = 0 (``min_trunk_z``: the initial trunk height [m]; whole simulation window)."""
    z = jnp.zeros(())
    zero_i = jnp.zeros((), jnp.int32)
    false = jnp.bool_(False)
    return Accum(min_trunk_z=min_trunk_z, max_slip=z, max_lift=z, nonfinite=false, nonfoot_floor=false,
                 wall_contact=false, max_tau_ratio=z, max_tau_excess=jnp.full((), -jnp.inf, z.dtype),
                 sum_prim_res=z, n_flag=zero_i, sum_qp_iters=zero_i, max_qp_iters=zero_i, n_steps=zero_i,
                 sum_track=z, off_steps=zero_i, max_off_s=z, sum_invH=z, sum_acc=z, n_boundary=zero_i,
                 first_contact_t=jnp.full((), jnp.nan, z.dtype), first_contact_k=jnp.full((), -1, jnp.int32),
                 overflow=false, t_end=jnp.full((), jnp.inf, z.dtype), n_win=zero_i,
                 min_clear=jnp.full((), jnp.inf, z.dtype), min_clear_t=jnp.full((), jnp.nan, z.dtype),
                 min_clear_k=jnp.full((), -1, jnp.int32), n_boundary_cone=zero_i, sum_invH_plan=z,
                 n_boundary_plan=zero_i, n_boundary_plan_cone=zero_i, n_solver_cap=zero_i, failed=false,
                 fail_t=jnp.full((), jnp.nan, z.dtype))


def in_window(acc: Accum, dt_control: float) -> jax.Array:
    """() bool: the control period now starting (index ``acc.n_steps``) counts in the metric window: its midpoint
    (n_steps + 1/2) x dt_control [s] is before ``acc.t_end`` (from the step counter, not the float time: no drift)."""
    return (acc.n_steps.astype(acc.t_end.dtype) + 0.5) * dt_control < acc.t_end


def fold_physics_step(acc: Accum, s: SubstepMonitors, in_win, dt_physics: float) -> Accum:
    """``acc`` with one physics step's monitors ``s`` added: integrals (value x ``dt_physics`` [s]) only while
    ``in_win`` (the period is in the metric window), flags OR'ed and extremes over every step."""
    h = dt_physics
    off_steps = jnp.where(s.off, acc.off_steps + 1, 0)
    first = s.nonfoot_floor & ~acc.nonfoot_floor
    closer = s.clear < acc.min_clear
    return acc._replace(
        min_clear=jnp.where(closer, s.clear, acc.min_clear),
        min_clear_t=jnp.where(closer, s.t, acc.min_clear_t),
        min_clear_k=jnp.where(closer, s.clear_k, acc.min_clear_k),
        nonfoot_floor=acc.nonfoot_floor | s.nonfoot_floor,
        first_contact_t=jnp.where(first, s.t, acc.first_contact_t),
        first_contact_k=jnp.where(first, s.nonfoot_k, acc.first_contact_k),
        wall_contact=acc.wall_contact | s.wall,
        nonfinite=acc.nonfinite | ~s.finite,
        overflow=acc.overflow | s.overflow,
        n_solver_cap=acc.n_solver_cap + s.solver_cap.astype(jnp.int32),
        off_steps=off_steps,
        max_off_s=jnp.maximum(acc.max_off_s, off_steps * h),
        sum_invH=acc.sum_invH + jnp.where(in_win, s.inv_h * h, 0.0),
        sum_acc=acc.sum_acc + jnp.where(in_win, s.acc * h, 0.0),
        n_boundary=acc.n_boundary + (in_win & (s.inv_h <= 0.0)).astype(jnp.int32),
        n_boundary_cone=acc.n_boundary_cone + (in_win & (s.inv_h <= 0.0) & s.cone).astype(jnp.int32),
    )


def fold_control_step(acc: Accum, c: ControlSample, dt_control: float) -> Accum:
    """``acc`` with one control step's sample ``c`` added (integrals: value x ``dt_control`` [s], only for a period
    in the metric window; ``acc.n_steps`` is still this period's index) and the step counted."""
    w = in_window(acc, dt_control)
    inv_h_plan, cone_plan = paper.planned_inv_H(c.qp.obj_forces, c.obj_mu)  # the QP's planned forces
    return acc._replace(
        min_trunk_z=jnp.minimum(acc.min_trunk_z, c.trunk_z),
        max_slip=jnp.maximum(acc.max_slip, c.slip),
        max_lift=jnp.maximum(acc.max_lift, c.lift),
        max_tau_ratio=jnp.maximum(acc.max_tau_ratio, c.tau_ratio),
        max_tau_excess=jnp.maximum(acc.max_tau_excess, c.qp.tau_excess),
        sum_prim_res=acc.sum_prim_res + c.qp.prim_res,
        n_flag=acc.n_flag + (c.qp.flag != 0).astype(jnp.int32),
        sum_qp_iters=acc.sum_qp_iters + c.qp.iters,
        max_qp_iters=jnp.maximum(acc.max_qp_iters, c.qp.iters),
        n_steps=acc.n_steps + 1,
        n_win=acc.n_win + w.astype(jnp.int32),
        sum_track=acc.sum_track + jnp.where(w, c.track_err * dt_control, 0.0),
        sum_invH_plan=acc.sum_invH_plan + jnp.where(w, inv_h_plan * dt_control, 0.0),
        n_boundary_plan=acc.n_boundary_plan + (w & (inv_h_plan <= 0.0)).astype(jnp.int32),
        n_boundary_plan_cone=acc.n_boundary_plan_cone + (w & (inv_h_plan <= 0.0) & cone_plan).astype(jnp.int32),
    )


def mark_failure(acc: Accum, failed_now, t) -> Accum:
    """``acc`` with ``failed`` set when ``failed_now`` (() bool) and ``fail_t`` the time ``t`` [s] of the first such
    step."""
    first = failed_now & ~acc.failed
    return acc._replace(failed=acc.failed | failed_now, fail_t=jnp.where(first, t, acc.fail_t))
