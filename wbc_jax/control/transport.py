"""Transport whole-body controller (transport paper, Sec. IV-C), in JAX.

Decision variables (n = nv_r + k n_l + k n_c):
    zeta = [vdot (nv_r = 24), Lambda_gr (k per foot, 4 feet), Lambda_b (k per object contact, 4)].
Forces are non-negative combinations of friction-pyramid edges: F_gr = E_g Lambda_gr (ground, world z
normal), F_c = E_c Lambda_b (tray on object, tray z normal). The robot receives -F_c at the object's
contact points, i.e. the generalized force -J_o^T W_b with W_b = G F_c the object wrench about its CoM
and J_o the 6D Jacobian of the tray at the object's CoM.

Cost (7)-(8): ||H zeta - l||_Q + ||zeta||_R with H = [ground contact wrench about the robot's CoM;
object wrench about its CoM] and l = [F_com,ref - observer estimate + F_b,ref moved to the robot's CoM; F_b,ref]:
the ground carries the object's target wrench as a constant, so Lambda_b is no lever for the CoM row (issue 23;
``TransportConfig.object_lever`` restores the old row with the robot's net contact wrench, Lambda_b included).
Constraints, switched between stance and swing through bounds only (fixed shapes):
    (9)  floating-base rows of M vdot + h = J_f^T E_g Lambda_gr - J_o^T W_b Lambda_b
    (10) stance feet: J_f vdot = -Jdot v - kd_stance v_f          (free rows for swing feet)
    (11) tray at the object: J_o vdot = [a_b,des; alpha_b,des] - Jdot_o v
    (12) Lambda >= 0 (swing feet: Lambda_gr = 0), normal force >= f_min on stance feet
    (13) tau_min <= M_a vdot + h_a - J_f,a^T E_g Lambda_gr + J_o,a^T W_b Lambda_b <= tau_max
    (14) swing feet: a_cmd - gamma <= J_sw vdot + Jdot_sw v <= a_cmd + gamma, gamma >= 0, with gamma's cost
         1/2 r_slack |gamma|^2. At the optimum gamma = |J_sw vdot + Jdot_sw v - a_cmd| (componentwise), so the
         slack and its 24 band rows are eliminated: the cost term 1/2 r_slack |J_sw vdot + Jdot_sw v - a_cmd|^2
         has the same optimum in (vdot, Lambda) with 12 variables and 36 rows fewer (issue 22).
The first 24 rows ((9), (10), (11)) are equalities or free and are held exactly in the solver's x-update
(``QPSettings.eq_rows``).
Torques (Sec. IV-C-4) are evaluated from the solution with the same expression as (13) and drive the
motors directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.control.variants import FULL, Variant
from wbc_jax.qp import QPResult, QPSettings, solve_qp
from wbc_jax.spatial import GRAVITY, cone_edges, cube_inertia, edge_wrenches, full_precision, rot_error
from wbc_jax.types import DynTerms, ObjectModel, ObjectState, Observation, Reference, RobotIds

N_FEET = 4
N_OBJ = 4
N_EQ_ROWS = 6 + 3 * N_FEET + 6  # (9), (10), (11): the QP's first rows, held exactly by the solver


class TransportGains(NamedTuple):
    """Controller gains and weights: pytree leaves, so a batch axis over them needs no recompilation.

    Attributes (units in brackets; vectors are world-frame x, y, z):
        kp_com, kd_com: (3,) CoM position gains [N/m], [N s/m].
        kp_rot, kd_rot: (3,) trunk orientation gains [N m/rad], [N m s/rad].
        kp_obj, kd_obj: () object position gains [1/s^2], [1/s] (acceleration level).
        kp_obj_rot, kd_obj_rot: () object orientation gains [1/s^2], [1/s].
        kp_sw, kd_sw: () swing-foot gains [1/s^2], [1/s].
        kd_stance: () stance-foot velocity damping in (10) [1/s].
        kp_post, kd_post: () arm posture gains [1/s^2], [1/s] (acceleration level, null space of (11)).
        w_com: (6,) Q weights of the CoM wrench [1/N^2, 1/(N m)^2].
        w_obj_f, w_obj_t: () Q weights of the object force and torque.
        w_post: () Q weight of the arm posture task [1/(rad/s^2)^2].
        r_vdot, r_lam: () R regularisation of vdot and Lambda.
        r_slack: () weight of the swing slack gamma of (14), i.e. of the swing-foot acceleration error.
        k_obs: () momentum-observer gain [1/s]; 0 disables the observer.
        f_min: () minimum normal force per stance foot [N].
        f_max: () normal-force cap of a fully loaded stance foot [N] (scaled by Reference.load).
        tau_margin: () fraction of the torque limit the QP may use.
    """

    kp_com: jax.Array
    kd_com: jax.Array
    kp_rot: jax.Array
    kd_rot: jax.Array
    kp_obj: jax.Array
    kd_obj: jax.Array
    kp_obj_rot: jax.Array
    kd_obj_rot: jax.Array
    kp_sw: jax.Array
    kd_sw: jax.Array
    kd_stance: jax.Array
    kp_post: jax.Array
    kd_post: jax.Array
    w_com: jax.Array
    w_obj_f: jax.Array
    w_obj_t: jax.Array
    w_post: jax.Array
    r_vdot: jax.Array
    r_lam: jax.Array
    r_slack: jax.Array
    k_obs: jax.Array
    f_min: jax.Array
    f_max: jax.Array
    tau_margin: jax.Array


def default_gains() -> TransportGains:
    """Defaults; public-code values where they exist (see README, "Transport controller")."""
    f = lambda *x: jnp.asarray(x if len(x) > 1 else x[0], dtype=float)  # noqa: E731
    return TransportGains(
        kp_com=f(2000.0, 2000.0, 2000.0), kd_com=f(300.0, 300.0, 300.0),
        kp_rot=f(600.0, 600.0, 600.0), kd_rot=f(50.0, 50.0, 50.0),
        kp_obj=f(250.0), kd_obj=f(50.0), kp_obj_rot=f(250.0), kd_obj_rot=f(50.0),
        kp_sw=f(1500.0), kd_sw=f(80.0), kd_stance=f(10.0), kp_post=f(100.0), kd_post=f(20.0),
        w_com=f(50.0, 50.0, 50.0, 50.0, 50.0, 50.0), w_obj_f=f(1000.0), w_obj_t=f(10000.0), w_post=f(1.0),
        r_vdot=f(1e-3), r_lam=f(1e-3), r_slack=f(1000.0), k_obs=f(10.0), f_min=f(2.0), f_max=f(400.0), tau_margin=f(0.98),
    )


class ObserverState(NamedTuple):
    """First-order centroidal momentum observer ([33]): r = K_O (h_G - h_G0 - int(W + m g + r) dt).

    Attributes: h0 (6,) initial momentum; integral (6,); r (6,) estimated external wrench about the
    CoM [N, N m]; w_cmd (6,) last commanded net contact wrench about the CoM.
    """

    h0: jax.Array
    integral: jax.Array
    r: jax.Array
    w_cmd: jax.Array


class ControlState(NamedTuple):
    """Controller memory between steps: warm start, observer, the arm's nominal posture q_post (6,)
    [rad] (its configuration at the start), and the run's ablation switches (:mod:`wbc_jax.control.variants`;
    data, constant over the run)."""

    warm: QPResult
    obs: ObserverState
    q_post: jax.Array
    variant: Variant


def control_qp_settings(iters: int = 4, **kw) -> QPSettings:
    """ADMM settings for the control loop (``kw``: other :class:`~wbc_jax.qp.QPSettings` fields).

    ``iters`` warm-started iterations (the previous step's x, z, y), then blocks of 4 more (``check_every``) while the
    residuals are outside the tolerance 1e-4 (abs and rel, OSQP's test) up to 200 (``max_iters``); the QP's first ``N_EQ_ROWS`` rows (floating base, stance feet,
    tray: equalities, or free for a swing foot) held exactly in every x-update (``eq_rows``); rho fixed at 3 on the
    remaining (inequality) rows, so one factorization per step; 2 Ruiz passes; the linear solve picked per backend (``linsolve="auto"``: Cholesky on the CPU, explicit inverse on a GPU); on a GPU the whole solve (equilibration, factorization, the iterations with the extension, residuals and flag) in three Pallas kernels of one program per problem (``kernel="auto"``, :mod:`wbc_jax.qp.fused`).

    Evidence, issue 22 (2026-11-25, CPU, float32; ``bench qp-rollout``'s acceptance: relative objective error
    <= 1e-3 and violation <= 1e-4 of max(1, |Ax|) against OSQP at eps 1e-9). Before: the swing slack (12
    variables, 36 rows), equalities through ``rho * 1e3``, 20 iterations at rho 1: course scene, 4 factor cells,
    first 4 s in closed loop: 15.7 % of the control steps flagged, 73.6 % of sampled QPs accepted. Chain of 1,499
    consecutive QPs of two cells from a closed loop (1.5-3.0 s on the course, each variant warm-started from its
    own previous solution; OSQP on every 10th)::

        variant (slack eliminated)                    flagged   accepted   mean / max iterations
        20, rho 1                                      1.20 %    96.3 %     20 / 20
        20, rho 1, equalities exact                    1.20 %    97.0 %     20 / 20
        20, rho 3, equalities exact                    0.40 %    100 %      20 / 20
        20, rho 10, equalities exact                   0.40 %    100 %      20 / 20
        20, rho 3, equalities exact, up to 200         0         100 %      20.08 / 40
        15, rho 3, equalities exact, up to 200         0         95.0 %     15.1 / 35
        10, same, tolerance 1e-4 (the default)         0         100 %      15.4 / 160
        5 / 15 / 20, same, tolerance 1e-4              0         100 %      13.2 / 17.3 / 20.7

    Closed loop on the course (4 cells, first 6 s, 2,400 sampled QPs), 20 iterations at tolerance 1e-3 with the
    extension: 0 of 24,000 control steps flagged, 99.83 % accepted (the 4 rejected: violations 1.04-2.1e-4, within
    the flag test's 1e-3 but not the acceptance's 1e-4); hence the tolerance 1e-4, which the extension reaches in
    float32 (mean over the runs and steps of the largest count of a step: 16.1 iterations on the chain).

    2026-11-26 (H100, course, Warp physics; ``bench rollout --batches 16384 --steps 50 --qp ...``, one call):
    physics + WBC env-steps/s with 10 fixed iterations and a test every 10 (the earlier default) 1,269,134; 5 and 5:
    1,370,667; **4 and 4: 1,392,525**; 3 and 3: 1,391,377; 5 and 3: 1,369,869. Every problem stops at its own
    converged test, so the accuracy holds by the same test. Paper campaign (H100): mean iterations per step 20.8 ->
    16.4, no run flagged (worst 0.027 % of its steps), R, T, S equal to the 4th digit; 2,700 runs: none flagged.

    Reading: eliminating the slack did most (its band rows relaxed toward the warm point slowly); the steps still
    flagged are touchdowns (every 265 steps, all runs at once), which need 30-40 iterations; the convergence-checked
    extension gives them those, at +0.4 % iterations on average. Two fixes made the test honest: rows without
    bounds (a swing foot's rows) now have z = A x (their relaxed z lagged behind and was counted as a primal
    residual), and a warm point is projected onto the exact rows before iterating.
    """
    return QPSettings(**{**dict(iters=iters, eps_abs=1e-4, eps_rel=1e-4, linsolve="auto", adapt_every=0,
                                rho=3.0, ruiz_iters=2, eq_rows=N_EQ_ROWS, max_iters=200, check_every=4,
                                kernel="auto"),
                          **kw})


@dataclass(frozen=True)
class TransportConfig:
    """Static controller structure (hashable; changing it recompiles).

    Attributes:
        k: friction-pyramid edges; qp: ADMM settings; dt: control period [s].
        object_lever: the CoM-wrench cost row takes the object's reaction on the robot from the decision
            variables Lambda_b (the behaviour before issue 23). The QP then trades object wrench for CoM wrench
            during two-foot support, plans an object wrench the cube's motion does not produce, and the tray is
            pushed off its path by the difference (T grows with m, mu, d: docs/method.md, "T's dependence on m,
            mu, d"). Default False: that row carries the object's *target* wrench F_b,ref as a constant.
    """

    k: int = 4
    qp: QPSettings = control_qp_settings()
    dt: float = 0.001
    object_lever: bool = False

    @property
    def n_var(self) -> int:
        return 24 + self.k * (N_FEET + N_OBJ)

    @property
    def n_con(self) -> int:
        return N_EQ_ROWS + 4 + 18 + self.k * (N_FEET + N_OBJ)


class QPDiag(NamedTuple):
    """Per-step QP health and command: tau (18,) applied (clipped) torques [N m], prim_res, dual_res, flag,
    tau_excess: () largest amount by which the unclipped QP torque exceeded its limit [N m] (< 0: within),
    iters: () int32 ADMM iterations the step took, obj_forces: (4, 3) the object contact forces the solution
    plans, tray contact frame, normal first [N] (:func:`planned_object_forces`)."""

    tau: jax.Array
    prim_res: jax.Array
    dual_res: jax.Array
    flag: jax.Array
    tau_excess: jax.Array
    iters: jax.Array
    obj_forces: jax.Array


def planned_object_forces(x, mu, nv: int, k: int) -> jax.Array:
    """The object contact forces F_c,i = E_c Lambda_b,i of a QP solution ``x`` (n,), in the tray's contact frame
    (E_c = ``cone_edges(mu, k)``, z = the contact normal), normal first: (N_OBJ, 3) [N].

    Args:
        x: [vdot (nv), Lambda_gr (k N_FEET), Lambda_b (k N_OBJ)]; mu: () tray friction; nv, k: static sizes.
    """
    lam_b = x[nv + k * N_FEET: nv + k * (N_FEET + N_OBJ)].reshape(N_OBJ, k)
    f = lam_b @ cone_edges(mu, k).T  # (N_OBJ, 3) x, y tangential, z normal
    return jnp.concatenate([f[:, 2:3], f[:, 0:2]], axis=1)


def contact_points(obj: ObjectState, om: ObjectModel):
    """(4, 3) world positions of the object's bottom contact points (A3)."""
    h = om.side / 2 - om.inset
    local = jnp.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]]) * h
    local = jnp.concatenate([local, -jnp.full((4, 1), om.side / 2)], axis=1)
    return obj.p + local @ obj.R.T


