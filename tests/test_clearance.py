"""Exact clearance (``wbc_jax.physics.clearance``) against MuJoCo C's ``mj_geomDistance``.

Poses of the course scene: the front-right leg crouched over block2's far edge (tests/test_course.py's poses; the
shank's closest box feature is the edge), the front legs standing on block2 (closest feature: the top face), the
robot lowered into the floor (penetration), in front of the wall (arm and tray vs the lintel), and random whole-body
poses. Positive distances agree with MuJoCo C within POS_TOL; a capsule/box penetration is checked against a dense
sampling of the box's signed distance along the capsule's segment (MuJoCo C reports a contact depth there, or,
for a segment through a block, a positive distance).
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from wbc_jax.physics import clearance as CL
from wbc_jax.physics import distance as DI
from wbc_jax.robot.model import Robot, mjx
from wbc_jax.rollout import clearance, clearance_name, make_sim

POS_TOL = 1e-4  # [m] the acceptance bound (measured: < 1e-6, float32 kinematics vs float64)
BRUTE_TOL = 2e-5  # [m] vs 200 001 samples of the segment (spacing <= 1.6 um on a 0.32 m segment)
DISTMAX = 10.0  # [m] mj_geomDistance's search radius: every pair of the scene is within it
CROUCH = ((-1.66, -0.14, 1.1, -2.2), (-1.70, -0.13, 1.15, -2.3), (-1.75, -0.10, 1.1, -2.1),
          (-1.70, -0.16, 1.15, -2.3), (-1.66, -0.17, 1.1, -2.2))  # (dy, dz, FR pitch, FR knee); the last penetrates
N_RANDOM = 24
RECOMPUTE_TOL = 1e-7  # [m] a broad-phase candidate's distance against the all-pairs one: float32 rounding (XLA fuses
#                       the two programs differently; measured <= 3.1e-8)


def _named_poses(robot) -> dict:
    """The module docstring's poses of the transport scene by name: qpos (nq,) each."""
    m = robot.mj_model
    jq = lambda n: m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]  # noqa: E731
    q = robot.home_qpos(0.08)
    poses = {}
    for i, (dy, dz, pitch, knee) in enumerate(CROUCH):
        p = q.copy()
        p[1] += dy
        p[2] += dz
        p[jq("FR_pitch")], p[jq("FR_knee")] = pitch, knee
        poses[f"crouch{i}"] = p
    p = q.copy()
    p[1], p[2] = -1.75 + 0.2875, q[2] + 0.035  # front feet on block2's top, mid-block
    poses["on_block2"] = p
    poses["home"] = q.copy()
    p = q.copy()
    p[2] -= 0.05  # the shanks' lowest points 20 mm into the floor (home: 30 mm above it)
    poses["lowered"] = p
    p = q.copy()
    p[1] = -1.535  # the tray's front edge 5 cm before the wall, tray and arm above the lintel's underside
    poses["wall"] = p
    rng = np.random.default_rng(0)
    for i in range(N_RANDOM):
        p = q.copy()
        p[0] += rng.uniform(-0.3, 0.3)
        p[1] = -2.45 + rng.uniform(-0.3, 0.3) if i % 3 == 0 else rng.uniform(-3.5, -0.5)
        p[2] += rng.uniform(-0.25, 0.1)
        ax = rng.normal(size=3)
        ang = rng.uniform(0.0, 0.4)
        p[3:7] = np.r_[np.cos(ang / 2), np.sin(ang / 2) * ax / np.linalg.norm(ax)]
        p[7:25] += rng.uniform(-0.6, 0.6, 18)
        poses[f"random{i}"] = p
    return poses


N_BROAD = 1500


