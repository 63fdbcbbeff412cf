"""The batched closed-loop rollout: config, state, step, loop, results; batching, sharding and distribution."""

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
    with_variant,
)
from wbc_jax.rollout.step import clearance, control_step, controller_inputs, seen_qvel

__all__ = [
    "SENSING",
    "Accum",
    "Log",
    "Push",
    "RunState",
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
    "with_variant",
]
