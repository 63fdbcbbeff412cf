"""Foundation acceptance: scenes, MJX vs MuJoCo C dynamics, batched factors, object at rest."""

import itertools
import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from wbc_jax.errors import FactorError, SceneError
from wbc_jax.physics import backend as physics
from wbc_jax.physics.observe import point_jacobians
from wbc_jax.robot import scenario
from wbc_jax.robot.model import Robot, mjx, resolve_ids
from wbc_jax.rollout import make_sim

MASS_TARGET = 24.26  # [kg] public code's total robot mass
MASS_TOL = 0.02  # relative
DYN_ATOL = 2e-4  # MJX (float32) vs MuJoCo C (float64), absolute, on M and qfrc_bias entries
DYN_RTOL = 2e-4
JAC_ATOL = 2e-5  # [m / rad]
FIELD_RTOL = 1e-6  # batched-model fields vs single-run compiled C model (float32 storage)
REST_SLIP_MAX = 1e-3  # [m] object slip on the held tray over 2 s
LEVELS = dict(m=(0.2, 0.3, 0.4), mu=(0.4, 0.7, 1.0), d=(0.06, 0.08, 0.10))


@pytest.fixture(scope="module")
def robot():
    return Robot("transport")


def test_scene_loads_in_c_and_mjx(robot):
    m = robot.mj_model
    assert m.nu == 18
    assert robot.ids.nv_robot == 24 and m.nv == 30
    assert abs(robot.total_robot_mass - MASS_TARGET) <= MASS_TOL * MASS_TARGET
    assert robot.mjx_model.nv == 30
    flat = Robot("flat")
    assert flat.mj_model.nv == 30 and flat.ids.wall_pair.size == 0
    # the object rests on the tray at about 0.80 m, trunk at about 0.45 m
    q = robot.home_qpos()
    assert abs(q[2] - 0.45) < 0.01
    assert abs(q[robot.ids.obj_qpos_adr + 2] - 0.80) < 0.02


def test_mjx_matches_mujoco_c_at_home(robot):
    m = robot.mj_model
    rng = np.random.default_rng(0)
    d = mujoco.MjData(m)
    d.qpos[:] = robot.home_qpos()
    d.qvel[:] = rng.normal(scale=0.5, size=m.nv)
    mujoco.mj_forward(m, d)
    M_c = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M_c)

    mx = robot.mjx_model
    dev = jax.local_devices()[0]
    dx = mjx.make_data(mx, device=dev).replace(qpos=jax.device_put(d.qpos, dev), qvel=jax.device_put(d.qvel, dev))
    # the backend's sensing pass (kinematics, mass matrix, bias forces): the program
    # test_static_contact_layout_equals_the_compiled_one compiles for this scene (one compile for both tests)
    dx = jax.jit(physics.sense)(mx, dx)
    np.testing.assert_allclose(np.asarray(mjx.full_m(mx, dx)), M_c, atol=DYN_ATOL, rtol=DYN_RTOL)
    np.testing.assert_allclose(np.asarray(dx.qfrc_bias), d.qfrc_bias, atol=DYN_ATOL, rtol=DYN_RTOL)

    ids = robot.ids
    points = [(ids.foot_body[i], d.site_xpos[ids.foot_site[i]]) for i in range(4)]
    points.append((ids.tray_body, d.site_xpos[ids.tray_site]))
    for body, point in points:
        jp_c, jr_c = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jp_c, jr_c, point, body)
        jp_x, jr_x = mjx.jac(mx, dx, jnp.asarray(point), body)
        np.testing.assert_allclose(np.asarray(jp_x).T, jp_c, atol=JAC_ATOL)
        np.testing.assert_allclose(np.asarray(jr_x).T, jr_c, atol=JAC_ATOL)

    # the controller's own point Jacobians (static body masks, no scan) and their Jdot v against MuJoCo C's
    pts = np.array([p for _, p in points])
    bodies = [b for b, _ in points]
    Jp, Jr, Jdp, Jdr = jax.jit(lambda d, p: point_jacobians(mx, d, ids, p, bodies))(dx, jnp.asarray(pts))
    nvr = ids.nv_robot
    for i, (body, point) in enumerate(points):
        jp_c, jr_c, jdp_c, jdr_c = (np.zeros((3, m.nv)) for _ in range(4))
        mujoco.mj_jac(m, d, jp_c, jr_c, point, body)
        mujoco.mj_jacDot(m, d, jdp_c, jdr_c, point, body)
        np.testing.assert_allclose(np.asarray(Jp[i]), jp_c[:, :nvr], atol=JAC_ATOL)
        np.testing.assert_allclose(np.asarray(Jr[i]), jr_c[:, :nvr], atol=JAC_ATOL)
        np.testing.assert_allclose(np.asarray(Jdp[i]), jdp_c @ d.qvel, atol=JAC_ATOL)
        np.testing.assert_allclose(np.asarray(Jdr[i]), jdr_c @ d.qvel, atol=JAC_ATOL)


