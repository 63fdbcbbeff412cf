"""``wbc-jax campaign --dry-run``: what a campaign would simulate, and whether it would start, without running it.

The same checks as the campaign's, in the same order (the spec, the gains, the output folder and its checkpoint, the
batch's size against this machine's memory, the horizon), then the batch built with its plans but not its initial
states (:func:`wbc_jax.campaign.build.build_ahead`), so that the figures are the run's own: runs, chunks, simulated
time, physics steps. The chunk program is not compiled and nothing is simulated; nothing is written in or beside the
output folder (it is checked, not claimed). The plans and the planner's small programs go into the compilation cache
as the campaign's would (its run then loads them). A campaign that would be refused raises the error the campaign
would.
"""

from __future__ import annotations

import jax

from wbc_jax.campaign import checkpoint, preflight
from wbc_jax.campaign.build import (
    LOG_EVERY,
    build_ahead,
    check_horizon,
    has_accelerator,
)
from wbc_jax.campaign.job import chunk_seconds
from wbc_jax.campaign.progress import stage
from wbc_jax.campaign.results import zero_noise_warning
from wbc_jax.campaign.resume import kept
from wbc_jax.campaign.size import memory_need, own_memories
from wbc_jax.campaign.spec import default_spec_path
from wbc_jax.campaign.spec_controller import controller_label
from wbc_jax.rollout.spread import choose


def dry_run(spec_path: str | None, out, *, resume: bool = False, force: bool = False, allow_large: bool = False,
            gains=None, inputs: tuple = (), backend: str | None = None, processes: int = 1,
            local_devices: int | None = None) -> dict:
    """Check a campaign as ``wbc_jax.campaign.runner.run_campaign`` would with these arguments, print what it would
    run, and return it. ``processes``: the processes the campaign will run as (``--num-processes``, SLURM's tasks),
    each with ``local_devices`` devices (``--local-device-ids``; None: this process's); the dry run joins none.

    Returns:
        dict: ``spec``, ``name``, ``runs``, ``cells``, ``reps``, ``factors`` ({name: levels}), ``controller``,
        ``scene``, ``backend`` (the physics), ``device``, ``seconds`` (simulated per run [s]), ``chunks``,
        ``chunk_seconds`` [s], ``physics_steps`` (per run), ``env_steps`` (all runs), ``memory_bytes`` (a device's
        estimate), ``available_bytes`` (None where unknown; this machine's), ``parts`` (the devices the runs are
        split over), ``out`` (as given), ``out_state`` ("new"; "replaced": an earlier campaign replaced with
        ``force``; "resumed"), ``chunks_done`` (kept in the checkpoint and not simulated again),
        ``chunks_discarded`` (finished chunks of a checkpoint that ``force`` deletes), ``checkpoint`` (with
        ``resume`` and none to resume: where none was found; else None).

    Raises:
        SpecError, OutputError, CheckpointError, LimitError: what the campaign would raise, before it compiled.
    """
    spec_path = spec_path if spec_path is not None else default_spec_path(has_accelerator())
    spec, physics, identity = preflight.checked_spec(spec_path, backend, gains)
    spread = choose(physics)
    parts = layout_parts(spread.parts, physics, processes, local_devices)
    out_p, ck = preflight.check_outputs(spec, out, identity, resume=resume, force=force, allow_large=allow_large,
                                        inputs=inputs, backend_flag=backend, parts=parts, claim=False)
    discarded = 0 if resume else kept(ck)[0]  # a checkpoint --force lets the campaign delete
    warning = zero_noise_warning(spec)
    for line in [*([f"warning: {warning}"] if warning else []), *([spread.note] if spread.note else []),
                 *preflight.notes(spec, physics, allow_large, parts)]:
        if line.startswith(("warning:", "note:")):
            print(line, flush=True)
    stage(f"planning the runs of {spec.path} (nothing is simulated)")
    built, _ = build_ahead(spec, gains)
    check_horizon(spec, built)
    done = 0
    if resume and checkpoint.read_meta(ck, identity, built.n_chunks, built.logs_per_chunk) is not None:
        done = kept(ck)[0]
    sim, n = built.sim, built.design.n
    chunk_s = chunk_seconds(built)
    steps = built.n_chunks * built.logs_per_chunk * LOG_EVERY * sim.n_substeps
    need, avail = memory_need(spec, parts)
    earlier = out_p is not None and out_p.is_dir() and any(out_p.iterdir())
    plan = dict(spec=spec.path, name=spec.campaign["name"], runs=n, cells=n // spec.reps, reps=spec.reps,
                factors={k: list(v) for k, v in spec.factors.items()},
                controller=controller_label(spec), scene=spec.campaign["scene"],
                backend=physics, device=jax.devices()[0].device_kind, seconds=built.n_chunks * chunk_s,
                chunks=built.n_chunks, chunk_seconds=chunk_s, physics_steps=steps, env_steps=steps * n,
                memory_bytes=need, available_bytes=avail, parts=parts, out=str(out),
                out_state="resumed" if done else "replaced" if earlier else "new", chunks_done=done,
                chunks_discarded=discarded, checkpoint=str(ck) if resume and not done else None)
    for line in describe(plan, per_device=own_memories(parts) > 1, dt_physics=sim.dt_physics):
        print(line, flush=True)
    return plan


