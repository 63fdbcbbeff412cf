"""``wbc-jax bench rollout --campaign SPEC``: the campaign's own control step, timed where the campaign runs it.

The spec is built as a campaign builds it (:func:`wbc_jax.campaign.build.build`: its scene, backend, sensing,
velocity noise, pushes, metric windows, variants and ADMM settings), and its runs walk the course with the
campaign's own chunk program (chunks of ``chunk_seconds``, each timed: the spec's batch as the campaign steps it)
up to ``snapshots`` states spread over the horizon. At every requested batch size the spec's runs are repeated
(run i of the batch is the spec's run i mod n) from each state, and these programs are timed on the same states:

* ``campaign``: the chunk program (:func:`wbc_jax.rollout.loop.make_chunk_fn`) as the campaign compiles it;
* ``no_clearance``: the same with the physics-rate clearance replaced by +inf (its computation drops out);
* ``no_monitors``: every physics-rate monitor but ``finite`` replaced by zeros and the control-rate metrics not
  folded (their computations drop out; the step count still advances, so the velocity noise still changes every
  step);
* ``no_noise``: the campaign's Sim without the controller's velocity noise (``Sim.sensor_noise`` off): what the
  noise costs: the ADMM iterations it adds to the warm-started QP and, on Warp, the physics' constraint-solver
  iterations (under the noisy torques some runs' solves stop at ``opt.iterations``, and Warp's solver loop runs
  until the batch's last world has converged);
* ``physics``: plain ``mjx.step`` calls on the same batch (``wbc_jax.bench.rollout.physics_only_fn``).

Each ablation is the campaign's Sim with ``monitors`` or ``sensor_noise`` changed (:func:`ablation_sim`), its chunk
program compiled and timed like the campaign's: ``--rounds`` calls per state, alternated with the other programs,
the median kept. Shares are 1 - (ablated program's time / the campaign program's time). Each state's first round
also gives the QP's mean ADMM iterations per control step (``Accum.sum_qp_iters``: runs that have failed, frozen,
count none) and the share of physics steps whose constraint solve stopped at the cap (``Accum.n_solver_cap``, Warp
only); not for ``no_monitors``, which does not fold them.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.bench.rollout import disturbed, physics_only_fn, qp_iterations, run_bench, solver_cap_share, timed
from wbc_jax.campaign.build import LOG_EVERY, build, with_backend
from wbc_jax.campaign.spec import load_spec
from wbc_jax.rollout import make_chunk_fn, runs
from wbc_jax.rollout.batch import chunk_args, take_runs
from wbc_jax.rollout.state import init_state

ABLATIONS = ("campaign", "no_clearance", "no_monitors", "no_noise")


def ablation_sim(sim, name: str):
    """The Sim whose chunk program is ablation ``name`` (:data:`ABLATIONS`) of ``sim``'s: ``Sim.monitors`` or
    ``Sim.sensor_noise`` changed. KeyError for an unknown name."""
    change = {"campaign": {}, "no_clearance": dict(monitors="no_clearance"),
              "no_monitors": dict(monitors="finite_only"), "no_noise": dict(sensor_noise=False)}[name]
    return dataclasses.replace(sim, **change) if change else sim


def compiled_chunk(sim, b, n_logs: int, ablation: str = "campaign"):
    """The chunk program of ``n_logs`` x LOG_EVERY control steps for batch ``b`` (ablation ``ablation``), compiled
    now: a callable of the batch's arguments (:func:`wbc_jax.rollout.batch.chunk_args`)."""
    fn = make_chunk_fn(ablation_sim(sim, ablation), n_logs, b.in_axes)
    return jax.jit(fn).lower(*chunk_args(b)).compile()


class Walk(NamedTuple):
    """The spec's batch stepped by the campaign's chunk program up to the last snapshot."""

    states: list  # RunState per snapshot
    times_s: list  # simulated time of each snapshot [s]
    chunk_wall_s: list  # wall time of each chunk call [s] (the first includes compilation)
    chunk_steps: int  # control steps per chunk


def walk(built, snapshots: int) -> Walk:
    """Step the spec's runs (``built``: :func:`wbc_jax.campaign.build.build`) with its chunk program, keeping the
    state after chunks spread evenly over the horizon (``snapshots`` of them; the first at the start)."""
    sim, b = built.sim, built.batch
    f = compiled_chunk(sim, b, built.logs_per_chunk)
    picks = sorted({int(round(i * (built.n_chunks - 1) / max(snapshots, 1))) for i in range(max(snapshots, 1))})
    chunk_steps = built.logs_per_chunk * LOG_EVERY
    states, times, walls, state = [], [], [], b.state
    for c in range(picks[-1] + 1):
        if c in picks:
            states.append(state)
            times.append(c * chunk_steps * sim.dt_control)
        if c == picks[-1]:
            break
        (state, _), wall = timed(f, *chunk_args(b._replace(state=state)))
        walls.append(wall)
    return Walk(states, times, walls, chunk_steps)


