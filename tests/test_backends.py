"""The two MJX physics backends (JAX and MuJoCo Warp, which also runs on the CPU) against each other and MuJoCo C.

References: MuJoCo C's ``mj_fullM`` for the dense mass matrix rebuilt from Warp's CSR storage; MJX's own collision
distances (JAX backend, every pair's slot) for the geometric sphere distances the Warp path computes; the JAX
backend's closed loop for the Warp backend's (same model, same controller, a short loaded stand and first steps);
MuJoCo Warp's own forward pass for the state the delayed sensing says the controller read.
"""

from __future__ import annotations

import json

import jax
import mujoco
import numpy as np
import pytest

pytest.importorskip("warp")

from test_transport import CHUNK_SECONDS, TROT_PLAN  # noqa: E402  (the walks share its compiled chunk program)

from wbc_jax.campaign.spec import SWEEPS
from wbc_jax.physics import backend as physics
from wbc_jax.physics import contacts
from wbc_jax.physics.observe import mass_matrix  # noqa: E402
from wbc_jax.planner.gait import GaitParams
from wbc_jax.robot import scenario  # noqa: E402
from wbc_jax.robot.model import Robot  # noqa: E402
from wbc_jax.rollout import final_results, make_sim, simulate  # noqa: E402
from wbc_jax.rollout.batch import prepare_batch  # noqa: E402

M_TOL = 1e-5  # relative, float32 CSR scatter vs MuJoCo C float64
DIST_TOL = 1e-5  # [m] geometric sphere distances vs MJX's collision functions (float32)
FORCE_RTOL, FORCE_ATOL = 0.05, 0.02  # [-], [N] object contact forces, float32 backends vs MuJoCo C float64
POS_TOL = 1e-3  # [m] trunk and object positions after the walk, Warp vs JAX
METRIC_RTOL = 0.05  # R and T, Warp vs JAX (the constraint solvers split the object's four forces differently)
SECONDS = 0.3  # the walks: 0.1 s standing loaded, then the first diagonal swing (the gait starts at 0.1 s)
NAN_SECONDS = 0.1  # the NaN walk: one chunk, against the clean walk's state after its first chunk
# the walks' Sim and plan shapes and chunk length are tests/test_transport.py's (log_every 50, its trot segment's
# plan and chunk length), so the JAX walk runs the compiled chunk program of that file's stand and trot (one compile
# for both files; the logs are not read here)
LOG_EVERY, PLAN = 50, dict(TROT_PLAN, gait=GaitParams(t_start=0.1))
FACTORS = (np.array([0.3, 0.4]), np.array([0.7, 0.4]), np.array([0.08, 0.06]))  # m [kg], mu, d [m]


@pytest.fixture(scope="module")
def walks():
    """Both backends' batch-2 closed loops over SECONDS on the flat scene, and Warp's with delayed sensing
    ("warp:delayed"): (sim, batch, final state, results); under "<key>@nan" the same after NAN_SECONDS (the walk
    runs on from that state: the same chunks as one call)."""
    out = {}
    for key in ("jax", "warp", "warp:delayed"):
        backend, _, sensing = key.partition(":")
        sim = make_sim(Robot("flat", backend=backend), log_every=LOG_EVERY, sensing=sensing or "exact")
        b = prepare_batch(sim, *FACTORS, plan_kwargs=PLAN)
        st = b.state
        for at, seconds in (("@nan", NAN_SECONDS), ("", SECONDS - NAN_SECONDS)):
            st, _ = simulate(sim, b.model, b.in_axes, st, b.plan, b.om, b.gains, b.push, b.mu_ground,
                             seconds=seconds, chunk_seconds=CHUNK_SECONDS)
            res = final_results(sim, st, np.zeros((2, 3)), FACTORS[1])
            out[key + at] = (sim, b, jax.device_get(st), res)
    return out


def _object_forces_c(robot, factors, d):
    """MuJoCo C (float64), one ``mj_step`` per run from the state ``d`` (batched: qpos, qvel, ctrl,
    qacc_warmstart) with that run's object: (B, 4, 3) forces at the object's contact spheres, contact frame,
    normal first (zero where a sphere does not touch)."""
    out = np.zeros((len(factors[0]), 4, 3))
    for i, (m, mu, side) in enumerate(zip(*factors)):
        mj = scenario.single_run_mj_model(str(robot.path), m, mu, side)
        data = mujoco.MjData(mj)
        for k in ("qpos", "qvel", "ctrl", "qacc_warmstart"):
            getattr(data, k)[:] = np.asarray(getattr(d, k)[i])
        mujoco.mj_step(mj, data)
        pairs = [{mj.pair_geom1[p], mj.pair_geom2[p]} for p in robot.ids.obj_pair]
        for k in range(data.ncon):
            c = data.contact[k]
            if {c.geom1, c.geom2} in pairs:
                f = np.zeros(6)
                mujoco.mj_contactForce(mj, data, k, f)
                out[i, pairs.index({c.geom1, c.geom2})] = f[:3]
    return out


