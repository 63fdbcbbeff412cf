"""Object path over the scene's obstacles by artificial potentials (transport paper, Sec. IV-B).

The object moves along the straight line from ``p_i`` to ``p_f`` in the horizontal plane; its height
is shaped by an artificial potential. The path is discretised into N nodes at fixed horizontal
positions (spacing ``ds``) with free heights ``z_k`` (an elastic band in the sense of Quinlan and
Khatib), and the potential

    U(z) = k_att / 2 sum_k (z_k - z_nom)^2 ds                     attraction to the nominal height
         + sum_k sum_o  U_rep(rho_k,o) ds                            repulsion from each obstacle o
         + k_str / 2 sum_k ((z_k+1 - z_k) / ds)^2 ds                 tension
         + k_bend / 2 sum_k ((z_k+1 - 2 z_k + z_k-1) / ds^2)^2 ds     bending

is minimised by Newton's method (:func:`band` gives the energy, its gradient and its Hessian): the energy is strictly
convex (every term is convex in z, the attraction strictly), the Hessian pentadiagonal, each step a banded solve with
backtracking, until the Newton decrement reaches float64's rounding: about 10 steps, where a quasi-Newton method
takes thousands of iterations for the same minimiser. ``rho_k,o`` is the vertical clearance between the top of
what is carried (object centre + ``top``) and the underside of an obstacle whose footprint overlaps
the carried footprint at node k, minus ``margin``;
``U_rep = eta / 2 (1/rho - 1/rho0)^2`` for ``0 < rho < rho0`` (Khatib's FIRAS potential), continued
quadratically below ``rho_min`` so that the initial straight band (which cuts through the lintel)
has a finite energy and a downward gradient. Obstacles whose footprint never overlaps the carried
one (the wall's pillars, for a path through the gap) exert no force.

Waypoints are the band subsampled every ``waypoint_spacing``; :func:`wbc_jax.planner.transport.course_plan`
fits the cubic splines through them and checks the clearance and the vertical acceleration.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.linalg import solveh_banded


class APFParams(NamedTuple):
    """Potential parameters (units: heights in m).

    Attributes:
        ds: node spacing along the path [m].
        k_att: attraction to the nominal height [1/m^2 (energy units per m^2)].
        eta: repulsion gain; rho0: influence distance [m]; rho_min: start of the quadratic continuation [m].
        k_str, k_bend: tension and bending weights of the band [k_att m^2, k_att m^4]: the dip's ramps
            decay over sqrt(k_str / k_att) = 0.15 m; k_str^2 > 4 k_bend k_att keeps them monotonic
            (no overshoot above the nominal height).
        margin: clearance kept between the carried top and an obstacle's underside [m].
        footprint: horizontal half-size of the carried load (tray) [m].
        waypoint_spacing: spacing of the returned waypoints along the path [m].
    """

    ds: float = 0.01
    k_att: float = 1.0
    eta: float = 2e-5
    rho0: float = 0.10
    rho_min: float = 0.01
    k_str: float = 0.0225
    k_bend: float = 1e-4
    margin: float = 0.03
    footprint: float = 0.10
    waypoint_spacing: float = 0.10


class DipPath(NamedTuple):
    """Result: s (N,) arc length [m], z (N,) band heights of the object centre [m], waypoints (K, 3),
    clearance (N,) vertical clearance of the carried top under the obstacles [m] (inf where none)."""

    s: np.ndarray
    z: np.ndarray
    waypoints: np.ndarray
    clearance: np.ndarray


def _rep(rho, p: APFParams):
    """FIRAS repulsion and its first and second derivatives in rho, continued quadratically below rho_min."""
    r = np.maximum(rho, p.rho_min)
    inv = 1.0 / r - 1.0 / p.rho0
    U = np.where(rho < p.rho0, 0.5 * p.eta * inv**2, 0.0)
    dU = np.where(rho < p.rho0, -p.eta * inv / r**2, 0.0)
    d2U = np.where(rho < p.rho0, p.eta * (3.0 / r - 2.0 / p.rho0) / r**3, 0.0)
    # below rho_min: U(rho_min) + dU(rho_min) (rho - rho_min) + (curvature) (rho - rho_min)^2 / 2
    c = 2.0 * p.eta / p.rho_min**4
    low = rho < p.rho_min
    dr = rho - p.rho_min
    U = np.where(low, U + dU * dr + 0.5 * c * dr**2, U)
    dU = np.where(low, dU + c * dr, dU)
    d2U = np.where(low, c, d2U)
    return U, dU, d2U


def _newton(energy, z0: np.ndarray, max_iter: int = 200) -> np.ndarray:
    """Minimiser of a strictly convex ``energy(z) -> (U, g, H)`` (H pentadiagonal) over z's interior (both end points
    fixed at ``z0``'s), by Newton steps with backtracking (Armijo), until a full step no longer lowers the energy or
    the Newton decrement reaches float64's rounding."""
    z = z0.copy()
    U, g, H = energy(z)
    for _ in range(max_iter):
        gi = g[1:-1]
        step = np.zeros_like(z)
        Hi = H[1:-1, 1:-1]  # pentadiagonal: solved in LAPACK's banded form (lower)
        band = np.zeros((3, Hi.shape[0]))
        for k in range(3):
            band[k, :Hi.shape[0] - k] = np.diagonal(Hi, -k)
        step[1:-1] = -solveh_banded(band, gi, lower=True)
        dec = -gi @ step[1:-1]  # Newton decrement squared
        if dec <= 1e-28 * max(abs(U), 1e-300):
            break
        t = 1.0
        while True:
            Un, gn, Hn = energy(z + t * step)
            if Un <= U - 0.25 * t * dec or t < 1e-12:
                break
            t *= 0.5
        if t < 1e-12 or Un >= U:  # rounding: no decrease left
            break
        z, U, g, H = z + t * step, Un, gn, Hn
    return z


