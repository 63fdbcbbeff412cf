"""Transport-paper motion planner: object path -> CoM reference -> trot footholds and swing refs.

The CoM reference is the object reference plus the constant initial offset (Sec. IV-B,
q_r,d = q_b,ref + q_b,r), except that a dip of the object below its start height is shared between
the CoM and the arm: the CoM goes down by ``com_dip_share`` of the object's dip and the arm folds
for the rest (the tray constraint of the QP makes the arm follow the object; its posture task acts
in the null space). The trunk keeps its initial orientation; feet follow a time-based trot and land
at their nominal offset from the CoM reference at mid-stance, on the terrain height there, moved off
block edges (and, beyond a block's far edge, only where the shin clears that edge from the planned hip at
touchdown: :func:`.scene_geometry.clear_of_edges`).

With ``com_plan="zmp"`` (the default) the CoM's horizontal reference is instead replanned at the start of every
footstep so that the cart-table ZMP stays on the support of each two-foot phase (the transport paper's Sec. IV-B):
:func:`zmp_com_path`, precomputed at plan time (footholds and the trunk's height still follow the object).

Plans: :func:`straight_plan` (flat ground) and :func:`course_plan` (the obstacle course: the object's
height profile from the artificial-potential planner over the scene's wall, :mod:`.apf`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.planner.apf import APFParams, overhead, plan_dip
from wbc_jax.planner.gait import PAIRS, GaitParams, foot_stance_time, gait_phase
from wbc_jax.planner.scene_geometry import clear_of_edges, leg_geometry, scene_geometry, start_pose, terrain_height
from wbc_jax.planner.spline import CubicPath, cubic_path, eval_path, max_abs_accel_z, straight_path
from wbc_jax.planner.swing import swing_reference
from wbc_jax.planner.zmp import preview_com_xy
from wbc_jax.runtime.transfer import to_device
from wbc_jax.types import Reference

GRAVITY = 9.81
EDGE_MARGIN = 0.01  # [m] footholds keep foot radius + this from a block's edge
LATE_WINDOW = 0.08  # [s] how long a foot may look for a late touchdown
LATE_SPEED = 0.2  # [m/s] descent speed of a foot looking for a late touchdown
ZMP_SAMPLES = 8  # samples per support phase of the ZMP replanning's least squares
ZMP_HORIZON = 3  # footsteps per preview window of the ZMP replanning (the first one is kept)


class TransportPlan(NamedTuple):
    """Per-run plan (pytree; leaves may carry a batch axis).

    Attributes:
        obj_path: object position path (CubicPath).
        com_offset: (3,) CoM minus object position at t = 0 [m].
        R_obj: (3, 3) object orientation reference (initial orientation).
        R_base: (3, 3) trunk orientation reference (initial orientation).
        foot_offset: (4, 3) nominal foot centre minus CoM in xy; z is the absolute foot-centre height [m].
        gait: GaitParams.
        swing_height: () swing apex above the higher end point [m].
        t_ramp: () duration of the load ramps before liftoff and after touchdown [s].
        z_obj0: () object start height [m]; com_dip_share: () fraction of the object's dip below
            z_obj0 that the CoM follows (the arm takes the rest).
        terrain: (nt, 2, 3) standable boxes (:mod:`.scene_geometry`); foot_clear: () [m] minimum
            distance of a foothold from a box edge.
        heading: (2,) unit walking direction in the horizontal plane.
        hip_offset: (4, 3) each leg's hip pitch axis minus the CoM at the start [m] (the trunk keeps its
            orientation): the planned hip at touchdown, for the shin's clearance over a block's far edge.
        leg: (5,) :class:`.scene_geometry.LegGeometry` values (thigh, shank, shank_len, shank_r, thigh_r) [m].
        com_xy: horizontal CoM reference replanned per footstep (:func:`zmp_com_path`; a CubicPath of (K-1, 4, 2)
            coefficients, one cubic per support phase), or None: the CoM follows the object (``com_plan="spline"``).
        landing: (S, 4, 3) each foot's landing point of every stepped half-cycle's swing (:func:`landing_table`)
            [m]: what :func:`reference` reads for a swinging foot (:func:`landing_at`), computed once per plan (a
            foot's landing depends on time only through its swing); the planners set it (None only while
            :func:`_make_plan` builds the plan it is computed from).
    """

    obj_path: CubicPath
    com_offset: jax.Array
    R_obj: jax.Array
    R_base: jax.Array
    foot_offset: jax.Array
    gait: GaitParams
    swing_height: jax.Array
    t_ramp: jax.Array
    z_obj0: jax.Array
    com_dip_share: jax.Array
    terrain: jax.Array
    foot_clear: jax.Array
    heading: jax.Array
    hip_offset: jax.Array
    leg: jax.Array
    com_xy: CubicPath | None = None
    landing: jax.Array | None = None


class PlanError(ValueError):
    """A plan that violates one of its checks (clearance, vertical acceleration)."""


TERRAINS = ("known", "blind")  # what the planner knows of the ground (course_plan)
COM_PLANS = ("spline", "zmp")  # the CoM's horizontal reference: the object's + offset, or replanned per footstep


# Host-side planning runs these jitted at module level, so that a process compiles each once per shape (the plan is
# an argument, not a constant of a new closure, and nothing runs op by op, which compiles each single operation).
_path_samples = jax.jit(jax.vmap(eval_path, in_axes=(None, 0)))  # (path, (N,) t) -> (p, v, a), each (N, 3)
_terrain_height = jax.jit(terrain_height)
_straight_path = jax.jit(straight_path)


@jax.jit
def _com_samples(plan, t):
    """(N,) times -> the CoM reference from the object's (p, v, a), each (N, 3) [m, m/s, m/s^2]."""
    return jax.vmap(lambda tt: _com_at(plan, tt))(t)