def test_warp_mass_matrix_and_distances_match_references(walks):
    """At the Warp walk's final state: M rebuilt from Warp's CSR vs MuJoCo C; foot and object-sphere distances
    (geometric on Warp) vs the JAX backend at the same positions. At each backend's own walk's final state (its
    torques and its constraint solver's warm start): one step's forces at the object's four contact spheres vs
    MuJoCo C in float64 from the same state (the scenes' object contacts make the force a continuous function of
    penetration, so the statically indeterminate split of the load over four corners does not follow float32
    rounding; with MuJoCo's default impedance the backends' splits were 0.13 N off C's).

    Why each backend's own state for the forces: the warm start is the solver's, not the model's; given the other
    backend's warm start, MJX's JAX solver (float32) stops off C's split of the load (whatever its iterations)."""
    out, own = {}, {}
    for backend in ("jax", "warp"):
        sim, b, st, _ = walks[backend]

        def one(m, d, sim=sim):
            ds = physics.sense(m, d)
            dist = contacts.object_contacts(sim, m, ds)[1]
            f = contacts.object_contacts(sim, m, physics.finish(m, ds, ds.ctrl))[0]  # one step's solved forces
            return mass_matrix(m, ds), contacts.foot_dist(sim, m, ds), dist, f

        f = jax.jit(jax.vmap(one, in_axes=(b.in_axes, 0)))

        def at(src, b=b):  # this backend's data at a walk's final state, torques and warm start included
            return b.state.d.replace(**{k: jax.numpy.asarray(getattr(src, k))
                                        for k in ("qpos", "qvel", "ctrl", "qacc_warmstart")})

        out[backend] = jax.device_get(f(b.model, at(walks["warp"][2].d)))  # the Warp walk's, on both backends
        own[backend] = jax.device_get(f(b.model, at(st.d)))[3]
    sim, _, st, _ = walks["warp"]
    mj, nvr = sim.robot.mj_model, sim.robot.ids.nv_robot
    data = mujoco.MjData(mj)  # MuJoCo C at run 0's configuration (the robot's block does not depend on the object)
    data.qpos[:], data.qvel[:] = np.asarray(st.d.qpos[0]), np.asarray(st.d.qvel[0])
    mujoco.mj_forward(mj, data)
    full = np.zeros((mj.nv, mj.nv))
    mujoco.mj_fullM(mj, data, full)
    M = np.asarray(out["warp"][0][0])
    np.testing.assert_allclose(M[:nvr, :nvr], full[:nvr, :nvr], rtol=M_TOL, atol=M_TOL * np.abs(full).max())
    np.testing.assert_allclose(out["warp"][0], out["jax"][0], rtol=M_TOL, atol=M_TOL * np.abs(full).max())
    np.testing.assert_allclose(out["warp"][1], out["jax"][1], atol=DIST_TOL)  # feet
    np.testing.assert_allclose(out["warp"][2], out["jax"][2], atol=DIST_TOL)  # object spheres
    for backend in ("jax", "warp"):
        f, f_c = own[backend], _object_forces_c(sim.robot, FACTORS, walks[backend][2].d)
        assert np.all(f_c[..., 0] > 0.05)  # every corner carries load at this state (the comparison means something)
        np.testing.assert_allclose(f[..., 0], f_c[..., 0], rtol=FORCE_RTOL, atol=FORCE_ATOL)  # normal
        np.testing.assert_allclose(np.linalg.norm(f[..., 1:], axis=-1), np.linalg.norm(f_c[..., 1:], axis=-1),
                                   rtol=FORCE_RTOL, atol=FORCE_ATOL)  # tangential magnitude (frames' signs differ)


