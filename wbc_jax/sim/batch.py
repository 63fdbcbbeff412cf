"""Build everything one batched transport rollout needs from factor values.

:func:`prepare_batch` returns the batched MJX model and its in_axes, per-run initial states,
plans, object models, gains, pushes and ground friction, each with a leading run axis B.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.sim import aot, scenario
from wbc_jax.control.transport import ObjectModel, TransportGains, default_gains
from wbc_jax.planner.scene_geometry import scene_geometry
from wbc_jax.planner.transport import TransportPlan, course_plan, straight_plan
from wbc_jax.sim.rollout import Push, RunState, Sim, init_state, no_push


class Batch(NamedTuple):
    model: object  # batched mjx.Model
    in_axes: object
    state: RunState
    plan: TransportPlan
    om: ObjectModel
    gains: TransportGains
    push: Push
    mu_ground: jax.Array
    factors: scenario.Factors


# Setup arithmetic is done in numpy and each leaf is placed on the device once: eager jnp operations would each
# compile a small program (hundreds per campaign, seconds of a warm start).


def _device(x):
    """One host -> device transfer of a numpy leaf (dtype as jnp.asarray gives it)."""
    return jnp.asarray(np.asarray(x))


def stack(trees, index=None):
    """Leafwise stack of pytrees along a new leading axis, optionally gathered with ``index`` (host arithmetic)."""
    def one(*xs):
        x = np.stack([np.asarray(v) for v in xs])
        return _device(x if index is None else x[index])

    return jax.tree_util.tree_map(one, *trees)


def broadcast(tree, B: int):
    """Every leaf repeated along a new leading axis of size B (host arithmetic, one transfer per leaf)."""
    return jax.tree_util.tree_map(lambda x: _device(np.broadcast_to(np.asarray(x), (B,) + np.shape(x))), tree)


_INIT_FNS: dict = {}


def _init_fn(sim: Sim, in_axes, n_runs: int):
    """jit(vmap(init_state)) over (model, qpos0, qvel0), one per Sim and batched-model layout (one compile; on
    the Warp backend also one per batch size, which sizes its shared contact list)."""
    n = n_runs if sim.robot.backend == "warp" else 1
    key = (id(sim), str(in_axes), n)
    if key not in _INIT_FNS:
        fn = jax.vmap(functools.partial(init_state, sim, n_runs=n), in_axes=(in_axes, 0, 0))
        _INIT_FNS[key] = aot.cached_jit("init", fn, aot.describe(sim, in_axes, n),
                                        exportable=sim.robot.backend != "warp")
    return _INIT_FNS[key]


def prepare_batch(sim: Sim, m, mu, d, gains: TransportGains | None = None, push: Push | None = None,
                  plan_kwargs: dict | None = None, qpos0=None, qvel0=None) -> Batch:
    """Validated factors (each (B,) or scalar) -> a ready Batch.

    Args:
        sim: static rollout structure; m, mu, d: object mass [kg], tray friction, object side [m].
        gains: per-run gains with leading axis B, or unbatched (broadcast), default gains if None.
        push: per-run or unbatched Push (none if None).
        plan_kwargs: keyword arguments of the planner: :func:`wbc_jax.planner.transport.course_plan` when
            the scene has obstacles or terrain (blocks, a wall), else :func:`~wbc_jax.planner.transport.straight_plan`.
        qpos0, qvel0: (B, nq), (B, nv) initial configurations and velocities; None: the home pose of each run's
            object side, at rest.
    """
    robot = sim.robot
    f = scenario.validate_factors(robot.ids, m, mu, d)
    B = f.m.shape[0]
    bm, in_axes = scenario.batch_model(robot.mjx_model, robot.mj_model, robot.ids, f)
    kw = plan_kwargs or {}
    course = scene_geometry(robot).is_course
    # start pose and plan depend on the run only through d (carried height): compute each level once
    levels, inverse = np.unique(f.d, return_inverse=True)
    q_levels = [robot.home_qpos(di) for di in levels]
    if qpos0 is None:
        qpos0 = np.stack(q_levels)[inverse]
    if qvel0 is None:
        qvel0 = np.zeros((B, robot.mj_model.nv))
    unique = [course_plan(robot, q, side=float(di), **kw) if course else straight_plan(robot, q, **kw)
              for q, di in zip(q_levels, levels)]
    plans = stack(unique, index=inverse)
    state = _init_fn(sim, in_axes, B)(bm, jnp.asarray(qpos0, float), jnp.asarray(qvel0, float))
    om = ObjectModel(mass=jnp.asarray(f.m), side=jnp.asarray(f.d), mu=jnp.asarray(f.mu),
                     inset=jnp.full(B, robot.ids.obj_sphere_radius))
    gains = default_gains() if gains is None else gains
    if jnp.ndim(gains.kp_obj) == 0:
        gains = broadcast(gains, B)
    push = no_push() if push is None else push
    if jnp.ndim(push.t0) == 0:
        push = broadcast(push, B)
    mu_ground = jnp.full(B, float(robot.mj_model.pair_friction[robot.ids.foot_pair[0, 0], 0]))
    return Batch(bm, in_axes, state, plans, om, gains, push, mu_ground, f)
