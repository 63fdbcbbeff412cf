"""Re-simulate some runs of a finished campaign exactly as the campaign simulated them.

The campaign's own builders make the batch (:func:`wbc_jax.campaign.build.build`: the same design, per-run draws,
gains, variants, physics backend and sensing); its rows are then chosen with
:func:`wbc_jax.rollout.batch.take_runs` so that the batch keeps the campaign's size and every requested run sits in
its own slot (XLA's outputs can depend on the batch's size and layout), the other slots repeating the requested
runs. The same chunk program as the campaign's (:func:`wbc_jax.campaign.build.chunk_fn`: same Sim, chunk length
and shapes, so a process that ran the campaign reuses its compiled program) steps the batch chunk by chunk, and the
results come from :func:`wbc_jax.rollout.final_results` as the campaign's did. On one device with the same backend
the replayed R, T, S therefore equal the campaign's bit for bit. On Warp physics the runs of a batch share one
contact list, so only ``whole_batch`` (the campaign's own rows in every slot) replays the exact batch.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.campaign import gains as gains_mod
from wbc_jax.campaign import interrupts
from wbc_jax.campaign.build import Built, chunk_fn, build, check_horizon
from wbc_jax.campaign.progress import ProgressBar
from wbc_jax.errors import InputError
from wbc_jax.rollout import final_results, runs
from wbc_jax.rollout.batch import take_runs
from wbc_jax.rollout.spread import choose
from wbc_jax.studies.replay_inputs import Recorded


class Replayed(NamedTuple):
    """The replayed runs.

    Attributes:
        built: the campaign's batch as built (Sim, design, chunk plan).
        slots: (B,) the campaign run simulated in each slot of the replayed batch (B: the campaign's runs).
        logs: run id -> its Log (host numpy; axis 0 the logged samples, every ``Sim.log_every`` control steps).
        results: run id -> its :func:`wbc_jax.rollout.final_results` entries (numpy scalars or strings).
        wall_s: the chunks' wall time [s] (the first chunk's compile or program load included).
    """

    built: Built
    slots: np.ndarray
    logs: dict
    results: dict
    wall_s: float


def fill_slots(run_ids, n: int, whole_batch: bool = False) -> np.ndarray:
    """(n,) the campaign run of each slot of an n-run batch: run r in slot r for every requested run, the other
    slots the requested runs in turn (``whole_batch``: every run in its own slot, the campaign's batch)."""
    if whole_batch:
        return np.arange(n)
    wanted = np.asarray(sorted(run_ids), dtype=int)
    slots = wanted[np.arange(n) % len(wanted)]
    slots[wanted] = wanted
    return slots


def _check_plan(recorded: Recorded, built: Built) -> None:
    """The rebuilt batch's size, seeds and chunks equal the manifest's (else the code that builds it changed)."""
    man, dz = recorded.manifest, built.design
    rebuilt = dict(n_runs=dz.n, n_chunks=built.n_chunks)
    for k, v in rebuilt.items():
        if k in man and int(man[k]) != v:
            raise InputError(f"{recorded.folder}/manifest.json {k} = {man[k]}: this version builds {v} from the same "
                             "spec; replay with the version that ran the campaign")
    if not np.array_equal(dz.seed.astype(np.uint64), np.asarray(man["seeds"], np.uint64)):
        raise InputError(f"{recorded.folder}/manifest.json seeds differ from the design this version builds from the "
                         "same spec; replay with the version that ran the campaign")


def announce(recorded: Recorded, run_ids, built: Built, spread_mode: str) -> str:
    """The opening line: which runs, the batch, the chunks, physics, sensing and device."""
    c, man = recorded.spec.campaign, recorded.manifest
    chunk_s = built.logs_per_chunk * built.sim.log_every * built.sim.dt_control
    note = ""
    campaign_device = (man.get("device") or {}).get("kind")
    if campaign_device and campaign_device != jax.devices()[0].device_kind:
        note = f"; the campaign ran on {campaign_device}: expect float rounding differences, not bit-for-bit equality"
    return (f"replaying run{'s' if len(run_ids) > 1 else ''} {', '.join(map(str, run_ids))} of campaign "
            f"{c['name']!r} ({recorded.folder}): a batch of {built.design.n} runs as the campaign's, "
            f"{built.n_chunks} chunks of {chunk_s:.2f} s, physics {man['physics_backend']}, sensing {man['sensing']}, "
            f"device {jax.devices()[0].device_kind} ({spread_mode}){note}")


def simulate_runs(recorded: Recorded, run_ids, whole_batch: bool = False, progress: bool = True) -> Replayed:
    """Re-simulate the campaign runs ``run_ids`` (module docstring); every chunk of the campaign is stepped.

    Raises:
        InputError: this version rebuilds a different batch from the spec (runs, seeds, chunks).
    """
    spec = recorded.spec
    gains_mod.check_design(spec, recorded.gains)
    print(f"building the campaign's batch ({len(recorded.results)} runs)", flush=True)
    built = build(spec, recorded.gains)
    check_horizon(spec, built)
    _check_plan(recorded, built)
    n, wanted = built.design.n, sorted(run_ids)
    slots = fill_slots(wanted, n, whole_batch)
    spread = choose(built.sim.robot.backend)
    batch = spread.place(take_runs(built.batch, slots))
    print(announce(recorded, wanted, built, spread.mode), flush=True)
    fn = chunk_fn(built.sim, batch.in_axes, built.logs_per_chunk, spread.mesh, batch.state_axes)
    chunk_s = built.logs_per_chunk * built.sim.log_every * built.sim.dt_control
    bar = ProgressBar(built.n_chunks, 0, chunk_s, n, built.sim.dt_physics) if progress else None
    state, kept, t_start = batch.state, [], time.perf_counter()
    try:
        with interrupts.Guard("wbc-jax replay") as guard:
            for _ in range(built.n_chunks):
                t0 = time.perf_counter()
                with guard.deferred():  # XLA compiling or running a chunk: a signal stops after it
                    state, logs = fn(batch.model, state, batch.plan, batch.om, batch.gains, batch.push,
                                     batch.mu_ground)
                    host = spread.gather(logs, n)
                guard.check()
                kept.append(runs.take(host, wanted))
                if bar is not None:
                    bar.chunk_done(time.perf_counter() - t0)
            final = spread.gather(state, n, batch.state_axes)
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t_start
    res = final_results(built.sim, final, np.asarray(host.p_obj_ref)[:, -1], built.design.mu[slots])
    logs = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *kept)
    per_run_logs = {r: jax.tree_util.tree_map(lambda x, i=i: x[i], logs) for i, r in enumerate(wanted)}
    results = {r: {k: v[r] for k, v in res.items()} for r in wanted}
    return Replayed(built, slots, per_run_logs, results, wall)