def init_control_state(cfg: TransportConfig, dyn: DynTerms, ids: RobotIds) -> ControlState:
    n, mcon = cfg.n_var, cfg.n_con
    z = jnp.zeros
    # no warm point yet (zeros), but a valid rho: the settings' initial rho (a 0 would be clipped to rho_min and,
    # with rho adaptation off, kept for the whole run)
    warm = QPResult(x=z(n), y=z(mcon), z=z(mcon), prim_res=z(()), dual_res=z(()),
                    flag=jnp.zeros((), jnp.int32), iters=jnp.zeros((), jnp.int32), rho=z(()) + cfg.qp.rho)
    obs = ObserverState(h0=dyn.h_G, integral=z(6), r=z(6), w_cmd=z(6))
    return ControlState(warm=warm, obs=obs, q_post=dyn.q[ids.act_qpos[12:]],
                        variant=Variant(*(jnp.asarray(v, float) for v in FULL)))


def observer_update(obs: ObserverState, dyn: DynTerms, k_obs, dt) -> ObserverState:
    """One Euler step of the momentum observer, using last step's commanded contact wrench."""
    g = jnp.array([0.0, 0.0, -GRAVITY * dyn.mass, 0.0, 0.0, 0.0])
    integral = obs.integral + (obs.w_cmd + g + obs.r) * dt
    r = k_obs * (dyn.h_G - obs.h0 - integral)
    return obs._replace(integral=integral, r=r)


