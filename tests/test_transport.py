"""Transport WBC: one QP against a high-accuracy reference and rigid-body dynamics; a short loaded stand and trot."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import osqp
import pytest
import scipy.sparse as sp

from wbc_jax.control.transport import TransportConfig, build_qp, control_qp_settings
from wbc_jax.physics import backend as physics
from wbc_jax.physics.observe import dyn_terms, object_state, point_jacobians
from wbc_jax.planner.gait import GaitParams
from wbc_jax.planner.transport import reference
from wbc_jax.qp import QPSettings, solve_qp
from wbc_jax.robot.model import Robot
from wbc_jax.rollout import make_sim, simulate
from wbc_jax.rollout.batch import prepare_batch

OBJ_RTOL = 1e-3  # relative objective error, ADMM (float32, ACCURATE_ITERS cold iterations) vs OSQP eps 1e-9
VIOL_TOL = 1e-2  # max constraint violation of the ADMM solution [rows mix N, N m, m/s^2]
WRENCH_TOL = 0.5  # [N, N m] the cost's wrenches H x, ADMM vs OSQP (unique even where forces are not:
#                  internal forces between feet cost almost nothing, so individual torques may differ)
ACCURATE_ITERS = 400
DYN_TOL = 0.5  # [N, N m] residual of the floating-base equations at the ADMM solution
STAND_SECONDS = 0.3
SLIP_MAX = 1e-3  # [m]
HEIGHT_TOL = 0.01  # [m]
TROT_SECONDS = 0.7  # two diagonal swings (gait starts at 0.1 s)
TROT_SLIP_MAX = 3e-3  # [m] over the segment
TROT_Z_BAND = (0.40, 0.50)  # [m] trunk height band during the segment
TROT_PLAN = dict(distance=0.3, ramp=0.5)  # the trot segment's path (the stand's plan has its shapes: setup)
CHUNK_SECONDS = 0.1  # simulated time per jit call: a common divisor of both horizons, so the stand and the trot
#                      run one compiled chunk function (same chunk length; the chunking leaves the logs unchanged)


@pytest.fixture(scope="module")
def setup():
    robot = Robot("flat")
    sim = make_sim(robot, TransportConfig(dt=0.001, qp=control_qp_settings()), log_every=50)  # the control loop's QP
    # gait starts after the test horizon: the robot stands under QP torque control, loaded; the path's distance
    # and ramp are the trot segment's (TROT_PLAN), which do not act before the gait starts but give the plan the
    # trot's array shapes, so the trot runs the stand's compiled chunk function (a second compile: ~1 min)
    plan_kwargs = dict(TROT_PLAN, gait=GaitParams(t_start=10.0))
    b = prepare_batch(sim, [0.2, 0.4], [0.4, 1.0], [0.10, 0.06], plan_kwargs=plan_kwargs)
    return robot, sim, b


def _take0(tree, axes=None):
    if axes is None:
        return jax.tree_util.tree_map(lambda x: x[0], tree)
    return jax.tree_util.tree_map(lambda x, a: x[0] if a == 0 else x, tree, axes)


def _qp_at(m, run_state, plan, om, gains, ids, cfg):
    """(DynTerms, ObjectState, TransportQP) of one run's state ``run_state`` (no observer estimate)."""
    d = physics.sense(m, run_state.d)
    dyn = dyn_terms(m, d, ids)
    ref = reference(plan, d.time, run_state.p_lift)
    obj = object_state(d, ids)
    Jp, Jr, Jdp, Jdr = point_jacobians(m, d, ids, obj.p[None], [ids.tray_body])
    J_o, Jdv_o = jnp.concatenate([Jp[0], Jr[0]]), jnp.concatenate([Jdp[0], Jdr[0]])
    return dyn, obj, build_qp(dyn, obj, J_o, Jdv_o, ref, om, gains, jnp.zeros(6), ids, cfg.k, 1.0, run_state.cs.q_post)


@pytest.fixture(scope="module")
def qp_at(setup):
    """(DynTerms, ObjectState, TransportQP) of run 0's initial state, one jitted program for both QP tests."""
    robot, sim, b = setup
    args = (_take0(b.model, b.in_axes), _take0(b.state), _take0(b.plan), _take0(b.om), _take0(b.gains))
    return jax.jit(functools.partial(_qp_at, ids=robot.ids, cfg=sim.cfg))(*args)