def overhead(obstacles: np.ndarray, xy: np.ndarray, footprint: float) -> np.ndarray:
    """(N, no) underside height of each obstacle above each path point, inf where the footprints do
    not overlap. obstacles (no, 2, 3), xy (N, 2)."""
    if obstacles.shape[0] == 0:
        return np.full((xy.shape[0], 0), np.inf)
    lo, hi = obstacles[:, 0], obstacles[:, 1]
    ov = ((xy[:, None, 0] + footprint > lo[None, :, 0]) & (xy[:, None, 0] - footprint < hi[None, :, 0])
          & (xy[:, None, 1] + footprint > lo[None, :, 1]) & (xy[:, None, 1] - footprint < hi[None, :, 1]))
    return np.where(ov, lo[None, :, 2], np.inf)


class Band(NamedTuple):
    """The discretised path of :func:`plan_dip`: s (N,) arc length [m], xy (N, 2) horizontal positions [m], z_nom
    (N,) nominal heights [m], under (N, no) obstacle undersides above each node [m] (inf: none), and
    ``energy(z) -> (U, gradient (N,), Hessian (N, N))`` of the potential (module docstring)."""

    s: np.ndarray
    xy: np.ndarray
    z_nom: np.ndarray
    under: np.ndarray
    energy: object


def band(p_i, p_f, obstacles, top: float, params: APFParams = APFParams()) -> Band:
    """The elastic band from p_i to p_f and its potential (arguments as :func:`plan_dip`)."""
    p_i, p_f = np.asarray(p_i, float), np.asarray(p_f, float)
    L = float(np.linalg.norm((p_f - p_i)[:2]))
    n = max(int(np.ceil(L / params.ds)), 2) + 1
    s = np.linspace(0.0, L, n)
    ds = s[1] - s[0]
    u = (p_f - p_i)[:2] / max(L, 1e-12)
    xy = p_i[:2] + s[:, None] * u
    z_nom = p_i[2] + (p_f[2] - p_i[2]) * s / max(L, 1e-12)
    under = overhead(np.asarray(obstacles, float), xy, params.footprint)  # (N, no)
    has = np.isfinite(under)
    under_f = np.where(has, under, 0.0)
    I = np.eye(n)
    D1 = np.diff(I, axis=0) / ds  # (n - 1, n) first differences
    D2 = np.diff(I, 2, axis=0) / ds**2  # (n - 2, n) second differences
    H_quad = params.k_att * ds * I + params.k_str * ds * D1.T @ D1 + params.k_bend * ds * D2.T @ D2

    def energy(z):
        e = z - z_nom
        d1, d2 = D1 @ z, D2 @ z
        rho = under_f - (z[:, None] + top) - params.margin
        Ur, dUr, d2Ur = _rep(rho, params)
        U = 0.5 * ds * (params.k_att * e @ e + params.k_str * d1 @ d1 + params.k_bend * d2 @ d2)
        U += ds * np.sum(np.where(has, Ur, 0.0))
        g = ds * (params.k_att * e + params.k_str * D1.T @ d1 + params.k_bend * D2.T @ d2)
        g -= ds * np.sum(np.where(has, dUr, 0.0), axis=1)
        H = H_quad + np.diag(ds * np.sum(np.where(has, d2Ur, 0.0), axis=1))
        return U, g, H

    return Band(s, xy, z_nom, under, energy)


def plan_dip(p_i, p_f, obstacles, top: float, params: APFParams = APFParams()) -> DipPath:
    """Heights of the object centre along the straight horizontal path p_i -> p_f.

    Args:
        p_i, p_f: (3,) start and goal [m] (the nominal height is p_i's z; p_f's z is the goal height).
        obstacles: (no, 2, 3) obstacle boxes (see :mod:`wbc_jax.planner.scene_geometry`).
        top: height of the carried top above the object centre [m] (d / 2 for a cube of side d).
        params: APFParams.
    """
    b = band(p_i, p_f, obstacles, top, params)
    s, xy, n = b.s, b.xy, b.s.shape[0]
    ds = s[1] - s[0]
    z = _newton(b.energy, b.z_nom.copy())  # end points pinned at the start and goal heights
    clearance = np.min(b.under - (z[:, None] + top), axis=1) if b.under.size else np.full(n, np.inf)  # inf: none
    k = max(int(round(params.waypoint_spacing / ds)), 1)
    idx = np.unique(np.concatenate([np.arange(0, n, k), [n - 1]]))
    wp = np.concatenate([xy[idx], z[idx, None]], axis=1)
    return DipPath(s=s, z=z, waypoints=wp, clearance=clearance)
