"""The obstacle course: scene geometry from the MJCF, the artificial-potential dip, footholds on blocks,
and the wall passage walked by the transport WBC in MJX (a segment, on a test scene whose wall is closer)."""

import mujoco
import numpy as np
import pytest

from wbc_jax.control.transport import TransportConfig, control_qp_settings
from wbc_jax.planner.apf import overhead, plan_dip
from wbc_jax.planner.scene_geometry import (
    HIP_DROP,
    SHIN_MARGIN,
    clear_of_edges,
    knee_position,
    leg_geometry,
    scene_geometry,
    shin_clearance,
    terrain_height,
)
from wbc_jax.planner.spline import eval_path, max_abs_accel_z
from wbc_jax.planner.transport import course_plan
from wbc_jax.robot.model import Robot, mjcf_dir
from wbc_jax.rollout import make_sim, simulate
from wbc_jax.rollout.batch import prepare_batch

LINTEL_UNDERSIDE = 0.65  # [m] scene_transport.xml: lintel box centre 0.925, half-height 0.275
WALL_Y = -2.45  # [m]
SEG_WALL_Y = -1.40  # [m] wall of the wall-passage test scene
SEG_DISTANCE = 1.35  # [m] the object ends 0.6 m past that wall
SEG_SLIP_MAX = 0.010  # [m] the acceptance bound on the object's slip
FALL_Z = 0.15  # [m]


def _moved_scene(tmp_path, wall_y: float, blocks_away: bool = True):
    """The transport scene with the wall at ``wall_y`` (and the blocks moved out of the way), saved as XML."""
    spec = mujoco.MjSpec.from_file(str(mjcf_dir() / "scene_transport.xml"))
    spec.body("wall").pos = [0.0, wall_y, 0.0]
    if blocks_away:
        for i, name in enumerate(("block1", "block2", "block3")):
            g = spec.geom(name)
            g.pos = [5.0 + i, 5.0, g.pos[2]]
    spec.compile()
    path = tmp_path / f"scene_wall_{abs(wall_y):.2f}.xml"
    path.write_text(spec.to_xml())
    return path


def test_scene_geometry_reads_blocks_and_wall():
    geo = scene_geometry(Robot("transport"))
    assert geo.terrain.shape == (3, 2, 3) and geo.obstacles.shape == (3, 2, 3)
    tops = sorted(np.round(geo.terrain[:, 1, 2], 4))
    assert tops == [0.015, 0.02, 0.035]
    lintel = geo.obstacles[np.argmax(geo.obstacles[:, 0, 2])]
    assert lintel[0, 2] == pytest.approx(LINTEL_UNDERSIDE)
    assert 0.5 * (lintel[0, 1] + lintel[1, 1]) == pytest.approx(WALL_Y)
    # terrain height: on block2 (0.035 m) and on the floor between blocks
    h = np.asarray(terrain_height(geo.terrain, np.array([[0.1, -1.75], [0.1, -1.4]])))
    np.testing.assert_allclose(h, [0.035, 0.0])
    # walking -y: block2's entry edge is y = -1.6, its exit edge y = -1.9
    u = np.array([0.0, -1.0])
    xy = np.asarray(clear_of_edges(geo.terrain, np.array([0.1, -1.59]), u, 0.038))  # 1 cm before entry edge
    assert xy[1] == pytest.approx(-1.6 + 0.038) and xy[0] == pytest.approx(0.1)
    xy = np.asarray(clear_of_edges(geo.terrain, np.array([0.1, -1.92]), u, 0.038))  # 2 cm past the exit edge
    assert xy[1] == pytest.approx(-1.9 - 0.038)  # without a hip: the foot's clearance only
    xy = np.asarray(clear_of_edges(geo.terrain, np.array([0.1, -1.88]), u, 0.038))  # on the block, near its end
    assert xy[1] == pytest.approx(-1.9 + 0.038)
    xy = np.asarray(clear_of_edges(geo.terrain, np.array([0.1, -1.75]), u, 0.038))  # mid-block: unchanged
    assert xy[1] == pytest.approx(-1.75)


