"""Centroidal WBC: momentum matrix against body velocities, MuJoCo C and finite differences; the
capture-point pattern against its closed form; one QP against OSQP; a short trot keeps the robot up."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import osqp
import pytest
import scipy.sparse as sp
from test_transport import run_case, solve_stand_in  # the unusable-solve tests' QP stand-in and its cases

from wbc_jax.control.centroidal import CentroidalRef, build_qp, default_gains, scaled_model
from wbc_jax.control.centroidal_dynamics import centroidal_terms
from wbc_jax.physics import backend as physics
from wbc_jax.physics.observe import dyn_terms
from wbc_jax.planner import capture_point as cpm
from wbc_jax.planner.gait import GaitParams
from wbc_jax.qp import QPSettings, solve_qp
from wbc_jax.robot.model import Robot, mjx
from wbc_jax.rollout.controllers.centroidal import walk_plan
from wbc_jax.studies.trot import TrotSettings, run_study
from wbc_jax.studies.trot_analysis import SNAPSHOT_SIZE, write_snapshots

MOM_RTOL = 2e-5  # float32 A_G v vs float64 references, relative to ||h||
FD_TOL = 2e-3  # [N, N m] Adot v vs central differences of the body-velocity momentum
FD_EPS = 1e-6  # [s] finite-difference step along q(t) = q + t v
INERTIA_TOL = 1e-4  # [kg, kg m^2]
CP_TOL = 1e-5  # [m]
QP_OBJ_RTOL = 1e-3  # ADMM (400 iterations) vs OSQP at eps 1e-9
QP_VIOL_TOL = 1e-2  # rows mix N, N m, m/s^2
TROT_SECONDS = 1.5  # 0.2 s standing, 4 steps of 0.25 s, 0.3 s settling
TROT_Z_MIN = 0.40  # [m] lowest trunk height allowed during the segment
TROT_ATTITUDE_MAX = 0.05  # [rad]
N_STATES = 3


@pytest.fixture(scope="module")
def robot():
    return Robot("flat")


@pytest.fixture(scope="module")
def dyn_fn(robot):
    """jit: (model, qpos, qvel) -> DynTerms, CentroidalTerms (the model is an argument: no recompile per model)."""
    ids = robot.ids

    @jax.jit
    def f(m, q, v):
        d = physics.sense(m, mjx.make_data(robot.mjx_model).replace(qpos=q, qvel=v))
        dyn = dyn_terms(m, d, ids)
        return dyn, centroidal_terms(dyn)

    return f


def random_state(robot, seed):
    rng = np.random.default_rng(seed)
    q = robot.home_qpos()
    q[7:25] += rng.uniform(-0.3, 0.3, 18)
    quat = q[3:7] + rng.normal(0.0, 0.2, 4)
    q[3:7] = quat / np.linalg.norm(quat)
    v = np.zeros(robot.mj_model.nv)
    v[: robot.ids.nv_robot] = rng.normal(0.0, 1.0, robot.ids.nv_robot)
    return q, v


def body_momentum(m, q, v, robot):
    """float64 centroidal momentum [l; k_G] summed over the robot's bodies from their velocities, and
    MuJoCo's subtree momentum (mj_subtreeVel) of the trunk's subtree."""
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q, v
    mujoco.mj_forward(m, d)
    root = robot.ids.trunk_body
    c = d.subtree_com[root]
    bodies = [b for b in range(1, m.nbody) if m.body_rootid[b] == root]
    l, k, Ibar = np.zeros(3), np.zeros(3), np.zeros((3, 3))
    for b in bodies:
        vel = np.zeros(6)  # [angular; linear] at the body's CoM, world orientation
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, vel, 0)
        R = d.ximat[b].reshape(3, 3)
        I = R @ np.diag(m.body_inertia[b]) @ R.T
        r = d.xipos[b] - c
        l += m.body_mass[b] * vel[3:]
        k += np.cross(r, m.body_mass[b] * vel[3:]) + I @ vel[:3]
        Ibar += I + m.body_mass[b] * (r @ r * np.eye(3) - np.outer(r, r))
    mujoco.mj_subtreeVel(m, d)
    h_sub = np.r_[m.body_subtreemass[root] * d.subtree_linvel[root], d.subtree_angmom[root]]
    return np.r_[l, k], h_sub, Ibar


@pytest.mark.parametrize("seed", range(N_STATES))
def test_cmm_against_body_velocities_mujoco_and_finite_differences(robot, dyn_fn, seed):
    m = robot.mj_model
    q, v = random_state(robot, seed)
    dyn, ct = dyn_fn(robot.mjx_model, jnp.asarray(q), jnp.asarray(v))
    h_bodies, h_sub, Ibar = body_momentum(m, q, v, robot)
    scale = np.linalg.norm(h_bodies)
    np.testing.assert_allclose(h_sub, h_bodies, atol=1e-9 * scale)  # the two references agree
    h = np.asarray(ct.A @ dyn.v, float)
    np.testing.assert_allclose(h, h_bodies, atol=MOM_RTOL * scale)

    # Adot v: with vdot = 0, hdot = Adot v; move q along q(t) = q + t v (MuJoCo's integrator, v fixed)
    def h_at(t):
        qt = q.copy()
        mujoco.mj_integratePos(m, qt, v, t)
        return body_momentum(m, qt, v, robot)[0]

    fd = (h_at(FD_EPS) - h_at(-FD_EPS)) / (2 * FD_EPS)
    np.testing.assert_allclose(np.asarray(ct.Adv, float), fd, atol=FD_TOL)

    # I_G = diag(m I3, Ibar_G): composite inertia about the CoM
    I_G = np.asarray(ct.I_G, float)
    mass = robot.total_robot_mass
    np.testing.assert_allclose(I_G[:3, :3], mass * np.eye(3), atol=INERTIA_TOL * mass)
    np.testing.assert_allclose(I_G[:3, 3:], 0.0, atol=INERTIA_TOL * mass)
    np.testing.assert_allclose(I_G[3:, :3], 0.0, atol=INERTIA_TOL * mass)
    np.testing.assert_allclose(I_G[3:, 3:], Ibar, atol=INERTIA_TOL)


def test_scaled_model_equals_a_model_with_scaled_bodies(robot, dyn_fn):
    """The controller's mass-error model (M, h scaled, armature kept) equals MJX on a model whose body
    masses and inertias are all scaled."""
    s = 1.2
    q, v = random_state(robot, 7)
    mx = robot.mjx_model
    ms = mx.replace(body_mass=mx.body_mass * s, body_inertia=mx.body_inertia * s,
                    body_subtreemass=mx.body_subtreemass * s)
    dyn, _ = dyn_fn(mx, jnp.asarray(q), jnp.asarray(v))
    dyn_s, ct_s = dyn_fn(ms, jnp.asarray(q), jnp.asarray(v))
    mine = scaled_model(dyn, s, mx.dof_armature[: robot.ids.nv_robot])
    for name in ("M", "h", "mass", "h_G"):
        a, b = np.asarray(getattr(mine, name), float), np.asarray(getattr(dyn_s, name), float)
        np.testing.assert_allclose(a, b, atol=1e-4 * max(1.0, np.abs(b).max()), err_msg=name)
    np.testing.assert_allclose(np.asarray(centroidal_terms(mine).I_G), np.asarray(ct_s.I_G), atol=1e-3)


def test_cp_recursion_matches_closed_form_and_pattern_starts_at_rest():
    rng = np.random.default_rng(3)
    N, T, w = 7, 0.25, 4.7
    P = rng.normal(0.0, 0.3, (N, 2))
    xi_f = rng.normal(0.0, 0.3, 2)
    b = np.exp(-w * T)
    # closed form of eq. 22: xi_eos[i] = sum_{j>i} (1 - b) b^(j-i-1) P_j + b^(N-1-i) xi_final
    closed = np.array([sum((1 - b) * b ** (j - i - 1) * P[j] for j in range(i + 1, N)) + b ** (N - 1 - i) * xi_f
                       for i in range(N)])
    eos = np.asarray(cpm.end_of_step_cps(jnp.asarray(P), T, w, jnp.asarray(xi_f)))
    np.testing.assert_allclose(eos, closed, atol=CP_TOL)
    # eq. 21 over a whole step lands on the recursion's end-of-step CP
    ini = np.asarray(cpm.initial_cps(jnp.asarray(P), jnp.asarray(eos), T, w))
    np.testing.assert_allclose(np.asarray(cpm.cp_trajectory(P[2], ini[2], T, w)), eos[2], atol=CP_TOL)

    # walking pattern: starts at the resting CoM, CP continuous across steps, ends on the last virtual leg
    feet0 = np.array([[0.19, -0.27, 0.028], [-0.19, -0.27, 0.028], [0.19, 0.30, 0.028], [-0.19, 0.30, 0.028]])
    com0 = np.array([0.0, -0.05, 0.43])
    gait = GaitParams(t_stance=0.08, t_swing=0.17, t_start=0.5)
    plan = cpm.cp_walk_plan(feet0, com0, -np.pi / 2, 0.1, N, gait, 0.06)
    ref = jax.jit(lambda t: cpm.cp_reference(plan.P, plan.xi_eos, t, plan.gait.t_start, T, plan.w).xi)
    np.testing.assert_allclose(np.asarray(ref(0.5)), com0[:2], atol=CP_TOL)
    for k in range(1, N):
        t_k = 0.5 + k * T
        np.testing.assert_allclose(np.asarray(ref(t_k - 1e-4)), np.asarray(ref(t_k)), atol=1e-3)
    np.testing.assert_allclose(np.asarray(ref(0.5 + N * T + 1.0)), np.asarray(plan.P[-1]), atol=CP_TOL)
    # footholds centred under the CoM after the first swing of each pair, one stride per step along -y
    np.testing.assert_allclose(np.asarray(plan.feet[-1]).mean(axis=0), com0[:2] + [0.0, -(N - 1) * 0.1], atol=CP_TOL)


def make_plan(robot, qpos0, stride, step_time, t_four, n_steps, t_start=0.5):
    """(CPWalkPlan, trunk R0 (3, 3)) of the rollout's centroidal plug-in."""
    plan = walk_plan(robot, qpos0, stride, step_time, t_four, n_steps, t_start=t_start)
    return plan.walk, plan.R0


