"""The transport controller's QP (transport paper, Sec. IV-C) in OSQP form, one function per block.

Decision variables (n = nv_r + k n_l + k n_c):
    zeta = [vdot (nv_r = 24), Lambda_gr (k per foot, 4 feet), Lambda_b (k per object contact, 4)].
Forces are non-negative combinations of friction-pyramid edges: F_gr = E_g Lambda_gr (ground, world z normal),
F_c = E_c Lambda_b (tray on object, tray z normal). The robot receives -F_c at the object's contact points, i.e.
the generalized force -J_o^T W_b with W_b = G F_c the object wrench about its CoM and J_o the 6D Jacobian of the
tray at the object's CoM.

    (7)-(8) cost ||H zeta - l||_Q + ||zeta||_R: the ground wrench about the robot's CoM tracks F_com,ref minus the
         observer's estimate plus the object's target wrench F_b,ref moved to the robot's CoM (a constant of the
         row, so Lambda_b is no lever for it); the object wrench tracks F_b,ref; an arm posture task in the null
         space of (11); the swing-foot acceleration error of (14)
    (9)  floating-base rows of M vdot + h = J_f^T E_g Lambda_gr - J_o^T W_b Lambda_b
    (10) stance feet: J_f vdot = -Jdot v - kd_stance v_f (free rows for swing feet)
    (11) tray at the object: J_o vdot = [a_b,des; alpha_b,des] - Jdot_o v
    (12) Lambda >= 0 (swing feet: Lambda_gr = 0), normal force of stance feet in [f_min, f_max load]
    (13) tau_min <= M_a vdot + h_a - J_f,a^T E_g Lambda_gr + J_o,a^T W_b Lambda_b <= tau_max
    (14) swing feet: a_cmd - gamma <= J_sw vdot + Jdot_sw v <= a_cmd + gamma with gamma's cost 1/2 r_slack |gamma|^2.
         At the optimum gamma = |J_sw vdot + Jdot_sw v - a_cmd| componentwise, so the slack and its band rows are
         eliminated: the cost term 1/2 r_slack |J_sw vdot + Jdot_sw v - a_cmd|^2 has the same optimum in
         (vdot, Lambda) with 12 variables and 36 rows fewer.

Stance and swing switch through bounds only (fixed shapes). Rows in order (9), (10), (11), normal force, (13),
multipliers: the first ``N_EQ_ROWS`` are equalities or free and are held exactly in the solver's x-update
(``QPSettings.eq_rows``); the multiplier rows come last, each bounding one of the last variables
(``QPSettings.box_rows``). Torques (Sec. IV-C-4) are ``A_tau zeta + h_a``, the same expression as (13).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.control.variants import FULL, Variant
from wbc_jax.runtime.transfer import to_device
from wbc_jax.spatial import GRAVITY, cone_edges, cube_inertia, edge_wrenches, rot_error
from wbc_jax.types import DynTerms, ObjectModel, ObjectState, Reference, RobotIds

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
    """Defaults; public-code values where they exist (docs/method.md, "Transport controller")."""
    f = lambda *x: to_device(x if len(x) > 1 else x[0], float)  # noqa: E731
    return TransportGains(
        kp_com=f(2000.0, 2000.0, 2000.0), kd_com=f(300.0, 300.0, 300.0),
        kp_rot=f(600.0, 600.0, 600.0), kd_rot=f(50.0, 50.0, 50.0),
        kp_obj=f(250.0), kd_obj=f(50.0), kp_obj_rot=f(250.0), kd_obj_rot=f(50.0),
        kp_sw=f(1500.0), kd_sw=f(80.0), kd_stance=f(10.0), kp_post=f(100.0), kd_post=f(20.0),
        w_com=f(50.0, 50.0, 50.0, 50.0, 50.0, 50.0), w_obj_f=f(1000.0), w_obj_t=f(10000.0), w_post=f(1.0),
        r_vdot=f(1e-3), r_lam=f(1e-3), r_slack=f(1000.0), k_obs=f(10.0), f_min=f(2.0), f_max=f(400.0),
        tau_margin=f(0.98),
    )


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


class Columns(NamedTuple):
    """The blocks of zeta: vdot (``nv``), Lambda_gr (``k`` per foot), Lambda_b (``k`` per object contact)."""

    nv: int
    k: int

    @property
    def ng(self) -> int:
        return self.k * N_FEET

    @property
    def nb(self) -> int:
        return self.k * N_OBJ

    @property
    def n(self) -> int:
        return self.nv + self.ng + self.nb

    @property
    def iv(self) -> slice:
        return slice(0, self.nv)

    @property
    def ig(self) -> slice:
        return slice(self.nv, self.nv + self.ng)

    @property
    def ib(self) -> slice:
        return slice(self.nv + self.ng, self.n)


class ContactMaps(NamedTuple):
    """Friction pyramids and what one unit of each multiplier does (world frame)."""

    Eg: jax.Array  # (N_FEET, 3, k) ground pyramid edges per foot (normal: world z)
    Ec: jax.Array  # (N_OBJ, 3, k) tray pyramid edges per object contact (normal: tray z)
    p_c: jax.Array  # (N_OBJ, 3) object contact points [m]
    JfE: jax.Array  # (nv, ng) generalized force per ground multiplier
    Wb: jax.Array  # (6, nb) object wrench about its CoM per object multiplier
    JoW: jax.Array  # (nv, nb) J_o^T W_b: the robot receives -JoW Lambda_b


class ObjectTarget(NamedTuple):
    """The object's desired acceleration and wrench F_b,ref = M_b (a_ref + Kd e_dot + Kp e) + C_b V_b + N_b."""

    acc: jax.Array  # (6,) [a_b,des; alpha_b,des] [m/s^2, rad/s^2]
    force: jax.Array  # (3,) [N]
    torque: jax.Array  # (3,) about its CoM [N m]


