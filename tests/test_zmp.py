"""Planner numerics of the ZMP side: support-polygon margin and clamping, the cart-table ZMP, the per-footstep CoM
replanning (preview).

References: hand computations, scipy's ConvexHull, float64 continuity checks.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from wbc_jax import planner as pl

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
