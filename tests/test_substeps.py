"""Control period longer than the physics step (``n_substeps`` > 1, zero-order hold): the physics-rate monitors
(1/H, ||object acceleration||, contact flags, boundary count) are sampled after every physics step, not once per
control period; ``campaign.control_substeps`` is validated like the other spec keys (one compile of a 2-run
control step with n_substeps = 2, and one of the hand reference).
"""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from wbc_jax import cli
from wbc_jax.campaign.spec import load_spec, parse_spec
from wbc_jax.control.transport import TransportConfig, control_qp_settings
from wbc_jax.errors import SpecError, WbcJaxError
from wbc_jax.metrics import paper as metrics
from wbc_jax.physics import contacts
from wbc_jax.physics.contacts import CONTACT_DIST
from wbc_jax.planner.gait import GaitParams
from wbc_jax.robot.model import Robot, mjx
from wbc_jax.rollout import contact_name, control_step, make_sim
from wbc_jax.rollout.batch import prepare_batch

N_SUB = 2
PERIODS = 3  # control periods checked (6 physics steps)
V_TOL = 1e-6  # [m/s] float32 rounding of velocities between the rollout's compiled step and the reference's (as the
#               1e-6 m of the positions): each ||dv|| term of the acceleration integral may differ by 2 V_TOL
INV_H_RTOL = 0.02  # 1/H of the object's contact forces, rollout vs reference: the two compiled float32 programs put
#                    the tray and the cube a rounding apart (~1e-7 m), and the object's compliant contacts (about
#                    0.25 N per um at rest, docs/method.md "Object contacts") turn that into up to ~1-2 % of a
#                    corner's force (0.8 % measured in 1/H while the cube settles into its contacts)


@pytest.fixture(scope="module")
def setup():
    robot = Robot("flat")
    h = float(robot.mj_model.opt.timestep)
    sim = make_sim(robot, TransportConfig(dt=h * N_SUB, qp=control_qp_settings(20)), n_substeps=N_SUB, log_every=1)
    # standing, loaded (the gait starts after the horizon); the first periods settle the object: non-zero acceleration
    b = prepare_batch(sim, [0.2, 0.4], [0.4, 1.0], [0.10, 0.06], plan_kwargs=dict(gait=GaitParams(t_start=10.0),
                                                                                 distance=0.1))
    return robot, sim, b


def _reference(sim, b):
    """Hand reference, independent of the rollout's substep code: one jitted ``mjx.step`` and one jitted
    ``metrics.step_integrands`` (physics timestep), both vmapped over the runs and called per physics step.

    Returns f(d0, tau) -> (qpos after the period, per-step arrays (B, N_SUB): 1/H, ||a||, non-foot contact, object
    off the tray, and the object's velocity change over the whole period (B, 3))."""
    ids = sim.robot.ids
    oa = ids.obj_dof_adr
    h = float(sim.robot.mj_model.opt.timestep)
    step = jax.jit(jax.vmap(mjx.step, in_axes=(b.in_axes, 0)))
    integrands = jax.jit(jax.vmap(
        lambda m, d, d1, mu: metrics.step_integrands(contacts.object_contacts(sim, m, d1)[0], mu,
                                                     d.qvel[oa:oa + 3], d1.qvel[oa:oa + 3], h),
        in_axes=(b.in_axes, 0, 0, 0)))

    def period(d0, tau):
        d = d0.replace(ctrl=tau, xfrc_applied=jnp.zeros_like(d0.xfrc_applied))
        out = []
        for _ in range(N_SUB):
            d1 = step(b.model, d)
            inv_h, a = integrands(b.model, d, d1, b.om.mu)
            dist = np.asarray(d1._impl.contact.dist)  # contacts of the step's start positions
            out.append((inv_h, a, np.any(dist[:, sim.nonfoot_slots] < 0.0, axis=1),
                        np.all(dist[:, sim.obj_slots] > CONTACT_DIST, axis=1)))
            d = d1
        inv_h, a, nonfoot, off = (np.stack([np.asarray(x) for x in xs], axis=1) for xs in zip(*out))
        dv = np.asarray(d.qvel[:, oa:oa + 3] - d0.qvel[:, oa:oa + 3])
        return np.asarray(d.qpos), inv_h, a, nonfoot, off, dv

    return period


@pytest.fixture(scope="module")
def step(setup):
    """The jitted, vmapped control step (one control period of N_SUB physics steps) of the module's batch."""
    robot, sim, b = setup
    return jax.jit(jax.vmap(functools.partial(control_step, sim), in_axes=(b.in_axes, 0, 0, 0, 0, 0, 0)))