def _broad_poses(robot):
    """N_BROAD random course poses (base anywhere along the course, tilted, lowered up to 0.3 m, joints +-0.8 rad:
    legs over and into the blocks, arm and trunk at the wall)."""
    rng = np.random.default_rng(1)
    Q = np.repeat(robot.home_qpos(0.08)[None], N_BROAD, 0)
    Q[:, 0] += rng.uniform(-0.4, 0.4, N_BROAD)
    Q[:, 1] = rng.uniform(-3.7, -0.3, N_BROAD)
    Q[:, 2] += rng.uniform(-0.3, 0.15, N_BROAD)
    ax = rng.normal(size=(N_BROAD, 3))
    ang = rng.uniform(0.0, 0.6, N_BROAD)
    Q[:, 3:7] = np.c_[np.cos(ang / 2), np.sin(ang / 2)[:, None] * ax / np.linalg.norm(ax, axis=1, keepdims=True)]
    Q[:, 7:25] += rng.uniform(-0.8, 0.8, (N_BROAD, 18))
    return Q


@pytest.fixture(scope="module")
def at_poses():
    """The transport scene, its pairs, the named poses, and one compiled pass at the named poses, the broad poses
    and a pose with a NaN joint angle: every pair's exact distance, the rollout's clearance and its pair, the broad
    phase's result and every bounded pair's lower bound (a dict by pair kind)."""
    robot = Robot("transport")
    pairs = CL.clearance_pairs(robot)
    sim = make_sim(robot)
    poses = _named_poses(robot)
    knee = mujoco.mj_name2id(robot.mj_model, mujoco.mjtObj.mjOBJ_JOINT, "FR_knee")
    nan_pose = robot.home_qpos(0.08)  # last: the front-right knee's angle NaN (that leg's geoms NaN, the others not)
    nan_pose[robot.mj_model.jnt_qposadr[knee]] = np.nan
    Q = np.concatenate([np.stack(list(poses.values())), _broad_poses(robot), nan_pose[None]])
    bounded = [k for k, name in enumerate(CL.KINDS) if name in CL.CANDIDATES]

    def one(qp):
        d = mjx.kinematics(robot.mjx_model, mjx.make_data(robot.mjx_model).replace(qpos=qp))
        lower = {k: jax.vmap(DI.BOUNDS[CL.KINDS[k]])(*CL._kind_inputs(pairs, d, np.where(pairs.kind == k)[0]))
                 for k in bounded}
        return CL.pair_distances(pairs, d), clearance(sim, d), CL.bounded_min_clearance(pairs, d), lower

    out = jax.device_get(jax.jit(jax.vmap(one))(jnp.asarray(Q)))
    return robot, sim, pairs, poses, Q, out


@pytest.fixture(scope="module")
def course(at_poses):
    """The transport scene, its pairs, the poses by name and every pair's distance (JAX) at each pose."""
    robot, sim, pairs, poses, Q, (exact, (c, k), _, _) = at_poses
    n = len(poses)
    return (robot, sim, pairs, list(poses), Q[:n], np.asarray(exact, float)[:n], np.asarray(c, float)[:n],
            np.asarray(k)[:n])


def _mj(robot, qpos, g1, g2):
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    return mujoco.mj_geomDistance(m, d, int(g1), int(g2), DISTMAX, None)