def test_short_loaded_walk_agrees_between_backends(walks):
    (jsim, _, js, jr), (_, _, ws, wr) = walks["jax"], walks["warp"]
    ids = jsim.robot.ids
    a = ids.obj_qpos_adr
    for q_j, q_w in ((js.d.qpos[:, :3], ws.d.qpos[:, :3]), (js.d.qpos[:, a:a + 3], ws.d.qpos[:, a:a + 3])):
        np.testing.assert_allclose(np.asarray(q_w), np.asarray(q_j), atol=POS_TOL)
    for k in ("R", "T"):
        np.testing.assert_allclose(wr[k], jr[k], rtol=METRIC_RTOL)
    assert np.all(wr["success"] == jr["success"])
    assert not np.any(ws.acc.overflow) and not np.any(ws.acc.nonfinite)
    assert np.all(np.asarray(ws.acc.n_steps) == np.asarray(js.acc.n_steps))


def test_warp_split_step_equals_mjx_forward_then_step(walks):
    """Warp: ``sense`` (MuJoCo Warp's ``step1`` through MJX's generated call) of a view with noisy velocities and
    ``finish`` (the rest of ``step``, the constraint rows made again with the true velocities) against MJX's own
    calls, ``mjx.forward`` of the view then ``mjx.step`` of it with the true velocities, from the Warp walk's final
    state: what the controller reads of the view, and the step's state and sensors, bit for bit; and exact sensing's
    first data (``initial``, MJX's forward call running MuJoCo Warp's ``forward``) against ``mjx.forward``, every
    field."""
    sim, b, st, _ = walks["warp"]
    mjx = physics.mjx
    read = ("xpos", "xmat", "subtree_com", "site_xpos", "site_xmat", "geom_xpos", "geom_xmat", "cvel", "cdof",
            "cdof_dot", "qfrc_bias")

    def both(m, d, noise):
        ds, view = physics.sense_with_view(m, d, d.qvel + noise)
        ref_view = mjx.forward(m, d.replace(qvel=d.qvel + noise))
        ref = mjx.step(m, ref_view.replace(qvel=d.qvel))
        mine = physics.finish(m, ds, d.ctrl)
        pick = ("time", "qpos", "qvel", "qacc_warmstart", "sensordata")
        first = physics.initial(m, d, sensed=True)  # exact sensing's first data: MJX's forward call of its own
        return ([getattr(view, k) for k in read] + [mass_matrix(m, view)] + jax.tree.leaves(first),
                [getattr(mine, k) for k in pick],
                [getattr(ref_view, k) for k in read] + [mass_matrix(m, ref_view)] + jax.tree.leaves(mjx.forward(m, d)),
                [getattr(ref, k) for k in pick])

    d = b.state.d.replace(**{k: jax.numpy.asarray(getattr(st.d, k)) for k in ("qpos", "qvel", "ctrl",
                                                                             "qacc_warmstart")})
    noise = 0.05 * jax.random.normal(jax.random.PRNGKey(0), d.qvel.shape)
    view, step, ref_view, ref = jax.device_get(jax.jit(jax.vmap(both, in_axes=(b.in_axes, 0, 0)))(b.model, d, noise))
    assert np.all(ref[0] > np.asarray(d.time))  # a step was taken
    exact = jax.device_get(jax.jit(jax.vmap(physics.sense, in_axes=(b.in_axes, 0)))(b.model, d))
    assert np.abs(view[read.index("qfrc_bias")] - exact.qfrc_bias).max() > 1e-6  # the noise reached the view
    assert np.abs(ref[4]).max() > 0  # the step's contact sensors hold forces
    for got, want in zip(view + step, ref_view + ref):
        np.testing.assert_array_equal(got, want)


def test_delayed_sensing_reads_the_last_steps_start(walks):
    """Sensing "delayed": the data's derived fields after a step are Warp's forward pass of the state ``prev``
    records (the step's start), so the controller's view is that state, consistently; the walk agrees with the
    exact-sensing one to the backends' tolerance; the option is refused where it saves nothing."""
    sim, b, st, res = walks["warp:delayed"]
    qpos, qvel, t = (np.asarray(v) for v in st.prev)
    assert np.all(np.abs(t - np.asarray(st.d.time) + sim.dt_physics) < 1e-6)  # one physics step old
    assert np.max(np.abs(qpos - np.asarray(st.d.qpos))) > 1e-5  # the robot moved in that step (the test can fail)
    d = b.state.d.replace(qpos=jax.numpy.asarray(qpos), qvel=jax.numpy.asarray(qvel),
                          ctrl=jax.numpy.asarray(st.d.ctrl))
    fwd = jax.device_get(jax.jit(jax.vmap(physics.mjx.forward, in_axes=(b.in_axes, 0)))(b.model, d))
    np.testing.assert_allclose(np.asarray(st.d.xpos), fwd.xpos, atol=1e-6)
    np.testing.assert_allclose(np.asarray(st.d.sensordata), fwd.sensordata, atol=1e-4, rtol=1e-4)
    _, _, ws, wr = walks["warp"]
    a = sim.robot.ids.obj_qpos_adr
    for sl in (slice(0, 3), slice(a, a + 3)):
        np.testing.assert_allclose(np.asarray(st.d.qpos[:, sl]), np.asarray(ws.d.qpos[:, sl]), atol=POS_TOL)
    for k in ("R", "T"):
        np.testing.assert_allclose(res[k], wr[k], rtol=METRIC_RTOL)
    assert np.all(res["success"] == wr["success"])
    with pytest.raises(ValueError, match="sensing = 'delayed' needs the Warp backend"):
        make_sim(walks["jax"][0].robot, sensing="delayed")