@jax.jit
def _landing_samples(plan, t):
    """(N,) times -> (N, 4, 3) each foot's next planned landing point (:func:`_landings`) [m]."""
    return jax.vmap(lambda tt: _landings(plan, tt, gait_phase(plan.gait, tt)))(t)


def _ground(terrain, xy) -> np.ndarray:
    """Ground height under (..., 2) points [m] (host-side)."""
    return np.asarray(_terrain_height(to_device(terrain, float), to_device(xy, float)))


def _check_options(terrain, com_plan):
    if terrain not in TERRAINS:
        raise ValueError(f"terrain = {terrain!r}: expected one of {TERRAINS}")
    if com_plan not in COM_PLANS:
        raise ValueError(f"com_plan = {com_plan!r}: expected one of {COM_PLANS}")


def _make_plan(robot, qpos0, path: CubicPath, gait: GaitParams, swing_height, t_ramp, com_dip_share,
               terrain, heading, com_plan="zmp") -> TransportPlan:
    p_obj, com, feet, R_obj, R_base, hips = start_pose(robot, qpos0)
    gait = gait._replace(t_stop=float(np.asarray(path.t_knots)[-1]))
    foot_off = feet.copy()
    foot_off[:, :2] -= com[:2]
    foot_off[:, 2] -= _ground(terrain, feet[:, :2])  # height above the ground
    f = lambda x: to_device(x, float)  # noqa: E731
    plan = TransportPlan(
        obj_path=path, com_offset=f(com - p_obj), R_obj=f(R_obj), R_base=f(R_base), foot_offset=f(foot_off),
        gait=GaitParams(*(f(x) for x in gait)), swing_height=f(swing_height), t_ramp=f(t_ramp),
        z_obj0=f(p_obj[2]), com_dip_share=f(com_dip_share), terrain=f(terrain),
        foot_clear=f(robot.ids.foot_radius + EDGE_MARGIN), heading=f(heading[:2] / np.linalg.norm(heading[:2])),
        hip_offset=f(hips - com), leg=f(leg_geometry(robot)),
    )
    plan = plan._replace(landing=to_device(landing_table(plan)))
    return plan._replace(com_xy=zmp_com_path(plan)) if com_plan == "zmp" else plan


