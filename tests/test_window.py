"""Metric window and clearance.

* R, T, S integrate over each run's window [0, t_end), t_end = T_plan + extra_seconds capped by max_seconds, not
  over the whole simulated time, so ``chunk_seconds`` (which rounds the simulation up to whole chunks) does not
  change them.
* The clearance (smallest signed distance of a non-foot robot geom to floor / terrain / wall) equals MuJoCo C's
  ``mj_geomDistance`` on the same configurations.

Reuses the compiled shapes of tests/test_campaign.py (the tiny spec's 2-log chunk function and its init function).
"""

import dataclasses

import jax
import mujoco
import numpy as np
import pytest

from wbc_jax.campaign import runner as C
from wbc_jax.campaign.build import chunk_plan
from wbc_jax.campaign.spec import SWEEPS, load_spec
from wbc_jax.metrics import paper as metrics
from wbc_jax.rollout import clearance, clearance_name, final_results, with_metric_window

TINY = SWEEPS.parent / "reports" / "baseline" / "spec.toml"
WINDOW_RTOL = 1e-6  # R, T, S of one window at two simulated lengths: float rounding only (same operations)
CLEAR_TOL = 2e-5  # [m] MJX (float32 kinematics) vs MuJoCo C (float64) geom distances
DISTMAX = 1.0  # [m] mj_geomDistance's search radius (the clearances here are ~1 cm)


def _spec(**campaign):
    s = load_spec(TINY)
    return dataclasses.replace(s, campaign={**s.campaign, **campaign})


def _finalize(sim, design, state):
    return metrics.finalize(jax.device_get(state.acc), sim.dt_control, design.mu, course=False,
                            final_err=np.zeros(design.n), substeps=sim.n_substeps)


@pytest.fixture(scope="module")
def windowed():
    """The tiny spec capped at 0.08 s (window 0.08 s) built for chunk_seconds 0.04 and 0.06 (both 2 chunks of 2
    logs: the chunks fit the cap); the 0.04 s chunk function run for 2, 3 and 4 chunks (0.08, 0.12, 0.16 s
    simulated, as whole chunks past a window would) and, from the 2-chunk state, one more chunk with no window."""
    spec_a, spec_b = _spec(max_seconds=0.08, chunk_seconds=0.04), _spec(max_seconds=0.08, chunk_seconds=0.06)
    sim, design, b, T_plan, lpc, n_chunks = C.build(spec_a)
    _, _, b6, _, lpc6, n6 = C.build(spec_b)
    assert (lpc, n_chunks) == (2, 2) and (lpc6, n6) == (2, 2)  # 0.08 s simulated
    fn = C.chunk_fn(sim, b.in_axes, lpc)
    states, state = {}, b.state
    for k in range(1, 5):
        state, _ = fn(b.model, state, b.plan, b.om, b.gains, b.push, b.mu_ground)
        states[k] = state
    open_tail, _ = fn(b.model, with_metric_window(states[2], np.inf), b.plan, b.om, b.gains, b.push, b.mu_ground)
    return sim, design, b, b6, T_plan, states, open_tail


def test_window_is_per_run_plan_end_capped_and_independent_of_chunking(windowed):
    sim, design, b, b6, T_plan, states, _ = windowed
    t_end = np.asarray(b.state.acc.t_end)
    np.testing.assert_array_equal(t_end, np.asarray(b6.state.acc.t_end))  # chunk_seconds does not enter
    np.testing.assert_allclose(t_end, 0.08, rtol=1e-6)  # T_plan (> 2 s) + 0 s, capped at max_seconds
    # uncapped: each run's own plan end + extra_seconds (plans differ by d)
    _, _, bu, _, _, _ = C.build(_spec(max_seconds=0.0, extra_seconds=0.25))
    ends = np.asarray(bu.plan.obj_path.t_knots)[:, -1]
    np.testing.assert_allclose(np.asarray(bu.state.acc.t_end), ends + 0.25, rtol=1e-6)
    assert T_plan == pytest.approx(ends.max())


@pytest.mark.parametrize("chunk_s, cap, planned_s, extra_s, plan", [
    (2.0, 0.0, 27.65, 0.5, (94, 15)),  # the paper course: 28.15 s in 15 chunks of 1.88 s (not 30 s)
    (2.0, 0.0, 5.0, 1.0, (100, 3)),  # a horizon of whole chunks keeps them
    (0.5, 0.0, 3.0, 0.5, (25, 7)),  # 3.5 s: 7 chunks of 0.5 s
    (0.5, 0.0, 3.01, 0.5, (22, 8)),  # 3.51 s: 8 chunks of 0.44 s, 3.52 s (4.0 s before)
    (2.0, 6.0, 27.65, 0.5, (100, 3)),  # a cap of whole chunks
    (0.07, 0.12, 2.5, 0.0, (3, 2)),  # a cap met exactly by 2 chunks of 0.06 s (at most 0.08 s asked)
    (0.04, 0.14, 2.5, 0.0, (1, 7)),  # 7 logs: only 1-log chunks divide it within 0.04 s
    (0.04, 0.13, 2.5, 0.0, (2, 4)),  # not a whole number of logs: 0.16 s, refused by check_horizon
])
def test_chunks_fit_the_horizon(chunk_s, cap, planned_s, extra_s, plan):
    """The fewest chunks of at most chunk_seconds (whole 0.02 s log intervals) that cover the horizon, each as short
    as covers it; a cap is met exactly where it is a whole number of log intervals. Hand-computed."""
    got = chunk_plan(dict(chunk_seconds=chunk_s, max_seconds=cap, extra_seconds=extra_s), 0.001, planned_s)
    assert got == plan