@pytest.mark.parametrize("top", [0.03, 0.05])
def test_apf_dip_clears_the_lintel_and_only_there(top):
    geo = scene_geometry(Robot("transport"))
    p_i = np.array([0.0, -0.69, 0.81])
    dip = plan_dip(p_i, p_i + [0.0, -3.4, 0.0], geo.obstacles, top)
    y = p_i[1] - dip.s
    under = np.isfinite(overhead(geo.obstacles, np.stack([np.zeros_like(y), y], 1), 0.1)).any(1)
    assert under.any()
    # under the lintel the carried top is below its underside with the APF margin (0.03 m) kept
    assert np.all(dip.z[under] + top <= LINTEL_UNDERSIDE - 0.03 + 1e-6)
    # away from the wall (> 1 m) the path stays at the nominal height, and never rises above it
    far = np.abs(y - WALL_Y) > 1.0
    np.testing.assert_allclose(dip.z[far], p_i[2], atol=2e-3)
    assert dip.z.max() <= p_i[2] + 1e-6


def test_dip_moves_with_the_wall(tmp_path):
    for wall_y in (-1.8, -2.9):
        robot = Robot(_moved_scene(tmp_path, wall_y))
        qpos0 = robot.home_qpos(0.08)
        plan = course_plan(robot, qpos0, side=0.08)
        t = np.linspace(0.0, 30.0, 6001)
        p = np.stack([np.asarray(eval_path(plan.obj_path, tt)[0]) for tt in t[::10]])
        y_low = p[np.argmin(p[:, 2]), 1]
        assert abs(y_low - wall_y) < 0.15, (wall_y, y_low)
        assert p[:, 2].min() + 0.04 <= LINTEL_UNDERSIDE - 0.015
        assert max_abs_accel_z(plan.obj_path) < 9.81


def test_plans_come_back_from_disk_equal_and_only_for_their_inputs(tmp_path, monkeypatch):
    """prepare_batch's plans (the transport plug-in's make_plan) are kept on disk: a second request with the same
    model, start pose and arguments reads the stored plan, leaf for leaf equal to a fresh course_plan, without planning;
    another object side is planned."""
    import jax

    from wbc_jax.rollout.controllers import transport as batch
    from wbc_jax.rollout.controllers.transport import TransportController

    controller = TransportController.default(0.001)
    monkeypatch.setenv("WBC_JAX_CACHE", str(tmp_path))
    robot = Robot("transport")
    q = robot.home_qpos(0.08)
    fresh = course_plan(robot, q, side=0.08)
    first = controller.make_plan(robot, True, q, dict(side=0.08))
    assert len(list((tmp_path / "exported").glob("plan-*.pkl"))) == 1
    planned = []
    real = batch.course_plan
    monkeypatch.setattr(batch, "course_plan", lambda *a, **k: planned.append(k["side"]) or real(*a, **k))
    again = controller.make_plan(robot, True, q, dict(side=0.08))
    assert planned == []
    leaves = jax.tree_util.tree_leaves
    assert len(leaves(fresh)) == len(leaves(again)) > 10
    for a, b, c in zip(leaves(fresh), leaves(first), leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), b)
        np.testing.assert_array_equal(b, c)
    other = controller.make_plan(robot, True, robot.home_qpos(0.10), dict(side=0.10))
    assert planned == [0.10]
    assert not np.array_equal(other.obj_path.coef, again.obj_path.coef)


@pytest.fixture(scope="module")
def wall_segment(tmp_path_factory):
    robot = Robot(_moved_scene(tmp_path_factory.mktemp("scene"), SEG_WALL_Y))
    sim = make_sim(robot, TransportConfig(qp=control_qp_settings()), log_every=50)
    b = prepare_batch(sim, [0.4], [0.4], [0.10], plan_kwargs=dict(distance=SEG_DISTANCE))
    from wbc_jax.planner.transport import plan_duration

    T = plan_duration(b.plan) + 0.3
    st, logs = simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground, T,
                        chunk_seconds=T)
    return robot, st, logs