class CostRows(NamedTuple):
    """Rows of the cost 1/2 sum_i w_i (H_i zeta - l_i)^2 (the paper's ||H zeta - l||_Q), zero outside the columns
    ``cols`` (static)."""

    H: jax.Array  # (r, len(cols)): the rows on their columns
    l: jax.Array  # (r,) target
    w: jax.Array  # (r,) weight
    cols: slice  # the columns of zeta the rows span


class ConstraintRows(NamedTuple):
    """Rows ``l <= A zeta <= u`` (``+-inf``: no bound)."""

    A: jax.Array  # (r, n)
    l: jax.Array  # (r,)
    u: jax.Array  # (r,)


class TransportQP(NamedTuple):
    """One control step's QP in OSQP form and its torque map (``tau = A_tau zeta + h_a``, Sec. IV-C-4)."""

    P: jax.Array  # (n, n)
    q: jax.Array  # (n,)
    A: jax.Array  # (m, n)
    l: jax.Array  # (m,)
    u: jax.Array  # (m,)
    A_tau: jax.Array  # (18, n)
    h_a: jax.Array  # (18,) [N m]
    H_com: jax.Array  # (6, n): H_com zeta is the robot's net contact wrench about its CoM [N, N m]


def _contact_maps(dyn: DynTerms, obj: ObjectState, J_o, om: ObjectModel, mu_ground, cols: Columns) -> ContactMaps:
    """``mu_ground``: () or (4,) friction under each foot."""
    mu_feet = jnp.broadcast_to(jnp.asarray(mu_ground, dyn.M.dtype), (N_FEET,))
    Eg = jax.vmap(lambda mu: cone_edges(mu, cols.k))(mu_feet)
    Ec = jnp.broadcast_to(cone_edges(om.mu, cols.k, dyn.R_tray), (N_OBJ, 3, cols.k))
    p_c = contact_points(obj, om)
    JfE = jnp.einsum("fcv,fcj->vfj", dyn.J_foot, Eg).reshape(cols.nv, cols.ng)
    Wb = edge_wrenches(p_c, obj.p, Ec)
    return ContactMaps(Eg, Ec, p_c, JfE, Wb, J_o.T @ Wb)