def test_substep_monitors_equal_hand_stepping(setup, step):
    robot, sim, b = setup
    h = sim.dt_physics
    assert sim.dt_control == pytest.approx(N_SUB * h)
    ref = _reference(sim, b)
    run_state = b.state
    total_acc, coarse_gap = 0.0, 0.0
    for _ in range(PERIODS):
        run_state_next, log = step(b.model, run_state, b.plan, b.om, b.gains, b.push, b.mu_ground)
        qpos, inv_h, a, nonfoot, off, dv = ref(run_state.d, log.tau)
        a0, a1 = jax.device_get(run_state.acc), jax.device_get(run_state_next.acc)
        # the state after the period is two physics steps with the held torques
        np.testing.assert_allclose(np.asarray(run_state_next.d.qpos), qpos, rtol=0, atol=1e-6)
        # integrals: sum over the physics steps x the physics timestep (not one sample x the control period)
        d_acc = np.asarray(a1.sum_acc - a0.sum_acc)
        np.testing.assert_allclose(d_acc, (a * h).sum(axis=1), rtol=1e-4, atol=2 * N_SUB * V_TOL)
        np.testing.assert_allclose(a1.sum_invH - a0.sum_invH, (inv_h * h).sum(axis=1), rtol=INV_H_RTOL, atol=1e-10)
        np.testing.assert_array_equal(a1.n_boundary - a0.n_boundary, (inv_h <= 0).sum(axis=1))
        np.testing.assert_array_equal(a1.nonfoot_floor, a0.nonfoot_floor | nonfoot.any(axis=1))
        expect_off = np.asarray(a0.off_steps)
        for k in range(N_SUB):
            expect_off = np.where(off[:, k], expect_off + 1, 0)
        np.testing.assert_array_equal(a1.off_steps, expect_off)
        np.testing.assert_array_equal(a1.n_steps, np.asarray(a0.n_steps) + 1)  # control steps
        assert np.all(np.asarray(a1.n_boundary_cone - a0.n_boundary_cone) <= np.asarray(a1.n_boundary - a0.n_boundary))
        # R of the QP's planned object forces: once per control step, by hand from the solution's Lambda_b
        inv_h_plan, fn_plan = _planned_by_hand(np.asarray(run_state_next.cs.warm.x, float), np.asarray(b.om.mu, float))
        np.testing.assert_allclose(a1.sum_invH_plan - a0.sum_invH_plan, inv_h_plan * sim.dt_control, rtol=1e-4,
                                   atol=1e-10)
        np.testing.assert_array_equal(a1.n_boundary_plan - a0.n_boundary_plan, inv_h_plan <= 0)
        assert np.all(np.asarray(a1.n_boundary_plan_cone - a0.n_boundary_plan_cone) <= (inv_h_plan <= 0))
        # the slice holds the object's multipliers: their normal forces carry about the object's weight
        np.testing.assert_allclose(fn_plan, np.asarray(b.om.mass) * 9.81, rtol=0.5)
        total_acc += (a * h).sum()
        # one sample per control period, ||v(t + 2h) - v(t)|| / (2h) x 2h, would have given this instead
        coarse_gap = max(coarse_gap, float(np.max(np.abs(d_acc - np.linalg.norm(dv, axis=1)) / d_acc)))
        run_state = run_state_next
    assert total_acc > 0 and coarse_gap > 1e-2  # the check is not vacuous: per-period sampling differs here
    # finalize: time averages over the control steps, boundary fraction over the physics steps
    res = metrics.finalize(jax.device_get(run_state.acc), sim.dt_control, np.asarray(b.om.mu), course=False,
                           final_err=np.zeros(2), substeps=N_SUB)
    acc = jax.device_get(run_state.acc)
    np.testing.assert_allclose(res["R"], np.asarray(acc.sum_invH) / (PERIODS * sim.dt_control), rtol=1e-6)
    np.testing.assert_allclose(res["boundary_fraction"], np.asarray(acc.n_boundary) / (PERIODS * N_SUB))
    np.testing.assert_allclose(res["R_plan"], np.asarray(acc.sum_invH_plan) / (PERIODS * sim.dt_control), rtol=1e-6)
    np.testing.assert_allclose(res["boundary_fraction_plan"], np.asarray(acc.n_boundary_plan) / PERIODS)


def _planned_by_hand(x, mu, nv=24, k=4):
    """numpy, per run: 1/H of the planned object forces in QP solutions x (B, n) (layout [vdot (nv), Lambda_gr
    (4k), Lambda_b (4k), gamma]; edge j = Rz(2 pi j / k) Ry(atan mu) z in the tray frame, the paper's H with the
    boundary rule) and the planned total normal force [N]."""
    out, fn = [], []
    for xi, m in zip(x, mu):
        th = np.arctan(m)
        a = 2 * np.pi * np.arange(1, k + 1) / k
        E = np.stack([np.sin(th) * np.cos(a), np.sin(th) * np.sin(a), np.cos(th) * np.ones(k)])  # (3, k)
        f = xi[nv + 4 * k: nv + 8 * k].reshape(4, k) @ E.T  # (4, 3) tray frame
        alpha = np.arctan2(np.linalg.norm(f[:, :2], axis=1), np.where(f[:, 2] > metrics.LOAD_EPS, f[:, 2], 1.0))
        g = (th - alpha) * (th + alpha)
        ok = np.all(f[:, 2] > metrics.LOAD_EPS) and np.all(g > 0)
        out.append(4.0 / np.sum(1.0 / g) if ok else 0.0)
        fn.append(f[:, 2].sum())
    return np.array(out), np.array(fn)