def straight_plan(robot, qpos0: np.ndarray, distance: float = 3.4, speed: float = 0.13, ramp: float = 1.0,
                  gait: GaitParams = GaitParams(), swing_height: float = 0.05, t_ramp: float = 0.06,
                  direction=(0.0, -1.0, 0.0), terrain: str = "known", com_plan: str = "zmp") -> TransportPlan:
    """Plan a straight transport of ``distance`` metres along ``direction`` at ``speed`` (flat ground).

    Args:
        robot: wbc_jax.robot.model.Robot; qpos0: (nq,) initial configuration (object on the tray).
        terrain: as :func:`course_plan` (on flat ground both give the same plan).
        com_plan: as :func:`course_plan`.
    """
    _check_options(terrain, com_plan)
    p_obj = start_pose(robot, qpos0).p_obj
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    path = _straight_path(p_obj, p_obj + distance * u, speed, gait.t_start, ramp)
    return _make_plan(robot, qpos0, path, gait, swing_height, t_ramp, 1.0, np.zeros((0, 2, 3)), u, com_plan)


def _time_law(length: float, speed: float, t0: float, ramp: float):
    """Knot-time function s -> t of the rest-to-rest speed profile of :func:`straight_path` (numpy)."""
    prof = _straight_path(np.zeros(3), np.array([length, 0.0, 0.0]), speed, t0, ramp)
    t = np.linspace(t0, float(np.asarray(prof.t_knots)[-1]), 20001)
    s = np.asarray(_path_samples(prof, to_device(t))[0])[:, 0]
    s = np.maximum.accumulate(s)
    return lambda q: np.interp(q, s, t)


def course_plan(robot, qpos0: np.ndarray, side: float, distance: float = 3.4, speed: float = 0.13,
                ramp: float = 1.0, gait: GaitParams = GaitParams(), swing_height: float = 0.05,
                t_ramp: float = 0.06, direction=(0.0, -1.0, 0.0), com_dip_share: float = 0.4,
                apf: APFParams = APFParams(), max_accel_z: float = GRAVITY, terrain: str = "known",
                com_plan: str = "zmp") -> TransportPlan:
    """Plan the transport through the scene's obstacles (the transport paper's course).

    The object's height along the straight horizontal path comes from :func:`.apf.plan_dip` over the
    scene's wall; cubic splines through its waypoints, timed by the rest-to-rest speed profile of
    :func:`straight_plan`, give the object reference. Checked here, raising :class:`PlanError`: the
    spline's clearance under every obstacle (at least half the APF margin, sampled every 5 mm) and
    its vertical acceleration (|a_z| < ``max_accel_z``; the paper's condition is a_z < g).

    Args:
        side: object side d [m] (the carried top is d / 2 above the object centre).
        com_dip_share: fraction of the object's dip the CoM follows; the arm folds for the rest.
        terrain: ``"known"``: footholds on the blocks' tops, moved off their edges (:func:`clear_of_edges`), as the
            scene file gives them; ``"blind"``: the planner does not see the blocks (footholds at the floor's
            height, no edge rule, swing apex above the higher end point as measured at liftoff); the touchdown
            rules of :func:`reference` (early contact ends the swing, a late one descends until contact) do the work.
            The object's path over the wall is planned in both.
        com_plan: ``"zmp"`` (default): the CoM reference's horizontal part replanned per footstep
            (:func:`zmp_com_path`); ``"spline"``: the object's plus the start offset (its dip scaled by
            ``com_dip_share``). "zmp" is the default: lower tracking error and slip in the paper campaign.
    """
    _check_options(terrain, com_plan)
    geo = scene_geometry(robot)
    p_obj = start_pose(robot, qpos0).p_obj
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    p_f = p_obj + distance * u
    dip = plan_dip(p_obj, p_f, geo.obstacles, side / 2.0, apf)
    wp = dip.waypoints
    s_wp = np.linalg.norm(wp[:, :2] - p_obj[:2], axis=1)
    times = _time_law(distance, speed, gait.t_start, ramp)(s_wp)
    path = cubic_path(wp, times)
    # checks on the spline actually used
    t = np.linspace(times[0], times[-1], max(int(distance / 0.005), 2))
    p = np.asarray(_path_samples(path, to_device(t))[0])
    under = overhead(geo.obstacles, p[:, :2], apf.footprint)
    clearance = float(np.min(under - (p[:, 2:3] + side / 2.0))) if under.size else np.inf
    if clearance < 0.5 * apf.margin:
        raise PlanError(f"object path clearance under the scene's obstacles is {clearance:.3f} m "
                        f"(need >= {0.5 * apf.margin:.3f} m)")
    az = max_abs_accel_z(path)
    if az >= max_accel_z:
        raise PlanError(f"object path vertical acceleration {az:.2f} m/s^2 exceeds {max_accel_z:.2f} m/s^2; "
                        "lower the speed")
    seen = geo.terrain if terrain == "known" else geo.terrain[:0]
    return _make_plan(robot, qpos0, path, gait, swing_height, t_ramp, com_dip_share, seen, u, com_plan)


