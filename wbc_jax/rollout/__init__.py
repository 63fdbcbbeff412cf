"""The batched closed-loop rollout: config, state, step, loop, results; batching, sharding and distribution.

The public names below are loaded on first use, so that the light submodules (``distributed``, ``runs``,
``packed``) can be imported before MJX and the controllers (e.g. to join a multi-process run).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from wbc_jax.metrics.accumulate import Accum
    from wbc_jax.rollout.config import SENSING, Sim, make_sim, resolve_sensing
    from wbc_jax.rollout.loop import make_chunk_fn, simulate
    from wbc_jax.rollout.results import clearance_name, contact_name, final_results
    from wbc_jax.rollout.state import (
        Log,
        Push,
        RunState,
        init_state,
        make_push,
        no_push,
        state_axes,
        with_metric_window,
        with_plugin_params,
        with_variant,
    )
    from wbc_jax.rollout.step import clearance, control_step, controller_inputs, seen_qvel

_HOMES = {
    "wbc_jax.metrics.accumulate": ("Accum",),
    "wbc_jax.rollout.config": ("SENSING", "Sim", "make_sim", "resolve_sensing"),
    "wbc_jax.rollout.loop": ("make_chunk_fn", "simulate"),
    "wbc_jax.rollout.results": ("clearance_name", "contact_name", "final_results"),
    "wbc_jax.rollout.state": ("Log", "Push", "RunState", "init_state", "make_push", "no_push", "state_axes",
                              "with_metric_window", "with_plugin_params", "with_variant"),
    "wbc_jax.rollout.step": ("clearance", "control_step", "controller_inputs", "seen_qvel"),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = [
    "Accum",
    "Log",
    "Push",
    "RunState",
    "SENSING",
    "Sim",
    "clearance",
    "clearance_name",
    "contact_name",
    "control_step",
    "controller_inputs",
    "final_results",
    "init_state",
    "make_chunk_fn",
    "make_push",
    "make_sim",
    "no_push",
    "resolve_sensing",
    "seen_qvel",
    "simulate",
    "state_axes",
    "with_metric_window",
    "with_plugin_params",
    "with_variant",
]


def __getattr__(name: str):
    module = _HOME_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'wbc_jax.rollout' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