def repeated(b, state, fresh, batch: int):
    """Batch ``b`` (n runs) repeated to ``batch`` runs (run i is run i mod n) from ``state``, a state of ``b``'s
    runs. The result takes its structure and shared leaves from ``fresh``, a state of ``batch`` runs
    (:func:`fresh_state`): on Warp both follow the batch size (the shared contact list, its static capacities)."""
    rows = np.arange(batch) % b.mu_ground.shape[0]
    leaves, _, axes = runs.leaves_and_axes(state, b.state_axes)
    shared, treedef = jax.tree_util.tree_flatten(fresh)
    if len(shared) != len(leaves):
        raise ValueError(f"a state of {len(leaves)} leaves repeated into one of {len(shared)}")
    tiled = treedef.unflatten([s if a is None else x[rows] for x, s, a in zip(leaves, shared, axes)])
    return take_runs(b, rows, state=tiled)._replace(state_axes=treedef.unflatten(axes))


def fresh_state(sim, b, batch: int):
    """An initial state of ``batch`` runs (run i is ``b``'s run i mod n) made as a campaign batch of that size is
    made (``wbc_jax.rollout.state.init_state`` vmapped over the runs; on Warp the shared contact list is sized for
    ``batch`` runs, one device, no padding); ``b``'s own state when no leaf is shared (JAX) or ``b`` has ``batch``
    runs."""
    axes = runs.leaves_and_axes(b.state, b.state_axes)[2]
    n = b.mu_ground.shape[0]
    if all(a is not None for a in axes) or batch == n:
        return b.state
    rows = np.arange(batch) % n
    init = jax.vmap(functools.partial(init_state, sim, n_runs=batch), in_axes=(b.in_axes, 0, 0))
    return jax.jit(init)(runs.take(b.model, rows, b.in_axes), b.state.d.qpos[rows], b.state.d.qvel[rows])


def _time_batch(sim, batch_at, n_states: int, n_logs: int, ablations, n_env: int, rounds: int = 1):
    """Each ablation's program and physics alone: compiled with its first call (on state 0), then timed ``rounds``
    times per state, alternated, the median kept; ``batch_at(i)`` gives the batch from state i (made when needed:
    one at a time in memory). Returns ({name: first call [s]}, {name: [median s per state]}, {program name:
    {"qp_iters_per_step": [mean QP iterations per control step, per state], "solver_cap_share":
    [:func:`~wbc_jax.bench.rollout.solver_cap_share`, per state]}}; no_monitors, which does not fold its
    control-rate counts, left out)."""
    b0 = batch_at(0)
    first, programs = {}, {}
    for name in ablations:
        t0 = time.perf_counter()
        programs[name] = compiled_chunk(sim, b0, n_logs, name)
        jax.block_until_ready(programs[name](*chunk_args(b0)))
        first[name] = time.perf_counter() - t0
    phys = physics_only_fn(b0, n_env)
    first["physics"] = timed(phys, b0.model, b0.state.d)[1]
    times = {name: [] for name in first}
    counts = {name: dict(qp_iters_per_step=[], solver_cap_share=[]) for name in programs if name != "no_monitors"}
    for i in range(n_states):
        b = b0 if i == 0 else batch_at(i)
        walls = {name: [] for name in first}
        for r in range(rounds):
            for name, f in programs.items():
                (state, _), wall = timed(f, *chunk_args(b))
                walls[name].append(wall)
                if name in counts and r == 0:
                    counts[name]["qp_iters_per_step"].append(qp_iterations(b.state, state, n_logs * LOG_EVERY))
                    counts[name]["solver_cap_share"].append(solver_cap_share(b.state, state, n_env))
            walls["physics"].append(timed(phys, b.model, b.state.d)[1])
        for name, w in walls.items():
            times[name].append(float(np.median(w)))
            phrase = disturbed(f"{name} program", w)
            if phrase:
                print(f"warning: the campaign's step, state {i}: {phrase}", flush=True)
        del b
    return first, times, counts


def batch_figures(first: dict, times: dict, batch: int, n_env: int, counts: dict | None = None) -> dict:
    """Figures of one batch size from :func:`_time_batch`'s timings: env-steps per second of each program over all
    states (total env-steps / total time), per state, its compile time (first call less the median call), the shares
    of the campaign program's time: physics alone, clearance, monitors (1 - ablated / campaign), and each program's
    counts (``counts``: {name: {key: per state}}) as ``{name}_{key}``, their mean over the states."""
    row = dict(batch=batch)
    for name, per_key in (counts or {}).items():
        for key, per_state in per_key.items():
            row[f"{name}_{key}"] = float(np.mean(per_state))
    total = {name: float(np.sum(t)) for name, t in times.items()}
    for name, t in times.items():
        row[f"{name}_steps_per_s"] = batch * n_env * len(t) / total[name]
        row[f"{name}_steps_per_s_by_state"] = [batch * n_env / x for x in t]
        row[f"{name}_compile_s"] = first[name] - float(np.median(t))
    base = total["campaign"]
    row["physics_share"] = total["physics"] / base
    for name, label in (("no_clearance", "clearance_share"), ("no_monitors", "monitors_share"),
                        ("no_noise", "noise_share")):
        if name in total:
            row[label] = 1.0 - total[name] / base
    return row