def _com_wrench_reference(dyn: DynTerms, ref: Reference, gains: TransportGains):
    """(6,) F_com,ref = Kp e + Kd e_dot + m g + m a_ref (force, then torque; world frame) [N, N m]."""
    e_p, e_v = ref.p_com - dyn.com, ref.v_com - dyn.com_vel
    e_o = rot_error(ref.R_base, dyn.R_base)
    e_w = -dyn.omega_base
    f_com = gains.kp_com * e_p + gains.kd_com * e_v + dyn.mass * (ref.a_com + jnp.array([0.0, 0.0, GRAVITY]))
    t_com = gains.kp_rot * e_o + gains.kd_rot * e_w
    return jnp.concatenate([f_com, t_com])


def _object_target(obj: ObjectState, ref: Reference, om: ObjectModel, gains: TransportGains) -> ObjectTarget:
    a_b = ref.a_obj + gains.kd_obj * (ref.v_obj - obj.v) + gains.kp_obj * (ref.p_obj - obj.p)
    al_b = gains.kd_obj_rot * (-obj.omega) + gains.kp_obj_rot * rot_error(ref.R_obj, obj.R)
    I_b = cube_inertia(om.mass, om.side)
    f_b = om.mass * (a_b + jnp.array([0.0, 0.0, GRAVITY]))
    t_b = I_b * al_b  # cube: isotropic inertia, omega x I omega = 0
    return ObjectTarget(jnp.concatenate([a_b, al_b]), f_b, t_b)


def _cost_com_wrench(dyn, obj, ref, maps: ContactMaps, target: ObjectTarget, r_ext, gains, cols) -> CostRows:
    """(7) f_1: the ground contact wrench about the robot's CoM tracks F_com,ref minus the observer's estimate
    ``r_ext`` (6,), plus the object's target wrench moved to the robot's CoM (the ground also carries the object)."""
    l = _com_wrench_reference(dyn, ref, gains) - r_ext
    l = l + jnp.concatenate([target.force, target.torque + jnp.cross(obj.p - dyn.com, target.force)])
    return CostRows(edge_wrenches(dyn.p_foot, dyn.com, maps.Eg), l, gains.w_com, cols.ig)


def _cost_object_wrench(maps: ContactMaps, target: ObjectTarget, gains, variant: Variant, cols) -> CostRows:
    """(8) f_2: the object wrench of the tray's contact forces tracks F_b,ref (weight scaled by ``tray_cone``)."""
    w = jnp.concatenate([jnp.full(3, gains.w_obj_f * variant.tray_cone),
                         jnp.full(3, gains.w_obj_t * variant.tray_cone)])
    return CostRows(maps.Wb, jnp.concatenate([target.force, target.torque]), w, cols.ib)


def _cost_arm_posture(dyn: DynTerms, ids: RobotIds, q_post, gains, variant: Variant, cols) -> CostRows:
    """Arm posture: vdot_arm tracks Kp (q_post - q) - Kd qdot. Without it the null space of (11) is free and the
    QP uses the arm as a reaction wheel for the moment two stance feet cannot produce."""
    arm_v, arm_q = ids.act_dof[12:], ids.act_qpos[12:]
    H = jnp.zeros((6, cols.nv)).at[jnp.arange(6), arm_v].set(1.0)
    a_post = gains.kp_post * (q_post - dyn.q[arm_q]) - gains.kd_post * dyn.v[arm_v]
    return CostRows(H, a_post, jnp.full(6, gains.w_post * variant.posture), cols.iv)


def _cost_swing_feet(dyn: DynTerms, ref: Reference, gains, cols) -> CostRows:
    """(14) with the slack eliminated: 1/2 r_slack |J_sw vdot - (a_cmd - Jdot_sw v)|^2 on swing feet."""
    sw3 = jnp.repeat(ref.swing, 3)
    a_cmd = ref.a_sw + gains.kd_sw * (ref.v_sw - dyn.v_foot) + gains.kp_sw * (ref.p_sw - dyn.p_foot)
    b14 = (a_cmd - dyn.Jdv_foot).reshape(12)
    return CostRows(dyn.J_foot.reshape(12, cols.nv), b14, jnp.where(sw3, gains.r_slack, 0.0), cols.iv)


