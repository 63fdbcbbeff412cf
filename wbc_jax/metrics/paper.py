"""The transport paper's metrics (Sec. V-B), computed online inside the rollout, plus safety flags.

Per physics step (inside the jitted scan, after every ``mjx.step`` of a control period, ``wbc_jax.rollout.step``;
cheap: four contact forces and a few norms):

* **Robustness** integrand 1/H(t), with
  H = (1/lambda) sum_i 1 / ((theta_i - alpha_i)(alpha_i + theta_i)), lambda = 4,
  theta_i = atan(mu) (the cone's half-aperture), alpha_i = the angle between contact i's normal and the
  force the *simulator* applies there (:func:`wbc_jax.physics.contacts.contact_forces` on the object's four
  contact slots, contact frame: row 0 normal, rows 1-2 tangential), alpha_i = atan2(||f_t||, f_n).
  **Boundary rule** (documented choice): a contact carrying no load (f_n <= :data:`LOAD_EPS`, e.g. a
  corner lifted off the tray or a slot not active this step) or a force on or outside the circular cone
  (alpha_i >= theta_i; MuJoCo's pyramidal cone, |f_t1| + |f_t2| <= mu f_n, is inscribed in the circular one, so
  this is a guard for solver slack rather than a regular case) counts as *at the cone boundary*: its term
  1/((theta-alpha)(theta+alpha)) is +inf, so H = inf and 1/H(t) = 0 at that step.
  1/H is therefore in [0, lambda / (n_c / theta^2)] = [0, theta^2] for n_c = 4 = lambda: a cube resting
  still on a level tray scores theta^2 = atan(mu)^2.
* **Robustness of the planned forces** (``R_plan``): the same integrand 1/H, boundary rule included, of the
  object contact forces the transport QP *planned* at that control step: F_c,i = E_c Lambda_b,i per object contact
  point i, Lambda_b the QP solution's pyramid-edge multipliers (``zeta = [vdot, Lambda_gr, Lambda_b, gamma]``,
  ``wbc_jax.control.transport``), E_c = ``cone_edges(mu, k)`` in the tray frame (normal = tray z), so alpha_i =
  atan2(||F_t||, F_n) there (:func:`planned_contact_forces`). Sampled once per control step (the QP's rate) from
  the ADMM solution ``x`` the torques were computed from, as it is: a multiplier slightly below 0 (ADMM's
  tolerance) can put a force outside the pyramid, which the boundary rule then counts like the simulator's. The
  pyramid is inscribed in the circular cone, so a planned force reaches alpha = theta only along an edge (one
  multiplier > 0 at that contact, the others 0). With the ablation variant ``no_tray_cone`` (Lambda_b pinned to 0)
  every contact is unloaded: R_plan = 0.
* **The boundary rule's share**: the fraction of the window's integrand samples (physics steps for R, control
  steps for R_plan) whose 1/H the rule set to 0 instead of the formula: ``boundary_fraction`` and
  ``boundary_fraction_plan``; ``boundary_cone_fraction`` (``boundary_cone_fraction_plan``) is the part of it with
  every contact loaded and a force on or outside the circular cone (the rest: a contact carried no load).
* **Tracking** integrand ||p_b,ref(t) - p_b(t)|| (object CoM vs the planned object path).
* **Smoothness** integrand ||vdot_b(t)||: the object CoM's linear acceleration over the physics step,
  (v(t + dt) - v(t)) / dt with dt the physics timestep, from the free joint's linear velocity (world frame).

The integrals sum these over physics steps times the physics timestep (the tracking integrand, a planner
quantity, is sampled once per control step times the control period).

**Metric window.** The integrals and their duration cover the run's *task window* [0, t_end), not the whole
simulated time: a control period counts when its midpoint is before t_end (``wbc_jax.metrics.accumulate.in_window``;
all physics steps of a period count or none). t_end is per-run data carried in the rollout state
(``Accum.t_end``, set by ``wbc_jax.rollout.state.with_metric_window``; +inf = the whole simulation), so one
compiled chunk serves every window. The campaign (``wbc_jax.campaign.runner.build``) sets
t_end = T_plan + settle, T_plan = the run's own plan duration (end of its object path; plans differ by d) and
settle = the spec's ``campaign.extra_seconds`` (default 0.5 s: standing after the path ends, while the object
comes to rest), capped by ``campaign.max_seconds`` when that is set. The campaign simulates whole chunks up to
max(T_plan) + extra_seconds or beyond, so the window always ends inside the simulation and R, T, S do not depend
on ``chunk_seconds``. Flags and extremes (falls, body and wall contact, drops, slip, lift, overflow, torque
ratios, clearance) keep counting over the whole simulation. With T_win = (control steps in the window) x the
control period:
R = (1/T_win) int 1/H dt [rad^2]; T = (1/T_win) int ||p_ref - p|| dt [m]; S = T_win / int ||vdot_b|| dt
[s^2/m] (the paper's S uses the duration T, not the tracking metric T).

**Clearance** (``wbc_jax.rollout.step.clearance``, every physics step): the smallest signed distance between a
non-foot robot geom and the floor, the terrain blocks or a wall over the whole run, with its time and pair. Exact
geometry from the geoms' poses (``wbc_jax.physics.clearance``: capsules and boxes vs planes and boxes; exact when
positive, the deepest point's depth when penetrating), the same on both backends; +inf only for a scene with no
such pair.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

LAMBDA = 4.0  # [-] the paper's lambda
LOAD_EPS = 1e-3  # [N] a contact whose normal force is at most this carries no load (counts at the boundary)

# flags (thresholds of :func:`finalize`)
SLIP_LIMIT = 0.010  # [m] max slip above this sets `slid`
DROP_LIFT = 0.01  # [m] object bottom lifted this far above the tray sets `dropped`
MAX_OFF_S = 0.05  # [s] object touching nothing on the tray for longer than this sets `dropped`
FALL_Z_FLAT = 0.3  # [m] trunk below this on flat ground sets `fell`
FALL_Z_COURSE = 0.15  # [m] the same on the obstacle course (the robot crouches under the wall)
DONE_TOL = 0.05  # [m] final object error above this: transport not completed
QP_FLAG_FRACTION = 0.001  # more than this fraction of flagged QPs sets `qp_flagged`


def cone_angle(f) -> tuple[jax.Array, jax.Array]:
    """Alpha (n,) [rad] between normal and force, and loaded (n,) bool, from contact-frame forces f (n, 3)."""
    fn = f[..., 0]
    ft = jnp.linalg.norm(f[..., 1:3], axis=-1)
    loaded = fn > LOAD_EPS
    return jnp.arctan2(ft, jnp.where(loaded, fn, 1.0)), loaded


def inv_H(alpha, loaded, mu, lam: float = LAMBDA) -> jax.Array:
    """1/H for one instant: alpha (n,) [rad], loaded (n,) bool, mu scalar friction. Boundary rule in the
    module docstring: any unloaded contact or alpha >= theta gives 0."""
    theta = jnp.arctan(mu)
    g = (theta - alpha) * (theta + alpha)  # (n,) > 0 strictly inside the cone
    inside = loaded & (g > 0)
    ok = jnp.all(inside) & (alpha.shape[-1] > 0)
    s = jnp.sum(1.0 / jnp.where(inside, g, 1.0))
    return jnp.where(ok, lam / s, 0.0)


def at_cone(alpha, loaded, mu) -> jax.Array:
    """() bool: every contact is loaded and some force lies on or outside the circular cone (alpha >= theta): the
    second trigger of the boundary rule (the first: a contact without load). alpha, loaded (n,); mu scalar."""
    theta = jnp.arctan(mu)
    return jnp.all(loaded) & jnp.any((theta - alpha) * (theta + alpha) <= 0)


def planned_inv_H(f_plan, mu) -> tuple[jax.Array, jax.Array]:
    """1/H [rad^2] of the object contact forces a controller planned (boundary rule included; 0 if not finite), and
    () bool :func:`at_cone` of those forces (every contact loaded, one on/outside the cone).

    Args:
        f_plan: (n_c, 3) planned contact forces in the contact frame, normal first [N]; mu: () tray friction.
    """
    alpha, loaded = cone_angle(f_plan)
    v = inv_H(alpha, loaded, mu)
    return jnp.where(jnp.isfinite(v), v, 0.0), at_cone(alpha, loaded, mu)


def step_integrands(f_obj, mu, v_obj_before, v_obj_after, dt):
    """Per-step integrands (1/H, ||vdot||) of one run (T's integrand ||p_ref - p|| is the rollout's
    ``sum_track``).

    Args:
        f_obj: (4, 3) simulator forces at the object's contact spheres, contact frames, normal first [N]
            (``wbc_jax.physics.contacts.object_contacts``); mu: () tray friction; v_obj_before, v_obj_after: (3,)
            object CoM velocity at the step's start and end [m/s]; dt: physics step [s].
    """
    alpha, loaded = cone_angle(f_obj)
    a = jnp.linalg.norm((v_obj_after - v_obj_before) / dt)
    return inv_H(alpha, loaded, mu), a


def run_failed(acc, course: bool) -> jax.Array:
    """() bool: the run has failed by a flag :func:`finalize` counts against success: the trunk below the fall
    height, a non-foot robot part on the floor or terrain, the object dropped (lifted or off the tray), a
    non-finite state or Warp's capacity overflow. ``acc``: one run's Accum; course: the scene has obstacles (the
    fall height, static). The rollout freezes a run from the control step after this turns true."""
    fall_z = FALL_Z_COURSE if course else FALL_Z_FLAT
    return ((acc.min_trunk_z < fall_z) | acc.nonfoot_floor | (acc.max_lift > DROP_LIFT)
            | (acc.max_off_s > MAX_OFF_S) | acc.nonfinite | acc.overflow)


def finalize(acc, dt: float, mu, course: bool, final_err, substeps: int = 1) -> dict[str, np.ndarray]:
    """Per-run metrics and flags from a (batched, host) rollout ``Accum``.

    Args:
        acc: rollout.Accum (or its packed form, ``RunState.acc``) with leading run axis; dt: control period [s];
            mu: (B,) tray friction;
        course: the scene has obstacles (fall threshold); final_err: (B,) final object error [m];
        substeps: physics steps per control step (``Sim.n_substeps``): ``acc.n_boundary`` counts physics steps.

    Returns:
        dict of (B,) arrays: R [rad^2], T [m], S [s^2/m] (time averages over the metric window, acc.n_win x dt),
        R_plan [rad^2] (R of the QP's planned object forces), max_slip_mm, boundary_fraction (of the window's
        physics steps: the boundary rule's share of R), boundary_cone_fraction (the part of it with a loaded force
        on/outside the cone), boundary_fraction_plan (of the window's control steps: the rule's share of R_plan),
        boundary_cone_fraction_plan (its part with a loaded planned force on/outside the cone),
        window_s (the window's duration [s]),
        min_clearance_mm (non-foot robot geom vs floor, terrain, wall; +inf: none reported) and min_clearance_s
        (its time; NaN: none), flags fell (= trunk_low or body_contact),
        trunk_low, body_contact, dropped, slid, hit_wall, qp_flag_fraction (of the control steps), qp_flagged,
        qp_iters_mean and qp_iters_max (ADMM iterations per control step: mean and most), nonfinite, overflow
        (Warp's contact or constraint capacity reached), solver_cap_fraction (of all physics steps: the constraint
        solver stopped at its iteration cap, opt.iterations; Warp only, ``wbc_jax.physics.backend.solver_capped``),
        success (no fall, no drop, finite, no overflow, final object error <= DONE_TOL), fail_reason (text, ""
        for a success) and failure_s (when :func:`run_failed` first held [s]; NaN if never). A failed run is frozen
        from the control step after its failure, so its metrics and flags are those up to that instant and its
        window (window_s) ends there.
    """
    n = np.asarray(acc.n_steps, float)
    n_win = np.asarray(acc.n_win, float)
    dur = np.maximum(n_win * dt, 1e-12)
    trunk_low = np.asarray(acc.min_trunk_z) < (FALL_Z_COURSE if course else FALL_Z_FLAT)
    body_contact = np.asarray(acc.nonfoot_floor)
    fell = trunk_low | body_contact
    nonfinite = np.asarray(acc.nonfinite)
    dropped = (np.asarray(acc.max_lift) > DROP_LIFT) | (np.asarray(acc.max_off_s) > MAX_OFF_S)
    final_err = np.asarray(final_err, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        S = np.where(np.asarray(acc.sum_acc) > 0, dur / np.asarray(acc.sum_acc), np.nan)
    out = dict(
        R=np.asarray(acc.sum_invH) / dur,
        R_plan=np.asarray(acc.sum_invH_plan) / dur,
        T=np.asarray(acc.sum_track) / dur,
        S=S,
        max_slip_mm=np.asarray(acc.max_slip) * 1e3,
        boundary_fraction=np.asarray(acc.n_boundary) / np.maximum(n_win * substeps, 1),
        boundary_cone_fraction=np.asarray(acc.n_boundary_cone) / np.maximum(n_win * substeps, 1),
        boundary_fraction_plan=np.asarray(acc.n_boundary_plan) / np.maximum(n_win, 1),
        boundary_cone_fraction_plan=np.asarray(acc.n_boundary_plan_cone) / np.maximum(n_win, 1),
        window_s=n_win * dt,
        min_clearance_mm=np.asarray(acc.min_clear, float) * 1e3,
        min_clearance_s=np.asarray(acc.min_clear_t, float),
        fell=fell | nonfinite,
        trunk_low=trunk_low,
        body_contact=body_contact,
        dropped=dropped,
        slid=np.asarray(acc.max_slip) > SLIP_LIMIT,
        hit_wall=np.asarray(acc.wall_contact),
        qp_flag_fraction=np.asarray(acc.n_flag) / np.maximum(n, 1),
        qp_iters_mean=np.asarray(acc.sum_qp_iters) / np.maximum(n, 1),
        qp_iters_max=np.asarray(acc.max_qp_iters),
        qp_flagged=np.asarray(acc.n_flag) / np.maximum(n, 1) > QP_FLAG_FRACTION,
        nonfinite=nonfinite,
        overflow=np.asarray(acc.overflow),
        solver_cap_fraction=np.asarray(acc.n_solver_cap) / np.maximum(n * substeps, 1),
        final_err_mm=final_err * 1e3,
        failure_s=np.asarray(acc.fail_t, float),
    )
    bad = out["fell"] | dropped | nonfinite | out["overflow"] | ~np.isfinite(final_err) | (final_err > DONE_TOL)
    for k in ("R", "T", "S"):
        bad |= ~np.isfinite(out[k])
    out["success"] = ~bad
    out["fail_reason"] = fail_reasons(out, final_err)
    return out


def fail_reasons(out: dict, final_err) -> np.ndarray:
    """(B,) text per run: why it failed ("" for a success), e.g. "body contact" for a non-foot robot part (knee,
    shin, trunk, arm) touching the floor or terrain with the trunk still up."""
    parts = [("nonfinite", "non-finite state"), ("trunk_low", "trunk below the fall height"),
             ("body_contact", "body contact with floor/terrain"), ("dropped", "object dropped"),
             ("overflow", "contact capacity overflow (Warp)")]
    reasons = []
    for i in range(len(out["success"])):
        r = [text for k, text in parts if out[k][i]]
        e = final_err[i]
        if not np.isfinite(e) or e > DONE_TOL:
            r.append("object not delivered")
        if not r and not out["success"][i]:
            r.append("non-finite metric")
        reasons.append("; ".join(r) if not out["success"][i] else "")
    return np.array(reasons, dtype=object)
