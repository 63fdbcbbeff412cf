"""Planner numerics: splines, trot scheduler, swing references, the APF band (the ZMP side: test_zmp.py; the
capture point: test_capture_point.py).

References: finite differences, hand computations, scipy's L-BFGS-B on the band energy.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax import planner as pl

ATOL_POS = 2e-5  # [m] float32 positions of order 1 m
FD_H = 1e-3  # [s] central-difference step
FD_RTOL = 2e-3  # finite differences vs analytic derivatives (relative to the signal scale)

# jitted entry points (eager dispatch of many small ops is slower than one compile)
eval_path_t = jax.jit(jax.vmap(pl.eval_path, in_axes=(None, 0)))
eval_path_j = jax.jit(pl.eval_path)
straight_j = jax.jit(pl.straight_path)


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


def test_apf_band_newton_is_the_minimiser():
    """plan_dip's Newton solve on the course's wall: the band's
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