def test_qp_matches_reference_and_dynamics(setup, qp_at):
    robot, sim, b = setup
    ids = robot.ids
    om = _take0(b.om)
    dyn, _, qp = qp_at
    Pn, qn, An, ln, un, Atn, han = (np.asarray(x, float) for x in (qp.P, qp.q, qp.A, qp.l, qp.u, qp.A_tau, qp.h_a))
    s = osqp.OSQP()
    s.setup(sp.csc_matrix(np.triu(Pn)), qn, sp.csc_matrix(An), np.maximum(ln, -1e20), np.minimum(un, 1e20),
            eps_abs=1e-9, eps_rel=1e-9, max_iter=200000, verbose=False, polishing=True)
    x_ref = s.solve().x
    res = jax.jit(solve_qp, static_argnames="settings")(qp.P, qp.q, qp.A, qp.l, qp.u,
                                                         settings=QPSettings(iters=ACCURATE_ITERS))
    x = np.asarray(res.x, float)
    obj = lambda z: 0.5 * z @ Pn @ z + qn @ z  # noqa: E731
    assert abs(obj(x) - obj(x_ref)) <= OBJ_RTOL * abs(obj(x_ref))
    viol = np.maximum(An @ x - un, 0) + np.maximum(ln - An @ x, 0)
    assert viol.max() < VIOL_TOL
    Hn = np.asarray(qp.H_com, float)
    np.testing.assert_allclose(Hn @ x, Hn @ x_ref, atol=WRENCH_TOL)
    assert np.all(np.abs(Atn @ x + han) <= np.asarray(ids.tau_max) + VIOL_TOL)

    # the solution obeys the floating-base equations of motion built independently here
    nv, k = ids.nv_robot, sim.cfg.k
    vdot, lam_g, lam_b = x[:nv], x[nv : nv + 4 * k], x[nv + 4 * k : nv + 8 * k]
    th = np.arctan(1.0)
    a = 2 * np.pi * np.arange(1, k + 1) / k
    edges = np.stack([np.sin(th) * np.cos(a), np.sin(th) * np.sin(a), np.cos(th) * np.ones(k)])
    F_gr = np.concatenate([edges @ lam_g[i * k : (i + 1) * k] for i in range(4)])
    Jf = np.asarray(dyn.J_foot).reshape(12, nv)
    gen = np.asarray(dyn.M) @ vdot + np.asarray(dyn.h) - Jf.T @ F_gr
    # object reaction on the floating base, J_o^T W_b Lambda_b (its map is also exercised by the tau check)
    W_reac = An[0:6, nv + 4 * k : nv + 8 * k] @ lam_b
    np.testing.assert_allclose(gen[:6] + W_reac, 0.0, atol=DYN_TOL)
    assert np.all(x[nv : nv + 8 * k] > -1e-3), "negative cone multipliers"
    # the stance feet carry the robot plus the object: total normal force = (m_r + m_obj) g
    total = (float(dyn.mass) + float(om.mass)) * 9.81
    assert abs(F_gr[2::3].sum() - total) < 0.02 * total


def test_object_wrench_is_no_lever_for_the_com_row(setup, qp_at):
    """The CoM-wrench cost row (7) carries the object's *target* wrench as a constant, so the cost does not couple
    the object's multipliers Lambda_b to the ground's (the QP cannot trade object wrench for CoM wrench), and their
    linear cost term is the object row's alone: q_b = -W_b^T Q_obj F_b,ref with F_b,ref = [m g e_z; 0] for the cube
    at rest on its reference (hand computation)."""
    robot, sim, b = setup
    ids = robot.ids
    om, gains = _take0(b.om), _take0(b.gains)
    dyn, obj, qp = qp_at
    P, q = np.asarray(qp.P, float), np.asarray(qp.q, float)
    k, nv = sim.cfg.k, ids.nv_robot
    ig, ib = slice(nv, nv + 4 * k), slice(nv + 4 * k, nv + 8 * k)
    assert np.abs(P[ig, ib]).max() == 0.0
    # hand computation of the object row's term: contact points at the cube's bottom corners, inset by the
    # sphere radius; pyramid edges about the tray normal; target force m g up (at rest on the reference)
    mass, side, mu, inset = (float(x) for x in (om.mass, om.side, om.mu, om.inset))
    h = side / 2 - inset
    R = np.asarray(obj.R, float)
    corners = np.array([[h, h, -side / 2], [-h, h, -side / 2], [-h, -h, -side / 2], [h, -h, -side / 2]])
    th, a = np.arctan(mu), 2 * np.pi * np.arange(1, k + 1) / k
    edges = np.asarray(dyn.R_tray, float) @ np.stack([np.sin(th) * np.cos(a), np.sin(th) * np.sin(a),
                                                      np.cos(th) * np.ones(k)])
    Wb = np.concatenate([np.concatenate([edges, np.cross(R @ c, edges.T).T]) for c in corners], axis=1)  # (6, 4k)
    target = np.array([0.0, 0.0, mass * 9.81, 0.0, 0.0, 0.0])
    Qobj = np.array([float(gains.w_obj_f)] * 3 + [float(gains.w_obj_t)] * 3)
    q_hand = -Wb.T @ (Qobj * target)
    np.testing.assert_allclose(q[ib], q_hand, rtol=2e-3, atol=2e-3 * np.abs(q_hand).max())