@pytest.mark.slow  # seconds of a batch-1 closed loop; the scene geometry, clearance and footholds are checked above
def test_wall_passage_segment(wall_segment):
    """Heaviest, largest, least grippy cell (m 0.4, d 0.10, mu 0.4) walks under the lintel."""
    robot, st, logs = wall_segment
    acc = st.acc
    assert not bool(acc.nonfinite[0])
    assert not bool(acc.wall_contact[0]), "touched the wall"
    assert not bool(acc.nonfoot_floor[0]), "a non-foot part touched the floor"
    assert float(acc.min_trunk_z[0]) > FALL_Z
    z0 = float(logs.trunk_z[0, 0])
    assert float(acc.min_trunk_z[0]) < z0 - 0.1, "the robot did not lower itself"
    assert float(acc.max_slip[0]) < SEG_SLIP_MAX
    assert float(acc.max_off_s[0]) <= 0.05
    assert float(acc.max_tau_excess[0]) <= 0.0
    p_obj = np.asarray(st.d.xpos[0, robot.ids.obj_body])
    assert p_obj[1] < SEG_WALL_Y - 0.3, "the object did not get past the wall"
    assert np.linalg.norm(p_obj - np.asarray(logs.p_obj_ref[0, -1])) < 0.05


def test_foot_ground_surface_and_friction_match_mujoco_c():
    """Each foot's nearest ground surface (floor or a block) and that pair's friction, which sizes the foot's
    friction pyramid in the QP (the floor's 1.0 on block1's 0.4 let a loaded foot slide off block1): front feet
    placed over block1, hind feet over the floor; distances and friction vs MuJoCo C (mj_geomDistance over each
    foot's pairs, pair_friction of the nearest)."""
    import jax

    from wbc_jax.physics import backend as physics
    from wbc_jax.physics import contacts
    from wbc_jax.robot.model import mjx

    robot = Robot("transport")
    m = robot.mj_model
    q = robot.home_qpos(0.08).copy()
    q[1] = -1.05 + 0.2875  # trunk y: the front hips (0.2875 m ahead, walking along -y) over block1's centre
    sim = make_sim(robot)
    d = mjx.make_data(robot.mjx_model).replace(qpos=jax.numpy.asarray(q))
    dist, mu = jax.device_get(jax.jit(lambda d: contacts.foot_ground(sim, robot.mjx_model,
                                                                     physics.sense(robot.mjx_model, d)))(d))
    dc = mujoco.MjData(m)
    dc.qpos[:] = q
    mujoco.mj_forward(m, dc)
    ref_d, ref_mu = [], []
    for pairs in robot.ids.foot_pair:
        ds = [mujoco.mj_geomDistance(m, dc, m.pair_geom1[p], m.pair_geom2[p], 0.5, None) for p in pairs]
        ref_d.append(min(ds))
        ref_mu.append(m.pair_friction[pairs[int(np.argmin(ds))], 0])
    np.testing.assert_allclose(dist, ref_d, atol=1e-5)
    np.testing.assert_allclose(mu, ref_mu, rtol=1e-6)
    names = [m.geom(int(m.pair_geom2[p[0]])).name for p in robot.ids.foot_pair]  # sanity of the placement
    assert mu[0] == mu[1] == np.float32(0.4) and mu[2] == mu[3] == np.float32(1.0), (mu, names)


def _hand_clearance(hip, foot, edge, L1, L2, Ls, rs, rt):
    """Leg capsules' distance to an edge by the law of cosines (an independent hand computation; (s, z) points)."""
    d = np.subtract(foot, hip)
    r = np.hypot(*d)
    phi = np.arctan2(d[1], d[0])
    gam = np.arccos((L1**2 + r**2 - L2**2) / (2 * L1 * r))  # angle at the hip between thigh and hip-foot line
    knees = [np.add(hip, L1 * np.array([np.cos(phi + sg * gam), np.sin(phi + sg * gam)])) for sg in (1, -1)]
    knee = min(knees, key=lambda k: k[0])  # the knee bends backwards

    def seg(p, a, b):
        a, b, p = (np.asarray(x, float) for x in (a, b, p))
        t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        return np.hypot(*(p - a - t * (b - a)))

    tip = knee + Ls * (np.asarray(foot) - knee) / L2
    return knee, min(seg(edge, knee, tip) - rs, seg(edge, hip, knee) - rt)