def _brute_segment_box(robot, qpos, cap, box):
    """min over 200 001 points of the capsule's segment of the box SDF, minus the radius (float64)."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    R, bR = d.geom_xmat[cap].reshape(3, 3), d.geom_xmat[box].reshape(3, 3)
    ends = [d.geom_xpos[cap] + s * m.geom_size[cap][1] * R[:, 2] for s in (-1.0, 1.0)]
    a, b = (bR.T @ (e - d.geom_xpos[box]) for e in ends)
    p = a + np.linspace(0.0, 1.0, 200001)[:, None] * (b - a)
    q = np.abs(p) - m.geom_size[box]
    return float(np.min(np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)) - m.geom_size[cap][0])


def _k(robot, pairs, a, b):
    gid = lambda n: mujoco.mj_name2id(robot.mj_model, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    return int(np.where((pairs.robot == gid(a)) & (pairs.env == gid(b)))[0][0])


def test_pairs_cover_legs_blocks_floor_and_wall():
    robot = Robot("transport")
    m = robot.mj_model
    pairs = CL.clearance_pairs(robot)
    names = {(m.geom(int(a)).name, m.geom(int(b)).name) for a, b in zip(pairs.robot, pairs.env)}
    legs = [f"{leg}_{part}" for leg in ("FL", "FR", "BL", "BR") for part in ("shank", "thigh")]
    ground, wall = ("floor", "block1", "block2", "block3"), ("wall_left", "wall_right", "wall_lintel")
    arm = [f"arm_link{i}" for i in range(1, 5)]
    want = {(g, e) for g in [*legs, "trunk"] for e in ground} | {(g, e) for g in [*arm, "trunk", "tray"] for e in wall}
    assert names == want  # no foot, no object; thighs vs blocks included though the scene has no such <pair>
    assert len(pairs) == 54 and [CL.KINDS[k] for k in np.unique(pairs.kind)] == ["capsule_plane", "capsule_box",
                                                                                   "box_plane", "box_box"]


@pytest.mark.parametrize("pose,pair", [("crouch0", ("FR_shank", "block2")), ("crouch1", ("FR_shank", "block2")),
                                       ("crouch2", ("FR_shank", "block2")), ("crouch3", ("FR_shank", "block2")),
                                       ("crouch0", ("FR_thigh", "block2")), ("on_block2", ("FL_shank", "block2")),
                                       ("on_block2", ("FR_thigh", "block2")), ("home", ("BR_shank", "floor")),
                                       ("home", ("trunk", "floor")), ("wall", ("arm_link3", "wall_lintel")),
                                       ("wall", ("tray", "wall_lintel")), ("wall", ("trunk", "wall_lintel"))])
def test_positive_distance_equals_mujoco(course, pose, pair):
    """Edge-closest (crouch), face-closest (on block2), capsule and box vs the floor, arm capsule and tray box vs the
    lintel: the named pair's distance equals mj_geomDistance; every pair positive in MuJoCo C at that pose too."""
    robot, _, pairs, names, Q, got, *_ = course
    i, k = names.index(pose), _k(robot, pairs, *pair)
    ref = _mj(robot, Q[i], pairs.robot[k], pairs.env[k])
    assert ref > 0.0
    assert got[i, k] == pytest.approx(ref, abs=POS_TOL)


def test_every_positive_pair_of_every_pose_equals_mujoco(course):
    """All 54 pairs at all poses (random ones included): where MuJoCo C's distance is positive (and, for a capsule
    and a box, the sampled segment does not enter the box: MuJoCo C reports positive distances for some segments
    through a block) the distances agree within POS_TOL."""
    robot, _, pairs, names, Q, got, *_ = course
    n_checked = 0
    for i in range(len(names)):
        for k in range(len(pairs)):
            ref = _mj(robot, Q[i], pairs.robot[k], pairs.env[k])
            if ref <= 0.0 or ref >= DISTMAX:
                continue
            if CL.KINDS[pairs.kind[k]] == "capsule_box" and got[i, k] < 0.0:
                brute = _brute_segment_box(robot, Q[i], pairs.robot[k], pairs.env[k])
                assert brute < 0.0 and got[i, k] == pytest.approx(brute, abs=BRUTE_TOL), (names[i], k)
                continue
            assert abs(got[i, k] - ref) < POS_TOL, (names[i], robot.mj_model.geom(int(pairs.robot[k])).name,
                                                    robot.mj_model.geom(int(pairs.env[k])).name, got[i, k], ref)
            n_checked += 1
    assert n_checked > 1000


