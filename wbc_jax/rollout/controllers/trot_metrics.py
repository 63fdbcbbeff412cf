"""The capture-point trot's metrics, reduced online at the control rate (:class:`TrotMetrics`) and finalized per run.

Windows (from the run's plan): the *walk* is [t_start, t_stop] (the first half-cycle's start to the last one's
end); the *steady* part leaves out ``min(STEADY_MARGIN, walk / 4)`` at either end (start-up and stop).

Per run (:func:`finalize`): ``speed_mps`` = forward CoM displacement over the walk / its duration (first and last
control step inside it); ``cp_err_x_rms_mm``, ``cp_err_y_rms_mm`` = rms over the walk's control steps of the
capture-point error xi - xi_d (xi = x + xdot / w, eq. 18) along and across the walking direction, and
``cp_err_x_max_mm``; ``roll_amp_deg``, ``pitch_amp_deg``, ``yaw_amp_deg`` = half the range of the trunk's attitude
(relative to its start) over the steady part (NaN when it is empty); ``max_tau_ratio`` = max |tau| / limit of the
applied torques over every joint and step; ``foot_slip_mm`` = the largest horizontal displacement of a foot while
it is in (planned) stance, from its position when that stance began; ``distance_m`` and ``walked`` (no fall and at
least ``PROGRESS_MIN`` of the planned distance); ``success`` = no fall (trunk low), no non-foot contact with the
floor or terrain, finite, no capacity overflow.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.metrics import paper

STEADY_MARGIN = 1.0  # [s] start-up and stop left out of the steady part (at most a quarter of the walk each)
PROGRESS_MIN = 0.8  # a run "walks" when it stays up and covers this fraction of the planned distance


class TrotLog(NamedTuple):
    """Logged every ``log_every`` control steps (per run), world frame unless noted."""

    t: jax.Array  # [s]
    com: jax.Array  # (3,) [m]
    com_vel: jax.Array  # (3,) [m/s]
    xi_d: jax.Array  # (2,) desired CP [m]
    P: jax.Array  # (2,) current virtual leg [m]
    v_des: jax.Array  # (2,) desired CoM velocity (eq. 19) [m/s]
    rpy: jax.Array  # (3,) trunk roll, pitch, yaw relative to its initial orientation [rad]
    trunk_z: jax.Array  # [m]
    tau: jax.Array  # (nu,) applied torques [N m]
    tau_grf: jax.Array  # (nu,) -J^T f part of the QP torques [N m]
    q_leg: jax.Array  # (12,) leg joint angles [rad]
    qd_leg: jax.Array  # (12,) leg joint velocities [rad/s]
    swing: jax.Array  # (4,) bool
    prim_res: jax.Array
    qpos: jax.Array  # (nq,) the full configuration (robot and cube)


class TrotMetrics(NamedTuple):
    """Online reductions of one run (module docstring); forward / lateral: along / across the walking direction."""

    n: jax.Array  # int32, control steps
    fwd_first: jax.Array  # [m] forward CoM position at the first control step
    fwd_last: jax.Array  # [m] at the latest
    t_walk0: jax.Array  # [s] first control step inside the walk
    fwd_walk0: jax.Array  # [m] forward CoM position then
    t_walk1: jax.Array  # [s] latest control step inside the walk
    fwd_walk1: jax.Array  # [m]
    n_walk: jax.Array  # int32, control steps inside the walk
    sum_ex2: jax.Array  # [m^2] sum of the squared forward CP error over the walk
    sum_ey2: jax.Array  # [m^2] lateral
    max_ex: jax.Array  # [m] largest |forward CP error| over the walk
    rpy_min: jax.Array  # (3,) [rad] over the steady part (+inf: none yet)
    rpy_max: jax.Array  # (3,) [rad] (-inf: none yet)
    max_abs_tau: jax.Array  # (nu,) [N m] applied torques
    p_touch: jax.Array  # (4, 2) [m] each foot's horizontal position when its stance began
    was_swing: jax.Array  # (4,) bool, the foot swung at the previous control step
    max_foot_slip: jax.Array  # [m]
    planned: jax.Array  # [m] planned forward distance (virtual legs: (steps - 1) x stride)


class StepValues(NamedTuple):
    """One control step's inputs to :func:`fold`."""

    t: jax.Array  # () [s]
    fwd: jax.Array  # () forward CoM position [m]
    e_cp: jax.Array  # (2,) CP error (forward, lateral) [m]
    rpy: jax.Array  # (3,) [rad]
    walking: jax.Array  # () bool, inside the walk
    steady: jax.Array  # () bool, inside its steady part
    planned: jax.Array  # () [m]


