"""Piecewise cubic paths in R^3 (object and CoM references of the transport paper).

A path is a :class:`CubicPath`: knot times ``t_knots (K,)`` and, per segment ``k``, the
power-basis coefficients of ``p(t) = c0 + c1 tau + c2 tau^2 + c3 tau^3`` in the local time
``tau = t - t_knots[k]``. Local time keeps float32 accurate on long runs (absolute times of
tens of seconds, segments of a few seconds).

Construction happens once at setup (:func:`cubic_path` uses scipy in float64); evaluation
(:func:`eval_path`) is pure ``jax.numpy``: jit-able with a traced ``t`` and vmap-able over
``t`` and over batched paths (every leaf with a leading batch axis, same ``K``).

Also here, because several planner modules share them: :func:`cubic_hermite` /
:func:`eval_cubic` (one cubic segment from end positions and velocities) and
:func:`poly_eval` (power-basis evaluation with derivatives).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from scipy.interpolate import CubicSpline

from wbc_jax.runtime.transfer import to_device

_EPS_LEN = 1e-9  # [m] paths shorter than this are treated as a point


class CubicPath(NamedTuple):
    """Piecewise cubic path in R^3.

    Attributes:
        t_knots: (K,) knot times [s], strictly increasing except that a zero-length
            segment is tolerated (it is never selected by :func:`eval_path`).
        coef: (K-1, 4, 3) power-basis coefficients; ``coef[k, j]`` multiplies
            ``(t - t_knots[k])**j`` on segment ``k`` [m / s^j].
    """

    t_knots: jnp.ndarray
    coef: jnp.ndarray


# ----------------------------------------------------------------------------- basics


def poly_eval(coef, tau):
    """Evaluate a cubic in power basis and its first two derivatives.

    Args:
        coef: (4, ...) coefficients, ``coef[j]`` multiplies ``tau**j``.
        tau: () local time [s].

    Returns:
        (p, v, a): each of shape ``coef.shape[1:]``; value, d/dtau, d^2/dtau^2.
    """
    c0, c1, c2, c3 = coef[0], coef[1], coef[2], coef[3]
    p = c0 + tau * (c1 + tau * (c2 + tau * c3))
    v = c1 + tau * (2.0 * c2 + 3.0 * tau * c3)
    a = 2.0 * c2 + 6.0 * tau * c3
    return p, v, a


def cubic_hermite(p0, v0, p1, v1, T):
    """Cubic segment from (p0, v0) at tau = 0 to (p1, v1) at tau = T.

    Args:
        p0: (D,) start position [m].
        v0: (D,) start velocity [m/s].
        p1: (D,) end position [m].
        v1: (D,) end velocity [m/s].
        T: () duration [s], > 0.

    Returns:
        coef: (4, D) power-basis coefficients for :func:`eval_cubic`.
    """
    dtype = jnp.result_type(float)
    p0, v0, p1, v1, T = (jnp.asarray(x, dtype=dtype) for x in (p0, v0, p1, v1, T))
    dp = p1 - p0
    c2 = (3.0 * dp - (2.0 * v0 + v1) * T) / T**2
    c3 = (-2.0 * dp + (v0 + v1) * T) / T**3
    return jnp.stack(jnp.broadcast_arrays(p0, v0, c2, c3))


def eval_cubic(coef, tau):
    """Evaluate a cubic segment (no clamping of ``tau``).

    Args:
        coef: (4, D) coefficients from :func:`cubic_hermite`.
        tau: () time since the segment start [s].

    Returns:
        (p, v, a): each (D,) [m], [m/s], [m/s^2].
    """
    return poly_eval(coef, tau)


# ----------------------------------------------------------------------------- paths


def cubic_path(waypoints, times, v0=None, vf=None) -> CubicPath:
    """Clamped C2 cubic spline through waypoints (setup time, numpy/scipy).

    Args:
        waypoints: (K, 3) positions [m], K >= 2.
        times: (K,) strictly increasing knot times [s].
        v0: (3,) velocity at ``times[0]`` [m/s]; default zero.
        vf: (3,) velocity at ``times[-1]`` [m/s]; default zero.

    Returns:
        CubicPath with ``t_knots = times`` and C2 continuity at interior knots.
    """
    w = np.asarray(waypoints, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 3 or w.shape[0] < 2 or t.shape != (w.shape[0],):
        raise ValueError(f"waypoints must be (K>=2, 3) and times (K,); got {w.shape}, {t.shape}")
    if np.any(np.diff(t) <= 0):
        raise ValueError("times must be strictly increasing")
    v0 = np.zeros(3) if v0 is None else np.asarray(v0, dtype=np.float64)
    vf = np.zeros(3) if vf is None else np.asarray(vf, dtype=np.float64)
    spline = CubicSpline(t, w, bc_type=((1, v0), (1, vf)))
    # scipy: c[m, k] multiplies (t - x_k)**(3 - m)
    coef = np.transpose(spline.c[::-1], (1, 0, 2))  # (K-1, 4, 3)
    return CubicPath(to_device(t), to_device(coef))


def waypoint_times(waypoints, speed, t0=0.0):
    """Knot times proportional to the polyline length between waypoints (setup helper).

    Args:
        waypoints: (K, 3) positions [m].
        speed: mean speed [m/s], > 0.
        t0: time of the first waypoint [s].

    Returns:
        (K,) numpy array of knot times [s] (a zero-length step gets 1e-3 s).
    """
    w = np.asarray(waypoints, dtype=np.float64)
    seg = np.maximum(np.linalg.norm(np.diff(w, axis=0), axis=1) / float(speed), 1e-3)
    return float(t0) + np.concatenate([[0.0], np.cumsum(seg)])


def straight_path(p_i, p_f, speed, t0=0.0, ramp=1.0) -> CubicPath:
    """Rest-to-rest straight path with a C2 trapezoid-like speed profile.

    The speed rises from 0 to ``speed`` over ``ramp`` seconds with a triangular
    acceleration pulse (two cubic segments of ``ramp / 2``; acceleration 0 at both ends,
    peak ``2 speed / ramp``), cruises, and falls back to 0 symmetrically at ``p_f``.
    Distance covered by each ramp: ``speed * ramp / 2``. When the path is shorter than
    ``speed * ramp``, the cruise vanishes and the peak speed drops to ``length / ramp``.
    Six knots always (the cruise segment may have zero length), so this is traceable:
    jit- and vmap-able over every argument.

    Args:
        p_i: (3,) start position [m].
        p_f: (3,) end position [m].
        speed: cruise speed [m/s], > 0.
        t0: start time [s]; the path is at rest at ``p_i`` before it.
        ramp: duration of the acceleration (and of the deceleration) [s], > 0.

    Returns:
        CubicPath with K = 6; end time ``t0 + 2 ramp + cruise``, cruise =
        ``max(length / speed - ramp, 0)`` [s].
    """
    p_i = jnp.asarray(p_i, dtype=jnp.result_type(float))
    p_f = jnp.asarray(p_f, dtype=p_i.dtype)
    speed, t0, ramp = (jnp.asarray(x, dtype=p_i.dtype) for x in (speed, t0, ramp))
    d = p_f - p_i
    length = jnp.linalg.norm(d)
    u = d / jnp.maximum(length, _EPS_LEN)  # (3,) unit direction (zero for a point)
    vmax = jnp.minimum(speed, length / ramp)
    cruise = jnp.maximum(length / jnp.maximum(vmax, 1e-12) - ramp, 0.0)
    cruise = jnp.where(length > _EPS_LEN, cruise, 0.0)
    h = 0.5 * ramp
    j = 2.0 * vmax / ramp / h  # [m/s^3] jerk magnitude of the ramps
    # 1D profile s(t): segments (s0, v0, a0, jerk), each s = s0 + v0 tau + a0/2 tau^2 + j/6 tau^3
    s_ramp = vmax * ramp / 2.0
    s1 = j * h**3 / 6.0  # end of first half ramp (= s_ramp / 2)
    v1 = 0.5 * j * h**2  # = vmax / 2
    a1 = j * h
    zero = jnp.zeros_like(length)
    # per segment: start s [m], start speed [m/s], start accel [m/s^2], jerk [m/s^3]
    s0 = jnp.stack([zero, s1, s_ramp, s_ramp + vmax * cruise, length - s1])
    sd0 = jnp.stack([zero, v1, vmax, vmax, v1])
    sdd0 = jnp.stack([zero, a1, zero, zero, -a1])
    jerk = jnp.stack([j, -j, zero, -j, j])
    coef1d = jnp.stack([s0, sd0, 0.5 * sdd0, jerk / 6.0], axis=1)  # (5, 4)
    coef = coef1d[:, :, None] * u  # (5, 4, 3)
    coef = coef.at[:, 0, :].add(p_i)
    t_knots = t0 + jnp.stack([zero, h, ramp, ramp + cruise, ramp + cruise + h, 2.0 * ramp + cruise])
    return CubicPath(t_knots, coef)


def eval_path(path: CubicPath, t):
    """Evaluate a path at time ``t`` (clamped outside the knot range).

    Args:
        path: CubicPath (K knots). Leaves may carry a leading batch axis under vmap.
        t: () time [s] (may be traced).

    Returns:
        (p, v, a): each (3,) position [m], velocity [m/s], acceleration [m/s^2]. Before
        the first knot: the start position with v = a = 0; after the last: the end
        position with v = a = 0.
    """
    tk = path.t_knots
    t = jnp.asarray(t, dtype=path.coef.dtype)
    tc = jnp.clip(t, tk[0], tk[-1])
    k = jnp.sum(tc >= tk[1:-1]).astype(jnp.int32)  # segment index in 0..K-2
    p, v, a = poly_eval(path.coef[k], tc - tk[k])
    inside = (t >= tk[0]) & (t <= tk[-1])
    return p, jnp.where(inside, v, 0.0), jnp.where(inside, a, 0.0)


def offset_path(path: CubicPath, offset) -> CubicPath:
    """The path shifted by a constant offset (e.g. CoM reference = object path + offset).

    Args:
        path: CubicPath.
        offset: (3,) constant offset [m].

    Returns:
        CubicPath with ``p(t) + offset`` and the same velocities and accelerations.
    """
    return CubicPath(path.t_knots, path.coef.at[..., 0, :].add(jnp.asarray(offset)))


def pad_path(path: CubicPath, n_knots: int) -> CubicPath:
    """The same path with ``n_knots`` knots (host-side): zero-length segments at the end, holding the end point
    at rest (what :func:`eval_path` returns after the last knot anyway), so that paths of different lengths stack.

    Args:
        path: CubicPath (unbatched) with K <= n_knots knots.
        n_knots: knot count of the result.
    """
    tk, coef = np.asarray(path.t_knots), np.asarray(path.coef)
    extra = int(n_knots) - len(tk)
    if extra < 0:
        raise ValueError(f"pad_path: the path has {len(tk)} knots, more than {n_knots}")
    T = tk[-1] - tk[-2]
    end = coef[-1, 0] + T * (coef[-1, 1] + T * (coef[-1, 2] + T * coef[-1, 3]))
    rest = np.zeros((extra,) + coef.shape[1:], coef.dtype)
    rest[:, 0] = end
    return CubicPath(to_device(np.append(tk, np.full(extra, tk[-1]))), to_device(np.concatenate([coef, rest])))


def path_end_time(path: CubicPath):
    """Time of the last knot [s] (scalar; traceable)."""
    return path.t_knots[-1]


def max_abs_accel_z(path: CubicPath, n: int = 2048) -> float:
    """Largest |vertical acceleration| of a path [m/s^2] (numpy, setup-time check).

    Samples ``n`` times uniformly over each segment plus both ends of every segment. The
    acceleration of a cubic is linear in time, so the segment ends alone already give the
    exact maximum; the dense samples are a cross-check. Used for the transport paper's
    condition that the object's desired z-acceleration stays below g.

    Args:
        path: CubicPath (unbatched).
        n: samples per segment.

    Returns:
        max |a_z| over the path [m/s^2] (python float).
    """
    tk = np.asarray(path.t_knots, dtype=np.float64)
    c = np.asarray(path.coef, dtype=np.float64)[:, :, 2]  # (K-1, 4) z coefficients
    dt = np.diff(tk)[:, None]  # (K-1, 1)
    tau = dt * np.linspace(0.0, 1.0, max(int(n), 2))[None, :]  # (K-1, n), includes both ends
    az = 2.0 * c[:, 2:3] + 6.0 * c[:, 3:4] * tau
    return float(np.max(np.abs(az)))