def test_batched_model_matches_single_run_models(robot):
    combos = list(itertools.product(LEVELS["m"], LEVELS["mu"], LEVELS["d"]))
    m, mu, d = (np.array(c) for c in zip(*combos))
    f = scenario.validate_factors(robot.ids, m, mu, d)
    bm, in_axes = scenario.batch_model(robot.mjx_model, robot.mj_model, robot.ids, f)
    ids = robot.ids
    assert in_axes.body_mass == 0 and in_axes.body_pos is None
    for i, (mi, mui, di) in enumerate(combos):
        c = scenario.single_run_mj_model(str(robot.path), mi, mui, di)
        ob = ids.obj_body
        # requested values
        np.testing.assert_allclose(bm.body_mass[i, ob], mi, rtol=FIELD_RTOL)
        np.testing.assert_allclose(bm.body_inertia[i, ob], [mi * di**2 / 6] * 3, rtol=FIELD_RTOL)
        np.testing.assert_allclose(bm.geom_size[i, ids.obj_box_geom], [di / 2] * 3, rtol=FIELD_RTOL)
        np.testing.assert_allclose(bm.pair_friction[i, ids.obj_pair, :2], mui, rtol=FIELD_RTOL)
        z = bm.geom_pos[i, ids.obj_contact_geom]
        np.testing.assert_allclose(np.abs(z), di / 2 - ids.obj_sphere_radius, rtol=FIELD_RTOL)
        # the same values, and the compiler-derived ones, in an independently compiled C model
        for field in ("body_mass", "body_inertia", "body_invweight0"):
            np.testing.assert_allclose(bm.__getattribute__(field)[i, ob], getattr(c, field)[ob], rtol=FIELD_RTOL)
        np.testing.assert_allclose(bm.dof_invweight0[i, 24:], c.dof_invweight0[24:], rtol=FIELD_RTOL)
        np.testing.assert_allclose(bm.geom_size[i, ids.obj_box_geom], c.geom_size[ids.obj_box_geom], rtol=FIELD_RTOL)
        np.testing.assert_allclose(bm.geom_pos[i, ids.obj_contact_geom], c.geom_pos[ids.obj_contact_geom],
                                   rtol=FIELD_RTOL)
        np.testing.assert_allclose(bm.pair_friction[i, ids.obj_pair], c.pair_friction[ids.obj_pair], rtol=FIELD_RTOL)
        # and nothing else changed
        np.testing.assert_allclose(bm.body_mass[i, :ob], robot.mj_model.body_mass[:ob], rtol=FIELD_RTOL)


def _held_robot_model(robot: Robot, q0: np.ndarray) -> mujoco.MjModel:
    """Test-only scene: trunk welded, every robot joint held by a stiff spring at its home angle."""
    spec = mujoco.MjSpec.from_file(str(robot.path))
    spec.delete(spec.joint("root"))
    m0 = robot.mj_model
    for j in range(m0.njnt):
        if m0.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            js = spec.joint(m0.joint(j).name)
            js.stiffness = [2000.0, 0, 0]
            js.springref = float(q0[m0.jnt_qposadr[j]])
            js.damping = [20.0, 0, 0]
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    return spec.compile()


@pytest.mark.slow  # 2 s of physics alone; tests/test_transport.py's loaded stand bounds the slip under QP control
def test_object_rests_on_held_tray(robot):
    m_obj, mu, d = 0.4, 0.4, 0.10
    q0 = robot.home_qpos(d)
    mm = _held_robot_model(robot, q0)
    ids = resolve_ids(mm)
    mx = mjx.put_model(mm)
    bm, in_axes = scenario.batch_model(mx, mm, ids, scenario.validate_factors(ids, m_obj, mu, d))
    data = mjx.make_data(mx).replace(qpos=jnp.asarray(q0[7:]))

    def run(m, dd):
        def body(dd, _):
            dd = mjx.step(m, dd)
            return dd, (dd.xpos[ids.obj_body], dd.site_xpos[ids.tray_site], dd.site_xmat[ids.tray_site])

        return jax.lax.scan(body, dd, None, length=int(round(2.0 / mm.opt.timestep)))

    _, (p_obj, p_tray, R_tray) = jax.jit(jax.vmap(run, in_axes=(in_axes, None)))(bm, data)
    rel = np.einsum("tji,tj->ti", np.asarray(R_tray[0]), np.asarray(p_obj[0] - p_tray[0]))  # tray frame
    slip = np.linalg.norm(rel[:, :2] - rel[0, :2], axis=1).max()
    assert np.all(np.abs(rel[:, 2] - d / 2) < 2e-3), "object left the tray"
    assert slip < REST_SLIP_MAX, f"object slid {slip * 1e3:.3f} mm"


