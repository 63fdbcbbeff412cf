"""The rollout's time loop: ``lax.scan`` over control steps, the runs vmapped inside each step, run in chunks.

Long runs are executed in chunks (one jit call per chunk) so progress can be shown and finished chunks kept.
Per-step quantities are reduced online (:class:`wbc_jax.metrics.accumulate.Accum`) and logged once every
``log_every`` control steps.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.rollout.config import Sim
from wbc_jax.rollout.state import RunState, empty_log
from wbc_jax.rollout.step import control_step
from wbc_jax.runtime.static import axes_key


def make_chunk_fn(sim: Sim, n_logs: int, model_axes):
    """One chunk of every run: ``n_logs`` x ``log_every`` control steps, the runs batched inside each step.

    Returns f(batched model, state, plan, obj_model, gains, push, mu_ground) -> (state, the controller's log with
    axes (run, log)),
    for ``jax.jit``; every argument after the model has the runs on its axis 0, the model on ``model_axes``
    (``Batch.in_axes``).

    The step is vmapped inside the scans (``scan(vmap(step))``), not the scans over one run's step
    (``vmap(scan(step))``): the step is traced once, batched, instead of traced and then run again under the scans'
    batching rules; the compiled programs are the same.
    """
    step = jax.vmap(functools.partial(control_step, sim), in_axes=(model_axes, 0, 0, 0, 0, 0, 0))

    def chunk(m, run_state, plan, obj_model, gains, push, mu_ground):
        # the log of the period's last step rides in the carry (overwritten every step) rather than as the inner
        # scan's stacked output, of which only the last row was kept
        log0 = jax.vmap(lambda d: empty_log(sim, d))(run_state.d)

        def inner(carry, _):
            return step(m, carry[0], plan, obj_model, gains, push, mu_ground), None

        def outer(run_state, _):
            return jax.lax.scan(inner, (run_state, log0), None, length=sim.log_every)[0]

        run_state, logs = jax.lax.scan(outer, run_state, None, length=n_logs)
        return run_state, jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), logs)  # (log, run) -> (run, log)

    return chunk


_CHUNK_FNS: dict = {}


def chunk_fn(sim: Sim, n_logs: int, model_axes):
    """``jax.jit(make_chunk_fn(sim, n_logs, model_axes))``, one per (Sim by value, chunk length, model axes)."""
    key = (sim, n_logs, axes_key(model_axes))
    if key not in _CHUNK_FNS:
        _CHUNK_FNS[key] = jax.jit(make_chunk_fn(sim, n_logs, model_axes))
    return _CHUNK_FNS[key]


def simulate(sim: Sim, bmodel, in_axes, state: RunState, plan, obj_model, gains, push, mu_ground, seconds: float,
             chunk_seconds: float = 2.0, progress=None, program=None):
    """Run ``seconds`` of simulated time in chunks of about ``chunk_seconds`` [s].

    Args:
        sim: static structure; bmodel, in_axes: the batched model and its run axes (``Batch.model``,
            ``Batch.in_axes``); state, plan, obj_model, gains, push, mu_ground: per run, runs on axis 0.
        progress: None or a callable taking the simulated time done [s] after each chunk.
        program: None (:func:`chunk_fn`) or a callable (sim, n_logs, in_axes) -> the chunk function to call, e.g.
            a campaign's (``wbc_jax.campaign.build.chunk_fn``), so a study and a campaign of the same shapes share
            one compiled program.

    Returns:
        (final RunState, Log with axes (run, log row)).
    """
    steps_per_log = sim.log_every
    dt = sim.dt_control
    logs_per_chunk = max(1, int(round(chunk_seconds / (dt * steps_per_log))))
    n_logs_total = int(np.ceil(seconds / (dt * steps_per_log)))
    out_logs = []
    done = 0
    while done < n_logs_total:
        n = min(logs_per_chunk, n_logs_total - done)
        state, logs = (program or chunk_fn)(sim, n, in_axes)(bmodel, state, plan, obj_model, gains, push, mu_ground)
        out_logs.append(jax.device_get(logs))
        done += n
        if progress is not None:
            progress(done * steps_per_log * dt)
    logs = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *out_logs)
    return state, logs