def test_knee_and_leg_clearance_match_mujoco():
    """The planar leg (knee, shank and thigh capsules vs block2's far edge) against MuJoCo C's kinematics and
    mj_geomDistance, for the front-right leg crouched over that edge."""
    robot = Robot("transport")
    m = robot.mj_model
    leg = leg_geometry(robot)
    assert leg == pytest.approx((0.315, 0.30, 0.2764, 0.015, 0.025))
    d = mujoco.MjData(m)
    q = robot.home_qpos(0.08)
    jq = lambda n: m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]  # noqa: E731
    gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    bid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)  # noqa: E731
    u = np.array([0.0, -1.0])
    edge = np.array([1.9, 0.035])  # block2's far edge as (s = -y, z)
    geo = scene_geometry(robot)
    for dy, dz, pitch, knee in ((-1.66, -0.14, 1.1, -2.2), (-1.70, -0.13, 1.15, -2.3), (-1.75, -0.10, 1.1, -2.1)):
        q2 = q.copy()
        q2[1] += dy
        q2[2] += dz
        q2[jq("FR_pitch")] = pitch
        q2[jq("FR_knee")] = knee
        d.qpos[:] = q2
        mujoco.mj_kinematics(m, d)
        sz = lambda p: np.array([p[:2] @ u, p[2]])  # noqa: E731
        hip, foot, k_mj = sz(d.xpos[bid("FR_thigh")]), sz(d.geom_xpos[gid("FR_foot")]), sz(d.xpos[bid("FR_calf")])
        assert foot[0] > 1.9  # the foot is beyond the edge
        np.testing.assert_allclose(np.asarray(knee_position(hip, foot, np.asarray(leg))), k_mj, atol=1e-6)
        ft = np.zeros(6)
        want = min(mujoco.mj_geomDistance(m, d, gid("FR_shank"), gid("block2"), 1.0, ft),
                   mujoco.mj_geomDistance(m, d, gid("FR_thigh"), gid("block2"), 1.0, ft))
        got = float(shin_clearance(hip, foot, edge, np.asarray(leg)))
        assert 0.0 < want < 0.06  # near the edge, not through it (a penetration depth is MuJoCo's own measure)
        assert got == pytest.approx(want, abs=1e-5)
        assert got == pytest.approx(_hand_clearance(hip, foot, edge, *leg)[1], abs=1e-6)  # float32
    assert geo.terrain.shape[0] == 3