def test_penetrations(course):
    """Capsule and box vs the floor: the exact signed depth (MuJoCo C's too). A shank into block2 (crouch4): the
    depth of the segment's deepest point minus the radius (dense sampling), MuJoCo C's contact depth differs but
    agrees in sign."""
    robot, _, pairs, names, Q, got, *_ = course
    i = names.index("lowered")
    for k in np.where(pairs.env == robot.ids.floor_geom)[0]:
        assert got[i, k] == pytest.approx(_mj(robot, Q[i], pairs.robot[k], pairs.env[k]), abs=POS_TOL)
    assert min(got[i, _k(robot, pairs, f"{leg}_shank", "floor")] for leg in ("FL", "FR", "BL", "BR")) < -0.015
    i, k = names.index("crouch4"), _k(robot, pairs, "FR_shank", "block2")
    brute = _brute_segment_box(robot, Q[i], pairs.robot[k], pairs.env[k])
    assert got[i, k] == pytest.approx(brute, abs=BRUTE_TOL) and brute < -0.015
    assert _mj(robot, Q[i], pairs.robot[k], pairs.env[k]) < 0.0


def test_capsule_box_matches_sampled_segment_at_random_poses(course):
    """Every capsule/box pair at every pose (penetrating or not) vs the dense sampling of the segment."""
    robot, _, pairs, names, Q, got, *_ = course
    ks = np.where(pairs.kind == CL.KINDS.index("capsule_box"))[0]
    for i in range(0, len(names), 3):
        for k in ks:
            assert got[i, k] == pytest.approx(_brute_segment_box(robot, Q[i], pairs.robot[k], pairs.env[k]),
                                              abs=BRUTE_TOL), (names[i], k)


def test_rollout_clearance_is_the_min_over_the_pairs(course):
    robot, sim, pairs, names, Q, got, c, k = course
    np.testing.assert_allclose(c, got.min(axis=1), rtol=0, atol=RECOMPUTE_TOL)
    np.testing.assert_array_equal(k, got.argmin(axis=1))
    m = robot.mj_model
    for i in range(len(names)):
        g, e = int(pairs.robot[k[i]]), int(pairs.env[k[i]])
        assert clearance_name(sim, int(k[i])) == f"{m.geom(g).name} (body {m.body(int(m.geom_bodyid[g])).name}) / " \
                                                 f"{m.geom(e).name}"
    assert clearance_name(sim, _k(robot, pairs, "FR_shank", "block2")) == "FR_shank (body FR_calf) / block2"
    assert clearance_name(sim, -1) == ""


def test_mjx_slot_distance_overstates_edge_clearance():
    """Why the clearance is not read from contacts: MJX's capsule/box contact slots of a shank 2.8 mm above
    block2's far edge read 5.0 mm (and a pair beyond the margin reads 1 m), while the exact clearance reads
    MuJoCo C's distance."""
    from wbc_jax.physics import backend as physics

    robot = Robot("transport")
    m = robot.mj_model
    sim = make_sim(robot)
    jq = lambda n: m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]  # noqa: E731
    gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    q = robot.home_qpos(0.08)
    dy, dz, pitch, knee = CROUCH[0]
    q[1] += dy
    q[2] += dz
    q[jq("FR_pitch")], q[jq("FR_knee")] = pitch, knee
    # the data placed on the device as physics.make_data places it (committed), as the other sensing passes of this
    # module's scene are, so the jitted sensing program is not compiled a second time for uncommitted inputs
    d = physics.make_data(robot).replace(qpos=jax.device_put(jnp.asarray(q), jax.local_devices()[0]))
    d = jax.jit(physics.sense)(robot.mjx_model, d)
    shank, block = gid("FR_shank"), gid("block2")
    slots = [s for s, g in zip(sim.nonfoot_slots, sim.nonfoot_geoms) if set(g) == {shank, block}]
    mjx_d = float(np.min(np.asarray(d._impl.contact.dist)[slots]))
    ref = _mj(robot, q, shank, block)
    pairs = CL.clearance_pairs(robot)
    exact = float(CL.pair_distances(pairs, d)[_k(robot, pairs, "FR_shank", "block2")])
    assert 0.0 < ref < 0.004 and mjx_d > ref + 0.002  # measured: 2.82 mm vs 5.00 mm
    assert exact == pytest.approx(ref, abs=POS_TOL)