def test_nan_run_is_frozen_and_others_unchanged_on_warp(walks):
    """Warp (one shared contact list for the batch): a run started with NaN velocities keeps its last finite state
    (``physics.freeze``: its positions stay the start's) and is marked non-finite, while the other run's walk equals
    the clean batch's over the same NAN_SECONDS (the same compiled chunk, so the same arithmetic)."""
    sim, b, st, res = walks["warp:delayed@nan"]
    d = b.state.d
    state = b.state._replace(d=d.replace(qvel=d.qvel.at[1].set(np.nan)))
    bad, _ = simulate(sim, b.model, b.in_axes, state, b.plan, b.om, b.gains, b.push, b.mu_ground,
                      seconds=NAN_SECONDS, chunk_seconds=CHUNK_SECONDS)
    bad = jax.device_get(bad)
    got = final_results(sim, bad, np.zeros((2, 3)), FACTORS[1])
    assert got["nonfinite"][1] and not got["success"][1] and not got["nonfinite"][0]
    np.testing.assert_array_equal(np.asarray(bad.d.qpos[1]), np.asarray(d.qpos[1]))  # frozen at the start
    np.testing.assert_array_equal(np.asarray(bad.prev[0][1]), np.asarray(d.qpos[1]))  # its view: that state
    np.testing.assert_allclose(np.asarray(bad.d.qpos[0]), np.asarray(st.d.qpos[0]), atol=1e-6)
    assert np.abs(np.asarray(st.d.qpos[0]) - np.asarray(d.qpos[0])).max() > 1e-4  # the clean run moved meanwhile
    for k in ("R", "T", "S"):
        assert np.isfinite(res[k][0]), k
        np.testing.assert_allclose(got[k][0], res[k][0], rtol=1e-5, err_msg=k)
    assert not np.any(np.asarray(bad.acc.overflow))


def test_solver_cap_is_counted(walks):
    """physics.solver_capped (Accum.n_solver_cap, results.csv's solver_cap_fraction), Warp: one physics step of
    the robot at home, the object pressed into the tray, with random joint and base velocities (seed 0, 1 rad/s or
    m/s), whose contacts need a constraint solve of several iterations. With a cap of 100 the solve stops at its
    tolerance (not capped); with a cap of 2, below that count, it stops at the cap (capped). The walks' fractions:
    a share on Warp, NaN on JAX (MJX's JAX solver does not report its iteration count)."""
    got = {}
    for iters in (100, 2):
        robot = Robot("flat", backend="warp", solver_iterations=iters)
        qpos = robot.home_qpos(0.08)
        # the object pressed into the tray to the end of its contacts' impedance ramp (solimp width), so its four
        # contacts carry load at full stiffness (at home they just touch and carry none)
        qpos[robot.ids.obj_qpos_adr + 2] -= robot.mj_model.pair_solimp[robot.ids.obj_pair[0], 2]
        qpos = jax.numpy.asarray(qpos)[None]
        qvel = jax.numpy.asarray(np.random.default_rng(0).normal(0.0, 1.0, robot.mj_model.nv))[None]
        d = jax.vmap(lambda q, v, robot=robot: physics.make_data(robot, 1).replace(qpos=q, qvel=v))(qpos, qvel)

        def one(m, d):
            d1 = physics.mjx.step(m, d)
            return physics.solver_capped(m, d1), d1._impl.solver_niter, d1._impl.nefc

        got[iters] = [np.asarray(x)[0] for x in jax.jit(jax.vmap(one, in_axes=(None, 0)))(robot.mjx_model, d)]
    (cap100, n100, nefc100), (cap2, n2, nefc2) = got[100], got[2]
    assert nefc100 > 0 and nefc2 > 0  # contacts: the solver runs
    assert not bool(cap100) and 2 < n100 < 100  # converged, after more iterations than the other cap
    assert bool(cap2) and n2 == 2
    frac = walks["warp"][3]["solver_cap_fraction"]
    assert np.all((frac >= 0) & (frac <= 1)) and np.all(np.isnan(walks["jax"][3]["solver_cap_fraction"]))


