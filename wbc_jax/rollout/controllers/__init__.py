"""The rollout's controller plug-in seam: a :class:`Controller` is what a control step calls between the physics.

The rollout (``wbc_jax.rollout.step``, ``loop``, ``batch``), the campaign, the report and ``regress`` are shared;
a controller brings, as methods of one frozen, hashable definition (part of the static ``Sim``, so equal
definitions share compiled programs):

- ``init_state(robot, d, dyn)``: its memory at t = 0 (a pytree carried in ``RunState.cs``).
- ``make_plan(robot, course, qpos0, kw)`` and ``align_plans(plans)``: one run's plan (setup time, numpy leaves) and
  a list of plans padded to one shape (stacked into the batch's per-run ``plan``); ``plan_end(plan)``: (B,) the
  end of each run's plan [s].
- ``reference(plan, t, obs, p_lift, foot_contact)``: the planner's reference at time t (a pytree with a ``swing``
  (4,) bool mask, which keeps the rollout's liftoff positions).
- ``control(obs, ref, obj_model, gains, state, ids, mu)`` -> ``(tau (nu,) [N m], state, diag)``: the controller;
  it sees the :class:`wbc_jax.types.Observation`, never the simulator's data. ``gains`` is the per-run parameter
  pytree (``default_gains()``; ``batched_gains(gains, B)`` broadcasts it).
- ``record(sim, d, obs, ref, tau, diag, rel0, obj_model, metrics, plan)`` -> :class:`Record`: the control-rate metric
  sample folded into the shared :class:`wbc_jax.metrics.accumulate.Accum`, the controller's own online
  reductions (``RunState.metrics``, from ``init_metrics``; None: none) and the step's log row (``empty_log``).
- ``failed(acc, course)``: () bool, the run has failed (the rollout freezes it from the next control step).
- ``freeze(frozen, new, old)`` (base: the old state where frozen): the controller state a run keeps after a step
  (the built-ins let the QP's warm start follow ``new``: :func:`~wbc_jax.rollout.controllers.base.keep_but_warm_start`).
- ``with_params(cs, params)`` (a plug-in's, optional): its own fields set per run in its state (``plugin.<field>``
  factors).
- ``final_input(logs)`` and ``finalize(sim, state, final_input, mu, n)``: the per-run results (host, numpy) of a
  finished batch; ``final_input`` is what finalization needs of the last log row, kept with the checkpoint.

The shared parts (sensing, sensor noise, pushes, physics-rate monitors, failure freezing, batching, sharding,
checkpoints, both physics backends) stay in the rollout. :data:`CONTROLLERS` names the implementations; a
subclass of one from outside the package is a plug-in (:mod:`wbc_jax.rollout.controllers.plugin`).
"""

from __future__ import annotations

from wbc_jax.rollout.controllers import plugin as plugins
from wbc_jax.rollout.controllers.base import Controller, Record, object_in_tray
from wbc_jax.rollout.controllers.centroidal import CentroidalController
from wbc_jax.rollout.controllers.transport import TransportController

CONTROLLERS = {c.name: c for c in (TransportController, CentroidalController)}
"""The controller definitions by name (``[campaign] controller`` of a spec)."""

__all__ = ["CONTROLLERS", "CentroidalController", "Controller", "Record", "TransportController", "controller_class",
           "object_in_tray"]


def controller_class(name: str, plugin: str = ""):
    """The :class:`Controller` subclass named ``name`` (:data:`CONTROLLERS`), or with ``plugin`` (``"module:Class"``)
    that plug-in, a subclass of it (:func:`wbc_jax.rollout.controllers.plugin.load`). Raises ValueError for another
    name or a plug-in that does not load."""
    if name not in CONTROLLERS:
        raise ValueError(f"controller {name!r}: expected one of {', '.join(CONTROLLERS)}")
    if plugin:
        return plugins.load(plugin, CONTROLLERS[name])
    return CONTROLLERS[name]