def test_same_on_the_warp_backend():
    """The clearance reads only geom poses, which both MJX backends fill: Warp's forward pass gives the JAX
    backend's distances (measured: 2e-8 m over the 54 pairs), separated pairs included (Warp's contact sensors
    report only penetrations)."""
    pytest.importorskip("warp")
    from wbc_jax.physics import backend as physics

    out = {}
    for backend in ("jax", "warp"):
        robot = Robot("transport", backend=backend)
        m = robot.mj_model
        jq = lambda n, m=m: m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]  # noqa: E731
        q = robot.home_qpos(0.08)
        dy, dz, pitch, knee = CROUCH[0]
        q[1] += dy
        q[2] += dz
        q[jq("FR_pitch")], q[jq("FR_knee")] = pitch, knee
        # placed as in test_mjx_slot_distance_overstates_edge_clearance: the JAX backend's sensing pass is that
        # test's compiled program (and tests/test_model.py's for this scene)
        d = physics.make_data(robot, 1).replace(qpos=jax.device_put(jnp.asarray(q), jax.local_devices()[0]))
        d = jax.jit(physics.sense)(robot.mjx_model, d)
        out[backend] = np.asarray(CL.pair_distances(CL.clearance_pairs(robot), d))
    np.testing.assert_allclose(out["warp"], out["jax"], atol=1e-6)
    assert np.sum(out["warp"] > 0.0) > 40


def test_box_box_equals_mujoco_at_close_random_poses():
    """Two boxes (a trunk-like and a wall-like one) at 3,000 random relative poses, their centres 0.5 to 1 x the sum
    of their half-diagonals apart: every separated pose (~500 within 5 cm; vertex / edge / face contacts of either
    box) agrees with MuJoCo C's ``mj_geomDistance`` within POS_TOL. The candidate set's exactness (module
    docstring: the vertices of both boxes, and the edges of the first at their points nearest the second's edge
    lines) is what this checks, where the course's poses seldom bring two boxes close."""
    ha, hb = np.array([0.24, 0.11, 0.06]), np.array([0.30, 0.05, 0.20])
    m = mujoco.MjModel.from_xml_string(f"""<mujoco><worldbody>
      <body><freejoint/><geom type="box" size="{ha[0]} {ha[1]} {ha[2]}"/></body>
      <body><freejoint/><geom type="box" size="{hb[0]} {hb[1]} {hb[2]}"/></body></worldbody></mujoco>""")
    rng = np.random.default_rng(7)
    n = 3000
    quat = rng.normal(size=(n, 2, 4))
    quat /= np.linalg.norm(quat, axis=2, keepdims=True)
    u = rng.normal(size=(n, 3))
    r = rng.uniform(0.5, 1.0, n) * (np.linalg.norm(ha) + np.linalg.norm(hb))
    pos = np.stack([u / np.linalg.norm(u, axis=1, keepdims=True) * r[:, None], np.zeros((n, 3))], axis=1)
    d = mujoco.MjData(m)
    R = np.zeros((n, 2, 3, 3))
    ref = np.zeros(n)
    for i in range(n):
        d.qpos[:] = np.concatenate([pos[i, 0], quat[i, 0], pos[i, 1], quat[i, 1]])
        mujoco.mj_kinematics(m, d)
        R[i] = d.geom_xmat.reshape(2, 3, 3)
        ref[i] = mujoco.mj_geomDistance(m, d, 0, 1, DISTMAX, None)
    got = np.asarray(jax.jit(jax.vmap(DI.box_box, in_axes=(0, 0, None, 0, 0, None)))(
        jnp.asarray(pos[:, 0]), jnp.asarray(R[:, 0]), jnp.asarray(ha), jnp.asarray(pos[:, 1]), jnp.asarray(R[:, 1]),
        jnp.asarray(hb)), float)
    close = (ref > 0.0) & (ref < 0.05)
    assert close.sum() > 300
    np.testing.assert_allclose(got[close], ref[close], atol=POS_TOL)
    far = (ref >= 0.05) & (ref < DISTMAX)
    np.testing.assert_allclose(got[far], ref[far], atol=POS_TOL)
    assert np.all(got[ref < 0.0] < 0.0)  # overlapping: the separating-axis depth, negative as MuJoCo's


