"""The two MJX physics backends (JAX and MuJoCo Warp, which also runs on the CPU) against each other and MuJoCo C.

References: MuJoCo C's ``mj_fullM`` for the dense mass matrix rebuilt from Warp's CSR storage; MJX's own collision
distances (JAX backend, every pair's slot) for the geometric sphere distances the Warp path computes; the JAX
backend's closed loop for the Warp backend's (same model, same controller, a short loaded stand and first steps).
"""

from __future__ import annotations

import jax
import mujoco
import numpy as np
import pytest

pytest.importorskip("warp")

from wbc_jax.control.dynamics import mass_matrix  # noqa: E402
from wbc_jax.sim import contacts, physics  # noqa: E402
from wbc_jax.sim.batch import prepare_batch  # noqa: E402
from wbc_jax.sim.model import Robot  # noqa: E402
from wbc_jax.sim.rollout import final_results, make_sim, simulate  # noqa: E402

M_TOL = 1e-5  # relative, float32 CSR scatter vs MuJoCo C float64
DIST_TOL = 1e-5  # [m] geometric sphere distances vs MJX's collision functions (float32)
POS_TOL = 1e-3  # [m] trunk and object positions after the walk, Warp vs JAX
METRIC_RTOL = 0.05  # R and T, Warp vs JAX (the constraint solvers split the object's four forces differently)
SECONDS = 0.6
FACTORS = (np.array([0.3, 0.4]), np.array([0.7, 0.4]), np.array([0.08, 0.06]))  # m [kg], mu, d [m]


@pytest.fixture(scope="module")
def walks():
    """Both backends' batch-2 closed loops over SECONDS on the flat scene: (sim, batch, final state, results)."""
    out = {}
    for backend in ("jax", "warp"):
        sim = make_sim(Robot("flat", backend=backend), log_every=20)
        b = prepare_batch(sim, *FACTORS)
        st, _ = simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground,
                         seconds=SECONDS, chunk_seconds=SECONDS)
        res = final_results(sim, st, np.zeros((2, 3)), FACTORS[1])
        out[backend] = (sim, b, jax.device_get(st), res)
    return out


def test_warp_mass_matrix_and_distances_match_references(walks):
    sim, b, st, _ = walks["warp"]
    jsim, jb, *_ = walks["jax"]
    m0 = jax.tree_util.tree_map(lambda a, x: x if a is None else x[0], b.in_axes, b.model,
                                is_leaf=lambda v: v is None)
    d_w = jax.jit(physics.sense)(m0, jax.tree_util.tree_map(lambda x: x, b.state.d).replace(
        qpos=st.d.qpos[0], qvel=st.d.qvel[0]))
    # MuJoCo C reference at the same state (the run's object fields are the nominal model's for run 0: d = 0.08)
    mj = sim.robot.mj_model
    data = mujoco.MjData(mj)
    data.qpos[:], data.qvel[:] = np.asarray(st.d.qpos[0]), np.asarray(st.d.qvel[0])
    mujoco.mj_forward(mj, data)
    full = np.zeros((mj.nv, mj.nv))
    mujoco.mj_fullM(mj, data, full)
    M = np.asarray(jax.jit(mass_matrix)(m0, d_w))
    np.testing.assert_allclose(M, full, rtol=M_TOL, atol=M_TOL * np.abs(full).max())
    # sphere distances: Warp's geometric ones vs the JAX backend's slots at the same positions
    jm0 = jax.tree_util.tree_map(lambda a, x: x if a is None else x[0], jb.in_axes, jb.model,
                                 is_leaf=lambda v: v is None)
    d_j = jax.jit(physics.sense)(jm0, jax.tree_util.tree_map(lambda x: x[0], jb.state.d).replace(
        qpos=st.d.qpos[0], qvel=st.d.qvel[0]))
    foot = [jax.jit(lambda m, d, s=s: contacts.foot_dist(s, m, d))(mm, dd) for s, mm, dd in
            ((sim, m0, d_w), (jsim, jm0, d_j))]
    np.testing.assert_allclose(foot[0], foot[1], atol=DIST_TOL)
    obj = [jax.jit(lambda m, d, s=s: contacts.object_contacts(s, m, d))(mm, dd) for s, mm, dd in
           ((sim, m0, d_w), (jsim, jm0, d_j))]
    np.testing.assert_allclose(obj[0][1], obj[1][1], atol=DIST_TOL)
    # total normal force on the object (its weight at rest, split differently by the two constraint solvers)
    np.testing.assert_allclose(obj[0][0][:, 0].sum(), obj[1][0][:, 0].sum(), rtol=0.05)


def test_short_loaded_walk_agrees_between_backends(walks):
    (jsim, _, js, jr), (wsim, _, ws, wr) = walks["jax"], walks["warp"]
    ids = jsim.robot.ids
    a = ids.obj_qpos_adr
    for q_j, q_w in ((js.d.qpos[:, :3], ws.d.qpos[:, :3]), (js.d.qpos[:, a:a + 3], ws.d.qpos[:, a:a + 3])):
        np.testing.assert_allclose(np.asarray(q_w), np.asarray(q_j), atol=POS_TOL)
    for k in ("R", "T"):
        np.testing.assert_allclose(wr[k], jr[k], rtol=METRIC_RTOL)
    assert np.all(wr["success"] == jr["success"])
    assert not np.any(ws.acc.overflow) and not np.any(ws.acc.nonfinite)
    assert np.all(np.asarray(ws.acc.n_steps) == np.asarray(js.acc.n_steps))


def test_backend_choice():
    assert physics.resolve_backend("jax") == "jax"
    assert physics.resolve_backend("auto") == "jax"  # until Warp's course physics agrees (physics docstring)
    with pytest.raises(ValueError, match="backend 'bullet'"):
        physics.resolve_backend("bullet")