def test_make_sim_rejects_inconsistent_period():
    robot = Robot("flat")
    with pytest.raises(ValueError, match="n_substeps"):
        make_sim(robot, TransportConfig(dt=float(robot.mj_model.opt.timestep)), n_substeps=2)


# ---------------------------------------------------------------- spec key

FACTORS = "[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n"


@pytest.mark.parametrize("value", [0, 11, 2.5])
def test_control_substeps_out_of_range(tmp_path, value):
    p = tmp_path / "bad.toml"
    p.write_text(f"[campaign]\ncontrol_substeps = {value}\n" + FACTORS)
    with pytest.raises(SpecError) as e:
        load_spec(p)
    msg = str(e.value)
    assert isinstance(e.value, WbcJaxError) and "\n" not in msg
    assert str(p) in msg and "campaign.control_substeps" in msg
    assert ("1 <= value <= 10" if isinstance(value, int) else "integer 1..10") in msg


def test_control_substeps_cli_exit_2(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[campaign]\ncontrol_substeps = 11\n" + FACTORS)
    out = tmp_path / "out"
    assert cli.main(["campaign", "--spec", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "campaign.control_substeps" in err[0] and "1 <= value <= 10" in err[0]
    assert not out.exists()


def test_control_substeps_default_and_hash():
    base = dict(factors=dict(m=[0.2, 0.3], mu=[0.4, 1.0], d=[0.06, 0.1]))
    s0 = parse_spec(base)
    s1 = parse_spec(dict(base, campaign=dict(control_substeps=1)))
    s2 = parse_spec(dict(base, campaign=dict(control_substeps=2)))
    assert s0.campaign["control_substeps"] == 1 and s2.campaign["control_substeps"] == 2
    assert s0.canonical()["campaign"]["control_substeps"] == 1  # recorded in the manifest's spec
    assert s0.hash == s1.hash != s2.hash  # the default keeps the hashes of specs written before the key existed


SINK = 0.35  # [m] run 0's trunk is lowered by this: knees and shins go below the floor


def test_first_body_contact_time_and_pair(setup, step):
    """The first non-foot contact is recorded with the time of its step and the deepest pair, as MuJoCo C finds it
    at the same positions; a run without such contact records none; a later period keeps the first record."""
    robot, sim, b = setup
    qpos = np.asarray(b.state.d.qpos).copy()
    qpos[0, 2] -= SINK
    # the same values as jnp.asarray(qpos), set into the batch's (committed) array: an uncommitted input would make
    # the module's jitted step compile a second program for the same shapes
    run_state = b.state._replace(d=b.state.d.replace(qpos=b.state.d.qpos.at[0, 2].set(qpos[0, 2])))
    args = (b.plan, b.om, b.gains, b.push, b.mu_ground)
    run_state1, _ = step(b.model, run_state, *args)
    run_state2, _ = step(b.model, run_state1, *args)
    a1, a2 = jax.device_get(run_state1.acc), jax.device_get(run_state2.acc)
    # reference: MuJoCo C collision at run 0's start positions, restricted to the non-foot pairs
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos[0]
    mujoco.mj_forward(m, d)
    nonfoot = {frozenset(map(int, g)) for g in sim.nonfoot_geoms}
    hits = [(c.dist, frozenset((int(c.geom1), int(c.geom2)))) for c in d.contact[:d.ncon]]
    hits = [h for h in hits if h[1] in nonfoot and h[0] < 0]
    assert hits, "the sunk run has no non-foot penetration: the test is vacuous"
    deepest = min(hits, key=lambda h: h[0])[1]
    assert bool(a1.nonfoot_floor[0]) and not bool(a1.nonfoot_floor[1])
    assert float(a1.first_contact_t[0]) == pytest.approx(float(b.state.d.time[0]), abs=1e-9)
    assert frozenset(map(int, sim.nonfoot_geoms[int(a1.first_contact_k[0])])) == deepest
    assert np.isnan(a1.first_contact_t[1]) and int(a1.first_contact_k[1]) == -1
    assert float(a2.first_contact_t[0]) == float(a1.first_contact_t[0])
    assert int(a2.first_contact_k[0]) == int(a1.first_contact_k[0])
    name = contact_name(sim, int(a1.first_contact_k[0]))
    geom_names = {m.geom(g).name for g in deepest}
    assert "(body " in name and all(n in name for n in geom_names if n)
    assert contact_name(sim, -1) == ""