@pytest.fixture(scope="module")
def broad(at_poses):
    """At the N_BROAD random course poses: every pair's exact distance, the broad phase's result and every bounded
    pair's lower bound."""
    _, _, pairs, poses, _, (exact, _, got, lower) = at_poses
    n = len(poses)
    rows = slice(n, n + N_BROAD)
    return (pairs, np.asarray(exact)[rows], jax.tree_util.tree_map(lambda x: x[rows], got),
            {k: v[rows] for k, v in lower.items()})


def test_broad_phase_bounds_are_lower_bounds(broad):
    """Every capsule/box and box/box bound is at most the pair's exact distance (float32 rounding: within the
    reported bound's BOUND_ROUNDING), penetrating pairs included; and tight enough to leave pairs out."""
    pairs, exact, _, lower = broad
    for k, lb in lower.items():
        sel = np.where(pairs.kind == k)[0]
        assert np.all(lb <= exact[:, sel] + CL.BOUND_ROUNDING), CL.KINDS[k]
        assert np.mean(lb > 0.1) > 0.5


def test_broad_phase_equals_the_exact_minimum_below_its_bound(broad):
    """Below the returned bound the broad phase gives the exact minimum over all 54 pairs and its pair (a
    capsule/box or box/box pair's distance within float32 rounding, RECOMPUTE_TOL; the others bit for bit); at or
    above it, the exact distance of the reported pair, never below the minimum. The bound is below the minimum at
    few of these (extreme) poses."""
    pairs, exact, got, _ = broad
    low = exact.min(axis=1)
    below = got.distance < got.bound
    assert np.mean(below) > 0.99
    np.testing.assert_array_equal(got.pair[below], exact[below].argmin(axis=1))
    bounded = np.isin(np.asarray(CL.KINDS)[pairs.kind[got.pair[below]]], list(CL.CANDIDATES))
    assert np.all((got.distance[below] == low[below]) | bounded)
    np.testing.assert_allclose(got.distance[below], low[below], rtol=0, atol=RECOMPUTE_TOL)
    assert np.all(got.distance >= low - RECOMPUTE_TOL)
    np.testing.assert_allclose(got.distance, exact[np.arange(len(low)), got.pair], rtol=0, atol=RECOMPUTE_TOL)


def test_broad_phase_non_finite_pose_and_empty_scene(at_poses):
    """A NaN pose (one leg's geoms NaN, the others finite) gives NaN and pair -1 (as the exact minimum does); a scene
    without pairs +inf and -1."""
    robot, _, pairs, _, _, (exact, _, got, _) = at_poses
    assert np.isnan(exact[-1]).any() and np.isfinite(exact[-1]).any()
    assert np.isnan(float(got.distance[-1])) and int(got.pair[-1]) == -1
    empty = CL.ClearancePairs(*(np.zeros((0,) + s, t) for s, t in [((), int), ((), int), ((), int), ((3,), float),
                                                                     ((3,), float)]))
    none = CL.bounded_min_clearance(empty, mjx.make_data(robot.mjx_model))
    assert float(none.distance) == np.inf and int(none.pair) == -1 and float(none.bound) == np.inf