def _quadratic_cost(blocks, gains, cols):
    """``(P, q)`` of ``||H zeta - l||_Q + ||zeta||_R`` from the cost blocks (R: ``r_vdot``, ``r_lam``): each run of
    consecutive blocks on the same columns gives its diagonal block of P (plus R's) and its part of q, the products
    over its rows only (the stacked rows' products, whose other terms are zeros, in the same order); P is then
    assembled in one pass. ValueError where two runs' columns overlap."""
    runs = []
    for b in blocks:
        if runs and b.cols == runs[-1][0].cols:
            runs[-1].append(b)
        else:
            runs.append([b])
    runs.sort(key=lambda r: r[0].cols.start)
    Rw = jnp.concatenate([jnp.full(cols.nv, gains.r_vdot), jnp.full(cols.ng + cols.nb, gains.r_lam)])
    segs, at = [], 0  # (columns, their block of P, their part of q), in column order
    for r in runs:
        c = r[0].cols
        if c.start < at:
            raise ValueError(f"cost blocks: columns {[(x[0].cols.start, x[0].cols.stop) for x in runs]} overlap")
        if c.start > at:  # columns no cost row spans: R only
            segs.append((slice(at, c.start), jnp.zeros((c.start - at, c.start - at)), jnp.zeros(c.start - at)))
        H, l, w = (jnp.concatenate([getattr(b, f) for b in r]) for f in ("H", "l", "w"))
        segs.append((c, H.T @ (w[:, None] * H), -H.T @ (w * l)))
        at = c.stop
    if at < cols.n:
        segs.append((slice(at, cols.n), jnp.zeros((cols.n - at, cols.n - at)), jnp.zeros(cols.n - at)))
    diag = [Pc + jnp.diag(Rw[c]) for c, Pc, _ in segs]
    P = jnp.block([[d if i == j else jnp.zeros((d.shape[0], e.shape[1])) for j, e in enumerate(diag)]
                   for i, d in enumerate(diag)])
    return P, jnp.concatenate([qc for _, _, qc in segs])


def _floating_base(dyn: DynTerms, maps: ContactMaps, cols) -> ConstraintRows:
    """(9) the floating base's rows of the equations of motion."""
    A = jnp.zeros((6, cols.n)).at[:, cols.iv].set(dyn.M[0:6]).at[:, cols.ig].set(-maps.JfE[0:6]).at[
        :, cols.ib].set(maps.JoW[0:6])
    return ConstraintRows(A, -dyn.h[0:6], -dyn.h[0:6])


def _stance_feet(dyn: DynTerms, ref: Reference, gains, cols) -> ConstraintRows:
    """(10) stance feet keep contact (damped); free rows for swing feet."""
    st3 = jnp.repeat(~ref.swing, 3)
    b10 = -(dyn.Jdv_foot + gains.kd_stance * dyn.v_foot).reshape(12)
    A = jnp.zeros((12, cols.n)).at[:, cols.iv].set(dyn.J_foot.reshape(12, cols.nv))
    return ConstraintRows(A, jnp.where(st3, b10, -jnp.inf), jnp.where(st3, b10, jnp.inf))


def _tray_motion(J_o, Jdv_o, target: ObjectTarget, cols) -> ConstraintRows:
    """(11) the tray at the object follows the object's desired acceleration."""
    b11 = target.acc - Jdv_o
    return ConstraintRows(jnp.zeros((6, cols.n)).at[:, cols.iv].set(J_o), b11, b11)


def _normal_force(maps: ContactMaps, ref: Reference, gains, cols) -> ConstraintRows:
    """(12) normal force of stance feet between f_min and the ramped cap f_max load; free for swing feet."""
    stance = ~ref.swing
    normal = (jnp.eye(N_FEET)[:, :, None] * maps.Eg[None, :, 2, :]).reshape(N_FEET, cols.ng)
    cap = gains.f_max * ref.load
    return ConstraintRows(jnp.zeros((N_FEET, cols.n)).at[:, cols.ig].set(normal),
                          jnp.where(stance, jnp.minimum(gains.f_min, cap), -jnp.inf), jnp.where(stance, cap, jnp.inf))