def test_qp_matches_osqp_and_obeys_the_model(robot):
    """A two-foot-support QP (FL, BR swinging): ADMM against OSQP, floating-base rows and friction pyramids."""
    ids = robot.ids
    q0 = robot.home_qpos()
    plan, R0 = make_plan(robot, q0, 0.1, 0.25, 0.08, 4)
    g = default_gains()

    @jax.jit
    def build():
        mx = robot.mjx_model
        d = physics.sense(mx, mjx.make_data(mx).replace(qpos=jnp.asarray(q0)))
        dyn = dyn_terms(mx, d, ids)
        J_t = mjx.jac(mx, d, dyn.p_tray, ids.tray_body)[0].T[:, : ids.nv_robot]
        wr = cpm.cp_walk_reference(plan, plan.gait.t_start + 0.15, dyn.com[:2], dyn.p_foot)
        ref = CentroidalRef(v_xy=wr.v_xy, z=plan.z0, R_base=jnp.asarray(R0), heading=plan.heading, swing=wr.swing,
                            p_sw=wr.p_sw, v_sw=wr.v_sw, a_sw=wr.a_sw)
        q_arm = d.qpos[ids.act_qpos[12:]]
        return dyn, wr.swing, build_qp(dyn, J_t, ref, g, jnp.zeros((4, 3)), q_arm, q_arm, ids)

    dyn, swing, (P, q, A, l, u, A_tau, b_tau, _) = build()
    assert np.array_equal(np.asarray(swing), [True, False, False, True])
    Pn, qn, An, ln, un = (np.asarray(x, float) for x in (P, q, A, l, u))
    s = osqp.OSQP()
    s.setup(sp.csc_matrix(np.triu(Pn)), qn, sp.csc_matrix(An), np.maximum(ln, -1e20), np.minimum(un, 1e20),
            eps_abs=1e-9, eps_rel=1e-9, max_iter=200000, verbose=False, polishing=True)
    x_ref = s.solve().x
    solve = jax.jit(solve_qp, static_argnames="settings")
    x = np.asarray(solve(P, q, A, l, u, settings=QPSettings(iters=400)).x, float)
    obj = lambda z: 0.5 * z @ Pn @ z + qn @ z  # noqa: E731
    assert abs(obj(x) - obj(x_ref)) <= QP_OBJ_RTOL * abs(obj(x_ref))
    assert (np.maximum(An @ x - un, 0) + np.maximum(ln - An @ x, 0)).max() < QP_VIOL_TOL
    nv = ids.nv_robot
    f = x[nv:].reshape(4, 3)
    assert np.allclose(f[[0, 3]], 0.0, atol=1e-2), "swing feet carry force"
    mu = float(g.mu)
    assert np.all(np.abs(f[[1, 2], :2]) <= mu * f[[1, 2], 2:3] + 1e-2)
    # stance pair carries robot + payload weight (the QP's vertical acceleration is small at rest)
    total = (robot.total_robot_mass + float(g.load_mass)) * 9.81
    assert abs(f[:, 2].sum() - total) < 0.05 * total
    assert np.all(np.abs(np.asarray(A_tau, float) @ x + np.asarray(b_tau, float)) <= np.asarray(ids.tau_max))