def test_far_edge_rule_by_hand():
    """Stepping down from block2 in the crouch (planned hip 0.336 m high, checked HIP_DROP lower): with the hip
    56 mm past the far edge at touchdown (a shank graze of the course) the shin cannot clear the edge anywhere near the
    nominal foothold, so the foot stays on the block; with the hip 125 mm past it the nominal foothold is kept; a
    nominal foothold just past the edge moves to the first landing that clears it."""
    robot = Robot("transport")
    geo = scene_geometry(robot)
    leg = np.asarray(leg_geometry(robot))
    u = np.array([0.0, -1.0])
    edge, zf, hz = np.array([1.9, 0.035]), 0.028, 0.336

    def rule(hip_s, foot_s):
        hip = np.array([-0.187, -hip_s, hz])
        return -float(clear_of_edges(geo.terrain, np.array([-0.187, -foot_s]), u, 0.038, hip, zf, leg)[1])

    def hand(hip_s, foot_s):  # the worst of the hip at its plan, HIP_DROP / 2 and HIP_DROP lower
        return min(_hand_clearance((hip_s, hz - f * HIP_DROP), (foot_s, zf), edge, *leg)[1] for f in (0.0, 0.5, 1.0))

    # hip 56 mm past the edge, foot under it: by hand the capsules miss the edge by less than the margin
    assert hand(1.956, 1.957) < SHIN_MARGIN
    assert rule(1.956, 1.957) == pytest.approx(1.9 - 0.038)  # stays on block2
    # hip 125 mm past: the nominal foothold (under the hip) clears by more than the margin and is kept
    assert hand(2.025, 2.026) > SHIN_MARGIN
    assert rule(2.025, 2.026) == pytest.approx(2.026)
    # hip 100 mm past, nominal 45 mm past the edge: too close; the first candidate landing (5 mm steps from the
    # foot clearance 38 mm) that clears by the margin, found here by hand
    assert hand(2.0, 1.945) < SHIN_MARGIN
    first = next(s for s in 1.938 + 0.005 * np.arange(80) if hand(2.0, s) >= SHIN_MARGIN)
    assert first - 1.945 < 1.945 - (1.9 - 0.038)  # nearer than the block side
    assert rule(2.0, 1.945) == pytest.approx(first, abs=1e-6)  # float32
    # far out (218 mm past the edge, hip 89 mm past): the dropped hip clears but the planned one does not (a lower
    # hip bends the knee more and lifts the shank): the rule takes the worst of the three heights
    at = [_hand_clearance((1.989, hz - f * HIP_DROP), (2.118, zf), edge, *leg)[1] for f in (0.0, 0.5, 1.0)]
    assert at[0] < SHIN_MARGIN <= at[2]
    assert rule(1.989, 2.118) != pytest.approx(2.118)