def plan_duration(plan: TransportPlan) -> float:
    """End time of the object path [s] (host-side)."""
    return float(np.max(np.asarray(plan.obj_path.t_knots)[..., -1]))


def _com_from_object(plan: TransportPlan, p_o, v_o, a_o):
    """CoM reference from the object's: constant offset, vertical dip scaled by com_dip_share."""
    k = jnp.array([1.0, 1.0, 0.0]) + jnp.array([0.0, 0.0, 1.0]) * plan.com_dip_share
    p_c = p_o + plan.com_offset
    p_c = p_c.at[2].add((plan.com_dip_share - 1.0) * (p_o[2] - plan.z_obj0))
    return p_c, k * v_o, k * a_o


def _com_at(plan: TransportPlan, t):
    """The CoM reference (p, v, a), each (3,) [m, m/s, m/s^2], from the object's path at time ``t`` [s]."""
    return _com_from_object(plan, *eval_path(plan.obj_path, t))


def _n_stepped(plan: TransportPlan) -> int:
    """Number of stepped half-cycles of the plan's gait (``gait._stepped``; host-side)."""
    ts, tw, t0, t_stop = (float(x) for x in plan.gait)
    return int(np.floor((t_stop - t0 + 1e-4) / (ts + tw)))


def landing_table(plan: TransportPlan) -> np.ndarray:
    """(S, 4, 3) every foot's landing point (:func:`_landings`) of each stepped half-cycle k's swing, evaluated in
    mid-swing (S = the stepped half-cycles, at least 1; a row's entries for the feet that do not swing in it are
    computed the same way and not used) [m]. Row k is what :func:`_landings` gives at every instant of that swing
    (its touchdown time, hence everything it depends on, is fixed for the swing), up to float rounding."""
    ts, tw, t0, _ = (float(x) for x in plan.gait)
    t_mid = t0 + (ts + tw) * np.arange(max(_n_stepped(plan), 1)) + ts + 0.5 * tw
    return np.asarray(_landing_samples(plan, to_device(t_mid)))


def landing_at(plan: TransportPlan, g):
    """(4, 3) the landing table's row of gait state ``g``'s half-cycle [m]: a swinging foot's landing (the other
    feet's entries are not used)."""
    return plan.landing[jnp.clip(g.step_index, 0, plan.landing.shape[0] - 1)]


def _landings(plan: TransportPlan, t, g):
    """(4, 3) each foot's next planned landing point at time t (gait state g): its nominal offset from the CoM
    the object's path gives at its mid-stance, on the terrain there, moved off block edges."""
    t_mid = t + g.t_to_touchdown + 0.5 * foot_stance_time(plan.gait)  # (4,) mid-stance after touchdown
    t_mid = jnp.where(jnp.isfinite(t_mid), t_mid, t)
    com_mid = jax.vmap(lambda tt: _com_at(plan, tt)[0])(t_mid)
    xy = com_mid[:, :2] + plan.foot_offset[:, :2]
    # the hips at touchdown (planned CoM + start offset): the shin's clearance over a far edge depends on them
    t_td = jnp.where(jnp.isfinite(g.t_to_touchdown), t + g.t_to_touchdown, t)
    com_td = jax.vmap(lambda tt: _com_at(plan, tt)[0])(t_td)
    hip_td = com_td + plan.hip_offset
    xy = jax.vmap(clear_of_edges, in_axes=(None, 0, None, None, 0, 0, None))(
        plan.terrain, xy, plan.heading, plan.foot_clear, hip_td, plan.foot_offset[:, 2], plan.leg)
    z = terrain_height(plan.terrain, xy) + plan.foot_offset[:, 2]
    return jnp.concatenate([xy, z[:, None]], axis=1)