def _torque_map(dyn: DynTerms, maps: ContactMaps, ids: RobotIds, cols):
    """``(A_tau (18, n), h_a (18,))``: the actuated rows of the equations of motion, tau = A_tau zeta + h_a."""
    act = jnp.asarray(ids.act_dof)
    A_tau = jnp.zeros((18, cols.n)).at[:, cols.iv].set(dyn.M[act]).at[:, cols.ig].set(-maps.JfE[act]).at[
        :, cols.ib].set(maps.JoW[act])
    return A_tau, dyn.h[act]


def _torque_limits(A_tau, h_a, ids: RobotIds, gains) -> ConstraintRows:
    """(13) |tau| within ``tau_margin`` of each actuator's limit."""
    tmax = gains.tau_margin * jnp.asarray(ids.tau_max)
    return ConstraintRows(A_tau, -tmax - h_a, tmax - h_a)


def _multipliers(ref: Reference, variant: Variant, cols) -> ConstraintRows:
    """(12) Lambda >= 0; swing feet's Lambda_gr = 0; Lambda_b = 0 without the tray cone (``variant``)."""
    ng, nb = cols.ng, cols.nb
    A = jnp.concatenate([jnp.zeros((ng, cols.n)).at[:, cols.ig].set(jnp.eye(ng)),
                         jnp.zeros((nb, cols.n)).at[:, cols.ib].set(jnp.eye(nb))])
    u_g = jnp.where(jnp.repeat(~ref.swing, cols.k), jnp.inf, 0.0)
    u_b = jnp.full(nb, jnp.where(jnp.asarray(variant.tray_cone) > 0, jnp.inf, 0.0))
    return ConstraintRows(A, jnp.concatenate([jnp.zeros(ng), jnp.zeros(nb)]), jnp.concatenate([u_g, u_b]))


def build_qp(dyn: DynTerms, obj: ObjectState, J_o, Jdv_o, ref: Reference, om: ObjectModel, gains: TransportGains,
             r_ext, ids: RobotIds, k: int, mu_ground, q_post, variant: Variant = FULL) -> TransportQP:
    """Assemble the QP (7)-(14) in OSQP form (module docstring).

    Args:
        dyn: the robot's dynamics terms; obj: the object's state; J_o: (6, nv) the tray's Jacobian at the object's
            CoM, Jdv_o: (6,) its Jdot v; ref: the planner's reference; om: the controller's object model.
        gains: the controller's gains and weights; r_ext: (6,) the observer's external wrench about the CoM
            [N, N m]; ids: static ids; k: friction-pyramid edges (static).
        mu_ground: () or (4,) friction under each foot; q_post: (6,) the arm's nominal posture [rad].
        variant: ablation switches (:mod:`wbc_jax.control.variants`).
    """
    cols = Columns(ids.nv_robot, k)
    maps = _contact_maps(dyn, obj, J_o, om, mu_ground, cols)
    target = _object_target(obj, ref, om, gains)
    com = _cost_com_wrench(dyn, obj, ref, maps, target, r_ext, gains, cols)
    P, q = _quadratic_cost([com, _cost_object_wrench(maps, target, gains, variant, cols),
                            _cost_arm_posture(dyn, ids, q_post, gains, variant, cols),
                            _cost_swing_feet(dyn, ref, gains, cols)], gains, cols)
    A_tau, h_a = _torque_map(dyn, maps, ids, cols)
    rows = [_floating_base(dyn, maps, cols), _stance_feet(dyn, ref, gains, cols),
            _tray_motion(J_o, Jdv_o, target, cols), _normal_force(maps, ref, gains, cols),
            _torque_limits(A_tau, h_a, ids, gains), _multipliers(ref, variant, cols)]
    H_com = jnp.zeros((6, cols.n)).at[:, com.cols].set(com.H).at[:, cols.ib].set(  # plus the object's reaction
        -edge_wrenches(maps.p_c, dyn.com, maps.Ec))
    return TransportQP(P, q, jnp.concatenate([r.A for r in rows]), jnp.concatenate([r.l for r in rows]),
                       jnp.concatenate([r.u for r in rows]), A_tau, h_a, H_com)
