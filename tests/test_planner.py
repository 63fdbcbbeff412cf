"""Planner numerics: splines, trot scheduler, swing references, ZMP support, capture point.

References: finite differences, hand computations, scipy's ConvexHull, closed-form LIPM
solutions and a float64 forward simulation of the capture-point dynamics.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from wbc_jax import planner as pl

ATOL_POS = 2e-5  # [m] float32 positions of order 1 m
FD_H = 1e-3  # [s] central-difference step
FD_RTOL = 2e-3  # finite differences vs analytic derivatives (relative to the signal scale)

# jitted entry points (eager dispatch of many small ops is slower than one compile)
eval_path_t = jax.jit(jax.vmap(pl.eval_path, in_axes=(None, 0)))
eval_path_j = jax.jit(pl.eval_path)
straight_j = jax.jit(pl.straight_path)
plan_trot_j = jax.jit(pl.footstep_plan_trot, static_argnums=3)
eos_j = jax.jit(pl.end_of_step_cps)
ini_j = jax.jit(pl.initial_cps)


def _fd_check(f, ts, h=FD_H, rtol=FD_RTOL):
    """f(ts) -> (p, v, a) arrays (n, ...); check v ~ dp/dt and a ~ dv/dt by central differences."""
    p, v, a = (np.asarray(x, np.float64) for x in f(ts))
    pp, vp, _ = (np.asarray(x, np.float64) for x in f(ts + h))
    pm, vm, _ = (np.asarray(x, np.float64) for x in f(ts - h))
    v_fd = (pp - pm) / (2 * h)
    a_fd = (vp - vm) / (2 * h)
    v_scale = max(np.abs(v).max(), 1e-3)
    a_scale = max(np.abs(a).max(), 1e-3)
    np.testing.assert_allclose(v_fd, v, atol=rtol * v_scale + 1e-4)
    np.testing.assert_allclose(a_fd, a, atol=rtol * a_scale + 1e-3)


# ----------------------------------------------------------------------------- splines


def _random_path():
    rng = np.random.default_rng(0)
    wp = rng.normal(size=(6, 3)) * 0.5
    times = np.concatenate([[0.3], 0.3 + np.cumsum(rng.uniform(0.5, 1.5, size=5))])
    v0, vf = np.array([0.1, -0.2, 0.05]), np.array([0.0, 0.3, -0.1])
    return wp, times, v0, vf, pl.cubic_path(wp, times, v0, vf)


def test_cubic_path_interpolates_and_is_c2():
    wp, times, v0, vf, path = _random_path()
    assert path.t_knots.shape == (6,) and path.coef.shape == (5, 4, 3)
    p, v, _ = eval_path_t(path, jnp.asarray(times))
    np.testing.assert_allclose(p, wp, atol=ATOL_POS)
    # clamped end velocities (just inside the range; outside v is clamped to 0)
    _, v_in, _ = eval_path_t(path, jnp.asarray([times[0] + 1e-6, times[-1] - 1e-6]))
    np.testing.assert_allclose(v_in, np.stack([v0, vf]), atol=1e-4)
    # C0, C1, C2 at interior knots: left segment at its end vs right segment at 0
    c = np.asarray(path.coef, np.float64)
    for k in range(1, 5):
        dt = times[k] - times[k - 1]
        left = pl.poly_eval(c[k - 1], dt)
        right = pl.poly_eval(c[k], 0.0)
        for lhs, rhs in zip(left, right):
            np.testing.assert_allclose(lhs, rhs, atol=1e-4)
    ts = jnp.asarray(np.linspace(times[0] + 2 * FD_H, times[-1] - 2 * FD_H, 301))
    _fd_check(lambda t: eval_path_t(path, t), ts)


def test_eval_path_clamps_outside():
    wp, times, _, _, path = _random_path()
    p, v, a = eval_path_t(path, jnp.asarray([times[0] - 1.0, times[-1] + 5.0]))
    np.testing.assert_allclose(p, wp[[0, -1]], atol=ATOL_POS)
    assert np.all(np.asarray(v) == 0.0) and np.all(np.asarray(a) == 0.0)


def test_two_knot_path_is_hermite():
    p0, p1 = np.array([0.0, 0.0, 0.5]), np.array([1.0, -2.0, 0.7])
    v0, v1 = np.array([0.2, 0.0, 0.0]), np.array([0.0, -0.1, 0.0])
    path = pl.cubic_path(np.stack([p0, p1]), [1.0, 3.0], v0, v1)
    coef = pl.cubic_hermite(p0, v0, p1, v1, 2.0)
    np.testing.assert_allclose(path.coef[0], coef, atol=1e-5)
    pe, ve, _ = pl.eval_cubic(coef, 2.0)
    np.testing.assert_allclose(pe, p1, atol=ATOL_POS)
    np.testing.assert_allclose(ve, v1, atol=1e-5)


def test_straight_path_profile():
    p_i, p_f = np.array([0.0, -0.7, 0.8]), np.array([0.3, -4.1, 0.6])
    speed, t0, ramp = 0.13, 0.5, 1.0
    path = straight_j(p_i, p_f, speed, t0, ramp)
    length = np.linalg.norm(p_f - p_i)
    t_end = t0 + length / speed + ramp
    np.testing.assert_allclose(float(pl.path_end_time(path)), t_end, rtol=1e-5)
    ts = jnp.asarray(np.linspace(0.0, t_end + 1.0, 4001))
    p, v, a = (np.asarray(x) for x in eval_path_t(path, ts))
    speed_t = np.linalg.norm(v, axis=1)
    assert speed_t.max() == pytest.approx(speed, rel=1e-4)
    cruise = (np.asarray(ts) > t0 + ramp + 0.01) & (np.asarray(ts) < t_end - ramp - 0.01)
    np.testing.assert_allclose(speed_t[cruise], speed, rtol=1e-4)
    np.testing.assert_allclose(p[0], p_i, atol=ATOL_POS)
    np.testing.assert_allclose(p[-1], p_f, atol=ATOL_POS)
    np.testing.assert_allclose(eval_path_j(path, t_end)[0], p_f, atol=ATOL_POS)
    assert np.abs(v[-1]).max() == 0.0 and np.abs(v[0]).max() == 0.0
    # velocity along the line, acceleration peak 2 speed / ramp, C2 (no jumps)
    u = (p_f - p_i) / length
    np.testing.assert_allclose(v, speed_t[:, None] * u, atol=1e-6)
    assert np.linalg.norm(a, axis=1).max() == pytest.approx(2 * speed / ramp, rel=1e-2)
    assert np.abs(np.diff(a, axis=0)).max() < 2 * (2 * speed / ramp) / (ramp / 2) * float(ts[1] - ts[0])
    _fd_check(lambda t: eval_path_t(path, t), ts[(ts > t0 + 0.01) & (ts < t_end - 0.01)])
    assert pl.max_abs_accel_z(path) == pytest.approx(2 * speed / ramp * abs(u[2]), rel=1e-4)


def test_straight_path_short_and_batched():
    """Shorter than speed * ramp: no cruise, peak speed length / ramp; jit + vmap over speeds."""
    p_i, p_f = jnp.zeros(3), jnp.array([0.0, -0.05, 0.0])
    speeds = jnp.array([0.13, 0.02, 0.04])
    build = jax.jit(jax.vmap(pl.straight_path, in_axes=(None, None, 0, None, None)))
    paths = build(p_i, p_f, speeds, 0.0, 1.0)
    assert paths.coef.shape == (3, 5, 4, 3)
    ts = jnp.linspace(0.0, 4.0, 801)
    p, v, _ = jax.vmap(lambda pa: eval_path_t(pa, ts))(paths)
    peak = np.linalg.norm(np.asarray(v), axis=-1).max(axis=1)
    np.testing.assert_allclose(peak, [0.05, 0.02, 0.04], rtol=1e-3)
    np.testing.assert_allclose(p[:, -1], np.broadcast_to(p_f, (3, 3)), atol=ATOL_POS)
    # a zero-length path stays put
    still = straight_j(p_i, p_i, 0.1, 0.0, 1.0)
    pp, vv, _ = eval_path_t(still, ts)
    assert np.all(np.isfinite(np.asarray(pp))) and np.abs(np.asarray(vv)).max() == 0.0


def test_max_abs_accel_z_and_offset():
    wp = np.array([[0, 0, 0.8], [0, -1, 0.6], [0, -2, 0.6], [0, -3, 0.8]], float)
    path = pl.cubic_path(wp, pl.waypoint_times(wp, 0.2, t0=1.0))
    ts = np.linspace(1.0, float(path.t_knots[-1]), 20001)
    az = np.asarray(eval_path_t(path, jnp.asarray(ts))[2])[:, 2]
    assert pl.max_abs_accel_z(path) == pytest.approx(np.abs(az).max(), rel=1e-3)
    assert pl.max_abs_accel_z(path) < 9.81
    off = pl.offset_path(path, jnp.array([0.0, 0.69, -0.36]))
    p0, v0, a0 = eval_path_j(path, 3.3)
    p1, v1, a1 = eval_path_j(off, 3.3)
    np.testing.assert_allclose(p1 - p0, [0.0, 0.69, -0.36], atol=ATOL_POS)
    np.testing.assert_allclose(v1, v0)
    np.testing.assert_allclose(a1, a0)


# ----------------------------------------------------------------------------- gait

GAIT_DT = 1e-3
gait_t = jax.jit(jax.vmap(pl.gait_phase, in_axes=(None, 0)))


def _intervals(mask, ts):
    """(start, end) times of the True runs of a boolean series."""
    m = np.concatenate([[False], mask, [False]]).astype(int)
    d = np.diff(m)
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(ts[s], ts[e - 1] + GAIT_DT) for s, e in zip(starts, ends)]


@pytest.mark.parametrize("params", [pl.GaitParams(), pl.GaitParams(0.05, 0.2, 0.3)])
def test_gait_trot_pattern(params):
    H = params.t_stance + params.t_swing
    ts = np.arange(0.0, params.t_start + 6 * H, GAIT_DT) + GAIT_DT / 2
    st = gait_t(params, jnp.asarray(ts))
    swing = np.asarray(st.swing)
    # only diagonal pairs swing, together
    patterns = {tuple(r) for r in swing.astype(int)}
    assert patterns <= {(0, 0, 0, 0), (1, 0, 0, 1), (0, 1, 1, 0)}
    assert not swing[ts < params.t_start + params.t_stance].any()
    np.testing.assert_array_equal(swing[:, 0], swing[:, 3])
    np.testing.assert_array_equal(swing[:, 1], swing[:, 2])
    fl, fr = _intervals(swing[:, 0], ts), _intervals(swing[:, 1], ts)
    assert len(fl) == 3 and len(fr) == 3
    assert fl[0][0] < fr[0][0]  # (FL, BR) first
    for k, (a, b) in enumerate(sorted(fl + fr)):
        assert b - a == pytest.approx(params.t_swing, abs=2 * GAIT_DT)
        assert a == pytest.approx(params.t_start + k * H + params.t_stance, abs=2 * GAIT_DT)
    # step index, time in half-cycle, swing phase
    k_expect = np.where(ts < params.t_start, -1, np.floor((ts - params.t_start) / H))
    np.testing.assert_array_equal(np.asarray(st.step_index), k_expect)
    tin = np.asarray(st.t_in_half)
    assert tin.min() >= 0.0 and tin.max() < max(H, params.t_start)
    ph = np.asarray(st.swing_phase)
    assert np.all(ph[~swing] == 0.0)
    for a, b in fl:
        sel = (ts >= a) & (ts < b)
        seg = ph[sel, 0]
        assert np.all(np.diff(seg) > 0) and seg[0] < 0.01 and seg[-1] > 0.99
        np.testing.assert_allclose(seg, (ts[sel] - a) / params.t_swing, atol=2e-3 / params.t_swing)
    # times to liftoff / touchdown agree with the observed events
    lift = {i: np.array([a for a, _ in _intervals(swing[:, i], ts)]) for i in range(4)}
    land = {i: np.array([b for _, b in _intervals(swing[:, i], ts)]) for i in range(4)}
    t_lo, t_td = np.asarray(st.t_to_liftoff), np.asarray(st.t_to_touchdown)
    for j in range(0, len(ts), 37):
        for i in range(4):
            nxt = lift[i][lift[i] > ts[j] + GAIT_DT]
            if len(nxt):
                assert ts[j] + t_lo[j, i] == pytest.approx(nxt[0], abs=2 * GAIT_DT)
            nxt = land[i][land[i] > ts[j]]
            if len(nxt):
                assert ts[j] + t_td[j, i] == pytest.approx(nxt[0], abs=2 * GAIT_DT)


def test_gait_stop_and_batched_params():
    base = pl.GaitParams()
    p_stop = base._replace(t_stop=pl.t_stop_after(base, 3))
    batched = pl.GaitParams(*(jnp.array([a, b]) for a, b in zip(base, p_stop)))
    ts = np.arange(0.0, 4.0, GAIT_DT) + GAIT_DT / 2
    st = jax.jit(jax.vmap(jax.vmap(pl.gait_phase, in_axes=(None, 0)), in_axes=(0, None)))(batched, jnp.asarray(ts))
    swing = np.asarray(st.swing)  # (2, T, 4)
    n_free = len(_intervals(swing[0, :, 0], ts)) + len(_intervals(swing[0, :, 1], ts))
    assert n_free == int((4.0 - base.t_start) // (base.t_stance + base.t_swing))
    lifts = sorted(_intervals(swing[1, :, 0], ts) + _intervals(swing[1, :, 1], ts))
    assert len(lifts) == 3 and lifts[-1][1] <= p_stop.t_stop + GAIT_DT
    after = ts > p_stop.t_stop
    assert not swing[1, after].any() and not np.asarray(st.stepping)[1, after].any()
    assert np.all(np.isinf(np.asarray(st.t_to_liftoff)[1, after]))
    assert np.all(np.isinf(np.asarray(st.t_to_touchdown)[1, after]))
    assert np.isfinite(np.asarray(st.t_to_liftoff)[0]).all()


# ----------------------------------------------------------------------------- swing


@pytest.mark.parametrize("kind", ["cubic", "quintic"])
def test_swing_reference(kind):
    p_lift = np.array([0.1, -0.5, 0.0])
    p_land = np.array([0.12, -0.7, 0.035])  # onto a 3.5 cm block
    T, h = 0.115, 0.06
    f = jax.jit(jax.vmap(lambda tt: pl.swing_reference(p_lift, p_land, tt / T, T, h, kind=kind)))
    p, v, a = f(jnp.asarray([0.0, 0.5 * T, T]))
    np.testing.assert_allclose(p[0], p_lift, atol=ATOL_POS)
    np.testing.assert_allclose(p[2], p_land, atol=ATOL_POS)
    assert p[1, 2] == pytest.approx(0.035 + h, abs=ATOL_POS)
    assert np.abs(np.asarray(v)[[0, 2]]).max() < 1e-5 and abs(float(v[1, 2])) < 1e-5
    ts = np.linspace(2 * FD_H * T, T - 2 * FD_H * T, 201)
    ts = ts[np.abs(ts - 0.5 * T) > 3 * FD_H * T]  # the cubic's vertical acceleration jumps at the apex
    _fd_check(lambda tt: f(jnp.asarray(tt)), ts, h=FD_H * T)
    z = np.asarray(f(jnp.asarray(np.linspace(0, T, 501)))[0])[:, 2]
    assert z.max() <= 0.035 + h + 1e-6 and z.min() >= -1e-6


def test_quintic_and_raibert():
    p0, p1 = np.zeros((2, 3)), np.arange(6.0).reshape(2, 3)
    q = jax.jit(jax.vmap(lambda tt: pl.quintic(p0, p1, 0.4, tt)))
    p, v, a = q(jnp.array([0.0, 0.4, -1.0, 2.0]))
    assert p.shape == (4, 2, 3)
    np.testing.assert_allclose(p, np.stack([p0, p1, p0, p1]), atol=1e-5)
    np.testing.assert_allclose(v, 0.0, atol=1e-5)
    np.testing.assert_allclose(a, 0.0, atol=1e-4)
    _fd_check(q, np.linspace(0.01, 0.39, 50), h=1e-4)
    foot = pl.raibert_foothold([0.2, -0.3], [0.0, -0.2], [0.0, -0.13], 0.415, k_v=0.2, t_to_touchdown=0.05)
    np.testing.assert_allclose(foot, [0.2, -0.3 - 0.13 * (0.05 + 0.2075) - 0.2 * 0.07], atol=1e-6)


# ----------------------------------------------------------------------------- ZMP / support

SQUARE = np.array([[0.2, 0.3], [-0.2, 0.3], [0.2, -0.3], [-0.2, -0.3]])  # FL FR BL BR
ALL = np.ones(4, bool)
margin_j = jax.jit(pl.support_margin)
clamp_j = jax.jit(pl.clamp_to_support)


def _seg_dist(q, a, b):
    d = b - a
    s = np.clip(np.dot(q - a, d) / max(np.dot(d, d), 1e-300), 0.0, 1.0)
    return np.linalg.norm(a + s * d - q)


def _margin_ref(q, feet, stance):
    """Independent reference: scipy ConvexHull (or segment/point distance without area)."""
    pts = feet[stance]
    if len(pts) == 0:
        return -np.inf
    dist = min(_seg_dist(q, a, b) for a in pts for b in pts)
    e = pts[1:] - pts[0]
    area2 = np.abs(e[:, None, 0] * e[None, :, 1] - e[:, None, 1] * e[None, :, 0]).max(initial=0.0)
    if len(pts) >= 3 and area2 > 1e-9:
        eq = ConvexHull(pts).equations  # n . x + c <= 0 inside, unit outward n
        s = eq[:, :2] @ q + eq[:, 2]
        if np.all(s <= 0):
            return float(-s.max())
    return -dist


def test_support_margin_by_hand():
    cases = [
        ([0.0, 0.0], ALL, 0.2),
        ([0.15, 0.0], ALL, 0.05),
        ([0.5, 0.0], ALL, -0.3),
        ([0.5, 0.6], ALL, -np.hypot(0.3, 0.3)),
        # triangle FL, FR, BL: hypotenuse from FR (-0.2, 0.3) to BL (0.2, -0.3)
        ([0.1, 0.1], np.array([1, 1, 1, 0], bool), min(0.1, 0.2, abs(0.6 * 0.1 + 0.4 * 0.1) / np.hypot(0.6, 0.4))),
        # trot diagonal (FL, BR): on the segment -> 0; off it -> minus the distance
        ([0.0, 0.0], np.array([1, 0, 0, 1], bool), 0.0),
        ([0.1, 0.0], np.array([1, 0, 0, 1], bool), -0.1 * 0.6 / np.hypot(0.4, 0.6)),
        ([0.5, 0.3], np.array([1, 0, 0, 0], bool), -0.3),
    ]
    for q, st, ref in cases:
        assert float(margin_j(jnp.asarray(q), SQUARE, st)) == pytest.approx(ref, abs=1e-6)
    assert float(margin_j(jnp.zeros(2), SQUARE, np.zeros(4, bool))) == -np.inf
    # collinear three feet: segment behaviour
    line = np.array([[0.0, 0.0], [0.1, 0.0], [0.3, 0.0], [5.0, 5.0]])
    st = np.array([1, 1, 1, 0], bool)
    assert float(margin_j(jnp.array([0.2, 0.05]), line, st)) == pytest.approx(-0.05, abs=1e-6)
    assert float(margin_j(jnp.array([0.4, 0.0]), line, st)) == pytest.approx(-0.1, abs=1e-6)
    # one foot inside the triangle of the other three: the hull is the triangle
    tri = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.2, 0.2]])
    assert float(margin_j(jnp.array([0.1, 0.3]), tri, ALL)) == pytest.approx(0.1, abs=1e-6)


def test_support_margin_random_vs_convex_hull():
    rng = np.random.default_rng(1)
    feet = rng.uniform(-0.4, 0.4, size=(200, 4, 2))
    stance = rng.uniform(size=(200, 4)) < 0.75
    q = rng.uniform(-0.5, 0.5, size=(200, 2))
    got = np.asarray(jax.jit(jax.vmap(pl.support_margin))(q, feet, stance))
    ref = np.array([_margin_ref(q[i], feet[i], stance[i]) for i in range(200)])
    fin = np.isfinite(ref)
    np.testing.assert_allclose(got[fin], ref[fin], atol=1e-5)
    assert np.all(np.isneginf(got[~fin]))


def test_clamp_to_support():
    # inside: unchanged; outside the square: projection; with a margin: onto the shrunk square
    np.testing.assert_allclose(clamp_j(jnp.array([0.05, -0.1]), SQUARE, ALL, 0.0), [0.05, -0.1], atol=1e-6)
    np.testing.assert_allclose(clamp_j(jnp.array([0.5, 0.1]), SQUARE, ALL, 0.0), [0.2, 0.1], atol=1e-6)
    np.testing.assert_allclose(clamp_j(jnp.array([0.5, 0.9]), SQUARE, ALL, 0.05), [0.15, 0.25], atol=1e-6)
    np.testing.assert_allclose(clamp_j(jnp.array([0.18, 0.0]), SQUARE, ALL, 0.05), [0.15, 0.0], atol=1e-6)
    # margin larger than the square allows: centroid
    np.testing.assert_allclose(clamp_j(jnp.array([0.5, 0.9]), SQUARE, ALL, 0.3), [0.0, 0.0], atol=1e-6)
    # diagonal pair: closest point of the segment shortened by the margin at both ends
    diag = np.array([1, 0, 0, 1], bool)
    np.testing.assert_allclose(clamp_j(jnp.array([0.1, 0.0]), SQUARE, diag, 0.0),
                               [0.1 * 0.16 / 0.52, 0.1 * 0.24 / 0.52], atol=1e-6)
    end = SQUARE[0] + 0.05 * (SQUARE[3] - SQUARE[0]) / np.linalg.norm(SQUARE[3] - SQUARE[0])
    np.testing.assert_allclose(clamp_j(jnp.array([0.5, 0.5]), SQUARE, diag, 0.05), end, atol=1e-6)
    np.testing.assert_allclose(clamp_j(jnp.array([0.5, 0.5]), SQUARE, np.array([0, 0, 1, 0], bool), 0.05),
                               SQUARE[2], atol=1e-6)
    # far from the world origin (float32): same answers as near it
    shift = np.array([0.3, -4.1])
    np.testing.assert_allclose(clamp_j(jnp.array([0.5, 0.9]) + shift, SQUARE + shift, ALL, 0.05),
                               np.array([0.15, 0.25]) + shift, atol=1e-6)
    np.testing.assert_allclose(clamp_j(jnp.array([0.5, 0.1]) + shift, SQUARE + shift, ALL, 0.0),
                               np.array([0.2, 0.1]) + shift, atol=1e-6)
    assert float(margin_j(jnp.array([0.15, 0.0]) + shift, SQUARE + shift, ALL)) == pytest.approx(0.05, abs=1e-6)
    # random polygons: result inside the shrunk region and no farther than any grid point in it
    rng = np.random.default_rng(2)
    grid = np.stack(np.meshgrid(np.linspace(-0.6, 0.6, 121), np.linspace(-0.6, 0.6, 121)), -1).reshape(-1, 2)
    gm = jax.jit(jax.vmap(pl.support_margin, in_axes=(0, None, None)))
    for _ in range(6):
        feet = rng.uniform(-0.4, 0.4, size=(4, 2))
        q = rng.uniform(-0.6, 0.6, size=2)
        m = 0.02
        c = np.asarray(clamp_j(jnp.asarray(q), feet, ALL, m))
        ok = np.asarray(gm(jnp.asarray(grid), feet, ALL)) >= m
        if not ok.any():
            continue
        assert float(margin_j(jnp.asarray(c), feet, ALL)) >= m - 1e-5
        assert np.linalg.norm(c - q) <= np.linalg.norm(grid[ok] - q, axis=1).min() + 1e-5


def test_zmp_and_com_segment():
    zmp = jax.jit(pl.zmp_xy)
    np.testing.assert_allclose(zmp(jnp.array([0.1, 0.2, 0.45]), jnp.zeros(3)), [0.1, 0.2], atol=1e-7)
    z = zmp(jnp.array([0.0, 0.0, 0.5]), jnp.array([1.0, -2.0, 0.19]), 9.81, 0.05)
    np.testing.assert_allclose(z, [-0.45 / 10.0, 0.9 / 10.0], atol=1e-6)

    @jax.jit
    def plan(y1):
        p0 = jnp.array([0.0, 0.0, 0.45])
        coef = pl.cubic_hermite(p0, jnp.zeros(3), p0.at[1].set(y1), jnp.zeros(3), 0.265)
        zmps = jax.vmap(lambda tt: pl.zmp_xy(*pl.eval_cubic(coef, tt)[::2]))(jnp.linspace(0.0, 0.265, 16))
        return pl.min_zmp_margin(coef, 0.265, SQUARE, ALL), zmps

    m_still, _ = plan(0.0)
    assert float(m_still) == pytest.approx(0.2, abs=1e-6)
    m_move, zmps = plan(-0.04)
    ref = min(_margin_ref(zz, SQUARE, ALL) for zz in np.asarray(zmps, np.float64))
    assert float(m_move) == pytest.approx(ref, abs=1e-5)
    assert zmps[0, 1] > 0.0  # accelerating towards -y pushes the ZMP towards +y
    # replanning: the goal is pulled onto the stance diagonal (FL, BR), velocity kept
    diag = np.array([1, 0, 0, 1], bool)
    goal, v_goal = jnp.array([0.05, -0.04, 0.45]), jnp.array([0.0, -0.13, 0.0])
    coef, m = jax.jit(pl.replan_com)(jnp.array([0.0, 0.0, 0.45]), jnp.zeros(3), goal, v_goal, 0.265, SQUARE, diag)
    p_end, v_end, _ = pl.eval_cubic(np.asarray(coef), 0.265)
    assert abs(_margin_ref(np.asarray(p_end[:2], np.float64), SQUARE, diag)) < 1e-6
    np.testing.assert_allclose(p_end[:2], np.asarray(clamp_j(goal[:2], SQUARE, diag, 0.0)), atol=1e-6)
    np.testing.assert_allclose(v_end, v_goal, atol=1e-5)
    assert float(m) <= 0.0


PREVIEW_ZMP_TOL = 0.005  # [m] replanned ZMP off its support line: an order below the object-following 37.5 mm
PREVIEW_C2_ATOL = 1e-9  # [m, m/s, m/s^2] float64 continuity at the phase boundaries


def _synthetic_trot(n_step=12, ts=0.15, tw=0.115, v=0.13, lead=0.04, h=0.45, n_s=8):
    """A straight trot along -y at v: feet on a 0.38 x 0.6 m rectangle around the desired CoM at each foot's
    mid-stance, the desired CoM ``lead`` ahead of the feet's centre (the arm's and object's share), the ZMP of
    each two-foot phase asked on the stance diagonal; ends with two four-foot footsteps at rest."""
    H = ts + tw
    n = n_step + 2
    T = np.tile([ts, tw], n)
    t0 = np.repeat(H * np.arange(n), 2) + np.tile([0.0, ts], n)
    tau = [(np.arange(n_s) + 0.5) / n_s * Ti for Ti in T]
    t_end = n_step * H

    def c_des(t):  # (.., 2) desired CoM: constant speed, then at rest
        y = -v * np.minimum(t, t_end)
        return np.stack([np.zeros_like(y), y], -1)

    nominal = np.array([[0.19, -0.3], [-0.19, -0.3], [0.19, 0.3], [-0.19, 0.3]]) + [0.0, lead]  # FL FR BL BR
    feet = c_des(np.zeros(1))[0] + nominal
    line_n, line_c, two = np.zeros((2 * n, 2)), np.zeros(2 * n), np.zeros(2 * n, bool)
    stance = []
    for k in range(n):
        if 1 <= k <= n_step:  # the pair that swung in k - 1 lands around the CoM of its mid-stance
            pair = list(pl.PAIRS[(k - 1) % 2])
            feet[pair] = c_des(np.array(k * H + 0.5 * (2 * ts + tw)))[None] + nominal[pair]
        if k < n_step:
            a, b = feet[list(pl.PAIRS[(k + 1) % 2])]
            d = (b - a) / np.linalg.norm(b - a)
            line_n[2 * k + 1], two[2 * k + 1] = (-d[1], d[0]), True
            line_c[2 * k + 1] = line_n[2 * k + 1] @ a
        stance.append(feet.copy())
    args = (np.zeros((3, 2)), T, [c_des(t0[i] + tau[i]) for i in range(2 * n)],
            [np.full(n_s, h / 9.81)] * (2 * n), line_n, line_c, two, tau)
    x_end = np.stack([c_des(np.array(t_end)), np.zeros(2), np.zeros(2)])
    return args, x_end, stance, h / 9.81


def _zmp_off_lines(coef, T, kz, stance, two, n_eval=30):
    """Largest distance of the ZMP (c - kz c'', evaluated by hand) from the stance diagonal's segment (the
    independent hull reference), over the two-foot phases."""
    worst = 0.0
    for i in np.flatnonzero(two):
        c = coef[i]
        mask = np.zeros(4, bool)
        mask[list(pl.PAIRS[(i // 2 + 1) % 2])] = True
        for tt in np.linspace(0.0, T[i], n_eval):
            p = c[0] + tt * c[1] + tt**2 * c[2] + tt**3 * c[3]
            zmp = p - kz * (2.0 * c[2] + 6.0 * tt * c[3])
            worst = max(worst, -_margin_ref(zmp, stance[i // 2], mask))
    return worst


def test_preview_com_xy_puts_the_zmp_on_the_support_line():
    """pl.preview_com_xy on a synthetic trot whose desired CoM leads the feet by 4 cm (its ZMP is then ~25-40 mm
    off every diagonal): the replanned CoM's ZMP, evaluated by hand from the returned cubics, stays within
    PREVIEW_ZMP_TOL of the stance pair's segment (scipy-free segment distance of the hull reference); without the
    ZMP term (w_zmp = 0) it does not. The cubics join with continuous position, velocity and acceleration and end
    at x_end."""
    args, x_end, stance, kz = _synthetic_trot()
    T, two = args[1], args[6]
    coef = pl.preview_com_xy(*args, x_end=x_end)
    assert _zmp_off_lines(coef, T, kz, stance, two) < PREVIEW_ZMP_TOL
    free = pl.preview_com_xy(*args, w_zmp=0.0, x_end=x_end)
    assert _zmp_off_lines(free, T, kz, stance, two) > 4 * PREVIEW_ZMP_TOL
    for i in range(len(T) - 1):  # C2 joins
        c, Ti = coef[i], T[i]
        end = [c[0] + Ti * c[1] + Ti**2 * c[2] + Ti**3 * c[3], c[1] + 2 * Ti * c[2] + 3 * Ti**2 * c[3],
               2 * c[2] + 6 * Ti * c[3]]
        np.testing.assert_allclose(end, [coef[i + 1, 0], coef[i + 1, 1], 2 * coef[i + 1, 2]], atol=PREVIEW_C2_ATOL)
    c, Ti = coef[-1], T[-1]
    np.testing.assert_allclose([c[0] + Ti * c[1] + Ti**2 * c[2] + Ti**3 * c[3], c[1] + 2 * Ti * c[2] + 3 * Ti**2 * c[3],
                                2 * c[2] + 6 * Ti * c[3]], x_end, atol=1e-7)


def test_pad_path_keeps_the_path():
    """pad_path appends zero-length segments: the same values everywhere (at the last knot itself the position;
    velocity and acceleration read the rest state there, as eval_path gives them after the end)."""
    path = pl.cubic_path(np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.05], [0.3, -0.1, 0.0]]), np.array([0.0, 0.4, 1.0]))
    padded = pl.pad_path(path, 7)
    assert padded.t_knots.shape == (7,) and padded.coef.shape == (6, 4, 3)
    for t in (-0.1, 0.0, 0.2, 0.4, 0.77, 0.999, 1.5):
        for a, b in zip(pl.eval_path(path, t), pl.eval_path(padded, t)):
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=ATOL_POS)
    np.testing.assert_allclose(np.asarray(pl.eval_path(padded, 1.0)[0]), [0.3, -0.1, 0.0], atol=ATOL_POS)
    with pytest.raises(ValueError, match="pad_path"):
        pl.pad_path(path, 2)


# ----------------------------------------------------------------------------- capture point


def test_cp_recursion_closed_form_constant_stride():
    """Uniform steps P_i = i s ending at rest: xi_eos[i] - P_i = s (1 - b^(N-1-i)) / (1 - b)."""
    w = float(pl.omega(0.43))
    assert w == pytest.approx(np.sqrt(9.81 / 0.43), rel=1e-6)
    N, s, T = 12, 0.1, 0.25
    P = np.stack([np.arange(N) * s, np.zeros(N)], 1)
    eos = np.asarray(eos_j(P, T, w, P[-1]))
    b = np.exp(-w * T)
    ref = s * (1 - b ** (N - 1 - np.arange(N))) / (1 - b)
    np.testing.assert_allclose(eos[:, 0] - P[:, 0], ref, atol=1e-5)
    np.testing.assert_allclose(eos[:, 1], 0.0, atol=1e-7)
    ini = np.asarray(ini_j(P, eos, T, w))
    np.testing.assert_allclose(ini[1:], eos[:-1], atol=1e-5)


def test_cp_forward_simulation_reaches_end_of_step_cps():
    """Integrate the LIPM x'' = w^2 (x - P) (float64 RK4) from a CoM whose CP is xi_ini[0]."""
    w = float(pl.omega(0.45))
    rng = np.random.default_rng(3)
    N = 7
    T = rng.uniform(0.2, 0.3, size=N)
    P = np.cumsum(rng.uniform(-0.05, 0.12, size=(N, 2)), axis=0)
    eos = np.asarray(eos_j(P, T, w, P[-1] + np.array([0.01, -0.02])), np.float64)
    ini = np.asarray(ini_j(P, eos, T, w), np.float64)
    x = np.array([0.03, -0.02])
    xd = w * (ini[0] - x)  # so that x + xd / w = xi_ini[0]
    n_sub = 400
    for i in range(N):
        h = T[i] / n_sub

        def f(state, Pi=P[i]):
            return np.concatenate([state[2:], w**2 * (state[:2] - Pi)])

        y = np.concatenate([x, xd])
        for _ in range(n_sub):
            k1 = f(y)
            k2 = f(y + 0.5 * h * k1)
            k3 = f(y + 0.5 * h * k2)
            k4 = f(y + h * k3)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        x, xd = y[:2], y[2:]
        np.testing.assert_allclose(np.asarray(pl.cp(x, xd, w)), eos[i], atol=2e-5)
    # eq. (21) inside a step and eq. (19) consistency
    xi_mid = pl.cp_trajectory(P[2], ini[2], 0.5 * T[2], w)
    np.testing.assert_allclose(xi_mid, P[2] + np.exp(w * 0.5 * T[2]) * (ini[2] - P[2]), atol=1e-5)
    np.testing.assert_allclose(pl.desired_com_velocity(x, eos[-1], w), -w * (x - eos[-1]), atol=1e-6)


def test_cp_reference_and_trot_plan():
    params = pl.GaitParams(t_stance=0.05, t_swing=0.2, t_start=0.5)
    T = params.t_stance + params.t_swing
    feet0 = np.array([[0.19, -0.29], [-0.19, -0.29], [0.19, 0.29], [-0.19, 0.29]])  # facing -y
    N, stride = 10, 0.1
    plan = plan_trot_j(feet0, -np.pi / 2, stride, N)
    P, feet = np.asarray(plan.P), np.asarray(plan.feet)
    np.testing.assert_allclose(P[:, 0], 0.0, atol=1e-6)
    np.testing.assert_allclose(P[:, 1], -stride * np.arange(N), atol=1e-6)
    moved = np.linalg.norm(np.diff(feet, axis=0), axis=-1)  # (N, 4)
    np.testing.assert_allclose(moved[0], [stride, 0, 0, stride], atol=1e-6)
    np.testing.assert_allclose(moved[3], [0, 2 * stride, 2 * stride, 0], atol=1e-6)
    np.testing.assert_allclose(moved[-1].max(), stride, atol=1e-6)
    np.testing.assert_allclose(feet[-1] - feet0, np.broadcast_to([0.0, -(N - 1) * stride], (4, 2)), atol=1e-6)
    np.testing.assert_allclose(plan.xi_final, P[-1], atol=1e-6)

    w = float(pl.omega(0.43))
    eos = eos_j(plan.P, T, w, plan.xi_final)
    P0 = jax.jit(pl.first_footstep_for_rest)(jnp.zeros(2), eos[0], T, w)
    P_rest = plan.P.at[0].set(P0)
    np.testing.assert_allclose(ini_j(P_rest, eos, T, w)[0], [0.0, 0.0], atol=1e-6)

    ref = jax.jit(jax.vmap(pl.cp_reference, in_axes=(None, None, 0, None, None, None)))
    ts = np.linspace(0.0, params.t_start + N * T + 0.5, 2001)
    r = ref(P_rest, eos, jnp.asarray(ts), params.t_start, T, w)
    xi = np.asarray(r.xi)
    assert np.abs(xi[ts <= params.t_start]).max() < 1e-6  # starts at the resting CoM
    np.testing.assert_allclose(xi[-1], plan.xi_final, atol=1e-5)
    assert np.abs(np.diff(xi, axis=0)).max() < 0.01  # continuous across steps
    step_ends = params.t_start + T * np.arange(1, N + 1)
    r_end = ref(P_rest, eos, jnp.asarray(step_ends - 1e-5), params.t_start, T, w)
    np.testing.assert_allclose(r_end.xi, eos, atol=1e-4)
    # the gait's step index matches the CP step inside the walk
    st = gait_t(params, jnp.asarray(ts))
    walking = (ts > params.t_start) & (ts < step_ends[-1])
    np.testing.assert_array_equal(np.asarray(st.step_index)[walking], np.asarray(r.step)[walking])
    mid = walking & (np.abs(((ts - params.t_start) % T) - T / 2) < T / 4)
    xd_fd = np.gradient(xi[:, 1], ts)
    np.testing.assert_allclose(xd_fd[mid], np.asarray(r.xi_dot)[mid, 1], atol=0.01)
    # vmap over strides (batched plans) through the whole chain
    def chain(s):
        pln = pl.footstep_plan_trot(feet0, -np.pi / 2, s, N)
        return pl.end_of_step_cps(pln.P, T, w, pln.xi_final)

    eos_b = jax.jit(jax.vmap(chain))(jnp.array([0.05, 0.1]))
    np.testing.assert_allclose(eos_b[1], eos, atol=1e-6)
    np.testing.assert_allclose(eos_b[0], 0.5 * np.asarray(eos), atol=1e-6)


def test_apf_band_newton_is_the_minimiser():
    """plan_dip's Newton solve (issue: it replaced L-BFGS-B, 6-20 s per plan) on the course's wall: the band's
    analytic gradient and Hessian against central differences of its energy, the result a stationary point (interior
    gradient at float64 rounding) that random interior moves do not improve, and the same minimiser as scipy's
    L-BFGS-B (an independent method) on a 1.2 m stretch through the wall."""
    from scipy.optimize import minimize

    from wbc_jax.planner.apf import band, plan_dip
    from wbc_jax.planner.scene_geometry import scene_geometry
    from wbc_jax.robot.model import Robot

    obstacles = scene_geometry(Robot("transport")).obstacles
    wall_y = float(np.mean(obstacles[:, :, 1]))
    p_i = np.array([0.0, wall_y + 0.6, 0.81])
    p_f = p_i + [0.0, -1.2, 0.0]
    top = 0.04
    b = band(p_i, p_f, obstacles, top)
    rng = np.random.default_rng(3)
    z = b.z_nom - 0.1 * np.exp(-((b.s - 0.6) / 0.2) ** 2) + 1e-3 * rng.normal(size=b.s.shape)  # a rough dip
    U, g, H = b.energy(z)
    h = 1e-6
    for i in rng.choice(np.arange(1, len(z) - 1), 8, replace=False):
        e = np.zeros_like(z)
        e[i] = h
        (Up, gp, _), (Um, gm, _) = b.energy(z + e), b.energy(z - e)
        assert (Up - Um) / (2 * h) == pytest.approx(g[i], rel=1e-5, abs=1e-9)
        np.testing.assert_allclose((gp - gm) / (2 * h), H[:, i], rtol=1e-5, atol=1e-7)
    dip = plan_dip(p_i, p_f, obstacles, top)
    U0, g0, _ = b.energy(dip.z)
    assert np.max(np.abs(g0[1:-1])) <= 1e-11
    for _ in range(5):
        d = np.zeros_like(dip.z)
        d[1:-1] = 1e-4 * rng.normal(size=len(d) - 2)
        assert b.energy(dip.z + d)[0] > U0
    bounds = [(b.z_nom[0], b.z_nom[0])] + [(None, None)] * (len(z) - 2) + [(b.z_nom[-1], b.z_nom[-1])]
    ref = minimize(lambda z: b.energy(z)[:2], b.z_nom.copy(), jac=True, method="L-BFGS-B", bounds=bounds,
                   options=dict(maxiter=20000, maxfun=40000, ftol=1e-15, gtol=1e-12))
    assert dip.z.min() < b.z_nom[0] - 0.1  # the band dips under the lintel ...
    np.testing.assert_allclose(dip.z, ref.x, atol=2e-6)  # ... to L-BFGS-B's minimiser (it stops within ~1 um)