def test_bad_scene_and_factor_values(robot, tmp_path):
    with pytest.raises(SceneError, match="no such file"):
        Robot(tmp_path / "missing.xml")
    bad = {"m": (0.0, 0.4, 0.08), "mu": (0.3, -0.1, 0.08), "d": (0.3, 0.4, 0.25)}
    for name, (m, mu, d) in bad.items():
        with pytest.raises(FactorError, match=rf"factor {name} = .* expected"):
            scenario.validate_factors(robot.ids, m, mu, d)
    with pytest.raises(FactorError, match="d = 0 m"):
        scenario.validate_factors(robot.ids, 0.3, 0.7, 0.0)


def test_cli_bad_scene_is_one_line_exit_2(tmp_path):
    out = tmp_path / "demo"
    p = subprocess.run([sys.executable, "-m", "wbc_jax", "demo", "--scene", str(tmp_path / "nope.xml"),
                        "--out", str(out)], capture_output=True, text=True)
    assert p.returncode == 2
    lines = [ln for ln in p.stderr.splitlines() if ln.strip() and "warp" not in ln]
    assert len(lines) == 1 and "no such file" in lines[0], p.stderr
    assert not out.exists()


@pytest.mark.parametrize("scene", ["flat", "transport"])
def test_static_contact_layout_equals_the_compiled_one(scene):
    """The JAX backend's contact-slot layout (which geom pair each of MJX's contact slots holds) worked out from the
    model alone equals the one a compiled sensing pass returns, on both scenes (the static layout spares a 25-40 s
    compile per scene on a CPU)."""
    from wbc_jax.physics.backend import slot_geoms_static
    from wbc_jax.physics.contacts import compiled_contact_geoms

    robot = Robot(scene)
    static = slot_geoms_static(robot.mjx_model)
    assert static is not None and len(static) > 0
    np.testing.assert_array_equal(static, compiled_contact_geoms(robot))


def test_robot_and_sim_compare_by_value(robot):
    """Static configuration is hashed by value: equal scenes and settings share the compiled programs' caches."""
    same = Robot("transport")
    assert same is not robot and same == robot and hash(same) == hash(robot)
    assert Robot("flat") != robot and Robot("transport", solver_iterations=3) != robot
    sim = make_sim(robot, log_every=10)
    assert make_sim(same, log_every=10) == sim and {sim: 1}[make_sim(same, log_every=10)] == 1
    assert make_sim(robot, log_every=20) != sim and make_sim(robot, log_every=10, sensor_noise=True) != sim


def test_initial_configuration_per_run(robot):
    """Each run's start (wbc_jax.campaign.build.initial_configuration): its object side's home pose (computed once
    per side), the object shifted by (obj_dx, obj_dy) and yawed by obj_yaw about world z, base and object moving at
    v0; checked per run against home_qpos and rotation matrices."""
    from wbc_jax.campaign.build import initial_configuration
    from wbc_jax.campaign.design import design
    from wbc_jax.campaign.spec import load_spec

    dz = design(load_spec("sweeps/paper_campaign.toml"))
    qpos, qvel = initial_configuration(robot, dz)
    a, v = robot.ids.obj_qpos_adr, robot.ids.obj_dof_adr
    assert qpos.shape == (dz.n, robot.mj_model.nq) and qvel.shape == (dz.n, robot.mj_model.nv)
    for i in range(0, dz.n, 7):
        home = robot.home_qpos(float(dz.d[i]))
        np.testing.assert_array_equal(np.delete(qpos[i], range(a, a + 7)), np.delete(home, range(a, a + 7)))
        np.testing.assert_allclose(qpos[i, a:a + 3], home[a:a + 3] + [dz.obj_dx[i], dz.obj_dy[i], 0.0], atol=1e-12)
        R0, R = np.zeros(9), np.zeros(9)
        mujoco.mju_quat2Mat(R0, home[a + 3:a + 7])
        mujoco.mju_quat2Mat(R, qpos[i, a + 3:a + 7])
        c, s = np.cos(dz.obj_yaw[i]), np.sin(dz.obj_yaw[i])
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        np.testing.assert_allclose(R.reshape(3, 3), Rz @ R0.reshape(3, 3), atol=1e-12)
        np.testing.assert_array_equal(qvel[i, :2], dz.v0[i])
        np.testing.assert_array_equal(qvel[i, v:v + 2], dz.v0[i])