def build_qp(dyn: DynTerms, obj: ObjectState, J_o, Jdv_o, ref: Reference, om: ObjectModel, gains: TransportGains,
             r_ext, ids: RobotIds, cfg: TransportConfig, mu_ground, q_post, variant: Variant = FULL):
    """Assemble the QP in OSQP form.

    ``q_post`` (6,) is the arm's nominal posture [rad]; the posture task only acts in the null space
    of the tray constraint (11): without it that null space is free and the QP uses the arm as a
    reaction wheel (joint accelerations of 1000 rad/s^2 at the torque limits, flipping sign within a
    millisecond) to make up the moment two stance feet cannot produce.
    ``variant``: ablation switches (:mod:`wbc_jax.control.variants`): ``tray_cone`` scales the object-wrench
    weights and, at 0, pins the object's contact multipliers to 0; ``posture`` scales the posture weight.
    ``mu_ground``: () or (4,) friction coefficient of the ground under each foot (the rollout passes the
    surface each foot is nearest to: floor or a block, :func:`wbc_jax.physics.contacts.foot_ground`).

    Returns:
        (P (n, n), q (n,), A (m, n), l (m,), u (m,), A_tau (18, n), h_a (18,), H_com (6, n)) where
        tau = A_tau zeta + h_a and H_com zeta is the robot's net contact wrench about its CoM.
    """
    k, nv = cfg.k, ids.nv_robot
    ng, nb = k * N_FEET, k * N_OBJ
    n = nv + ng + nb
    inf = jnp.inf
    stance = ~ref.swing

    # friction pyramids: each multiplier's generalized force and wrenches, per point (no block-diagonal matrices)
    mu_feet = jnp.broadcast_to(jnp.asarray(mu_ground, dyn.M.dtype), (N_FEET,))  # () or (4,): per foot's surface
    Eg_feet = jax.vmap(lambda mu: cone_edges(mu, k))(mu_feet)  # (4, 3, k) ground normal = world z
    Ec = jnp.broadcast_to(cone_edges(om.mu, k, dyn.R_tray), (N_OBJ, 3, k))  # contact normal = tray z axis
    p_c = contact_points(obj, om)

    Jf = dyn.J_foot.reshape(12, nv)  # (12, nv)
    JfE = jnp.einsum("fcv,fcj->vfj", dyn.J_foot, Eg_feet).reshape(nv, ng)  # (nv, 4k) gen. force per ground multiplier
    Wb = edge_wrenches(p_c, obj.p, Ec)  # (6, 4k) object wrench about its CoM
    JoW = J_o.T @ Wb  # (nv, 4k) generalized force on the robot is -JoW Lambda_b

    # ---- cost: ground contact wrench about the robot's CoM, object wrench about its CoM
    H = jnp.zeros((12, n))
    H = H.at[0:6, nv : nv + ng].set(edge_wrenches(dyn.p_foot, dyn.com, Eg_feet))
    H_net = H[0:6].at[:, nv + ng : nv + ng + nb].set(-edge_wrenches(p_c, dyn.com, Ec))  # + the object's reaction
    if cfg.object_lever:
        H = H.at[0:6].set(H_net)
    H = H.at[6:12, nv + ng : nv + ng + nb].set(Wb)

    # CoM wrench reference: F = Kp e + Kd edot + m g + M_com a_ref
    m_r = dyn.mass
    e_p, e_v = ref.p_com - dyn.com, ref.v_com - dyn.com_vel
    e_o = rot_error(ref.R_base, dyn.R_base)
    e_w = -dyn.omega_base
    f_com = gains.kp_com * e_p + gains.kd_com * e_v + m_r * (ref.a_com + jnp.array([0.0, 0.0, GRAVITY]))
    t_com = gains.kp_rot * e_o + gains.kd_rot * e_w

    # object: F_b = M_b (a_ref + Kd edot + Kp e) + C_b V_b + N_b, world frame
    a_b = ref.a_obj + gains.kd_obj * (ref.v_obj - obj.v) + gains.kp_obj * (ref.p_obj - obj.p)
    al_b = gains.kd_obj_rot * (-obj.omega) + gains.kp_obj_rot * rot_error(ref.R_obj, obj.R)
    I_b = cube_inertia(om.mass, om.side)
    f_b = om.mass * (a_b + jnp.array([0.0, 0.0, GRAVITY]))
    t_b = I_b * al_b  # cube: isotropic inertia, omega x I omega = 0

    # the ground wrench carries the CoM reference plus the object: its target wrench F_b,ref, moved to the robot's
    # CoM, is a constant of the row, not a function of Lambda_b (object_lever: the old, variable form)
    l_com = jnp.concatenate([f_com, t_com]) - r_ext
    if not cfg.object_lever:
        l_com = l_com + jnp.concatenate([f_b, t_b + jnp.cross(obj.p - dyn.com, f_b)])
    # arm posture: vdot_arm = Kp (q_post - q) - Kd qdot
    arm_v, arm_q = ids.act_dof[12:], ids.act_qpos[12:]
    H = jnp.concatenate([H, jnp.zeros((6, n)).at[jnp.arange(6), arm_v].set(1.0)])
    a_post = gains.kp_post * (q_post - dyn.q[arm_q]) - gains.kd_post * dyn.v[arm_v]
    l_vec = jnp.concatenate([l_com, f_b, t_b, a_post])
    Qw = jnp.concatenate([gains.w_com, jnp.full(3, gains.w_obj_f * variant.tray_cone),
                          jnp.full(3, gains.w_obj_t * variant.tray_cone), jnp.full(6, gains.w_post * variant.posture)])
    Rw = jnp.concatenate([jnp.full(nv, gains.r_vdot), jnp.full(ng + nb, gains.r_lam)])
    # (14) swing feet, slack eliminated: 1/2 r_slack |J_sw vdot - b14|^2 with b14 = a_cmd - Jdot_sw v
    sw3 = jnp.repeat(ref.swing, 3)
    a_cmd = ref.a_sw + gains.kd_sw * (ref.v_sw - dyn.v_foot) + gains.kp_sw * (ref.p_sw - dyn.p_foot)
    b14 = (a_cmd - dyn.Jdv_foot).reshape(12)
    H = jnp.concatenate([H, jnp.zeros((12, n)).at[:, :nv].set(dyn.J_foot.reshape(12, nv))])
    l_vec = jnp.concatenate([l_vec, b14])
    Qw = jnp.concatenate([Qw, jnp.where(sw3, gains.r_slack, 0.0)])
    P = H.T @ (Qw[:, None] * H) + jnp.diag(Rw)
    q = -H.T @ (Qw * l_vec)

    # ---- constraints
    iv, ig, ib = slice(0, nv), slice(nv, nv + ng), slice(nv + ng, n)
    act = jnp.asarray(ids.act_dof)
    rows, lo, hi = [], [], []

    def add(Arow, lrow, urow):
        rows.append(Arow), lo.append(lrow), hi.append(urow)

    # (9) floating base
    A9 = jnp.zeros((6, n)).at[:, iv].set(dyn.M[0:6]).at[:, ig].set(-JfE[0:6]).at[:, ib].set(JoW[0:6])
    add(A9, -dyn.h[0:6], -dyn.h[0:6])
    # (10) stance feet
    st3 = jnp.repeat(stance, 3)
    b10 = -(dyn.Jdv_foot + gains.kd_stance * dyn.v_foot).reshape(12)
    add(jnp.zeros((12, n)).at[:, iv].set(Jf), jnp.where(st3, b10, -inf), jnp.where(st3, b10, inf))
    # (11) tray at the object follows the object's desired acceleration
    b11 = jnp.concatenate([a_b, al_b]) - Jdv_o
    add(jnp.zeros((6, n)).at[:, iv].set(J_o), b11, b11)
    # (12b) normal force of stance feet between f_min and the (ramped) cap
    An = jnp.zeros((4, n)).at[:, ig].set((jnp.eye(N_FEET)[:, :, None] * Eg_feet[None, :, 2, :]).reshape(N_FEET, ng))
    cap = gains.f_max * ref.load
    add(An, jnp.where(stance, jnp.minimum(gains.f_min, cap), -inf), jnp.where(stance, cap, inf))
    # (13) torque limits
    A_tau = jnp.zeros((18, n)).at[:, iv].set(dyn.M[act]).at[:, ig].set(-JfE[act]).at[:, ib].set(JoW[act])
    h_a = dyn.h[act]
    tmax = gains.tau_margin * jnp.asarray(ids.tau_max)
    add(A_tau, -tmax - h_a, tmax - h_a)
    # (12) multipliers
    add(jnp.zeros((ng, n)).at[:, ig].set(jnp.eye(ng)), jnp.zeros(ng), jnp.where(jnp.repeat(stance, k), inf, 0.0))
    add(jnp.zeros((nb, n)).at[:, ib].set(jnp.eye(nb)), jnp.zeros(nb),  # the tray cone; pinned to 0 without it
        jnp.full(nb, jnp.where(jnp.asarray(variant.tray_cone) > 0, inf, 0.0)))

    A = jnp.concatenate(rows)
    l = jnp.concatenate(lo)
    u = jnp.concatenate(hi)
    return P, q, A, l, u, A_tau, h_a, H_net