def _stepped(robot, qpos, m=None):
    """One Warp physics step of the runs at ``qpos`` (runs, nq) from rest: the batched mjx.Data after it."""
    d = jax.vmap(lambda q: physics.make_data(robot, len(qpos)).replace(qpos=q))(jax.numpy.asarray(qpos))
    return jax.jit(jax.vmap(physics.mjx.step, in_axes=(None, 0)))(m or robot.mjx_model, d)


def _mujoco_contacts(robot, qpos, pairs):
    """Per pair of ``pairs`` (ids) the dists of MuJoCo C's contacts at ``qpos`` (float64 ``mj_forward``)."""
    mj = robot.mj_model
    data = mujoco.MjData(mj)
    data.qpos[:] = qpos
    mujoco.mj_forward(mj, data)
    return [[float(c.dist) for c in data.contact[:data.ncon]
             if {int(c.geom1), int(c.geom2)} == {int(mj.pair_geom1[p]), int(mj.pair_geom2[p])}] for p in pairs]


def test_object_sensor_slots_hold_every_match(monkeypatch):
    """The Warp scene's contact sensors are the object spheres' (one per sphere vs the tray), their slots
    ``contact_sensor_maxmatch`` the most contacts of a sphere's pair (:func:`wbc_jax.robot.sensors.max_pair_contacts`:
    1), at least ``sensors.MIN_SLOTS`` (2), instead of MuJoCo Warp's default 64: the cube pressed 1 mm into the tray,
    one physics step: each sensor's count equals MuJoCo C's contacts of its pair (float64 ``mj_forward``), the
    sensordata equal bit for bit, and no match overflow is read (``contacts.match_overflow``), which reads one where
    the slots are fewer than the count."""
    import dataclasses
    from types import SimpleNamespace

    robot = Robot("transport", backend="warp")
    mx = robot.mjx_model
    assert physics.contact_sensor_slots(mx) == 2 and len(robot.sensors.obj) == 4
    assert robot.mj_model.nsensor == 4 and physics.contact_sensor_slots(Robot("flat").mjx_model) is None
    qpos = robot.home_qpos(0.08)
    qpos[robot.mj_model.jnt_qposadr[robot.mj_model.body_jntadr[robot.ids.obj_body]] + 2] -= 1e-3
    sim = SimpleNamespace(robot=robot)
    wide = mx.replace(opt=mx.opt.replace(_impl=dataclasses.replace(mx.opt._impl, contact_sensor_maxmatch=64)))
    d1, d64 = _stepped(robot, qpos[None]), _stepped(robot, qpos[None], wide)
    sd = np.asarray(d1.sensordata[0])
    np.testing.assert_array_equal(sd, np.asarray(d64.sensordata[0]))
    want = [len(c) for c in _mujoco_contacts(robot, qpos, robot.ids.obj_pair)]
    np.testing.assert_array_equal(sd[robot.sensors.found], want)
    assert sum(want) == 4  # the cube, pressed 1 mm into the tray, touches it at its four spheres
    def over():
        return bool(np.asarray(jax.jit(jax.vmap(lambda d: contacts.match_overflow(sim, mx, d)))(d1))[0])
    assert not over()
    monkeypatch.setattr(physics, "contact_sensor_slots", lambda m: 0)  # fewer slots than a sensor's count
    assert over()