def test_max_pair_contacts_by_geom_types():
    """``robot.sensors.max_pair_contacts`` (the Warp scene's contact-sensor slots) from the pairs' geom types, hand
    counted from MuJoCo Warp's collision functions: sphere pairs 1, capsule vs plane or box 2, box vs plane 4, box
    vs box 4 on the convex path and 8 on the box_box primitive (native CCD disabled), other types MuJoCo Warp's
    default; the largest over the pairs."""
    from wbc_jax.robot.sensors import WARP_MAXMATCH, max_pair_contacts

    spec = mujoco.MjSpec()
    G = mujoco.mjtGeom
    kinds = {"plane": G.mjGEOM_PLANE, "sphere": G.mjGEOM_SPHERE, "capsule": G.mjGEOM_CAPSULE, "box": G.mjGEOM_BOX,
             "box2": G.mjGEOM_BOX, "ellipsoid": G.mjGEOM_ELLIPSOID}
    for name, t in kinds.items():
        spec.worldbody.add_geom(name=name, type=t, size=[0.1, 0.1, 0.1])
    m = spec.compile()
    g = {name: m.geom(name).id for name in kinds}
    cases = [(("sphere", "plane"), 1), (("box", "sphere"), 1), (("capsule", "plane"), 2), (("box", "capsule"), 2),
             (("plane", "box"), 4), (("box", "box2"), 4), (("ellipsoid", "box"), WARP_MAXMATCH)]
    for (a, b), want in cases:
        assert max_pair_contacts(m, [(g[a], g[b])]) == want, (a, b)
    assert max_pair_contacts(m, [(g["sphere"], g["plane"]), (g["capsule"], g["plane"])]) == 2
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_NATIVECCD)
    assert max_pair_contacts(m, [(g["box"], g["box2"])]) == 8
    assert max_pair_contacts(m, [(g["plane"], g["box"])]) == 4


def test_zero_stages_are_off_only_where_mujoco_c_computes_zeros(robot):
    """``robot.sensors.zero_stages``: the transport scene (no joint stiffness or damping, no friction loss, no
    gravity compensation, no fluid) gets springs, dampers and friction loss off, and MuJoCo C steps the scene with
    them off exactly as with them on (0.3 s from home with a push and random torques: qpos, qvel, qacc equal bit for
    bit); one damped joint keeps springs and dampers on, one joint with friction loss keeps friction loss on, and
    either stage, turned off there, would change the motion."""
    from wbc_jax.robot.sensors import zero_stages

    D = mujoco.mjtDisableBit
    passive, friction = int(D.mjDSBL_SPRING) | int(D.mjDSBL_DAMPER), int(D.mjDSBL_FRICTIONLOSS)
    base = robot.mj_model
    assert zero_stages(base) == passive | friction
    if physics.warp_available():  # the Warp scene is compiled with them off
        assert Robot("transport", backend="warp").mj_model.opt.disableflags & (passive | friction) == passive | friction

    def roll(m):
        d = mujoco.MjData(m)
        mujoco.mj_resetDataKeyframe(m, d, robot.ids.key_home)
        rng = np.random.default_rng(0)
        for k in range(300):
            d.ctrl[:] = rng.uniform(-5.0, 5.0, m.nu)
            d.xfrc_applied[robot.ids.trunk_body, :3] = [20.0, 10.0, 0.0] if k < 100 else 0.0
            mujoco.mj_step(m, d)
        return [d.qpos.copy(), d.qvel.copy(), d.qacc.copy(), d.qfrc_passive.copy()]

    off = mujoco.MjModel.from_xml_path(str(robot.path))
    off.opt.disableflags |= zero_stages(off)
    for a, b in zip(roll(base), roll(off)):
        np.testing.assert_array_equal(a, b)

    for field, kept in (("dof_damping", passive), ("dof_frictionloss", friction)):
        m = mujoco.MjModel.from_xml_path(str(robot.path))
        getattr(m, field)[7] = 0.5
        assert zero_stages(m) == (passive | friction) & ~kept, field
        cut = mujoco.MjModel.from_xml_path(str(robot.path))
        getattr(cut, field)[7] = 0.5
        cut.opt.disableflags |= kept  # what zero_stages keeps on does act here
        assert np.abs(roll(m)[0] - roll(cut)[0]).max() > 1e-3, field
