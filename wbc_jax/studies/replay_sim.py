"""Re-simulate some runs of a finished campaign with the campaign's arithmetic.

A chaotic closed loop near its failure boundary amplifies the last bit of a difference, and XLA compiles a
different program (fusion, tiling, reduction order) for a batch of another shape, layout or XLA setting. So the
replay rebuilds the campaign's batch with its own builders (:func:`wbc_jax.campaign.build.build`: design, per-run
draws, gains, variants, physics backend, sensing, chunks) and steps it with the campaign's chunk program
(:func:`wbc_jax.campaign.build.chunk_fn`) on a batch of the campaign's shape:

* this machine spreads the runs as the campaign did (``manifest.json``'s ``program``: the spread, the devices one
  program spans, the runs per device): the campaign's whole batch, each requested run in its own slot, the other
  slots repeating the requested runs (:func:`fill_slots`), placed and padded as the campaign's;
* otherwise: for each part of the campaign's batch (a device's or a process's runs) that holds a requested run, a
  batch of that part's size on one device, each requested run in its slot of that part (:func:`part_rows`): the
  same per-device program where the campaign's parts ran the one-device program (Warp's blocks), the nearest one
  to a mesh program otherwise.

XLA's settings that shape the program (its deterministic GPU ops: :mod:`wbc_jax.runtime.jaxcfg`) are taken from
the manifest before JAX starts (:func:`adopt_xla`). What can still make the replay differ (another device, layout,
XLA setting or version) is listed in :attr:`Replayed.notes`. On Warp physics the runs of a batch share one contact
list, so only ``whole_batch`` (the campaign's own rows in every slot) replays the exact batch.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.campaign import gains as gains_mod
from wbc_jax.campaign import interrupts
from wbc_jax.campaign.build import Built, build, check_horizon, chunk_fn
from wbc_jax.campaign.manifest import NUMERICS, versions
from wbc_jax.campaign.progress import ProgressBar
from wbc_jax.errors import InputError
from wbc_jax.rollout import final_results, runs
from wbc_jax.rollout.batch import take_runs, with_contact_list
from wbc_jax.rollout.spread import Spread, choose
from wbc_jax.runtime import jaxcfg
from wbc_jax.studies.replay_inputs import Recorded

NOT_DETERMINISTIC = ("its GPU program's scatter adds (atomics) sum in an order that changes from call to call, so "
                     "a run near its failure boundary need not fail again (rerun the campaign with the deterministic "
                     "ops, the default)")


class Program(NamedTuple):
    """How a batch's runs are cut into programs: the spread (one, mesh, blocks), the parts (devices of a mesh,
    processes of blocks, else 1) and the runs each part's program steps (``per_device``, padding included)."""

    spread: str
    parts: int
    per_device: int
    dealt: bool = False  # the runs dealt to the parts in turn (run r: part r % parts, slot r // parts), not cut

    def part_slot(self, r: int) -> tuple[int, int]:
        """(part, slot in the part) of run ``r``."""
        return (r % self.parts, r // self.parts) if self.dealt else (r // self.per_device, r % self.per_device)


class Replayed(NamedTuple):
    """The replayed runs.

    Attributes:
        built: the campaign's batch as built (Sim, design, chunk plan).
        batches: the campaign run in each slot of every simulated batch (one array per batch).
        same_layout: the batch was the campaign's whole batch, spread as the campaign spread it.
        notes: what can make the replay differ from the campaign (another device, layout, XLA setting, version).
        logs: run id -> its Log (host numpy; axis 0 the logged samples, every ``Sim.log_every`` control steps).
        results: run id -> its :func:`wbc_jax.rollout.final_results` entries (numpy scalars or strings).
        wall_s: the chunks' wall time [s] (the first chunk's compile or program load included).
    """

    built: Built
    batches: list
    same_layout: bool
    notes: list
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


def part_rows(run_ids, n: int, program: Program, whole_batch: bool = False) -> list[np.ndarray]:
    """The batches that replay ``run_ids`` part by part: for each part of the campaign's n-run batch
    (:meth:`Program.part_slot`; a part's slots past the last run padded with it) that holds a requested run, the
    (per_device,) campaign run of each slot: the part's own runs (``whole_batch``) or each requested run in its
    slot, the other slots the part's requested runs in turn."""
    out, size = [], program.per_device
    for part in sorted({program.part_slot(r)[0] for r in run_ids}):
        slots = np.arange(size)
        own = np.minimum(part + program.parts * slots if program.dealt else part * size + slots, n - 1)
        if whole_batch:
            out.append(own)
            continue
        mine = sorted(r for r in run_ids if program.part_slot(r)[0] == part)
        rows = np.asarray(mine, dtype=int)[slots % len(mine)]
        rows[[program.part_slot(r)[1] for r in mine]] = mine
        out.append(rows)
    return out


def campaign_program(manifest: dict, n: int) -> Program:
    """The campaign's :class:`Program`: its manifest's ``program`` record, else (an older manifest) its layout's."""
    record = manifest.get("program")
    if isinstance(record, dict):
        return Program(str(record["spread"]), int(record["parts"]), int(record["per_device_runs"]),
                       bool(record.get("dealt", False)))
    layout = manifest.get("layout") or {}
    spread = str(layout.get("spread", "one"))
    parts = {"mesh": len(layout.get("devices") or [None]), "blocks": int(layout.get("processes", 1))}.get(spread, 1)
    return Program(spread, parts, -(-n // parts))


def this_program(spread: Spread, n: int) -> Program:
    """The :class:`Program` this process would run an n-run batch with."""
    parts = {"mesh": spread.mesh.size if spread.mesh is not None else 1, "blocks": spread.processes}.get(spread.mode, 1)
    return Program(spread.mode, parts, -(-n // parts), spread.mode == "blocks")


def _other_flags(flags) -> list[str]:
    """The flags of an ``XLA_FLAGS`` string but the deterministic ops', sorted."""
    return sorted(f for f in str(flags).split() if f.partition("=")[0] != jaxcfg.DETERMINISTIC_FLAG)


def adopt_xla(manifest: dict) -> list[str]:
    """Set XLA's deterministic GPU ops as the campaign had them (before JAX starts; :mod:`wbc_jax.runtime.jaxcfg`).
    Returns notes on XLA settings that still differ from the campaign's (none: an empty list)."""
    record = (manifest.get("program") or {}).get("xla") if isinstance(manifest.get("program"), dict) else None
    on_gpu = (manifest.get("device") or {}).get("backend") == "gpu"
    if not isinstance(record, dict):
        return ([f"the campaign's manifest records no XLA settings (an older version): {NOT_DETERMINISTIC}"]
                if on_gpu else [])
    wanted = bool(record.get("deterministic_ops"))
    notes = [f"the campaign ran with XLA's deterministic GPU ops off: {NOT_DETERMINISTIC}"] if on_gpu and not wanted \
        else []
    if not jaxcfg.set_deterministic_ops(wanted):
        notes.append(f"the campaign compiled with XLA's deterministic GPU ops {'on' if wanted else 'off'}, this "
                     "process started JAX with them "
                     f"{'on' if jaxcfg.deterministic_ops() else 'off'} (replay in a new process)")
    here = jaxcfg.xla_record()["flags"]
    if _other_flags(record.get("flags", "")) != _other_flags(here):
        notes.append(f"XLA_FLAGS differ from the campaign's ({record.get('flags')!r}, here {here!r})")
    return notes


def _notes(recorded: Recorded, program: Program, here: Program) -> list[str]:
    """What can make the replay differ from the campaign besides XLA's flags: the device, the layout, versions."""
    man, notes = recorded.manifest, []
    kind, campaign_kind = jax.devices()[0].device_kind, (man.get("device") or {}).get("kind")
    if campaign_kind and campaign_kind != kind:
        notes.append(f"the campaign ran on {campaign_kind}, this replay on {kind}")
    if program != here:
        notes.append(f"the campaign's program spanned {program.parts} part(s) of {program.per_device} runs "
                     f"({program.spread}), this machine would run {here.parts} ({here.spread}): each part is "
                     f"replayed as a {program.per_device}-run batch on one device")
    found = versions()
    moved = [f"{p} {(man.get('versions') or {}).get(p)} -> {found.get(p)}" for p in NUMERICS
             if p in (man.get("versions") or {}) and man["versions"][p] != found.get(p)]
    if moved:
        notes.append("versions differ from the campaign's: " + ", ".join(moved))
    return notes


def recorded_chunks(recorded: Recorded, built: Built) -> Built:
    """``built`` with the chunks the campaign stepped (its manifest's ``program`` record, else its ``chunk_s`` and
    ``n_chunks``), whatever chunk plan this version makes from the spec: a replay steps the campaign's chunks."""
    man = recorded.manifest
    program = man.get("program") if isinstance(man.get("program"), dict) else {}
    log_dt = built.sim.log_every * built.sim.dt_control
    logs = program.get("logs_per_chunk") or (round(float(man["chunk_s"]) / log_dt) if man.get("chunk_s") else None)
    n_chunks = program.get("n_chunks", man.get("n_chunks"))
    if logs is None or n_chunks is None:
        return built
    return built._replace(logs_per_chunk=int(logs), n_chunks=int(n_chunks))


def _check_plan(recorded: Recorded, built: Built) -> None:
    """The rebuilt batch's size and seeds equal the manifest's (else the code that builds it changed; its chunks
    are the manifest's: :func:`recorded_chunks`)."""
    man, dz = recorded.manifest, built.design
    recorded_value = man.get("n_runs", (man.get("program") or {}).get("n_runs"))
    if recorded_value is not None and int(recorded_value) != dz.n:
        raise InputError(f"{recorded.folder}/manifest.json n_runs = {recorded_value}: this version builds {dz.n} "
                         "from the same spec; replay with the version that ran the campaign")
    if not np.array_equal(dz.seed.astype(np.uint64), np.asarray(man["seeds"], np.uint64)):
        raise InputError(f"{recorded.folder}/manifest.json seeds differ from the design this version builds from the "
                         "same spec; replay with the version that ran the campaign")


def announce(recorded: Recorded, run_ids, built: Built, batches: list, same_layout: bool, spread_mode: str) -> str:
    """The opening line: which runs, the batches, the chunks, physics, sensing and device."""
    c, man = recorded.spec.campaign, recorded.manifest
    chunk_s = built.logs_per_chunk * built.sim.log_every * built.sim.dt_control
    shape = (f"a batch of {built.design.n} runs as the campaign's ({spread_mode})" if same_layout else
             f"{len(batches)} batch(es) of {len(batches[0])} runs, the campaign's per-device batch, on one device")
    xla = (f", XLA deterministic ops {'on' if jaxcfg.deterministic_ops() else 'off'}"
           if jax.default_backend() == "gpu" else "")
    return (f"replaying run{'s' if len(run_ids) > 1 else ''} {', '.join(map(str, run_ids))} of campaign "
            f"{c['name']!r} ({recorded.folder}): {shape}, {built.n_chunks} chunks of {chunk_s:.2f} s, physics "
            f"{man['physics_backend']}, sensing {man['sensing']}, device {jax.devices()[0].device_kind}{xla}")


def _simulate_batch(built: Built, rows: np.ndarray, spread: Spread, slots: dict, bar, first: bool):
    """Step the batch of campaign runs ``rows`` through every chunk; returns ({run: Log}, {run: results}) of the
    runs of ``slots`` (run -> its slot in ``rows``). A signal stops it after the chunk in progress."""
    # the contact list sized as the campaign sized it: its batch's (same layout), each block its own (Warp's blocks)
    batch = spread.place(with_contact_list(take_runs(built.batch, rows)), own_contacts=True)
    fn = chunk_fn(built.sim, batch.in_axes, built.logs_per_chunk, spread.mesh, batch.state_axes)
    n, wanted = len(rows), sorted(slots)
    positions = [slots[r] for r in wanted]
    state, kept = batch.state, []
    if bar is not None and first:
        bar.compiling("compiling or loading the chunk program, then chunk 1")
    with interrupts.Guard("wbc-jax replay") as guard:
        for _ in range(built.n_chunks):
            t0 = time.perf_counter()
            with guard.deferred():  # XLA compiling or running a chunk: a signal stops after it
                state, logs = fn(batch.model, state, batch.plan, batch.om, batch.gains, batch.push, batch.mu_ground)
                host = spread.gather(logs, n)
            guard.check()
            kept.append(runs.take(host, positions))
            if bar is not None:
                bar.chunk_done(time.perf_counter() - t0, fresh=first)
            first = False
        final = spread.gather(state, n, batch.state_axes)
    res = final_results(built.sim, final, np.asarray(built.sim.controller.final_input(host)), built.design.mu[rows])
    logs = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *kept)
    return ({r: jax.tree_util.tree_map(lambda x, i=i: x[i], logs) for i, r in enumerate(wanted)},
            {r: {k: v[slots[r]] for k, v in res.items()} for r in wanted})


def simulate_runs(recorded: Recorded, run_ids, whole_batch: bool = False, progress: bool = True) -> Replayed:
    """Re-simulate the campaign runs ``run_ids`` (module docstring); every chunk of the campaign is stepped.

    Raises:
        InputError: this version rebuilds a different batch from the spec (runs, seeds, chunks).
    """
    spec = recorded.spec
    gains_mod.check_design(spec, recorded.gains)
    print(f"building the campaign's batch ({len(recorded.results)} runs)", flush=True)
    built = recorded_chunks(recorded, build(spec, recorded.gains))
    check_horizon(spec, built)
    _check_plan(recorded, built)
    n, wanted = built.design.n, sorted(run_ids)
    spread = choose(built.sim.robot.backend)
    program, here = campaign_program(recorded.manifest, n), this_program(spread, n)
    same_layout = program == here
    if same_layout:
        batches, slots = [fill_slots(wanted, n, whole_batch)], [{r: r for r in wanted}]
    else:
        batches, spread = part_rows(wanted, n, program, whole_batch), Spread("one")
        parts = sorted({program.part_slot(r)[0] for r in wanted})
        slots = [{r: program.part_slot(r)[1] for r in wanted if program.part_slot(r)[0] == part} for part in parts]
    notes = _notes(recorded, program, here)
    print(announce(recorded, wanted, built, batches, same_layout, spread.mode), flush=True)
    chunk_s = built.logs_per_chunk * built.sim.log_every * built.sim.dt_control
    bar = (ProgressBar(built.n_chunks * len(batches), 0, chunk_s, len(batches[0]), built.sim.dt_physics)
           if progress else None)
    logs, results, t_start = {}, {}, time.perf_counter()
    try:
        for i, (rows, batch_slots) in enumerate(zip(batches, slots)):
            batch_logs, batch_results = _simulate_batch(built, rows, spread, batch_slots, bar, first=i == 0)
            logs.update(batch_logs)
            results.update(batch_results)
    finally:
        if bar is not None:
            bar.close()
    return Replayed(built, batches, same_layout, notes, logs, results, time.perf_counter() - t_start)