def zmp_com_path(plan: TransportPlan) -> CubicPath:
    """The horizontal CoM reference replanned at the start of every footstep (the transport paper, Sec. IV-B).

    Each footstep of the trot (a four-foot phase, then a two-foot phase: :mod:`.gait`) is one cubic per phase,
    continuous in position, velocity and acceleration. At each footstep's start the next ``ZMP_HORIZON``
    footsteps are solved by least squares from the reference state reached so far and the first is kept
    (:func:`.zmp.preview_com_xy`): the CoM follows the object's CoM trajectory (object path + start offset)
    while the cart-table ZMP, ``c - (z - z_ground) c'' / (g + z'')`` with the object's planned height profile,
    stays on the line through the two stance feet of each two-foot phase (their planned footholds, from the
    object's path as in :func:`reference`; the ground under them). After the last footstep, four-foot phases
    bring the CoM to rest at the object's end + offset. Host-side, once per plan.

    Returns:
        CubicPath with (K,) knots (phase starts and the end) and (K-1, 4, 2) coefficients.
    """
    ts, tw, t0, t_stop = (float(x) for x in plan.gait)
    H = ts + tw
    n_step = _n_stepped(plan)
    n_tail = max(2, int(np.ceil((t_stop - (t0 + n_step * H)) / H)) + 1)  # four-foot footsteps to come to rest
    starts = t0 + H * np.arange(n_step + n_tail)
    T = np.tile([ts, tw], n_step + n_tail)
    t_phase = np.stack([starts, starts + ts], 1).reshape(-1)  # (M,)
    tau = (np.arange(ZMP_SAMPLES) + 0.5) / ZMP_SAMPLES * T[:, None]  # (M, ns)

    def com(tt: float) -> np.ndarray:
        return np.asarray(_com_samples(plan, to_device([tt]))[0])[0]

    c_p, _, c_a = (np.asarray(x) for x in _com_samples(plan, to_device((t_phase[:, None] + tau).reshape(-1))))
    c_p, c_a = c_p.reshape(tau.shape + (3,)), c_a.reshape(tau.shape + (3,))
    # footholds: every foot's landing of footstep k's swing, the start's before
    land = np.asarray(plan.landing)  # (n_step, 4, 3)
    c0 = com(t0)
    feet = np.asarray(plan.foot_offset)[:, :2] + c0[:2]
    feet = np.concatenate([feet, _ground(plan.terrain, feet)[:, None]], 1)
    line_n, line_c = np.zeros((len(T), 2)), np.zeros(len(T))
    kz = np.empty(tau.shape)
    two_foot = np.zeros(len(T), bool)
    for k in range(n_step + n_tail):
        if k >= 1 and k - 1 < n_step:  # the pair that swung in footstep k - 1 has landed
            pair = list(PAIRS[(k - 1) % 2])
            feet[pair] = land[k - 1, pair]
        ground = float(np.mean(_ground(plan.terrain, feet[:, :2])))
        if k < n_step:
            a, b = feet[list(PAIRS[(k + 1) % 2]), :2]  # the stance pair of the two-foot phase
            d = (b - a) / np.linalg.norm(b - a)
            line_n[2 * k + 1] = (-d[1], d[0])
            line_c[2 * k + 1] = line_n[2 * k + 1] @ a
            two_foot[2 * k + 1] = True
            ground = float(np.mean(_ground(plan.terrain, np.stack([a, b]))))
        kz[2 * k:2 * k + 2] = (c_p[2 * k:2 * k + 2, :, 2] - ground) / (GRAVITY + c_a[2 * k:2 * k + 2, :, 2])
    x0 = np.stack([c0[:2], np.zeros(2), np.zeros(2)])
    x_end = np.stack([com(starts[-1] + H)[:2], np.zeros(2), np.zeros(2)])
    coef = preview_com_xy(x0, T, list(c_p[..., :2]), list(kz), line_n, line_c, two_foot, list(tau),
                          horizon=ZMP_HORIZON, x_end=x_end)
    return CubicPath(to_device(np.append(t_phase, t_phase[-1] + T[-1])), to_device(coef))