def test_unusable_solve_is_not_applied(robot, monkeypatch):
    """A centroidal control step whose QP solve is unusable (FLAG_NONFINITE, FLAG_DIVERGED; its iterate 1e30)
    applies the last solution: its torques equal those of the same step given that solution as its own, the
    state's warm result carries it; a converged solve's torques are its own."""
    import wbc_jax.control.centroidal as cc
    from wbc_jax.physics.observe import observe
    from wbc_jax.qp import FLAG_DIVERGED, FLAG_NONFINITE

    ids, cfg = robot.ids, cc.CentroidalConfig()
    q0 = robot.home_qpos()
    plan, R0 = make_plan(robot, q0, 0.1, 0.25, 0.08, 4)
    mx = robot.mjx_model
    last = jnp.linspace(-1.0, 1.0, cfg.n_var)
    cs = cc.init_state(cfg, jnp.asarray(q0), ids)
    cs = cs._replace(warm=cs.warm._replace(x=last))
    solve = cc.solve_qp

    @jax.jit
    def control(flag, x, fill, as_last):
        """One program for every case (traced once; the state sensed inside it, not op by op), the solve changed
        by ``test_transport.solve_stand_in``; a case runs through ``test_transport.run_case``."""
        d = physics.sense(mx, mjx.make_data(mx).replace(qpos=jnp.asarray(q0)))
        obs = observe(mx, d, ids)
        wr = cpm.cp_walk_reference(plan, plan.gait.t_start + 0.15, obs.robot.com[:2], obs.robot.p_foot)
        ref = CentroidalRef(v_xy=wr.v_xy, z=plan.z0, R_base=jnp.asarray(R0), heading=plan.heading, swing=wr.swing,
                            p_sw=wr.p_sw, v_sw=wr.v_sw, a_sw=wr.a_sw)
        monkeypatch.setattr(cc, "solve_qp", solve_stand_in(solve, last, flag, x, fill, as_last))
        tau, new, _ = cc.centroidal_control(obs, ref, default_gains(), cs, ids, cfg)
        return tau, new.warm.x

    given_last = run_case(control, -1, as_last=True)
    converged = run_case(control, -1)
    for flag in (FLAG_NONFINITE, FLAG_DIVERGED):
        bad = run_case(control, flag, 1e30, fill=True)
        np.testing.assert_array_equal(bad[0], given_last[0])
        np.testing.assert_array_equal(bad[1], np.asarray(last))
        assert np.all(np.isfinite(bad[0])) and not np.array_equal(bad[0], converged[0])


