"""Build everything one batched rollout needs from factor values.

:func:`prepare_batch` returns the batched MJX model and its in_axes, per-run initial states,
plans, object models, gains, pushes and ground friction, each with a leading run axis B; the plans and gains are
those of the Sim's controller (:mod:`wbc_jax.rollout.controllers`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.planner.scene_geometry import scene_geometry
from wbc_jax.robot import scenario
from wbc_jax.rollout import runs
from wbc_jax.rollout.config import Sim
from wbc_jax.rollout.state import Push, RunState, init_state, no_push, state_axes
from wbc_jax.rollout.state import with_contact_list as state_contacts
from wbc_jax.runtime import aot
from wbc_jax.runtime.static import axes_key
from wbc_jax.runtime.transfer import to_device
from wbc_jax.types import ObjectModel


class Batch(NamedTuple):
    """Everything one batched rollout takes, each per-run field with a leading run axis B."""

    model: object  # batched mjx.Model
    in_axes: object  # the model's run axes (0 per run, None shared)
    state: RunState
    plan: object  # the controller's plan of each run (the transport's: wbc_jax.planner.transport.TransportPlan)
    om: ObjectModel  # the object model of each run
    gains: object  # the controller's parameters of each run (the transport's: TransportGains)
    push: Push
    mu_ground: jax.Array
    factors: scenario.Factors
    state_axes: object = 0  # the state's run axes (wbc_jax.rollout.state.state_axes: Warp's contact list is shared)


def chunk_args(b: Batch) -> tuple:
    """The arguments of a chunk program (``wbc_jax.campaign.build.chunk_fn``) for batch ``b``, in its order."""
    return (b.model, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground)


def take_runs(b: Batch, rows, state=None, gains=None) -> Batch:
    """The runs ``rows`` (indices into ``b``) of every per-run field of ``b`` (:func:`wbc_jax.rollout.runs.take`, the
    model and the state with their run axes; shared leaves stay whole). ``state``, ``gains``: already selected
    replacements for those fields (e.g. runs continued from earlier states, candidate gains) instead of ``b``'s
    rows."""
    return b._replace(model=runs.take(b.model, rows, b.in_axes),
                      state=runs.take(b.state, rows, b.state_axes) if state is None else state,
                      plan=runs.take(b.plan, rows), om=runs.take(b.om, rows),
                      gains=runs.take(b.gains, rows) if gains is None else gains, push=runs.take(b.push, rows),
                      mu_ground=runs.take(b.mu_ground, rows), factors=runs.take(b.factors, rows))

def with_contact_list(b: Batch, n_runs: int | None = None) -> Batch:
    """``b`` with Warp's shared contact list sized for ``n_runs`` runs (None: ``b``'s own), ``state_axes`` with it
    (:func:`wbc_jax.rollout.state.with_contact_list`): for runs taken from another batch (a block of a larger batch,
    or sub-batches larger than the batch they are taken from)."""
    n = int(np.shape(b.mu_ground)[0]) if n_runs is None else n_runs
    state, axes = state_contacts(b.state, b.state_axes, n)
    return b._replace(state=state, state_axes=axes)

# Setup arithmetic is done in numpy and each leaf is placed on the device once (runtime.transfer.to_device): eager
# jnp operations would each compile a small program (hundreds per campaign, seconds of a warm start).


def stack(trees, index=None):
    """Leafwise stack of pytrees along a new leading axis, optionally gathered with ``index`` (host arithmetic)."""
    def one(*xs):
        x = np.stack([np.asarray(v) for v in xs])
        return to_device(x if index is None else x[index])

    return jax.tree_util.tree_map(one, *trees)


def broadcast(tree, B: int):
    """Every leaf repeated along a new leading axis of size B (host arithmetic, one transfer per leaf)."""
    return jax.tree_util.tree_map(lambda x: to_device(np.broadcast_to(np.asarray(x), (B,) + np.shape(x))), tree)


_INIT_FNS: dict = {}


def _init_fn(sim: Sim, in_axes, n_runs: int):
    """jit(vmap(init_state)) over (model, qpos0, qvel0), one per Sim (by value) and batched-model layout (one
    compile; on the Warp backend also one per batch size, which sizes its shared contact list)."""
    n = n_runs if sim.robot.backend == "warp" else 1
    key = (sim, axes_key(in_axes), n)
    if key not in _INIT_FNS:
        fn = jax.vmap(functools.partial(init_state, sim, n_runs=n), in_axes=(in_axes, 0, 0))
        _INIT_FNS[key] = aot.cached_jit("init", fn, aot.describe(sim, in_axes, n), exportable=sim.exportable)
    return _INIT_FNS[key]


def initial_states(sim: Sim, model, in_axes, qpos0, qvel0, shapes_only: bool = False) -> RunState:
    """The runs' initial states (``init_state`` of each run, batched): ``model`` the batched model (run axes
    ``in_axes``), ``qpos0``, ``qvel0`` (B, nq), (B, nv). ``shapes_only``: their shapes and dtypes
    (``jax.ShapeDtypeStruct`` leaves, ``jax.eval_shape``: nothing runs, MuJoCo Warp's kernels are not called), the
    same program traced once for both."""
    fn = _init_fn(sim, in_axes, int(np.shape(qpos0)[0]))
    args = (model, to_device(qpos0, float), to_device(qvel0, float))
    return jax.eval_shape(fn, *args) if shapes_only else fn(*args)


def prepare_batch(sim: Sim, m, mu, d, gains=None, push: Push | None = None,
                  plan_kwargs: dict | None = None, qpos0=None, qvel0=None, speed=None, ground_mu=None,
                  ramp=None, shapes_only: bool = False) -> Batch:
    """Validated factors (each (B,) or scalar) -> a ready Batch.

    Args:
        sim: static rollout structure; m, mu, d: object mass [kg], tray friction, object side [m].
        gains: per-run gains with leading axis B, or unbatched (broadcast), default gains if None.
        push: per-run or unbatched Push (none if None).
        plan_kwargs: keyword arguments of the controller's planner (``Controller.make_plan``; the transport's:
            :func:`wbc_jax.planner.transport.course_plan` when the scene has obstacles or terrain (blocks, a wall),
            else :func:`~wbc_jax.planner.transport.straight_plan`).
        qpos0, qvel0: (B, nq), (B, nv) initial configurations and velocities; None: the home pose of each run's
            object side, at rest.
        speed: (B,) cruise speed of each run's plan [m/s] instead of ``plan_kwargs``' (None: that one).
        ground_mu: (B,) foot/ground friction of each run, in the physics and the controller (None: the scene's).
        ramp: (B,) duration of each run's speed ramps [s] (the planner's ``ramp``) instead of ``plan_kwargs``'.
        shapes_only: the state holds the initial states' shapes only (:func:`initial_states`), for a program
            compiled before they exist; the caller makes them with the same ``qpos0``, ``qvel0``.
    """
    robot, controller = sim.robot, sim.controller
    f = scenario.validate_factors(robot.ids, m, mu, d)
    B = f.m.shape[0]
    bm, in_axes = scenario.batch_model(robot.mjx_model, robot.mj_model, robot.ids, f, ground_mu)
    kw = plan_kwargs or {}
    course = scene_geometry(robot).is_course
    # start pose and plan depend on the run only through d (carried height), the speed and the ramp: each once
    per_run = {k: np.broadcast_to(v, f.d.shape) for k, v in (("speed", speed), ("ramp", ramp)) if v is not None}
    keys = np.stack([f.d, *per_run.values()], axis=1)
    levels, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    q_levels = [robot.home_qpos(key[0]) for key in levels]
    if qpos0 is None:
        qpos0 = np.stack(q_levels)[inverse]
    if qvel0 is None:
        qvel0 = np.zeros((B, robot.mj_model.nv))
    kws = [dict(kw, **{k: float(v) for k, v in zip(per_run, key[1:])}) for key in levels]
    unique = [controller.make_plan(robot, course, q, dict(k, side=float(key[0])) if course else k)
              for q, key, k in zip(q_levels, levels, kws)]
    plans = stack(controller.align_plans(unique), index=inverse)
    state = initial_states(sim, bm, in_axes, qpos0, qvel0, shapes_only)
    obj_model = ObjectModel(mass=to_device(f.m), side=to_device(f.d), mu=to_device(f.mu),
                            inset=to_device(np.full(B, robot.ids.obj_sphere_radius)))
    gains = controller.default_gains() if gains is None else gains
    if not controller.batched(gains):
        gains = broadcast(gains, B)
    push = no_push() if push is None else push
    if jnp.ndim(push.t0) == 0:
        push = broadcast(push, B)
    if ground_mu is None:
        # the scene's value as a strong-typed array like a ground_mu factor's (to_device: float32, or float64 under
        # x64): a weak-typed jnp.full made batches with and without that factor compile separate programs
        mu_ground = to_device(np.full(B, float(robot.mj_model.pair_friction[robot.ids.foot_pair[0, 0], 0])))
    else:
        mu_ground = to_device(np.broadcast_to(np.asarray(ground_mu, float), (B,)))
    return Batch(bm, in_axes, state, plans, obj_model, gains, push, mu_ground, f, state_axes(sim, state))