@full_precision
def assemble(obs: Observation, ref: Reference, om: ObjectModel, gains: TransportGains, cs: ControlState,
             ids: RobotIds, cfg: TransportConfig, mu_ground=1.0):
    """Observer step and the QP of this control step: (new ObserverState, :func:`build_qp`'s outputs)."""
    dyn = obs.robot
    observer = observer_update(cs.obs, dyn, gains.k_obs * cs.variant.observer, cfg.dt)
    return observer, build_qp(dyn, obs.obj, obs.J_tray_obj, obs.Jdv_tray_obj, ref, om, gains, observer.r, ids, cfg,
                              mu_ground, cs.q_post, cs.variant)


@full_precision
def transport_control(obs: Observation, ref: Reference, om: ObjectModel, gains: TransportGains,
                      cs: ControlState, ids: RobotIds, cfg: TransportConfig, mu_ground=1.0):
    """One control step: observer, QP, torques.

    Args:
        obs: what the controller reads of the state (:func:`wbc_jax.physics.observe.observe`); ref: the planner's
            reference; om: the controller's object model; gains; cs: its state; ids: static ids; cfg: its
            static configuration; mu_ground: () or (4,) friction under each foot.

    Returns:
        (tau (18,) actuator torques [N m], new ControlState, QPDiag).
    """
    with jax.named_scope("qp_assemble"):
        observer, (P, q, A, l, u, A_tau, h_a, H_com) = assemble(obs, ref, om, gains, cs, ids, cfg, mu_ground)
    # the multiplier rows (12) are the QP's last rows, each bounding one of its last variables (QPSettings.box_rows)
    res = solve_qp(P, q, A, l, u, warm=cs.warm, settings=cfg.qp._replace(box_rows=cfg.k * (N_FEET + N_OBJ)))
    tau_raw = A_tau @ res.x + h_a
    tmax = jnp.asarray(ids.tau_max)
    tau = jnp.clip(tau_raw, -tmax, tmax)
    # commanded net contact wrench about the CoM, for the observer's next step
    observer = observer._replace(w_cmd=H_com @ res.x)
    diag = QPDiag(tau=tau, prim_res=res.prim_res, dual_res=res.dual_res, flag=res.flag,
                  tau_excess=jnp.max(jnp.abs(tau_raw) - tmax), iters=res.iters,
                  obj_forces=planned_object_forces(res.x, om.mu, ids.nv_robot, cfg.k))
    return tau, cs._replace(warm=res, obs=observer), diag