@pytest.mark.slow  # its own 1.5 s closed-loop compile; tests/test_trot_campaign.py's campaign walks this controller
def test_short_trot_keeps_the_robot_up(robot, tmp_path):
    """Four steps at 0.4 m/s with the exact model and a 20 % too light one (one batch of the shared rollout with
    the centroidal plug-in); the Fig. 9 strip of its logged configurations (skipped part without an offscreen
    OpenGL backend)."""
    ids = robot.ids
    study = run_study(TrotSettings(n_steps=4, mass_errors=(0.0, -0.2), log_every=10, t_start=0.2, t_settle=0.3),
                      chunk_seconds=TROT_SECONDS, verbose=False)
    acc, res, logs = jax.device_get(study.state.acc), study.results, study.logs
    assert not acc.nonfinite.any() and not acc.nonfoot_floor.any() and res["success"].all()
    assert np.all(acc.min_trunk_z > TROT_Z_MIN), acc.min_trunk_z
    assert np.all(res["max_tau_ratio"] <= 1.0)
    assert np.all(np.abs(logs.rpy).max(axis=(1, 2)) < TROT_ATTITUDE_MAX), np.abs(logs.rpy).max(axis=1)
    plan = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], study.batch.plan.walk)
    h = np.asarray(plan.heading)
    progress = (logs.com[:, -1, :2] - logs.com[:, 0, :2]) @ h  # planned: 3 strides = 0.3 m
    assert np.all(progress > 0.2), progress
    np.testing.assert_allclose(res["planned_distance_m"], 0.3, rtol=1e-6)
    # it stepped: every foot moved forward by about two strides or more
    feet0 = np.asarray(jax.device_get(study.batch.state.d.site_xpos[:, ids.foot_site, :2]))
    feet = (np.asarray(study.state.d.site_xpos[:, ids.foot_site, :2]) - feet0) @ h
    assert np.all(feet > 0.15), feet
    snap = write_snapshots(tmp_path / "fig9.png", robot, logs, 0, plan, 0.2, 1.2, 0.25, 4)
    assert len(snap["times_s"]) == 4
    if snap["written"] is not None:
        from PIL import Image

        assert Image.open(tmp_path / "fig9.png").size == (4 * SNAPSHOT_SIZE[1], SNAPSHOT_SIZE[0])
    else:
        assert snap["reason"].startswith("no snapshots")