def trunk_rpy(R0, R):
    """(3,) ZYX roll, pitch, yaw of R relative to R0 (trunk frame: x forward) [rad]."""
    E = R0.T @ R
    return jnp.array([jnp.arctan2(E[2, 1], E[2, 2]), -jnp.arcsin(jnp.clip(E[2, 0], -1.0, 1.0)),
                      jnp.arctan2(E[1, 0], E[0, 0])])


def init_metrics(dyn, nu: int) -> TrotMetrics:
    """The reductions at t = 0 (``dyn``: the run's DynTerms then; ``nu``: actuators)."""
    z, zi = jnp.zeros((), dyn.com.dtype), jnp.zeros((), jnp.int32)
    inf3 = jnp.full(3, jnp.inf, dyn.com.dtype)
    return TrotMetrics(n=zi, fwd_first=z, fwd_last=z, t_walk0=z, fwd_walk0=z, t_walk1=z, fwd_walk1=z, n_walk=zi,
                       sum_ex2=z, sum_ey2=z, max_ex=z, rpy_min=inf3, rpy_max=-inf3,
                       max_abs_tau=jnp.zeros(nu, dyn.com.dtype), p_touch=dyn.p_foot[:, :2],
                       was_swing=jnp.zeros(4, bool), max_foot_slip=z, planned=z)


def step_values(plan, ref, dyn, rpy, t) -> StepValues:
    """:class:`StepValues` of one control step: ``plan`` the run's TrotPlan, ``ref`` its TrotReference at time
    ``t`` [s], ``dyn`` the observed DynTerms, ``rpy`` (3,) the trunk's attitude [rad]."""
    walk = plan.walk
    h = walk.heading
    lat = jnp.stack([-h[1], h[0]])
    xi = dyn.com[:2] + dyn.com_vel[:2] / walk.w  # eq. 18
    e = xi - ref.xi_d
    t0, t1 = walk.gait.t_start, walk.gait.t_stop
    margin = jnp.minimum(STEADY_MARGIN, 0.25 * (t1 - t0))
    return StepValues(t=t, fwd=dyn.com[:2] @ h, e_cp=jnp.stack([e @ h, e @ lat]), rpy=rpy,
                      walking=(t >= t0) & (t <= t1), steady=(t >= t0 + margin) & (t <= t1 - margin),
                      planned=(walk.P.shape[0] - 1) * plan.stride)


def fold(m: TrotMetrics, s: StepValues, swing, p_foot, tau) -> TrotMetrics:
    """``m`` with one control step added: ``s`` (:func:`step_values`), ``swing`` (4,) bool, ``p_foot`` (4, 3) [m]
    the feet, ``tau`` (nu,) [N m] the applied torques."""
    w, started = s.walking, m.n_walk > 0
    ex, ey = s.e_cp[0], s.e_cp[1]
    stance = ~swing
    p_touch = jnp.where((stance & m.was_swing)[:, None], p_foot[:, :2], m.p_touch)
    slip = jnp.where(stance, jnp.linalg.norm(p_foot[:, :2] - p_touch, axis=1), 0.0)
    return TrotMetrics(
        n=m.n + 1, fwd_first=jnp.where(m.n == 0, s.fwd, m.fwd_first), fwd_last=s.fwd,
        t_walk0=jnp.where(w & ~started, s.t, m.t_walk0), fwd_walk0=jnp.where(w & ~started, s.fwd, m.fwd_walk0),
        t_walk1=jnp.where(w, s.t, m.t_walk1), fwd_walk1=jnp.where(w, s.fwd, m.fwd_walk1),
        n_walk=m.n_walk + w.astype(jnp.int32), sum_ex2=m.sum_ex2 + jnp.where(w, ex * ex, 0.0),
        sum_ey2=m.sum_ey2 + jnp.where(w, ey * ey, 0.0), max_ex=jnp.where(w, jnp.maximum(m.max_ex, jnp.abs(ex)),
                                                                            m.max_ex),
        rpy_min=jnp.where(s.steady, jnp.minimum(m.rpy_min, s.rpy), m.rpy_min),
        rpy_max=jnp.where(s.steady, jnp.maximum(m.rpy_max, s.rpy), m.rpy_max),
        max_abs_tau=jnp.maximum(m.max_abs_tau, jnp.abs(tau)), p_touch=p_touch, was_swing=swing,
        max_foot_slip=jnp.maximum(m.max_foot_slip, jnp.max(slip)), planned=s.planned)