def solve_stand_in(solve, last, flag, x, fill, as_last):
    """The QP solve ``solve`` with its result changed (all arguments traced scalars but ``last``): its flag set to
    ``flag`` where ``flag >= 0``, its x replaced by ``x`` everywhere where ``fill``, by ``last`` (the last step's
    solution) where ``as_last``."""
    def fake(*a, **kw):
        res = solve(*a, **kw)
        out_x = jnp.where(fill, jnp.full_like(res.x, x), jnp.where(as_last, last, res.x))
        return res._replace(flag=jnp.where(flag >= 0, flag.astype(res.flag.dtype), res.flag), x=out_x)

    return fake


def run_case(control, flag, x=0.0, fill=False, as_last=False):
    """One case of a jitted ``control(flag, x, fill, as_last)`` built on :func:`solve_stand_in` (the arguments as
    its traced scalars; ``flag`` -1 keeps the solve's own), the outputs as numpy arrays."""
    return [np.asarray(v) for v in control(jnp.int32(flag), jnp.float32(x), jnp.bool_(fill), jnp.bool_(as_last))]


def test_diverged_solve_is_not_applied(setup, monkeypatch):
    """A control step whose QP solve is unusable (FLAG_NONFINITE or FLAG_DIVERGED; its iterate 1e30) applies the
    last step's solution: the torques and the observer's commanded wrench equal those of the same step given that
    solution as its own, and the state's warm result carries it; a converged solve's are its own."""
    import wbc_jax.control.transport as tc
    from wbc_jax.physics.observe import observe
    from wbc_jax.qp import FLAG_DIVERGED, FLAG_NONFINITE

    robot, sim, b = setup
    m, st = _take0(b.model, b.in_axes), _take0(b.state)
    last = jnp.linspace(-1.0, 1.0, sim.cfg.n_var)
    cs = st.cs._replace(warm=st.cs.warm._replace(x=last))
    solve = tc.solve_qp

    @jax.jit
    def control(flag, x, fill, as_last):
        """One program for every case (traced once; the state sensed inside it, not op by op), the solve changed
        by :func:`solve_stand_in`; a case runs through :func:`run_case`."""
        d = physics.sense(m, st.d)
        obs, ref = observe(m, d, robot.ids), reference(_take0(b.plan), d.time, st.p_lift)
        monkeypatch.setattr(tc, "solve_qp", solve_stand_in(solve, last, flag, x, fill, as_last))
        tau, new, _ = tc.transport_control(obs, ref, _take0(b.om), _take0(b.gains), cs, robot.ids, sim.cfg)
        return tau, new.obs.w_cmd, new.warm.x

    converged = run_case(control, 0)
    given_last = run_case(control, -1, as_last=True)
    for flag in (FLAG_NONFINITE, FLAG_DIVERGED):
        diverged = run_case(control, flag, 1e30, fill=True)
        np.testing.assert_array_equal(diverged[0], given_last[0])
        np.testing.assert_array_equal(diverged[1], given_last[1])
        np.testing.assert_array_equal(diverged[2], np.asarray(last))
        assert np.all(np.isfinite(diverged[0])) and not np.array_equal(converged[0], diverged[0])