def test_blind_terrain_lands_at_floor_height():
    """course_plan(terrain="blind"): the planner does not see the blocks, so every planned landing is at the
    floor's height (the touchdown rules handle the blocks); "known" lands on block2's top (0.035 m) somewhere.
    The object's path is the same in both. A swinging foot's landing read from the plan's landing table equals the
    one evaluated at that instant (``_landings``), exactly, on both terrains."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.planner.gait import gait_phase
    from wbc_jax.planner.transport import _landings, landing_at, reference

    robot = Robot("transport")
    qpos0 = robot.home_qpos(0.08)
    z_end = {}
    for terrain in ("known", "blind"):
        plan = course_plan(robot, qpos0, side=0.08, terrain=terrain)
        t = jnp.arange(0.0, float(plan.gait.t_stop), 0.005)

        def landing_z(tt, plan=plan):  # planned foot height at the end of each swing, else -inf
            ref = reference(plan, tt, jnp.zeros((4, 3)))
            g = gait_phase(plan.gait, tt)
            return jnp.where(g.swing & (g.swing_phase > 0.97), ref.p_sw[:, 2], -jnp.inf)

        z_end[terrain] = np.asarray(jax.jit(jax.vmap(landing_z))(t))

        def both(tt, plan=plan):  # the table's row and the instant's evaluation, in one program (same rounding)
            g = gait_phase(plan.gait, tt)
            row = landing_at(plan, g)  # what the reference reads
            # inside the swing: at its first and last instants (time to touchdown below float32's resolution of t)
            # the instant's evaluation can flip a foothold decision by rounding, which the table, one value per
            # swing, does not
            return g.swing & (g.swing_phase > 0.02) & (g.swing_phase < 0.98), row, _landings(plan, tt, g)

        sw, row, now = (np.asarray(x) for x in jax.jit(jax.vmap(both))(t))
        assert sw.sum() > 1000 and np.array_equal(row[sw], now[sw])
        assert plan.terrain.shape[0] == (3 if terrain == "known" else 0)
    floor = float(np.max(z_end["blind"]))
    assert np.all(z_end["blind"][np.isfinite(z_end["blind"])] <= floor + 1e-3)
    assert float(np.max(z_end["known"])) == pytest.approx(floor + 0.035, abs=2e-3)
    with pytest.raises(ValueError, match="terrain"):
        course_plan(robot, qpos0, side=0.08, terrain="dark")


ZMP_LINE_TOL = 0.010  # [m] replanned ZMP off the stance pair's segment on the course (the object-following plan:
#                       median 37.5 mm; 10 mm is a third of the foot sphere's 28 mm radius)


def test_zmp_com_plan_keeps_the_zmp_on_the_support():
    """course_plan(com_plan="zmp"): over the walk, the reference's cart-table ZMP (planner.zmp.zmp_xy over the
    ground under the stance feet) lies within ZMP_LINE_TOL of the stance pair's segment in every two-foot phase
    and inside the four feet's polygon in the four-foot phases (planner.zmp.support_margin, the footholds read
    from the plan in mid-swing); the object-following plan's (com_plan="spline") does not (median > 3
    ZMP_LINE_TOL). Footholds and the object's path are the same in both; the end is the same at rest. A bad
    com_plan names the option."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.planner.gait import gait_phase
    from wbc_jax.planner.scene_geometry import terrain_height
    from wbc_jax.planner.transport import _landings, reference
    from wbc_jax.planner.zmp import support_margin, zmp_xy

    robot = Robot("transport")
    qpos0 = robot.home_qpos(0.08)
    zmp_plan = course_plan(robot, qpos0, side=0.08, com_plan="zmp")
    t = np.arange(0.0, float(zmp_plan.gait.t_stop) + 1.0, 0.005)
    dt_mid = int(round(0.5 * float(zmp_plan.gait.t_swing) / 0.005))

    def one(plan, tt):
        ref, g = reference(plan, tt, jnp.zeros((4, 3))), gait_phase(plan.gait, tt)
        return ref.p_com, ref.a_com, ref.p_obj, _landings(plan, tt, g), g.swing

    def worst(plan):
        p, a, p_obj, land, swing = (np.asarray(x) for x in jax.jit(jax.vmap(lambda tt: one(plan, tt)))(jnp.asarray(t)))
        feet = np.empty((len(t), 4, 2))
        feet[0] = p[0, :2] + np.asarray(plan.foot_offset[:, :2])
        pending = feet[0].copy()
        for k in range(1, len(t)):  # each foot's last landing, read in mid-swing
            started = swing[k] & ~swing[k - 1]
            pending[started] = land[min(k + dt_mid, len(t) - 1), started, :2]
            feet[k] = np.where((~swing[k] & swing[k - 1])[:, None], pending, feet[k - 1])

        def margin(p_k, a_k, feet_k, st):
            ground = jnp.sum(jnp.where(st, terrain_height(plan.terrain, feet_k), 0.0)) / jnp.sum(st)
            return support_margin(zmp_xy(p_k, a_k, z_ground=ground), feet_k, st)

        m = np.asarray(jax.jit(jax.vmap(margin))(p, a, feet, ~swing))
        two = swing.sum(1) == 2
        H = float(plan.gait.t_stance + plan.gait.t_swing)
        steps = np.floor((t - float(plan.gait.t_start)) / H).astype(int)  # per two-foot phase: its largest distance
        off = np.array([-m[two & (steps == s)].min() for s in np.unique(steps[two])])
        return off, m[~two & (t > float(plan.gait.t_start)) & (t < float(plan.gait.t_stop))], p, p_obj

    off, inside, p, p_obj = worst(zmp_plan)
    assert len(off) == 102 and off.max() < ZMP_LINE_TOL, (len(off), off.max())  # the course's 102 footsteps
    assert inside.min() > 0.0
    off_s, _, p_s, p_obj_s = worst(course_plan(robot, qpos0, side=0.08, com_plan="spline"))
    assert np.median(off_s) > 3 * ZMP_LINE_TOL, np.median(off_s)
    np.testing.assert_allclose(p_obj, p_obj_s, atol=1e-6)
    np.testing.assert_allclose(p[-1], p_s[-1], atol=1e-4)
    with pytest.raises(ValueError, match="com_plan"):
        course_plan(robot, qpos0, side=0.08, com_plan="preview")
