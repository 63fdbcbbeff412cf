"""The controller plug-in interface: :class:`Controller` (described in :mod:`wbc_jax.rollout.controllers`) and
its per-step :class:`Record`."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp


def keep_where(frozen, new, old):
    """``old`` where ``frozen`` (() bool), else ``new``, leaf for leaf of two pytrees of one structure."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(frozen, b, a), new, old)


def keep_but_warm_start(frozen, new, old):
    """:func:`keep_where` of two controller states (NamedTuples with a ``warm`` field, the QP's warm start) but the
    warm start following ``new``: it only starts the next solve, whose result a frozen run discards. A frozen run
    poses the same QP every step (its state is held), so from its last solution the next solve passes its first
    convergence check instead of repeating the iterations of the step it failed at (a batch's solve lasts as long
    as its longest)."""
    kept = keep_where(frozen, new._replace(warm=None), old._replace(warm=None))
    return kept._replace(warm=new.warm)


class Record(NamedTuple):
    """What :meth:`Controller.record` returns for one control step of one run."""

    sample: Any  # wbc_jax.metrics.accumulate.ControlSample folded into the shared Accum
    metrics: Any  # the controller's own online reductions after this step (None: none)
    log: Any  # the step's log row


def object_in_tray(d, ids):
    """(3,) [m] the object's position in the tray-top frame."""
    R = d.site_xmat[ids.tray_site]
    return R.T @ (d.xpos[ids.obj_body] - d.site_xpos[ids.tray_site])


class Controller:
    """Base of the controller definitions (module docstring); subclasses are frozen dataclasses with a ``cfg``
    field (static settings; ``cfg.dt``: the control period [s]) and a class attribute ``name``."""

    name = ""
    extra_columns: tuple = ()  # results.csv columns a plug-in adds to its family's: its finalize returns each, (n,)

    def init_metrics(self, robot, d, dyn):
        """The controller's own online reductions at t = 0 (None: it has none)."""
        return None

    def with_params(self, cs, params: dict):
        """The controller state ``cs`` (batched) with per-run values of the controller's own fields: ``params``
        maps a field's name to its (B,) levels (numpy) of the spec's ``plugin.<field>`` factor. A plug-in whose
        fields a spec varies keeps them in its state and sets them here
        (:func:`wbc_jax.rollout.packed.broadcast_like` sets a leaf); the built-in controllers have none."""
        raise NotImplementedError(f"{type(self).__qualname__} has no per-run fields (with_params)")

    def freeze(self, frozen, new, old):
        """The controller state a run keeps after a step: ``old`` where ``frozen`` (() bool: the run failed at an
        earlier step and keeps its state), else ``new``. A controller may let scratch that no kept value depends on
        follow ``new`` (sparing its copy)."""
        return keep_where(frozen, new, old)
