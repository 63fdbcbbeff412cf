"""Exact clearance between the robot's non-foot geoms and the scene's static geoms, from the geoms' world
poses (``d.geom_xpos``, ``d.geom_xmat``, which both MJX backends fill) and the model's sizes.

MJX's contact slots do not give a separated pair's distance (the JAX backend's capsule-box collider reports its
candidate points', a pair beyond the margin reads 1 m, and Warp lists penetrations only); the distances here
are the same on both backends and exact when positive: each pair's is its kind's signed distance in
:mod:`wbc_jax.physics.distance`.

Which pairs (:func:`clearance_pairs`): every robot geom (not a foot, not the carried object) that the scene pairs
with the floor or the terrain, against the floor and every terrain block; and every robot geom that the scene pairs
with a wall part, against every wall part. A pair the scene does not list (e.g. a thigh against a block) is
measured too, at no physics cost (the clearance is not a contact). Sizes are the scene's (static); poses are per
run. Other geom types raise :class:`wbc_jax.errors.SceneError` when the pairs are built.

Broad phase (:func:`bounded_min_clearance`, which :func:`min_clearance` uses): capsule/box and box/box pairs first
get a cheap lower bound of their distance (the robot geom's extent along the scene box's axes); only the few with
the smallest bounds (:data:`CANDIDATES`, a fixed count, so shapes stay static) get the exact distance. The minimum is
the exact one whenever it lies below the smallest bound left out, which the call returns.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.errors import SceneError
from wbc_jax.physics import distance

_PLANE, _SPHERE, _CAPSULE, _BOX = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_SPHERE),
                                   int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_BOX))
_ROBOT_TYPES = {_SPHERE: "sphere", _CAPSULE: "capsule", _BOX: "box"}
_ENV_TYPES = {_PLANE: "plane", _BOX: "box"}
KINDS = ("capsule_plane", "capsule_box", "sphere_plane", "sphere_box", "box_plane", "box_box")  # pair order


@dataclass(frozen=True, eq=False)
class ClearancePairs:
    """The measured pairs of a scene, in :data:`KINDS` order (a pair's index is its position here).

    Attributes:
        robot, env: (n,) geom ids of each pair's robot geom and scene geom.
        kind: (n,) index into :data:`KINDS`.
        size: (n, 3) the robot geom's size (capsule: radius, half-length; sphere: radius; box: half-sizes).
        env_size: (n, 3) the scene geom's size (box: half-sizes; plane: unused).
    """

    robot: np.ndarray
    env: np.ndarray
    kind: np.ndarray
    size: np.ndarray
    env_size: np.ndarray

    def __len__(self) -> int:
        return int(self.robot.size)


_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def clearance_pairs(robot) -> ClearancePairs:
    """The pairs measured for ``robot``'s scene (module docstring; computed once per Robot)."""
    if robot not in _CACHE:
        _CACHE[robot] = _build_pairs(robot.mj_model, robot.ids)
    return _CACHE[robot]


def _build_pairs(m: mujoco.MjModel, ids) -> ClearancePairs:
    g1, g2 = np.asarray(m.pair_geom1), np.asarray(m.pair_geom2)
    fp = np.asarray(ids.foot_pair, int).ravel()
    ground = np.unique(np.concatenate([[ids.floor_geom], np.where(np.isin(g1[fp], ids.foot_geom), g2[fp], g1[fp])]))
    wall = np.array([i for i in range(m.ngeom) if (m.geom(i).name or "").startswith("wall")], int)

    def robot_side(pairs, env):
        p = np.asarray(pairs, int)
        r = np.where(np.isin(g1[p], env), g2[p], g1[p])
        keep = ~np.isin(r, ids.foot_geom) & (m.geom_bodyid[r] != ids.obj_body) & (m.geom_bodyid[r] != 0)
        return np.unique(r[keep])

    cand = [(r, e) for r in robot_side(ids.nonfoot_floor_pair, ground) for e in ground]
    cand += [(r, e) for r in robot_side(ids.wall_pair, wall) for e in wall]
    rows = []
    for r, e in cand:
        tr, te = int(m.geom_type[r]), int(m.geom_type[e])
        if tr not in _ROBOT_TYPES or te not in _ENV_TYPES:
            raise SceneError(f"clearance: geom pair {m.geom(int(r)).name!r} ({tr}) / {m.geom(int(e)).name!r} ({te}): "
                             "robot geoms must be capsules, spheres or boxes, scene geoms planes or boxes")
        rows.append((KINDS.index(f"{_ROBOT_TYPES[tr]}_{_ENV_TYPES[te]}"), int(r), int(e)))
    rows.sort(key=lambda x: x[0])  # stable: pairs keep their order within a kind
    k = np.array([x[0] for x in rows], int).reshape(-1)
    r = np.array([x[1] for x in rows], int).reshape(-1)
    e = np.array([x[2] for x in rows], int).reshape(-1)
    return ClearancePairs(robot=r, env=e, kind=k, size=np.asarray(m.geom_size[r], float).reshape(-1, 3),
                          env_size=np.asarray(m.geom_size[e], float).reshape(-1, 3))


def _kind_inputs(pairs: ClearancePairs, d, sel):
    """The primitives' arguments for pairs ``sel`` (indices of one kind): robot geom pose and size, scene geom pose
    and size, each with the pairs on axis 0."""
    r, e = pairs.robot[sel], pairs.env[sel]
    dt = d.geom_xpos.dtype
    return (d.geom_xpos[r], d.geom_xmat[r].reshape(-1, 3, 3), jnp.asarray(pairs.size[sel], dt), d.geom_xpos[e],
            d.geom_xmat[e].reshape(-1, 3, 3), jnp.asarray(pairs.env_size[sel], dt))


def pair_distances(pairs: ClearancePairs, d) -> jax.Array:
    """(len(pairs),) signed distance [m] of each pair at the geom poses of ``d`` (one run; vmap for a batch)."""
    out = []
    for k, name in enumerate(KINDS):
        sel = np.where(pairs.kind == k)[0]
        if sel.size:
            out.append(distance.over_pairs(distance.PRIMITIVES[name], _kind_inputs(pairs, d, sel)))
    if not out:
        return jnp.zeros((0,))
    return jnp.concatenate(out)


# ---------------------------------------------------------------------------------------------------------------
# broad phase

CANDIDATES = {"capsule_box": 8, "box_box": 3}
"""Pairs of each bounded kind whose exact distance is computed at every pose: those with the smallest bounds."""
BOUND_ROUNDING = 1e-5  # [m] taken off the reported bound: a float32 bound can exceed the exact distance by rounding


class Clearance(NamedTuple):
    """The smallest clearance over a scene's pairs at one pose (:func:`bounded_min_clearance`)."""

    distance: jax.Array  # () [m] the smallest exact distance over the candidate pairs (+inf: no pairs)
    pair: jax.Array  # () int32 its pair index (-1: none or not finite)
    bound: jax.Array  # () [m] every pair left out is at least this far (+inf: none left out)


def bounded_min_clearance(pairs: ClearancePairs, d) -> Clearance:
    """The smallest signed distance over ``pairs`` at the geom poses of ``d`` (one run), with a broad phase.

    Planes and spheres are exact for every pair; of each kind in :data:`CANDIDATES` only that many pairs, those with
    the smallest lower bounds (:func:`capsule_box_bound`, :func:`box_box_bound`), get their exact distance. The
    distance equals the minimum of :func:`pair_distances` (same value, same pair, ties to the lowest index) whenever
    it is below ``bound``, the smallest bound of a pair left out; otherwise it is the exact distance of a pair and at
    least that minimum. Non-finite poses give NaN and -1 as the exact minimum does."""
    dist, index, bounds, bad = [], [], [], jnp.bool_(False)
    for k, name in enumerate(KINDS):
        sel = np.where(pairs.kind == k)[0]
        if sel.size == 0:
            continue
        args, idx = _kind_inputs(pairs, d, sel), jnp.asarray(sel, jnp.int32)
        n_exact = CANDIDATES.get(name, sel.size)
        if n_exact < sel.size:
            lower = distance.over_pairs(distance.BOUNDS[name], args)
            neg, pick = jax.lax.top_k(-lower, n_exact + 1)
            bounds.append(-neg[n_exact])
            bad = bad | jnp.any(jnp.isnan(lower))
            args, idx = tuple(a[pick[:n_exact]] for a in args), idx[pick[:n_exact]]
        dist.append(distance.over_pairs(distance.PRIMITIVES[name], args))
        index.append(idx)
    if not dist:
        return Clearance(jnp.full((), jnp.inf), jnp.full((), -1, jnp.int32), jnp.full((), jnp.inf))
    dist, index = jnp.concatenate(dist), jnp.concatenate(index)
    best = jnp.where(bad, jnp.nan, jnp.min(dist))
    k = jnp.min(jnp.where(dist == best, index, len(pairs)))
    bound = jnp.min(jnp.stack(bounds)) - BOUND_ROUNDING if bounds else jnp.full((), jnp.inf, best.dtype)
    return Clearance(best, jnp.where(jnp.isfinite(best), k, -1).astype(jnp.int32), bound)


def min_clearance(pairs: ClearancePairs, d):
    """(() smallest signed distance [m] over ``pairs`` (+inf: no pairs), () int32 its pair index (-1: none or
    not finite)), by :func:`bounded_min_clearance`: exact below its bound."""
    out = bounded_min_clearance(pairs, d)
    return out.distance, out.pair