def test_pair_minima_as_mujoco_c():
    """The non-foot and wall distances read from MuJoCo Warp's shared contact list (``contacts.pair_minima``, one
    reduction for the batch): three runs stepped at once, one physics step each: at home (nothing listed: +inf),
    the tray pushed 25 mm into the wall's lintel with the cube yawed 45 deg 10 mm into its underside (box-box pairs on
    MuJoCo Warp's box_box primitive, native CCD disabled in the Warp scene, more than 4 contacts a pair), and the
    robot lowered 0.25 m into the floor (trunk, thighs and shanks, boxes and capsules, several contacts a pair).
    Each run's entries equal the smallest dist of MuJoCo C's contacts of each non-foot pair and of all wall pairs
    (float64 ``mj_forward``; +inf where MuJoCo C lists none), so the runs' contacts land in their own entries, every
    contact counted; ``contacts.penetrations`` flags the wall and the floor where they are."""
    from types import SimpleNamespace

    robot = Robot("transport", backend="warp")
    ccd = int(mujoco.mjtDisableBit.mjDSBL_NATIVECCD)
    assert robot.mj_model.opt.disableflags & ccd and not Robot("transport").mj_model.opt.disableflags & ccd
    mj, ids = robot.mj_model, robot.ids
    home = robot.home_qpos(0.08)
    data = mujoco.MjData(mj)
    data.qpos[:] = home
    mujoco.mj_kinematics(mj, data)
    lintel, tray = mj.geom("wall_lintel").id, mj.geom("tray").id  # the lintel's face toward the robot
    face = data.geom_xpos[lintel, 1] + mj.geom_size[lintel, 1]
    wall = home.copy()
    wall[1] += face - 0.025 - data.geom_xpos[tray, 1]  # the tray's centre 25 mm behind the face
    wall[2] += 0.02  # the feet off the ground
    obj = mj.jnt_qposadr[mj.body_jntadr[mj.geom_bodyid[mj.geom("object").id]]]  # the cube, yawed 45 deg, 10 mm
    bottom = data.geom_xpos[lintel, 2] - mj.geom_size[lintel, 2]  # into the lintel's underside by its edge
    wall[obj:obj + 7] = [0.0, face - 0.02, bottom - 0.03, np.cos(np.pi / 8), 0.0, 0.0, np.sin(np.pi / 8)]
    sunk = home.copy()
    sunk[2] -= 0.25
    runs = np.stack([home, wall, sunk])
    d1 = _stepped(robot, runs)
    sim = SimpleNamespace(robot=robot, **dict(zip(("nonfoot_slots", "wall_slots"),
                                                  contacts.sim_indices(robot)[:2])))
    minima, (nonfoot, walls) = jax.jit(jax.vmap(lambda d: (contacts.pair_minima(sim, d),
                                                           contacts.penetrations(sim, d))))(d1)
    minima = np.asarray(minima)
    assert minima.shape == (3, len(ids.nonfoot_floor_pair) + 1)
    n_wall, n_floor = [], []
    for r, q in enumerate(runs):
        nf = _mujoco_contacts(robot, q, ids.nonfoot_floor_pair)
        wl = _mujoco_contacts(robot, q, ids.wall_pair)
        want = np.array([min(c, default=np.inf) for c in nf] + [min(sum(wl, []), default=np.inf)])
        np.testing.assert_array_equal(np.isinf(minima[r]), np.isinf(want))
        fin = np.isfinite(want)
        np.testing.assert_allclose(minima[r][fin], want[fin], atol=2e-6)
        n_wall.append(max(len(c) for c in wl))
        n_floor.append(sum(len(c) > 1 for c in nf))
    assert np.all(np.isinf(minima[0])) and n_wall[1] > 4 and n_floor[2] > 3
    np.testing.assert_array_equal(np.asarray(walls).ravel() < 0, [False, True, False])
    np.testing.assert_array_equal(np.any(np.asarray(nonfoot) < 0, axis=1), [False, False, True])


def test_backend_choice(monkeypatch):
    assert physics.resolve_backend("jax") == "jax"
    assert physics.resolve_backend("auto") == "jax"  # a CPU: MuJoCo Warp's CPU path is for tests
    monkeypatch.setattr(physics.jax, "default_backend", lambda: "gpu")
    assert physics.resolve_backend("auto") == "warp"  # a CUDA GPU with warp-lang (this test's import needs it)
    monkeypatch.setattr(physics, "warp_available", lambda: False)
    assert physics.resolve_backend("auto") == "jax"
    with pytest.raises(ValueError, match="backend 'bullet'"):
        physics.resolve_backend("bullet")


