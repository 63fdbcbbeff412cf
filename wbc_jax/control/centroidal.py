"""Centroidal-momentum whole-body controller (centroidal paper, Sec. 2.3.2-2.3.4), in JAX.

Decision variables (n = nv_r + 3 n_feet = 36):
    chi = [vdot (nv_r = 24), f (3 per foot, world frame, FL, FR, BL, BR)].

Momentum-rate reference (eqs. 23, 25), world frame, about the CoM:
    kdot_d = Ibar_G R (Kp,k * R^T e_R - Kd,k * R^T omega)       (trunk-frame gains, e_R = log(R_d R^T))
    ldot_d = m [Kd,xy (v_xy,d - v_xy); Kp,z (z_d - z) - Kd,z zdot]   (Kd,xy: forward / lateral gains)
Cost (27): ||A_G vdot + Adot v - hdot_d||^2_Q + f'W f + w_post ||vdot_arm - a_post||^2 + r ||vdot||^2, with the
linear rows expressed in the heading frame (forward, lateral, up) so that Q = diag(1, 0, 1, 1, 1, 1) drops the
lateral row. The arm's posture task keeps it at its initial (home) posture holding the tray.
Constraints (fixed shapes; stance / swing switch bounds only):
    (28) 6   floating base: M[0:6] vdot - J_f[:, 0:6]^T f = -h[0:6] + J_t[:, 0:6]^T F_load
    (29/30) 12 feet: stance J_f vdot = -Jdot v - alpha J_f v; swing J_f vdot = pddot_sw - Jdot v (eq. 33)
    (31) 16  friction pyramids |f_x|, |f_y| <= mu f_z             4 normal force: f_min <= f_z <= f_max
                                                                         (swing: f_z = 0, hence f = 0)
    (32) 18  torque limits on tau = M_a vdot + h_a - J_f,a^T f - J_t,a^T F_load
F_load = (0, 0, -m_load g) is the payload known to the controller, applied at the tray's top centre.
Torques: eq. (34) for stance legs and the arm; swing legs add eqs. (35)-(36), a PD on joint targets from
one Gauss-Newton IK step of the quintic swing reference (theta_d = theta + J_leg^-1 (p_d - p),
thetadot_d = thetadot + J_leg^-1 (v_d - v_foot), J_leg the foot's Jacobian over its own three joints).

Model errors: ``gains.mass_scale`` scales every body mass and inertia of the controller's model (M without
armature, h, m, A_G, I_G all scale with it), the robustness study of the paper's Fig. 12.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.control.centroidal_dynamics import centroidal_terms
from wbc_jax.control.transport import control_qp_settings
from wbc_jax.control.transport_qp import ConstraintRows
from wbc_jax.qp import QPResult, QPSettings, last_usable, solve_qp
from wbc_jax.runtime.transfer import to_device
from wbc_jax.spatial import GRAVITY, full_precision, rot_error
from wbc_jax.types import DynTerms, Observation, RobotIds

N_FEET = 4
N_ROWS = 6 + 12 + 16 + 4 + 18  # QP rows (see the module docstring)


class CentroidalGains(NamedTuple):
    """Gains and weights: pytree leaves, so a batch axis over them (e.g. mass_scale) needs no recompile.

    Attributes (units in brackets):
        kd_xy: (2,) CoM velocity gains, forward / lateral, eq. 25 [1/s].
        kp_z, kd_z: () CoM height gains [1/s^2], [1/s].
        kp_rot, kd_rot: (3,) trunk orientation gains (trunk frame), eq. 23 [1/s^2], [1/s].
        kp_sw, ki_sw, kd_sw: () swing-foot PID of eq. 33 [1/s^2], [1/s^3], [1/s].
        alpha: () stance-foot velocity damping of eq. 29 [1/s].
        kp_post, kd_post: () arm posture task [1/s^2], [1/s]; w_post: () its weight.
        q_two, q_four: (6,) Q of eq. 27 in two-foot / four-foot support (heading frame forward, lateral, up;
            then world angular).
        w_f: () W of eq. 27 [1/N^2]; r_vdot: () regularisation of vdot.
        mu: () friction coefficient of the pyramids [-]; f_min, f_max: () stance normal-force bounds [N].
        tau_margin: () fraction of the torque limit the QP may use.
        k_ff: () feed-forward gain K_P,ff of eq. 35; kp_joint, kd_joint: () swing-leg joint PD of eq. 36
            [N m/rad], [N m s/rad].
        mass_scale: () controller's model mass / true mass (1: exact model).
        load_mass: () payload mass the controller assumes on the tray [kg].
    """

    kd_xy: jax.Array
    kp_z: jax.Array
    kd_z: jax.Array
    kp_rot: jax.Array
    kd_rot: jax.Array
    kp_sw: jax.Array
    ki_sw: jax.Array
    kd_sw: jax.Array
    alpha: jax.Array
    kp_post: jax.Array
    kd_post: jax.Array
    w_post: jax.Array
    q_two: jax.Array
    q_four: jax.Array
    w_f: jax.Array
    r_vdot: jax.Array
    mu: jax.Array
    f_min: jax.Array
    f_max: jax.Array
    tau_margin: jax.Array
    k_ff: jax.Array
    kp_joint: jax.Array
    kd_joint: jax.Array
    mass_scale: jax.Array
    load_mass: jax.Array


def default_gains(**overrides) -> CentroidalGains:
    """Defaults (paper's Q and W; the rest tuned on this robot, docs/method.md, "Centroidal controller")."""
    f = lambda *x: to_device(x if len(x) > 1 else x[0], float)  # noqa: E731
    g = CentroidalGains(
        kd_xy=f(10.0, 30.0), kp_z=f(400.0), kd_z=f(40.0), kp_rot=f(200.0, 200.0, 200.0),
        kd_rot=f(30.0, 30.0, 30.0), kp_sw=f(400.0), ki_sw=f(0.0), kd_sw=f(40.0), alpha=f(10.0),
        kp_post=f(100.0), kd_post=f(20.0), w_post=f(5.0), q_two=f(1.0, 0.0, 1.0, 1.0, 1.0, 1.0),
        q_four=f(1.0, 1.0, 1.0, 1.0, 1.0, 1.0), w_f=f(0.01), r_vdot=f(1e-4), mu=f(0.7), f_min=f(5.0),
        f_max=f(500.0), tau_margin=f(0.95), k_ff=f(1.0), kp_joint=f(30.0), kd_joint=f(1.0), mass_scale=f(1.0),
        load_mass=f(0.3),
    )
    return g._replace(**{k: to_device(v, float) for k, v in overrides.items()})


class CentroidalRef(NamedTuple):
    """Walking-pattern output at one instant (world frame).

    Attributes:
        v_xy: (2,) desired horizontal CoM velocity (eq. 19) [m/s]; z: () CoM height reference [m].
        R_base: (3, 3) trunk orientation reference; heading: (2,) unit walking direction.
        swing: (4,) bool swing mask; p_sw, v_sw, a_sw: (4, 3) swing-foot references.
    """

    v_xy: jax.Array
    z: jax.Array
    R_base: jax.Array
    heading: jax.Array
    swing: jax.Array
    p_sw: jax.Array
    v_sw: jax.Array
    a_sw: jax.Array


class CentroidalState(NamedTuple):
    """Controller memory: QP warm start, swing-error integrals sw_int (4, 3) [m s], arm posture q_post (6,)."""

    warm: QPResult
    sw_int: jax.Array
    q_post: jax.Array


class CentroidalDiag(NamedTuple):
    """Per-step command and QP health.

    Attributes:
        tau: (18,) applied (clipped) torques [N m]; tau_grf: (18,) the part -J_f,a^T f against the ground
        forces (the paper's Fig. 10 split: tau_qp = tau_star + tau_grf); f: (4, 3) QP ground forces [N];
        hdot_d: (6,) momentum-rate reference [N, N m]; prim_res, flag: ADMM residual and flag; iters: () int32
        ADMM iterations; tau_excess: () largest |tau| - limit before clipping [N m] (< 0: within).
    """

    tau: jax.Array
    tau_grf: jax.Array
    f: jax.Array
    hdot_d: jax.Array
    prim_res: jax.Array
    flag: jax.Array
    iters: jax.Array
    tau_excess: jax.Array


def centroidal_qp_settings(iters: int = 40) -> QPSettings:
    """ADMM settings of the centroidal controller: ``iters`` warm-started iterations, rho
    adapted every 10 from an initial 1, 5 Ruiz passes, the 18 equality rows (28)-(30) held exactly (the transport
    loop's :func:`control_qp_settings` otherwise: tolerance 1e-4, continued while unconverged up to 200)."""
    return control_qp_settings(iters, adapt_every=10, ruiz_iters=5, rho=1.0, eq_rows=6 + 3 * N_FEET)


@dataclass(frozen=True)
class CentroidalConfig:
    """Static structure (hashable): qp: ADMM settings; dt: control period [s]."""

    qp: QPSettings = centroidal_qp_settings()
    dt: float = 0.001

    @property
    def n_var(self) -> int:
        return 24 + 3 * N_FEET

    @property
    def n_con(self) -> int:
        return N_ROWS


def init_state(cfg: CentroidalConfig, qpos, ids: RobotIds) -> CentroidalState:
    """Cold warm-start, zero integrals, arm posture = the arm's joints in ``qpos`` (nq,)."""
    z = jnp.zeros
    warm = QPResult(x=z(cfg.n_var), y=z(cfg.n_con), z=z(cfg.n_con), prim_res=z(()), dual_res=z(()),
                    flag=jnp.zeros((), jnp.int32), iters=jnp.zeros((), jnp.int32), rho=z(()))
    return CentroidalState(warm=warm, sw_int=z((N_FEET, 3)), q_post=qpos[ids.act_qpos[12:]])


def scaled_model(dyn: DynTerms, s, armature) -> DynTerms:
    """The controller's view of the dynamics when every body mass and inertia is scaled by ``s``.

    M and h are linear in the body inertias; the rotor armature (nv_r,) is not a body inertia and stays.
    """
    arm = jnp.diag(armature)
    return dyn._replace(M=s * (dyn.M - arm) + arm, h=s * dyn.h, mass=s * dyn.mass, h_G=s * dyn.h_G)


def heading_frame(heading):
    """(3, 3) world-from-heading rotation: columns forward, lateral (left), up."""
    c, s = heading[0], heading[1]
    return jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def momentum_rate_reference(dyn: DynTerms, Ibar, ref: CentroidalRef, gains: CentroidalGains):
    """hdot_d (6,) of eqs. 23 and 25 (world frame, about the CoM) [N, N m]; dyn is the controller's model."""
    Rh = heading_frame(ref.heading)
    e_v = Rh[:2, :2].T @ (ref.v_xy - dyn.com_vel[:2])  # (forward, lateral) velocity error
    l_xy = dyn.mass * (Rh[:2, :2] @ (gains.kd_xy * e_v))
    l_z = dyn.mass * (gains.kp_z * (ref.z - dyn.com[2]) - gains.kd_z * dyn.com_vel[2])
    R = dyn.R_base
    e_R = R.T @ rot_error(ref.R_base, R)
    k = Ibar @ (R @ (gains.kp_rot * e_R - gains.kd_rot * (R.T @ dyn.omega_base)))
    return jnp.concatenate([l_xy, l_z[None], k])


class CentroidalQP(NamedTuple):
    """One control step's QP (26)-(32) in OSQP form, its torque map (eq. 34: ``tau = A_tau chi + b_tau``) and the
    momentum-rate reference."""

    P: jax.Array  # (n, n)
    q: jax.Array  # (n,)
    A: jax.Array  # (m, n)
    l: jax.Array  # (m,)
    u: jax.Array  # (m,)
    A_tau: jax.Array  # (18, n)
    b_tau: jax.Array  # (18,) [N m]
    hdot_d: jax.Array  # (6,) [N, N m]


def _cost(dyn: DynTerms, ct, ref: CentroidalRef, gains: CentroidalGains, q_post, q_arm, ids: RobotIds, n: int):
    """(27): ``(P, q, hdot_d)``, momentum-rate tracking with the linear rows in the heading frame, force weight W,
    arm posture, vdot regularisation; ``ct``: :func:`~wbc_jax.control.centroidal_dynamics.centroidal_terms`."""
    nv = ids.nv_robot
    four = ~jnp.any(ref.swing)
    hdot_d = momentum_rate_reference(dyn, ct.Ibar, ref, gains)
    Rh = heading_frame(ref.heading)
    T6 = jax.scipy.linalg.block_diag(Rh.T, jnp.eye(3))
    E = jnp.zeros((6, n)).at[:, :nv].set(T6 @ ct.A)
    b = T6 @ (hdot_d - ct.Adv)
    Qw = jnp.where(four, gains.q_four, gains.q_two)
    arm_v = ids.act_dof[12:]
    S_arm = jnp.zeros((6, n)).at[jnp.arange(6), arm_v].set(1.0)
    a_post = gains.kp_post * (q_post - q_arm) - gains.kd_post * dyn.v[arm_v]
    reg = jnp.concatenate([jnp.full(nv, gains.r_vdot), jnp.full(3 * N_FEET, gains.w_f)])
    P = E.T @ (Qw[:, None] * E) + gains.w_post * S_arm.T @ S_arm + jnp.diag(reg)
    q = -E.T @ (Qw * b) - gains.w_post * S_arm.T @ a_post
    return P, q, hdot_d


def _floating_base(dyn: DynTerms, Jf, g_load) -> ConstraintRows:
    """(28) the floating base's rows of the equations of motion, the payload's generalized force ``g_load``."""
    b28 = -dyn.h[0:6] + g_load[0:6]
    return ConstraintRows(jnp.concatenate([dyn.M[0:6], -Jf[:, 0:6].T], axis=1), b28, b28)


def _feet(dyn: DynTerms, Jf, ref: CentroidalRef, gains: CentroidalGains, sw_int, nv: int, n: int) -> ConstraintRows:
    """(29) stance feet: no slip with damping; (30) swing feet: operational-space tracking with the PID of (33)."""
    e_sw = ref.p_sw - dyn.p_foot
    a_sw = ref.a_sw + gains.kp_sw * e_sw + gains.ki_sw * sw_int + gains.kd_sw * (ref.v_sw - dyn.v_foot)
    b_feet = jnp.where(ref.swing[:, None], a_sw - dyn.Jdv_foot, -dyn.Jdv_foot - gains.alpha * dyn.v_foot).reshape(12)
    return ConstraintRows(jnp.zeros((12, n)).at[:, :nv].set(Jf), b_feet, b_feet)


def _friction_pyramids(gains: CentroidalGains, nv: int, n: int) -> ConstraintRows:
    """(31) per foot: f_x - mu f_z <= 0, f_x + mu f_z >= 0, the same for y."""
    inf = jnp.inf
    fr = jnp.array([[1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [0.0, 1.0, -1.0], [0.0, 1.0, 1.0]]) * jnp.array(
        [1.0, 1.0, gains.mu])
    return ConstraintRows(jnp.zeros((16, n)).at[:, nv:].set(jax.scipy.linalg.block_diag(*([fr] * N_FEET))),
                          jnp.tile(jnp.array([-inf, 0.0, -inf, 0.0]), N_FEET),
                          jnp.tile(jnp.array([0.0, inf, 0.0, inf]), N_FEET))


def _normal_force(ref: CentroidalRef, gains: CentroidalGains, nv: int, n: int) -> ConstraintRows:
    """Normal force in [f_min, f_max] in stance, 0 in swing (the pyramid then zeroes f_x, f_y)."""
    stance = ~ref.swing
    fz = jnp.zeros((N_FEET, n)).at[jnp.arange(N_FEET), nv + 3 * jnp.arange(N_FEET) + 2].set(1.0)
    return ConstraintRows(fz, jnp.where(stance, gains.f_min, 0.0), jnp.where(stance, gains.f_max, 0.0))


def build_qp(dyn: DynTerms, J_t, ref: CentroidalRef, gains: CentroidalGains, sw_int, q_post, q_arm,
             ids: RobotIds) -> CentroidalQP:
    """Assemble the QP (26)-(32) in OSQP form from the controller's model ``dyn``.

    Args:
        J_t: (3, nv_r) translational Jacobian of the tray's top centre (where the payload weighs).
        sw_int: (4, 3) swing-error integrals [m s]; q_post: (6,) arm posture [rad]; q_arm: (6,) arm joints now [rad].
    """
    nv = ids.nv_robot
    n = nv + 3 * N_FEET
    P, q, hdot_d = _cost(dyn, centroidal_terms(dyn), ref, gains, q_post, q_arm, ids, n)
    Jf = dyn.J_foot.reshape(3 * N_FEET, nv)  # (12, nv)
    F_load = jnp.array([0.0, 0.0, -gains.load_mass * GRAVITY])
    g_load = J_t.T @ F_load  # (nv,) generalized force of the payload
    act = jnp.asarray(ids.act_dof)
    A_tau = jnp.concatenate([dyn.M[act], -Jf[:, act].T], axis=1)  # (32) tau = A_tau chi + b_tau
    b_tau = dyn.h[act] - g_load[act]
    tmax = gains.tau_margin * jnp.asarray(ids.tau_max)
    rows = [_floating_base(dyn, Jf, g_load), _feet(dyn, Jf, ref, gains, sw_int, nv, n),
            _friction_pyramids(gains, nv, n), _normal_force(ref, gains, nv, n),
            ConstraintRows(A_tau, -tmax - b_tau, tmax - b_tau)]
    return CentroidalQP(P, q, jnp.concatenate([r.A for r in rows]), jnp.concatenate([r.l for r in rows]),
                        jnp.concatenate([r.u for r in rows]), A_tau, b_tau, hdot_d)


def swing_leg_feedback(dyn: DynTerms, ref: CentroidalRef, gains: CentroidalGains, ids: RobotIds):
    """(12,) eq. 36 for the legs: joint PD on one Gauss-Newton IK step of the swing reference (0 in stance)."""
    def one(J_foot, dofs, p_d, p, v_d, v):
        J = J_foot[:, dofs]  # (3, 3) foot velocity per own joint velocity
        JtJ = J.T @ J + 1e-6 * jnp.eye(3)
        d_th = jnp.linalg.solve(JtJ, J.T @ (p_d - p))  # theta_d - theta
        d_thd = jnp.linalg.solve(JtJ, J.T @ (v_d - v))  # thetadot_d - thetadot
        return gains.kp_joint * d_th + gains.kd_joint * d_thd

    dofs = jnp.asarray(ids.act_dof[:12]).reshape(N_FEET, 3)
    fb = jax.vmap(one)(dyn.J_foot, dofs, ref.p_sw, dyn.p_foot, ref.v_sw, dyn.v_foot)  # (4, 3)
    return jnp.where(ref.swing[:, None], fb, 0.0).reshape(12)


@full_precision
def centroidal_control(obs: Observation, ref: CentroidalRef, gains: CentroidalGains, cs: CentroidalState,
                       ids: RobotIds, cfg: CentroidalConfig):
    """One control step: momentum references, QP, torques (eqs. 34-36).

    Args:
        obs: what the controller reads of the state (:func:`wbc_jax.physics.observe.observe`; its ``robot`` terms
            are the true ones, which ``gains.mass_scale`` rescales into the controller's model).

    Returns:
        (tau (18,) actuator torques [N m], new CentroidalState, CentroidalDiag). An :func:`~wbc_jax.qp.unusable`
        solve is not applied: the last applied solution stands in, and the state's warm result carries it.
    """
    nv = ids.nv_robot
    dyn = obs.robot
    dyn_c = scaled_model(dyn, gains.mass_scale, obs.armature)
    J_t = obs.J_tray_top  # (3, nv)
    sw_int = jnp.where(ref.swing[:, None], cs.sw_int + (ref.p_sw - dyn.p_foot) * cfg.dt, 0.0)
    qp = build_qp(dyn_c, J_t, ref, gains, sw_int, cs.q_post, obs.qpos[ids.act_qpos[12:]], ids)
    res = last_usable(solve_qp(qp.P, qp.q, qp.A, qp.l, qp.u, warm=cs.warm, settings=cfg.qp), cs.warm)
    tau_qp = qp.A_tau @ res.x + qp.b_tau  # (34)
    sw_leg = jnp.concatenate([jnp.repeat(ref.swing, 3), jnp.zeros(6, bool)])
    fb = jnp.concatenate([swing_leg_feedback(dyn, ref, gains, ids), jnp.zeros(6)])
    tau_raw = jnp.where(sw_leg, gains.k_ff * tau_qp, tau_qp) + fb  # (35)
    tmax = jnp.asarray(ids.tau_max)
    tau = jnp.clip(tau_raw, -tmax, tmax)
    f = res.x[nv:]
    tau_grf = -dyn_c.J_foot.reshape(12, nv)[:, jnp.asarray(ids.act_dof)].T @ f
    diag = CentroidalDiag(tau=tau, tau_grf=tau_grf, f=f.reshape(N_FEET, 3), hdot_d=qp.hdot_d, prim_res=res.prim_res,
                          flag=res.flag, iters=res.iters, tau_excess=jnp.max(jnp.abs(tau_raw) - tmax))
    return tau, cs._replace(warm=res, sw_int=sw_int), diag