def test_loaded_stand_under_qp_torques(setup):
    robot, sim, b = setup
    st, logs = simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground,
                        STAND_SECONDS, chunk_seconds=CHUNK_SECONDS)
    acc = jax.device_get(st.acc)
    z0 = np.asarray(b.state.d.xpos[:, robot.ids.trunk_body, 2])
    assert np.all(np.abs(logs.trunk_z - z0[:, None]).max(axis=1) < HEIGHT_TOL)
    assert np.all(acc.max_slip < SLIP_MAX), acc.max_slip
    assert not acc.nonfoot_floor.any() and not acc.nonfinite.any()
    assert np.all(acc.max_tau_ratio <= 1.0)
    assert np.all(acc.max_tau_excess <= 0.0), "QP asked for torques beyond the limits"


def test_short_loaded_trot_segment(setup):
    """Two diagonal swings with the object on the tray: the QP keeps the robot up and the object on."""
    robot, sim, _ = setup
    b = prepare_batch(sim, [0.2, 0.4], [0.4, 1.0], [0.10, 0.06],
                      plan_kwargs=dict(TROT_PLAN, gait=GaitParams(t_start=0.1)))  # the stand's shapes: no recompile
    st, logs = simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground,
                        TROT_SECONDS, chunk_seconds=CHUNK_SECONDS)
    acc = jax.device_get(st.acc)
    feet_z = np.asarray(st.d.site_xpos[:, robot.ids.foot_site, 2])
    assert np.all(acc.min_trunk_z > TROT_Z_BAND[0]) and np.all(logs.trunk_z < TROT_Z_BAND[1])
    assert not acc.nonfoot_floor.any() and not acc.nonfinite.any()
    assert np.all(acc.max_slip < TROT_SLIP_MAX), acc.max_slip
    assert np.all(acc.max_tau_ratio <= 1.0)
    # it really stepped: the object moved forward along -y with the reference
    dy = np.asarray(logs.p_obj[:, -1, 1] - logs.p_obj[:, 0, 1])
    assert np.all(dy < -0.02), dy
    assert np.all(np.abs(feet_z - robot.ids.foot_radius) < 0.02)


def test_cost_blocks_equal_the_stacked_rows():
    """``transport_qp._quadratic_cost`` (each run of cost blocks on the same columns: its own block of P and q)
    equals the stacked rows' ``H' Q H + diag(R)`` and ``-H' Q l`` (hand-stacked, float64) on the transport QP's
    layout: ground-force rows, tray-force rows, then a posture block and a swing block on the vdot columns;
    overlapping runs are refused."""
    from types import SimpleNamespace

    from wbc_jax.control.transport_qp import Columns, CostRows, _quadratic_cost

    cols = Columns(24, 4)
    rng = np.random.default_rng(3)
    post = np.zeros((6, cols.nv))
    post[np.arange(6), np.arange(18, 24)] = 1.0
    spec = [(rng.normal(size=(6, cols.ng)), cols.ig), (rng.normal(size=(6, cols.nb)), cols.ib), (post, cols.iv),
            (rng.normal(size=(12, cols.nv)), cols.iv)]
    gains = SimpleNamespace(r_vdot=1e-4, r_lam=1e-3)
    with jax.enable_x64(True):
        blocks = [CostRows(jnp.asarray(H), jnp.asarray(rng.normal(size=len(H))),
                           jnp.asarray(rng.uniform(0.1, 2.0, size=len(H))), c) for H, c in spec]
        P, q = (np.asarray(a) for a in _quadratic_cost(blocks, gains, cols))
        with pytest.raises(ValueError, match="overlap"):
            _quadratic_cost([blocks[0], blocks[2]._replace(cols=slice(20, 30), H=np.zeros((6, 10)))], gains, cols)
    H = np.zeros((30, cols.n))
    for (Hb, c), r in zip(spec, (slice(0, 6), slice(6, 12), slice(12, 18), slice(18, 30))):
        H[r, c] = Hb
    w, l = (np.concatenate([np.asarray(getattr(b, f)) for b in blocks]) for f in ("w", "l"))
    R = np.concatenate([np.full(cols.nv, 1e-4), np.full(cols.ng + cols.nb, 1e-3)])
    np.testing.assert_allclose(P, H.T @ (w[:, None] * H) + np.diag(R), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(q, -H.T @ (w * l), rtol=1e-12, atol=1e-12)
    with jax.enable_x64(True):  # the vdot columns spanned by no row: R alone there
        P2, q2 = (np.asarray(a) for a in _quadratic_cost(blocks[:2], gains, cols))
    np.testing.assert_allclose(P2, H[:12].T @ (w[:12, None] * H[:12]) + np.diag(R), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(q2, -H[:12].T @ (w[:12] * l[:12]), rtol=1e-12, atol=1e-12)