def test_warp_state_run_axes_and_blocks(walks):
    """The run axes of a batched state (``rollout.state_axes``, from ``physics.data_axes``): on Warp every leaf
    with the run axis first is 0 and the shared contact list and its counters are None; on JAX every leaf is 0. A
    block of the batch (``Spread`` "blocks", one per process) takes its rows of the first and keeps the second, its
    contact list cut to the block's slots (``physics.size_contact_list``); the blocks joined back (``runs.concat``,
    ``runs.first``) are the batch's per-run state. A run stepped in its block with the cut list ends bit for bit
    where it ends with the whole batch's list."""
    from wbc_jax.rollout import runs
    from wbc_jax.rollout.batch import take_runs
    from wbc_jax.rollout.spread import Spread

    _, bj, _, _ = walks["jax"]
    assert set(jax.tree_util.tree_leaves(bj.state_axes)) == {0}
    sim, b, _, _ = walks["warp:delayed"]
    leaves, treedef = jax.tree_util.tree_flatten_with_path(b.state)
    axes = treedef.flatten_up_to(b.state_axes)
    shared = [jax.tree_util.keystr(p) for (p, _), a in zip(leaves, axes) if a is None]
    assert any("contact__pos" in k for k in shared) and any(k.endswith("nacon") for k in shared)
    assert all(k.startswith(".d._impl.") and ("contact" in k or k.endswith(("nacon", "ncollision", "cdof_tri_col",
                                                                             "cdof_tri_row"))) for k in shared)
    assert all(np.shape(x)[0] == 2 for (_, x), a in zip(leaves, axes) if a == 0)
    slots = physics.NACON_PER_RUN
    assert b.state.d._impl.naconmax == 2 * slots
    assert Spread("blocks", process=0, processes=2).place(b).state.d._impl.naconmax == 2 * slots  # a tune's
    blocks = [Spread("blocks", process=i, processes=2).place(b, own_contacts=True) for i in range(2)]  # a campaign's
    for i, blk in enumerate(blocks):
        assert blk.state.d._impl.naconmax == slots and blk.state.d._impl.naccdmax == slots
        for (p, x), (_, y), a in zip(leaves, jax.tree_util.tree_flatten_with_path(blk.state)[0], axes):
            x, y = np.asarray(x), np.asarray(y)
            cut = a is None and "contact__" in jax.tree_util.keystr(p)
            np.testing.assert_array_equal(y, x[i:i + 1] if a == 0 else x[:slots] if cut else x)
    back = runs.first(runs.concat([jax.device_get(blk.state) for blk in blocks], blocks[0].state_axes), 2,
                      blocks[0].state_axes)
    for x, y, a in zip(jax.tree_util.tree_leaves(jax.device_get(b.state)), jax.tree_util.tree_leaves(back), axes):
        if a == 0:
            np.testing.assert_array_equal(x, y)
    ends = []
    for blk in (take_runs(b, np.array([1])), blocks[1]):  # run 1 with the whole batch's list, then its block's
        st, _ = simulate(sim, blk.model, blk.in_axes, blk.state, blk.plan, blk.om, blk.gains, blk.push, blk.mu_ground,
                         seconds=0.2, chunk_seconds=CHUNK_SECONDS)
        ends.append(runs.leaves_and_axes(jax.device_get(st), blk.state_axes))
    (whole, _, ax), (cut, _, _) = ends
    assert sum(a == 0 for a in ax) > 100
    for x, y, a in zip(whole, cut, ax):
        if a == 0:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_warp_contact_list_sized_for_more_runs(walks):
    """Runs taken into a batch larger than the one they came from (a gain search's sub-batches): with the source
    batch's contact list (2 runs' slots for 8 runs) Warp's broad phase overflows and every run is flagged
    (``physics.overflow``: the step's candidate pairs reached ``naconmax``); with the list sized for the 8 runs
    (``rollout.batch.with_contact_list``) none is, and each run's state, sensors, controller state and
    accumulators end bit for bit where the same runs prepared as one batch of 8 end (the same compiled program:
    XLA compiles a batch of 2 and one of 8 apart, whose arithmetic may differ in the last bits; the physics data's
    contact indices into the shared list differ)."""
    from wbc_jax.rollout.batch import take_runs, with_contact_list

    sim, b, _, _ = walks["warp:delayed@nan"]  # the 2-run walk's batch
    rows = np.array([0, 1] * 4)
    sub = take_runs(b, rows)
    sized = with_contact_list(sub)
    own = prepare_batch(sim, *(f[rows] for f in FACTORS), plan_kwargs=PLAN)  # the same runs as their own batch
    assert sub.state.d._impl.naconmax == 2 * physics.NACON_PER_RUN
    assert sized.state.d._impl.naconmax == sized.state.d._impl.naccdmax == 8 * physics.NACON_PER_RUN
    flagged, ends = [], []
    for batch in (sub, sized, own):
        st, _ = simulate(sim, batch.model, batch.in_axes, batch.state, batch.plan, batch.om, batch.gains, batch.push,
                         batch.mu_ground, seconds=NAN_SECONDS, chunk_seconds=CHUNK_SECONDS)
        flagged.append(np.asarray(final_results(sim, st, np.zeros((8, 3)), FACTORS[1][rows])["overflow"]))
        ends.append(jax.device_get(st))  # the integrated physics state, the sensors, and everything but the data
    assert flagged[0].all() and not flagged[1].any() and not flagged[2].any()
    st, ref = ends[1:]
    assert np.abs(np.asarray(st.d.qpos) - np.asarray(sub.state.d.qpos)).max() > 1e-4  # the runs moved
    for name in (*physics.STATE_FIELDS, "sensordata"):
        if getattr(ref.d, name, None) is not None:
            np.testing.assert_array_equal(np.asarray(getattr(st.d, name)), np.asarray(getattr(ref.d, name)))
    got = jax.tree_util.tree_leaves(st._replace(d=None))
    want = jax.tree_util.tree_leaves(ref._replace(d=None))
    assert len(got) == len(want) > 20
    for x, y in zip(got, want):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_campaign_chunk_program_compiled_ahead(tmp_path, monkeypatch, capsys):
    """A Warp campaign on one device compiles its chunk program from the batch's shapes before the initial states
    exist (``build_ahead``, ``states_and_program``: MuJoCo Warp's first call compiles the model's kernels, which a
    fresh GPU does beside the program's compile) and calls it: the CI baseline spec on Warp (8 runs, 3
    chunks), results.csv equal in every column to the same campaign whose chunk program is traced and compiled at
    its first chunk (as before), no note of a program that did not take the state."""
    import pandas as pd

    from wbc_jax import cli
    from wbc_jax.campaign import runner

    spec = str(SWEEPS.parent / "reports" / "baseline" / "spec.toml")
    assert cli.main(["campaign", "--spec", spec, "--backend", "warp", "--out", str(tmp_path / "ahead"),
                     "--no-report"]) == 0
    assert "compiled ahead does not take" not in capsys.readouterr().err
    manifest = json.loads((tmp_path / "ahead" / "manifest.json").read_text())
    assert manifest["chunk_compiled_ahead_s"] > 0 and manifest["physics_backend"] == "warp"
    monkeypatch.setattr(runner, "states_and_program",  # the program traced at the first chunk
                        lambda built, with_states, ahead: (with_states(), None, 0.0))
    assert cli.main(["campaign", "--spec", spec, "--backend", "warp", "--out", str(tmp_path / "first"),
                     "--no-report"]) == 0
    a, b = (pd.read_csv(tmp_path / d / "results.csv") for d in ("ahead", "first"))
    assert len(a) == 8 and list(a.columns) == list(b.columns)
    pd.testing.assert_frame_equal(a, b, check_exact=True)


