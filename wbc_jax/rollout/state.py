"""The rollout's per-run data: disturbances (:class:`Push`), carried state (:class:`RunState`), the log."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import numpy as np

from wbc_jax.control.variants import Variant
from wbc_jax.metrics.accumulate import init_accum
from wbc_jax.physics import backend as physics
from wbc_jax.physics.observe import dyn_terms
from wbc_jax.robot.model import mjx
from wbc_jax.rollout.config import Sim
from wbc_jax.rollout.controllers.base import object_in_tray
from wbc_jax.rollout.controllers.transport import Log
from wbc_jax.rollout.packed import Packed, broadcast_like, pack
from wbc_jax.runtime.transfer import to_device

__all__ = ["Log", "Push", "RunState", "empty_log", "init_state", "make_push", "no_push", "object_in_tray",
           "state_axes", "with_metric_window", "with_plugin_params", "with_variant"]


class Push(NamedTuple):
    """Per-run disturbances: an external force on the trunk and noise on the state the controller sees.

    Attributes:
        force: (3,) world-frame force on the trunk [N], applied for t in [t0, t0 + duration).
        t0, duration: () [s].
        qvel_noise_std: () std of white Gaussian noise added, every control step, to every generalized velocity
            the controller reads (robot and object; [m/s] for translations, [rad/s] for rotations). The physics
            integrates the true state; only the controller's view (its Jacobian-dot terms, CoM and foot
            velocities, observer momentum, object velocity) is noisy. Used only when ``Sim.sensor_noise``.
        key: (2,) uint32 raw PRNG key of the run's noise; step k draws from ``fold_in(key, k)``.
    """

    force: jax.Array
    t0: jax.Array
    duration: jax.Array
    qvel_noise_std: jax.Array
    key: jax.Array


def make_push(force, t0, duration, qvel_noise_std=0.0, seed=0) -> Push:
    """A Push from plain values (one run; or arrays with a leading run axis: ``seed`` (B,) then gives (B, 2) keys)."""
    seed = np.asarray(seed, dtype=np.uint64)
    key = np.stack([np.zeros_like(seed), seed], axis=-1).astype(np.uint32)
    return Push(to_device(force, float), to_device(t0, float), to_device(duration, float),
                to_device(qvel_noise_std, float), to_device(key))


def no_push() -> Push:
    """A Push of no force and no noise (one run)."""
    return make_push(np.zeros(3), 0.0, 0.0)


class RunState(NamedTuple):
    """Carried state of one run: MJX data, controller memory, swing bookkeeping, accumulators."""

    d: mjx.Data
    cs: Any  # the controller's state (Controller.init_state; the transport's: wbc_jax.control.transport.ControlState)
    p_lift: jax.Array  # (4, 3) [m] each foot's lift-off position
    rel0: jax.Array  # (3,) [m] object position in the tray frame at t = 0
    acc: Packed  # the run's wbc_jax.metrics.accumulate.Accum, packed (acc.max_slip reads a field; acc.unpack())
    prev: Any = None  # Sim.sensing "delayed": (qpos (nq,), qvel (nv,), time ()) of the state d's derived fields
    #                   (kinematics, M, contacts, sensors) belong to, the start of the last physics step; else None
    metrics: Any = None  # the controller's own online reductions (Controller.init_metrics; None: none)


def empty_log(sim: Sim, d):
    """The controller's log row of zeros shaped like one run's (``d``: that run's mjx.Data): the inner loop's
    initial carry, which the first control step overwrites."""
    return sim.controller.empty_log(d, sim.robot.mj_model.nu)


def state_axes(sim: Sim, state: RunState) -> RunState:
    """The run axes of a batched RunState: 0 on every leaf but the Warp data's shared contact list (None:
    :func:`wbc_jax.physics.backend.data_axes`). The ``in_axes`` of the state in ``vmap``, sharding and row selection
    (``wbc_jax.rollout.runs``)."""
    zeros = jax.tree_util.tree_map(lambda _: 0, state)
    return zeros._replace(d=physics.data_axes(sim.robot, state.d))


def with_contact_list(state, axes, n_runs: int):
    """(``state``, ``axes``) of a RunState of ``n_runs`` runs taken from another batch (run axes ``axes``) with
    Warp's shared contact list sized for them (:func:`wbc_jax.physics.backend.size_contact_list`). Any other pytree
    (no ``d``) unchanged."""
    if not isinstance(state, RunState):
        return state, axes
    d, d_axes = physics.size_contact_list(state.d, axes.d, n_runs)
    return state._replace(d=d), axes._replace(d=d_axes)


def init_state(sim: Sim, m, qpos0, qvel0=None, n_runs: int = 1) -> RunState:
    """Initial RunState of one run (vmappable over m, qpos0 and qvel0; qvel0 None: at rest). ``n_runs``: the size
    of the batch it is vmapped over (sizes the Warp backend's shared contact list)."""
    ids = sim.robot.ids
    d = physics.make_data(sim.robot, n_runs).replace(qpos=qpos0)
    if qvel0 is not None:
        d = d.replace(qvel=qvel0)
    d = physics.initial(m, d, sensed=sim.sensing != "delayed")
    dyn = dyn_terms(m, d, ids)
    acc = init_accum(dyn.p_base[2])
    prev = (d.qpos, d.qvel, d.time) if sim.sensing == "delayed" else None
    return RunState(d=d, cs=sim.controller.init_state(sim.robot, d, dyn), p_lift=dyn.p_foot,
                    rel0=object_in_tray(d, ids), acc=pack(acc), prev=prev,
                    metrics=sim.controller.init_metrics(sim.robot, d, dyn))


def with_metric_window(state: RunState, t_end) -> RunState:
    """``state`` (batched or not) with its metric window set to [0, ``t_end``) [s] (scalar or (B,) per run)."""
    return state._replace(acc=state.acc._replace(t_end=t_end))


def with_plugin_params(state: RunState, params: dict, controller) -> RunState:
    """``state`` (batched) with a plug-in ``controller``'s per-run fields set (``params``: field -> (B,) levels of
    the spec's ``plugin.<field>`` factors; :meth:`Controller.with_params`); unchanged for no ``params``."""
    return state._replace(cs=controller.with_params(state.cs, params)) if params else state


def with_variant(state: RunState, variant: Variant, controller) -> RunState:
    """``state`` (batched or not) with the transport ``controller``'s ablation switches set
    (:mod:`wbc_jax.control.variants`; each field 0/1, scalar or (B,) per run)."""
    old = controller.variant(state.cs)
    switches = Variant(*(broadcast_like(o, v) for o, v in zip(old, variant)))
    return state._replace(cs=controller.with_variant(state.cs, switches))