def reference(plan: TransportPlan, t, p_lift, contact=None, p_foot=None) -> Reference:
    """References at time t, with the touchdown rule.

    The trot is time-based; the simulator's foot contacts adjust it:

    * early touchdown: a foot past mid-swing that already touches the ground (a block higher than
      planned, tracking error) becomes a stance foot at once, with its load cap at the minimum until the
      scheduled touchdown's load ramp takes over;
    * late touchdown: a foot whose scheduled touchdown has passed without contact stays a swing foot for
      up to ``LATE_WINDOW`` seconds, holding its horizontal position and descending at ``LATE_SPEED``
      until it touches.

    Args:
        plan: TransportPlan; t: () time [s]; p_lift: (4, 3) each foot's position at its last liftoff [m].
        contact: (4,) bool, foot touches floor or terrain (None: scheduled contacts, no adjustment).
        p_foot: (4, 3) measured foot centres [m] (needed with ``contact``).
    """
    p_o, v_o, a_o = eval_path(plan.obj_path, t)
    p_c, v_c, a_c = _com_from_object(plan, p_o, v_o, a_o)
    if plan.com_xy is not None:  # replanned per footstep (zmp_com_path); the height still follows the object
        p_xy, v_xy, a_xy = eval_path(plan.com_xy, t)
        p_c, v_c, a_c = p_c.at[:2].set(p_xy), v_c.at[:2].set(v_xy), a_c.at[:2].set(a_xy)
    g = gait_phase(plan.gait, t)
    p_land = landing_at(plan, g)
    # quintic pieces: the acceleration is continuous at liftoff, apex and touchdown (cubic pieces jump by
    # ~200 m/s^2 at the apex for a 0.06 m step in 0.115 s, a jolt the whole body and the tray feel)
    swing_fn = functools.partial(swing_reference, kind="quintic")
    p_sw, v_sw, a_sw = jax.vmap(swing_fn, in_axes=(0, 0, 0, None, None))(
        p_lift, p_land, g.swing_phase, plan.gait.t_swing, plan.swing_height)
    t_since_td = foot_stance_time(plan.gait) - g.t_to_liftoff  # valid while stepping
    ramp_td = jnp.where(jnp.isfinite(g.t_to_liftoff) & g.stepping, t_since_td, jnp.inf)
    load = jnp.clip(jnp.minimum(g.t_to_liftoff, ramp_td) / plan.t_ramp, 0.02, 1.0)
    swing = g.swing
    if contact is not None:
        early = g.swing & (g.swing_phase > 0.5) & contact
        late = ~g.swing & ~contact & (t_since_td >= 0.0) & (t_since_td < LATE_WINDOW)
        swing = (g.swing & ~early) | late
        load = jnp.where(early, 0.02, load)
        z_late = terrain_height(plan.terrain, p_foot[:, :2]) + plan.foot_offset[:, 2] - LATE_SPEED * t_since_td
        p_late = jnp.concatenate([p_foot[:, :2], z_late[:, None]], axis=1)
        v_late = jnp.zeros((4, 3)).at[:, 2].set(-LATE_SPEED)
        p_sw = jnp.where(late[:, None], p_late, p_sw)
        v_sw = jnp.where(late[:, None], v_late, v_sw)
        a_sw = jnp.where(late[:, None], 0.0, a_sw)
    return Reference(p_obj=p_o, v_obj=v_o, a_obj=a_o, R_obj=plan.R_obj, p_com=p_c, v_com=v_c, a_com=a_c,
                     R_base=plan.R_base, swing=swing, p_sw=p_sw, v_sw=v_sw, a_sw=a_sw, load=load)
