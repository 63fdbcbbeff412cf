"""The transport paper's metrics (wbc_jax.metrics.paper) against hand computations."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.metrics import paper as metrics
from wbc_jax.metrics.accumulate import Accum
from wbc_jax.physics import contacts
from wbc_jax.robot.model import mjx

TOL = 1e-6


def test_cone_angle_by_hand():
    f = jnp.array([[2.0, 0.0, 0.0], [1.0, 0.3, 0.4], [0.0, 0.1, 0.0], [1e-4, 0.0, 0.0]])
    alpha, loaded = metrics.cone_angle(f)
    np.testing.assert_allclose(alpha[:2], [0.0, np.arctan(0.5)], atol=TOL)
    assert loaded.tolist() == [True, True, False, False]  # 1e-4 N <= LOAD_EPS: no load


def test_inv_H_by_hand():
    mu = 0.7
    th = np.arctan(mu)
    # all forces along the normals: H = (1/4) * 4 / th^2 -> 1/H = th^2
    np.testing.assert_allclose(metrics.inv_H(jnp.zeros(4), jnp.ones(4, bool), mu), th**2, rtol=TOL)
    a = np.array([0.1, 0.2, 0.3, 0.05])
    H = (1 / 4) * np.sum(1 / ((th - a) * (a + th)))
    np.testing.assert_allclose(metrics.inv_H(jnp.asarray(a), jnp.ones(4, bool), mu), 1 / H, rtol=1e-5)
    # larger friction -> larger 1/H for the same angles
    assert metrics.inv_H(jnp.asarray(a), jnp.ones(4, bool), 1.0) > metrics.inv_H(jnp.asarray(a), jnp.ones(4, bool), 0.4)


def test_inv_H_boundary_rule():
    mu = 0.4
    th = np.arctan(mu)
    ok = jnp.ones(4, bool)
    # one contact unloaded -> at the boundary -> 1/H = 0
    assert float(metrics.inv_H(jnp.zeros(4), ok.at[2].set(False), mu)) == 0.0
    # one force on / outside the circular cone -> 0
    th32 = jnp.arctan(jnp.float32(mu))  # exactly on the cone in the rollout's precision
    assert float(metrics.inv_H(jnp.array([0.0, 0.0, 0.0, 0.0]).at[2].set(th32), ok, mu)) == 0.0
    assert float(metrics.inv_H(jnp.array([0.0, 0.0, th + 0.2, 0.0]), ok, mu)) == 0.0
    # just inside: small but positive, finite
    v = float(metrics.inv_H(jnp.array([0.0, 0.0, th - 1e-3, 0.0]), ok, mu))
    assert 0.0 < v < 1e-2 and np.isfinite(v)
    # gradient-free and jit/vmap-able
    f = jax.jit(jax.vmap(metrics.inv_H, in_axes=(0, 0, 0)))
    out = f(jnp.zeros((3, 4)), jnp.ones((3, 4), bool).at[1, 0].set(False), jnp.array([0.4, 0.7, 1.0]))
    np.testing.assert_allclose(out, [np.arctan(0.4) ** 2, 0.0, np.arctan(1.0) ** 2], rtol=1e-5)


NV, K = 24, 4  # the transport QP's vdot size and pyramid edges (TransportConfig's defaults)


def _x_with(lam_b, seed=0):
    """A transport QP solution vector x (TransportConfig().n_var) with Lambda_b = lam_b (4, K) and random other
    entries (vdot, ground multipliers: must not matter)."""
    from wbc_jax.control.transport import N_FEET, N_OBJ, TransportConfig

    n = TransportConfig().n_var
    assert n == NV + K * (N_FEET + N_OBJ)  # the layout planned_object_forces reads
    x = np.random.default_rng(seed).uniform(-50, 50, n)
    x[NV + K * N_FEET: NV + K * (N_FEET + N_OBJ)] = np.asarray(lam_b, float).ravel()
    return jnp.asarray(x)


def _planned(x, mu):
    """The planned object forces of solution x (the controller's decoding of its own variable layout)."""
    from wbc_jax.control.transport import planned_object_forces

    return planned_object_forces(x, mu, NV, K)


def _pih(x, mu, nv=NV, k=K):
    return metrics.planned_inv_H(_planned(x, mu), mu)[0]


def test_planned_R_by_hand():
    """R of the QP's planned object forces (F_c = E_c Lambda_b) against a hand computation: edges j = 1..4 point
    (in the tangent plane) along +y, -x, -y, +x at atan(mu) from the normal, so each force's tan(alpha) is known."""
    mu = 0.7
    th = np.arctan(mu)
    s, c = np.sin(th), np.cos(th)
    lam = np.array([[1.0, 1.0, 1.0, 1.0],    # symmetric: along the normal, alpha = 0
                    [3.0, 0.0, 1.0, 0.0],    # f_y = 2 s, f_n = 4 c: tan alpha = mu / 2
                    [1.0, 1.0, 0.0, 0.0],    # f = s (-1, 1), f_n = 2 c: tan alpha = mu / sqrt 2
                    [0.5, 0.5, 0.5, 2.0]])   # f_x = 1.5 s, f_n = 3.5 c: tan alpha = mu 1.5 / 3.5
    f = np.asarray(_planned(_x_with(lam), mu))
    np.testing.assert_allclose(f[1], [4 * c, 0.0, 2 * s], atol=1e-5)  # normal first, then x, y
    np.testing.assert_allclose(f[2], [2 * c, -s, s], atol=1e-5)
    alpha = np.arctan(mu * np.array([0.0, 0.5, 1 / np.sqrt(2), 1.5 / 3.5]))
    hand = 4.0 / np.sum(1.0 / ((th - alpha) * (th + alpha)))
    np.testing.assert_allclose(_pih(_x_with(lam), mu, NV, K), hand, rtol=1e-5)
    # every contact along its normal: the maximum th^2, whatever the load
    np.testing.assert_allclose(_pih(_x_with(np.full((4, 4), 2.5)), mu, NV, K), th**2, rtol=1e-5)
    # boundary rule: a contact without planned load -> 0; a force along one edge (alpha = theta) -> 0 up to
    # rounding; a slightly negative multiplier (ADMM tolerance) that puts a force outside the cone -> 0
    assert float(_pih(_x_with(np.r_[lam[:3], np.zeros((1, 4))]), mu, NV, K)) == 0.0
    assert float(_pih(_x_with(np.r_[lam[:3], [[0.0, 2.0, 0.0, 0.0]]]), mu, NV, K)) < 1e-5 * th**2
    assert float(_pih(_x_with(np.r_[lam[:3], [[-0.1, 0.0, 1.0, 0.0]]]), mu, NV, K)) == 0.0
    outside = _planned(_x_with(np.r_[lam[:3], [[-0.1, 0.0, 1.0, 0.0]]]), mu)
    assert bool(metrics.planned_inv_H(outside, mu)[1])  # the cone
    assert not bool(metrics.planned_inv_H(_planned(_x_with(np.r_[lam[:3], np.zeros((1, 4))]), mu), mu)[1])  # unloaded
    # the simulator's R path is untouched: the same forces through cone_angle / inv_H give the same value
    alpha_s, loaded = metrics.cone_angle(jnp.asarray(f))
    np.testing.assert_allclose(metrics.inv_H(alpha_s, loaded, mu), hand, rtol=1e-5)
    assert not bool(metrics.at_cone(alpha_s, loaded, mu))
    assert bool(metrics.at_cone(alpha_s.at[3].set(th + 0.1), loaded, mu))
    assert not bool(metrics.at_cone(alpha_s.at[3].set(th + 0.1), loaded.at[0].set(False), mu))  # unloaded first


def _accum(**kw):
    z = np.zeros(2)
    base = dict(min_trunk_z=np.array([0.45, 0.45]), max_slip=z, max_lift=z, nonfoot_floor=np.zeros(2, bool),
                wall_contact=np.zeros(2, bool), max_tau_ratio=z, max_tau_excess=z, sum_prim_res=z,
                n_flag=np.zeros(2, int), sum_qp_iters=np.array([10000, 15000]), max_qp_iters=np.array([10, 60]),
                n_steps=np.array([1000, 1000]), sum_track=z, nonfinite=np.zeros(2, bool),
                off_steps=np.zeros(2, int), max_off_s=z, sum_invH=z, sum_acc=z, n_boundary=np.zeros(2, int),
                first_contact_t=np.full(2, np.nan), first_contact_k=np.full(2, -1), overflow=np.zeros(2, bool),
                t_end=np.full(2, np.inf), n_win=np.array([1000, 1000]), min_clear=np.full(2, np.inf),
                min_clear_t=np.full(2, np.nan), min_clear_k=np.full(2, -1), n_boundary_cone=np.zeros(2, int),
                sum_invH_plan=z, n_boundary_plan=np.zeros(2, int), n_boundary_plan_cone=np.zeros(2, int),
                n_solver_cap=np.zeros(2, int), failed=np.zeros(2, bool), fail_t=np.full(2, np.nan))
    base.update(kw)
    return Accum(**base)


def test_finalize_by_hand():
    dt = 1e-3  # 1000 steps -> T_run = 1 s
    acc = _accum(sum_invH=np.array([0.3, 0.1]), sum_track=np.array([0.002, 0.004]), sum_acc=np.array([0.5, 2.0]),
                 max_slip=np.array([0.004, 0.012]), n_flag=np.array([1, 20]), n_boundary=np.array([0, 100]),
                 wall_contact=np.array([False, True]), n_boundary_cone=np.array([0, 40]),
                 sum_invH_plan=np.array([0.25, 0.2]), n_boundary_plan=np.array([10, 500]),
                 n_boundary_plan_cone=np.array([0, 100]), n_solver_cap=np.array([0, 250]))
    r = metrics.finalize(acc, dt, np.array([0.7, 0.7]), course=False, final_err=np.array([0.001, 0.002]))
    np.testing.assert_allclose(r["R"], [0.3, 0.1])
    np.testing.assert_allclose(r["T"], [0.002, 0.004])
    np.testing.assert_allclose(r["S"], [1 / 0.5, 1 / 2.0])  # T_run / int ||a|| dt
    np.testing.assert_allclose(r["max_slip_mm"], [4.0, 12.0])
    np.testing.assert_allclose(r["boundary_fraction"], [0.0, 0.1])
    np.testing.assert_allclose(r["boundary_cone_fraction"], [0.0, 0.04])
    np.testing.assert_allclose(r["R_plan"], [0.25, 0.2])
    np.testing.assert_allclose(r["boundary_fraction_plan"], [0.01, 0.5])  # of the control steps
    np.testing.assert_allclose(r["boundary_cone_fraction_plan"], [0.0, 0.1])
    assert r["slid"].tolist() == [False, True]
    assert r["hit_wall"].tolist() == [False, True]
    assert r["qp_flagged"].tolist() == [False, True]  # 0.1 % is the line: 2 % > 0.1 % >= 0.1 %
    np.testing.assert_allclose(r["qp_flag_fraction"], [0.001, 0.02])  # 1 and 20 of 1000 control steps
    np.testing.assert_allclose(r["qp_iters_mean"], [10.0, 15.0])
    assert r["qp_iters_max"].tolist() == [10, 60]
    np.testing.assert_allclose(r["solver_cap_fraction"], [0.0, 0.25])  # of all 1000 physics steps
    assert r["success"].tolist() == [True, True]  # sliding, wall contact and QP flags are flags, not failures


def test_finalize_averages_over_the_metric_window():
    """The same integrals over a 0.5 s window of a 1 s simulation: R and T doubled, S halved, boundary fraction of
    the window's steps; flags unchanged."""
    kw = dict(sum_invH=np.array([0.3, 0.1]), sum_track=np.array([0.002, 0.004]), sum_acc=np.array([0.5, 2.0]),
              n_boundary=np.array([0, 100]), min_clear=np.array([0.011, -0.002]), min_clear_t=np.array([0.2, 0.7]))
    full = metrics.finalize(_accum(**kw), 1e-3, np.array([0.7, 0.7]), course=False, final_err=np.zeros(2))
    half = metrics.finalize(_accum(n_win=np.array([500, 500]), **kw), 1e-3, np.array([0.7, 0.7]), course=False,
                            final_err=np.zeros(2))
    np.testing.assert_allclose(half["R"], 2 * full["R"])
    np.testing.assert_allclose(half["T"], 2 * full["T"])
    np.testing.assert_allclose(half["S"], full["S"] / 2)
    np.testing.assert_allclose(half["boundary_fraction"], [0.0, 0.2])
    np.testing.assert_allclose(half["window_s"], [0.5, 0.5])
    np.testing.assert_allclose(half["min_clearance_mm"], [11.0, -2.0])
    np.testing.assert_allclose(half["min_clearance_s"], [0.2, 0.7])
    assert half["success"].tolist() == full["success"].tolist() == [True, True]


def test_finalize_failures():
    acc = _accum(min_trunk_z=np.array([0.2, 0.45]), max_lift=np.array([0.0, 0.02]), sum_acc=np.array([1.0, 1.0]))
    r = metrics.finalize(acc, 1e-3, np.array([0.7, 0.7]), course=False, final_err=np.array([0.0, 0.0]))
    assert r["fell"].tolist() == [True, False] and r["dropped"].tolist() == [False, True]
    assert r["success"].tolist() == [False, False]
    # the course allows a lower trunk (crouching under the wall); a NaN run fails
    acc = _accum(min_trunk_z=np.array([0.2, 0.45]), nonfinite=np.array([False, True]), sum_acc=np.array([1.0, 1.0]))
    r = metrics.finalize(acc, 1e-3, np.array([0.7, 0.7]), course=True, final_err=np.array([0.0, np.nan]))
    assert r["fell"].tolist() == [False, True] and r["success"].tolist() == [True, False]
    assert r["fail_reason"].tolist() == ["", "non-finite state; object not delivered"]
    # a run whose contacts overflowed Warp's capacity fails, with its reason
    acc = _accum(overflow=np.array([False, True]), sum_acc=np.array([1.0, 1.0]))
    r = metrics.finalize(acc, 1e-3, np.array([0.7, 0.7]), course=False, final_err=np.array([0.0, 0.0]))
    assert r["success"].tolist() == [True, False] and "overflow" in r["fail_reason"][1]
    # a knee or shin touching the ground with the trunk up is a fall, named as body contact
    acc = _accum(min_trunk_z=np.array([0.4, 0.1]), nonfoot_floor=np.array([True, False]), sum_acc=np.array([1.0, 1.0]))
    r = metrics.finalize(acc, 1e-3, np.array([0.7, 0.7]), course=True, final_err=np.array([0.0, 0.0]))
    assert r["fell"].tolist() == [True, True] and r["body_contact"].tolist() == [True, False]
    assert r["fail_reason"].tolist() == ["body contact with floor/terrain", "trunk below the fall height"]


CUBE = """
<mujoco>
  <option timestep="0.001" cone="pyramidal" gravity="{gx} 0 {gz}"/>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1" contype="0" conaffinity="0"/>
    <body name="cube" pos="0 0 0.05">
      <freejoint/>
      <geom type="box" size="0.04 0.04 0.04" mass="{m}" contype="0" conaffinity="0"/>
      <geom name="c0" type="sphere" size="0.005" pos=" 0.035  0.035 -0.035" mass="0" contype="0" conaffinity="0"/>
      <geom name="c1" type="sphere" size="0.005" pos="-0.035  0.035 -0.035" mass="0" contype="0" conaffinity="0"/>
      <geom name="c2" type="sphere" size="0.005" pos="-0.035 -0.035 -0.035" mass="0" contype="0" conaffinity="0"/>
      <geom name="c3" type="sphere" size="0.005" pos=" 0.035 -0.035 -0.035" mass="0" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="c0" geom2="floor" condim="3" friction="{mu} {mu} 0.005 0.0001 0.0001"/>
    <pair geom1="c1" geom2="floor" condim="3" friction="{mu} {mu} 0.005 0.0001 0.0001"/>
    <pair geom1="c2" geom2="floor" condim="3" friction="{mu} {mu} 0.005 0.0001 0.0001"/>
    <pair geom1="c3" geom2="floor" condim="3" friction="{mu} {mu} 0.005 0.0001 0.0001"/>
  </contact>
</mujoco>
"""


def test_simulator_contact_forces_on_an_incline():
    """A cube at rest under gravity tilted by phi (an incline, phi < atan mu): the simulator's contact forces
    read by contacts.contact_forces carry the weight, with total tangential / normal = tan(phi) (hand statics)."""
    m_obj, mu, phi, g = 0.3, 0.7, 0.2, 9.81
    mj = mujoco.MjModel.from_xml_string(CUBE.format(gx=g * np.sin(phi), gz=-g * np.cos(phi), m=m_obj, mu=mu))
    mx = mjx.put_model(mj)

    def step(d, _):
        return mjx.step(mx, d), None

    d, _ = jax.jit(lambda d: jax.lax.scan(step, d, None, length=600))(mjx.make_data(mx))
    d = jax.jit(mjx.forward)(mx, d)
    f = np.asarray(contacts.contact_forces(mx, d, np.arange(4)))  # (4, 3) contact frames, normal first
    total = mj.body_mass[1] * g
    fn = f[:, 0].sum()
    ft = np.linalg.norm(f[:, 1:].sum(axis=0))
    np.testing.assert_allclose(fn, total * np.cos(phi), rtol=0.02)
    np.testing.assert_allclose(ft, total * np.sin(phi), rtol=0.05)
    alpha, loaded = metrics.cone_angle(jnp.asarray(f))
    assert bool(jnp.all(loaded))
    th = np.arctan(mu)
    ih = float(metrics.inv_H(alpha, loaded, mu))
    np.testing.assert_allclose(ih, 4 / np.sum(1 / (th**2 - np.asarray(alpha) ** 2)), rtol=1e-5)
    assert 0 < ih < th**2