def _common(acc, course: bool, substeps: int) -> dict:
    """The flags and solver figures every controller reports, from the shared Accum (host, leading run axis)."""
    n = np.asarray(acc.n_steps, float)
    trunk_low = np.asarray(acc.min_trunk_z) < (paper.FALL_Z_COURSE if course else paper.FALL_Z_FLAT)
    body_contact = np.asarray(acc.nonfoot_floor)
    nonfinite, overflow = np.asarray(acc.nonfinite), np.asarray(acc.overflow)
    n_flag = np.asarray(acc.n_flag)
    return dict(
        fell=trunk_low | body_contact | nonfinite, trunk_low=trunk_low, body_contact=body_contact,
        nonfinite=nonfinite, overflow=overflow, min_trunk_z_m=np.asarray(acc.min_trunk_z, float),
        object_slip_mm=np.asarray(acc.max_slip) * 1e3, max_qp_tau_excess_Nm=np.asarray(acc.max_tau_excess, float),
        qp_flag_fraction=n_flag / np.maximum(n, 1), qp_flagged=n_flag / np.maximum(n, 1) > paper.QP_FLAG_FRACTION,
        qp_iters_mean=np.asarray(acc.sum_qp_iters) / np.maximum(n, 1), qp_iters_max=np.asarray(acc.max_qp_iters),
        solver_cap_fraction=np.asarray(acc.n_solver_cap) / np.maximum(n * substeps, 1),
        min_clearance_mm=np.asarray(acc.min_clear, float) * 1e3, min_clearance_s=np.asarray(acc.min_clear_t, float),
        failure_s=np.asarray(acc.fail_t, float))


def finalize(acc, metrics: TrotMetrics, ids, course: bool, substeps: int = 1) -> dict[str, np.ndarray]:
    """Per-run results (module docstring) from the host Accum ``acc`` and :class:`TrotMetrics` ``metrics`` (leading
    run axis). Returns a dict of (B,) arrays."""
    m = jax.tree_util.tree_map(np.asarray, metrics)
    out = _common(acc, course, substeps)
    with np.errstate(divide="ignore", invalid="ignore"):
        dt_walk = m.t_walk1 - m.t_walk0
        n_walk = np.maximum(m.n_walk, 1)
        amp = np.where(np.isfinite(m.rpy_max - m.rpy_min), np.rad2deg((m.rpy_max - m.rpy_min) / 2), np.nan)
        out.update(
            speed_mps=np.where(dt_walk > 0, (m.fwd_walk1 - m.fwd_walk0) / dt_walk, np.nan),
            cp_err_x_rms_mm=np.where(m.n_walk > 0, np.sqrt(m.sum_ex2 / n_walk) * 1e3, np.nan),
            cp_err_y_rms_mm=np.where(m.n_walk > 0, np.sqrt(m.sum_ey2 / n_walk) * 1e3, np.nan),
            cp_err_x_max_mm=m.max_ex * 1e3, roll_amp_deg=amp[:, 0], pitch_amp_deg=amp[:, 1], yaw_amp_deg=amp[:, 2],
            max_tau_ratio=np.max(m.max_abs_tau / np.asarray(ids.tau_max), axis=1),
            foot_slip_mm=m.max_foot_slip * 1e3, distance_m=m.fwd_last - m.fwd_first, planned_distance_m=m.planned)
    out["walked"] = ~out["fell"] & (out["distance_m"] >= PROGRESS_MIN * m.planned)
    out["success"] = ~(out["fell"] | out["overflow"])
    parts = [("nonfinite", "non-finite state"), ("trunk_low", "trunk below the fall height"),
             ("body_contact", "body contact with floor/terrain"), ("overflow", "contact capacity overflow (Warp)")]
    out["fail_reason"] = np.array(["; ".join(text for k, text in parts if out[k][i]) for i in range(len(out["fell"]))],
                                  dtype=object)
    return out