def run_campaign_step(spec, batches, steps: int = 200, snapshots: int = 3, breakdown=None,
                      rounds: int = 1) -> dict:
    """The campaign's step at each batch size (module docstring).

    Args:
        spec: a loaded, validated Spec (``wbc_jax.campaign.spec.load_spec``; backend as the campaign resolves it).
        batches: batch sizes; steps: control steps per timed call (rounded to whole logged intervals of LOG_EVERY);
        snapshots: states spread over the horizon that each program is timed from; breakdown: batch sizes at which
        the ablations are timed too (None: every one); rounds: timed calls per program and state, alternated, the
        median kept.

    Returns:
        dict: spec, backend, sensing, runs of the spec, the walk (the spec's batch in the campaign's chunks: wall
        time per chunk and env-steps per second after the first) and one row per batch size (:func:`batch_figures`).
    """
    built = build(spec)
    sim, n = built.sim, built.design.n
    steps_walk = walk(built, snapshots)
    chunk_env = n * steps_walk.chunk_steps * sim.n_substeps
    later = steps_walk.chunk_wall_s[1:]
    out = dict(spec=str(spec.path), backend=sim.robot.backend, sensing=sim.sensing, n_runs=n,
               snapshots_s=steps_walk.times_s,
               walk=dict(chunk_wall_s=steps_walk.chunk_wall_s, chunk_steps=steps_walk.chunk_steps,
                         env_steps_per_s=chunk_env * len(later) / sum(later) if later else None), batches=[])
    n_logs = max(1, int(round(steps / LOG_EVERY)))
    n_env = n_logs * LOG_EVERY * sim.n_substeps
    device = jax.devices()[0].device_kind
    for B in batches:
        fresh = fresh_state(sim, built.batch, B)
        names = ABLATIONS if breakdown is None or B in breakdown else ABLATIONS[:1]
        def batch_at(i, fresh=fresh, B=B):
            return repeated(built.batch, steps_walk.states[i], fresh, B)

        first, times, counts = _time_batch(sim, batch_at, len(steps_walk.states), n_logs, names, n_env, rounds)
        row = batch_figures(first, times, B, n_env, counts)
        out["batches"].append(row)
        shares = "".join(f", {k.split('_')[0]} {row[k]:.1%}" for k in ("clearance_share", "monitors_share",
                                                                       "noise_share") if k in row)
        for title, key, fmt in (("QP iterations per step", "_qp_iters_per_step", ".1f"),
                                ("physics steps at the constraint solver's cap", "_solver_cap_share", ".1%")):
            shares += f"; {title} " + ", ".join(f"{k[:-len(key)]} {v:{fmt}}" for k, v in row.items() if k.endswith(key))
        print(f"{device} campaign step ({spec.campaign['name']}, {sim.robot.backend}:{sim.sensing}) batch {B:6d}: "
              f"{row['campaign_steps_per_s']:12.0f} env-steps per s from t = "
              f"{', '.join(f'{t:g}' for t in steps_walk.times_s)} s; physics alone {row['physics_steps_per_s']:12.0f}"
              f" (share {row['physics_share']:.1%}){shares}; compile {row['campaign_compile_s']:.1f} s", flush=True)
    return out


def run_bench_with_campaign(spec_path: str, batches, steps: int = 200, snapshots: int = 3, breakdown=None,
                            spec_backend: str | None = None, json_path: str | None = None, rounds: int = 5,
                            **bench) -> dict:
    """``bench rollout --campaign SPEC``: the campaign's step (:func:`run_campaign_step`) next to the bench's
    physics-only and physics + WBC rows at the same batch sizes (``wbc_jax.bench.rollout.run_bench`` with
    ``bench``'s keyword arguments), in one process, with each batch's ratio campaign step / bench physics + WBC
    where both ran the same backend.

    Args:
        spec_path: the campaign spec (validated before anything is timed); spec_backend: its ``campaign.backend``
            replaced (None: the spec's); json_path: where the dict is written (None: not written); rounds: the
            bench's timed rounds and the campaign step's calls per program and state, medians kept.
    """
    spec = with_backend(load_spec(spec_path), spec_backend)  # a bad spec fails here, before any timing
    out = run_bench(batches=batches, steps=steps, rounds=rounds, **bench)
    out["campaign_step"] = step = run_campaign_step(spec, batches, steps, snapshots, breakdown, rounds)
    bench_rows = {(r["batch"], r["backend"]): r for r in out["batches"]}
    for row in step["batches"]:
        ref = bench_rows.get((row["batch"], step["backend"]))
        row["ratio_to_bench_wbc"] = row["campaign_steps_per_s"] / ref["wbc_steps_per_s"] if ref else None
        if ref:
            print(f"batch {row['batch']:6d}: campaign step / bench physics + WBC = {row['ratio_to_bench_wbc']:.3f}",
                  flush=True)
    if json_path and jax.process_index() == 0:
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=2)
    return out