def test_tune_on_warp_sizes_the_contact_list_for_its_rollout_calls(tmp_path, capsys):
    """`wbc-jax tune` on Warp steps rollout calls of ``tune.batch`` runs taken from its campaign's batch (4 runs per
    call: 2 candidates x the 2 chosen cells of a design of 8): its evaluators are built with Warp's shared contact
    list sized for a call's runs (``rollout.batch.with_contact_list``), not the design's 8 nor one run's. With the
    list of one run (before: the evaluators were built before the call size was known) every run of such a tune
    overflowed the broad phase and failed; now every run of the search and of the confirmation succeeds and none is
    flagged."""
    import pandas as pd

    from wbc_jax import cli
    from wbc_jax.studies import tune

    spec = tmp_path / "tune.toml"
    spec.write_text(f"""[tune]
name = "warp sub-batches"
campaign = "{SWEEPS.parent / 'reports' / 'baseline' / 'spec.toml'}"
method = "random"
candidates = 2
rounds = 1
seed = 5
cells = [[0.2, 0.4, 0.06], [0.4, 1.0, 0.10]]
batch = 4
[start]
[leaves]
kp_com = [0.9, 1.1]
""")
    t = tune._prepare(str(spec), str(tmp_path / "out"), None, None, None, False, "warp")
    assert t.ev.size == 4 and t.ev.n == 2 and t.evc is None
    assert t.ev.batch.state.d._impl.naconmax == 4 * physics.NACON_PER_RUN
    assert cli.main(["tune", "--spec", str(spec), "--out", str(tmp_path / "out"), "--backend", "warp",
                     "--no-progress"]) == 0
    board = pd.read_csv(tmp_path / "out" / "leaderboard.csv")
    assert len(board) == 2 and (board.success_rate == 1.0).all() and board.feasible.all()
    runs = pd.read_csv(tmp_path / "out" / "confirm_runs.csv")
    assert len(runs) == 4 and runs.success.all() and runs.fail_reason.isna().all()  # before: "contact capacity
    # overflow (Warp)" in every run, which the closing lines now name
    assert "failed runs: default none, rank 1 none" in capsys.readouterr().out