def test_tail_after_the_window_is_excluded(windowed):
    """0.08 s simulated (window = simulation) vs 0.12 and 0.16 s with the same 0.08 s window: equal integrals,
    R, T, S and window; the flags and counters still see the tail; without the window the tail adds to them."""
    sim, design, b, _, _, states, open_tail = windowed
    acc = {k: jax.device_get(states[k].acc) for k in (2, 3, 4)}
    res = {k: _finalize(sim, design, states[k]) for k in (2, 3, 4)}
    for k in (3, 4):
        np.testing.assert_array_equal(acc[k].n_steps, 40 * k)
        np.testing.assert_array_equal(acc[k].n_win, 80)
        for f in ("sum_invH", "sum_acc", "sum_track", "n_boundary"):
            np.testing.assert_allclose(getattr(acc[k], f), getattr(acc[2], f), rtol=WINDOW_RTOL, err_msg=f)
        for f in ("R", "T", "S", "boundary_fraction", "window_s"):
            np.testing.assert_allclose(res[k][f], res[2][f], rtol=WINDOW_RTOL, err_msg=f)
        assert np.all(acc[k].max_slip >= acc[2].max_slip)
    np.testing.assert_allclose(res[2]["window_s"], 0.08, rtol=1e-9)
    # the tail's integrands are not zero (standing, loaded: 1/H > 0), so including it would change R and T
    tail = jax.device_get(open_tail.acc)
    assert np.all(tail.n_win == 120) and np.all(tail.sum_invH > acc[2].sum_invH)
    assert np.all(tail.sum_track > acc[2].sum_track)


def _pairs(sim):
    """The clearance's pairs (robot geom, scene geom), in its index order."""
    from wbc_jax.physics.clearance import clearance_pairs

    p = clearance_pairs(sim.robot)
    return [(int(a), int(b)) for a, b in zip(p.robot, p.env)]


def _c_clearance(sim, qpos):
    """Smallest mj_geomDistance over the clearance's pairs at ``qpos`` (MuJoCo C): (distance [m], pair)."""
    m = sim.robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    pairs = _pairs(sim)
    dist = [mujoco.mj_geomDistance(m, d, g1, g2, DISTMAX, None) for g1, g2 in pairs]
    k = int(np.argmin(dist))
    return dist[k], pairs[k]


@pytest.mark.parametrize("drop", [0.0, 0.03])
def test_clearance_equals_mujoco_geom_distance(windowed, drop):
    """Home poses (about 1 cm clearance) and the robot lowered 3 cm (shanks into the floor): the clearance
    (exact geometry, wbc_jax.physics.clearance) and its pair equal MuJoCo C's smallest geom distance over the same
    pairs."""
    from wbc_jax.rollout.batch import _init_fn

    sim, design, b, *_ = windowed
    qpos = np.asarray(b.state.d.qpos, float).copy()
    qpos[:, 2] -= drop
    st = _init_fn(sim, b.in_axes, design.n)(b.model, qpos, np.asarray(b.state.d.qvel))  # sensed: contacts filled
    c, k = jax.jit(jax.vmap(lambda d: clearance(sim, d)))(st.d)
    c, k = np.asarray(c), np.asarray(k)
    for i in range(design.n):
        ref, pair = _c_clearance(sim, np.asarray(st.d.qpos[i], float))
        assert abs(c[i] - ref) < CLEAR_TOL, (i, c[i], ref)
        got = _pairs(sim)[k[i]]
        # the same pair, or a tie (left and right legs are symmetric)
        assert got == pair or abs(_c_dist(sim, qpos[i], got) - ref) < CLEAR_TOL
        assert clearance_name(sim, int(k[i])).endswith("/ floor")
    assert (np.all(c < 0) if drop else np.all(c > 0))


def _c_dist(sim, qpos, pair):
    m = sim.robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    return mujoco.mj_geomDistance(m, d, pair[0], pair[1], DISTMAX, None)


def test_run_clearance_bounds_logged_configurations_and_is_reported(windowed):
    """The run's min clearance is at most MuJoCo C's clearance at every logged configuration (every 20 steps) and
    lies in the run; final_results names its pair."""
    sim, design, b, _, _, states, _ = windowed
    fn = C.chunk_fn(sim, b.in_axes, 2)
    _, logs = fn(b.model, states[1], b.plan, b.om, b.gains, b.push, b.mu_ground)  # chunk 2 again: its logs
    acc = jax.device_get(states[2].acc)
    q = np.asarray(logs.qpos, float)  # (B, 2, nq)
    for i in range(design.n):
        logged = min(_c_clearance(sim, q[i, j])[0] for j in range(q.shape[1]))
        assert acc.min_clear[i] <= logged + CLEAR_TOL
        assert 0.0 <= acc.min_clear_t[i] < 0.08
    res = final_results(sim, states[2], np.zeros((design.n, 3)), design.mu)
    np.testing.assert_allclose(res["min_clearance_mm"], acc.min_clear * 1e3)
    assert all(" (body " in p and p.endswith("/ floor") for p in res["min_clearance_pair"])