def layout_parts(here: int, physics: str, processes: int, local_devices: int | None = None) -> int:
    """The devices a campaign of ``processes`` processes splits its runs over (``wbc_jax.rollout.spread``; ``here``:
    this process's split): on Warp physics one block per process, on JAX physics one mesh over every process's
    ``local_devices`` (None: as many as this process has)."""
    if processes <= 1:
        return here
    if physics == "warp":
        return processes
    return processes * (local_devices if local_devices else jax.local_device_count())


def memory_phrase(need: float, available: int | None, devices: int = 1) -> str:
    """A dry run's memory estimate ``need`` [bytes] (a device's, on each of ``devices`` when more than one) with the
    ``available`` memory [bytes] when known, e.g. "about 28.94 GiB, 104.4 GiB available"."""
    return (f"about {need / 2**30:,.2f} GiB" + (f" on each of {devices} devices" if devices > 1 else "")
            + (f", {available / 2**30:,.1f} GiB available" if available else ""))


def describe(plan: dict, per_device: bool = False, dt_physics: float | None = None) -> list[str]:
    """The dry run's lines for a :func:`dry_run` result."""
    levels = "; ".join(f"{k} = {', '.join(str(v) for v in vals)}" for k, vals in plan["factors"].items())
    step = f" of {dt_physics * 1e3:g} ms" if dt_physics else ""
    memory = memory_phrase(plan["memory_bytes"], plan["available_bytes"], plan["parts"] if per_device else 1)
    where = {"new": "a new folder" + (f"; no checkpoint at {plan['checkpoint']}: starts from the beginning"
                                      if plan.get("checkpoint") else ""),
             "replaced": "holds an earlier campaign, which --force replaces",
             "resumed": f"resumes after {plan['chunks_done']} of {plan['chunks']} chunks (--resume)"}[plan["out_state"]]
    if plan.get("chunks_discarded"):
        where += f"; --force deletes the checkpoint of {plan['chunks_discarded']} finished chunks beside it"
    return [f"dry run of campaign {plan['name']!r} ({plan['spec']}): nothing is simulated, nothing written in --out",
            f"  {plan['runs']:,} runs = {plan['cells']} cells x {plan['reps']} reps; {levels}",
            f"  each run {plan['seconds']:.2f} s simulated in {plan['chunks']} chunks of {plan['chunk_seconds']:.2f} s "
            f"({plan['physics_steps']:,} physics steps{step}); {plan['env_steps']:,} env-steps in all",
            f"  controller {plan['controller']}, scene {plan['scene']}, physics {plan['backend']} on "
            f"{plan['device']}; memory {memory}",
            f"  --out {plan['out']}: {where}",
            "the campaign would start: the same command without --dry-run runs it"]
