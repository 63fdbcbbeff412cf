"""``wbc-jax campaign``: a spec's whole factorial design (cells x repetitions) as one batched rollout.

spec (``wbc_jax.campaign.spec``) -> design table with per-run seeds and perturbations -> one Batch of all runs
(``wbc_jax.campaign.build``) -> chunked, jitted, vmapped rollout (``chunk_seconds`` of simulated time per call; the
state is checkpointed after every chunk) -> per-run metrics and flags (``wbc_jax.metrics.paper``) ->
``results.csv`` and ``manifest.json`` in DIR (written atomically; ``wbc_jax.campaign.results``,
``wbc_jax.campaign.manifest``), then the ANOVA report (``wbc_jax.analysis.report``) in ``DIR/report/``. A report
that fails leaves the results, writes ``DIR/report_error.txt`` and ends the command with a one-line error (rerun
``wbc-jax report DIR/results.csv``).

DIR must be new or empty, or (``--force``) hold an earlier campaign (``wbc_jax.io_utils.check_out_dir``); it is
checked, with the spec's size against the machine's memory (``wbc_jax.campaign.size.check_size``), before anything
is compiled.

Checkpoint (``wbc_jax.campaign.checkpoint``): ``.<DIR name>.campaign-ckpt/`` next to DIR holds the state after the
last finished chunk and the run's identity (``wbc_jax.campaign.manifest.run_identity``), written in the background
while the next chunk runs and complete before the command ends. Ctrl-C keeps it;
``--resume`` continues from it (the chunks are the same, so the results equal an uninterrupted run's) after checking
the identity and the checksum: a mismatch or damage is a one-line error; it is deleted once the results are
written (the last chunk's own write, then no longer needed, is cancelled). A run that goes non-finite is frozen
by the rollout and reported failed; the others continue.

Several devices or processes (``wbc_jax.rollout.distributed``: ``jax.distributed`` initialised by the CLI): the runs
are spread over them (``wbc_jax.rollout.spread``: on JAX physics one program over every device of every process, on
Warp physics a block of runs per process); every process builds the same batch and steps its own runs; the
states are gathered after each chunk and only process 0 writes (DIR, the checkpoint; the others write nothing).
The checkpoint holds the real runs only (no padding), so a run can resume on another layout; process 0 reads it
and hands it to the others. ``manifest.json``'s ``layout`` records the processes and devices.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import jax

from wbc_jax.campaign import checkpoint, interrupts, preflight
from wbc_jax.campaign.blocks import Blocks
from wbc_jax.campaign.build import (
    _sim,  # noqa: F401  (reached as runner._sim by callers of the campaign's Sim cache)
    build,
    build_ahead,
    check_horizon,
    chunk_fn,
    has_accelerator,
    initial_configuration,  # noqa: F401  (reached as runner.initial_configuration)
    sensing_of,
    states_and_program,
)
from wbc_jax.campaign.job import Job, Status
from wbc_jax.campaign.manifest import COMMAND, Timing, campaign_manifest, setup_figures
from wbc_jax.campaign.manifest import git_commit as _git_commit  # noqa: F401  (reached as runner._git_commit)
from wbc_jax.campaign.manifest import versions as _versions  # noqa: F401  (reached as runner._versions)
from wbc_jax.campaign.progress import ProgressBar, stage, throughput
from wbc_jax.campaign.results import campaign_report, results_table, summarize, zero_noise_warning
from wbc_jax.campaign.resume import Start, kept, start_point
from wbc_jax.campaign.size import n_runs_of
from wbc_jax.campaign.spec import default_spec_path
from wbc_jax.campaign.spec_controller import controller_label
from wbc_jax.errors import OutputError, WbcJaxError
from wbc_jax.io_utils import atomic_dir, release_out_dir, write_json_atomic
from wbc_jax.physics import warp_kernels
from wbc_jax.rollout import distributed
from wbc_jax.rollout.spread import choose

# the stage line before the chunk program compiles
COMPILING = ("compiling the chunk program (the first run on a machine: minutes; later runs load it from the "
             "compilation cache)")


def after_chunk(done: int, n_chunks: int) -> None:
    """Called in every process after each finished chunk (``done`` of ``n_chunks``), once process 0 has begun
    its checkpoint (or with Warp's blocks, each process its block; written in the background, complete before the
    next one begins and before the command ends, however it ends); does nothing. A test replaces it (e.g. to raise
    KeyboardInterrupt after the first chunk)."""


class Rollout(NamedTuple):
    """The finished chunks: the final state (every run, gathered), the object goals of the last chunk, the chunk
    marks of every session, the chunks' wall time of every session and of the earlier ones [s], and when this
    session's chunks began (``time.perf_counter``), and every session's record."""

    state: object
    p_goal: object
    marks: list
    wall_s: float
    wall_before: float
    t_run: float
    sessions: list


def _announce(job: Job) -> None:
    """The campaign's opening lines: warnings, the spread's note, what is simulated where."""
    spec, dz, sp = job.spec, job.built.design, job.spread
    if zero_noise_warning(spec) and job.writer:
        print("warning: all perturbations are zero: repetitions are identical (deterministic runs)", flush=True)
    if sp.note and job.writer:
        print(sp.note, flush=True)
    print(f"{'' if job.writer else f'process {jax.process_index()}: '}campaign {spec.campaign['name']!r} "
          f"({spec.path}): {dz.n} runs = {dz.n // spec.reps} cells x {spec.reps} reps, {job.seconds:.2f} s simulated "
          f"in {job.built.n_chunks} chunks of {job.chunk_s:.2f} s, scene {spec.campaign['scene']}, controller "
          f"{controller_label(spec)}, device {jax.devices()[0].device_kind}"
          f"{sp.describe()}", flush=True)


def _meta(job: Job, start: Start, done: int, marks: list, t_run: float, p_goal) -> dict:
    """The checkpoint's meta.json fields after chunk ``done`` (process 0; the writer adds the state files')."""
    return dict(identity=job.identity, chunks_done=done, n_chunks=job.built.n_chunks,
                logs_per_chunk=job.built.logs_per_chunk, marks=list(marks),
                p_goal=None if p_goal is None else p_goal.tolist(),
                wall_s=start.wall_before + time.perf_counter() - t_run, sessions=list(start.sessions))


def _save(job: Job, start: Start, saver: checkpoint.Writer, gathering, done: int, marks: list, t_run: float):
    """Process 0: chunk ``done``'s gathered (object goal, state) on the host (``gathering``:
    :meth:`wbc_jax.rollout.spread.Gathering.finish`) and its checkpoint begun in the background (``saver``, once
    the previous write ended: one host copy of the state at a time); returns them."""
    saver.join()
    p_goal, state = gathering.finish()
    saver.save(job.ckpt, state, _meta(job, start, done, marks, t_run, p_goal),
               on_saved=lambda: setattr(job.status, "saved", done))
    return p_goal, state


def _dispatch(fn, compiled, b):
    """``state -> fn(b's chunk arguments with that state)`` (dispatch only), with ``compiled`` (the program compiled
    ahead) instead of ``fn`` while its arguments' types match (else traced and compiled again, with a note)."""
    program = [fn if compiled is None else compiled]

    def step(st):
        try:
            return program[0](b.model, st, b.plan, b.om, b.gains, b.push, b.mu_ground)
        except TypeError as e:  # the program compiled ahead takes other argument types
            if program[0] is fn:
                raise
            print(f"note: the chunk program compiled ahead does not take this state ({str(e)[:160]}); compiling "
                  "it again", file=sys.stderr, flush=True)
            program[0] = fn
            return fn(b.model, st, b.plan, b.om, b.gains, b.push, b.mu_ground)
    return step


def _run_chunks(job: Job, start: Start, progress: bool, report: bool, guard: interrupts.Guard,
                saver: checkpoint.Writer, blocks: Blocks | None = None, compiled=None) -> tuple[Rollout, object]:
    """Step every chunk from ``start``, checkpointing after each in the background: the whole state gathered to
    process 0 (``saver``), or with ``blocks`` each process's own runs but the last chunk's; returns the finished
    rollout and the report worker started during it (None without ``report``). A signal stops the run once the
    compile or the chunk in progress ends (``guard``); the finished chunks' checkpoint is kept. ``compiled``: the
    chunk program compiled ahead (:func:`wbc_jax.campaign.build.states_and_program`), called instead of the jitted one
    where its arguments' types match (else the program is traced and compiled again, with a note)."""
    b, sp, n_chunks, dz = job.batch, job.spread, job.built.n_chunks, job.built.design
    fn = chunk_fn(job.built.sim, b.in_axes, job.built.logs_per_chunk, sp.mesh, b.state_axes)
    bar = (ProgressBar(n_chunks, start.done, job.chunk_s, dz.n, job.built.sim.dt_physics)
           if progress and job.writer else None)
    state, done, marks, p_goal, gathered = start.state, start.done, start.marks, start.p_goal, None
    t_run = time.perf_counter()
    first_in_process = True  # that chunk's wall time includes compilation
    step = _dispatch(fn, compiled, b)
    final_input = job.built.sim.controller.final_input  # what finalization needs of the last logs (p_goal)
    reporter = None
    if done < n_chunks and job.writer and compiled is None:
        stage(COMPILING)
    if bar is not None and done < n_chunks and compiled is None:
        bar.compiling(f"compiling, then chunk {done + 1}")
    try:
        with guard.deferred():
            nxt, t0 = (step(state) if done < n_chunks else None), t_run  # the first call compiles
        guard.check()
        if report and job.writer:  # the report's process gets ready during the rollout (wbc_jax.analysis.render),
            from wbc_jax.analysis.render import ReportWorker  # started once the first chunk is traced and compiled

            reporter = ReportWorker.for_machine()
        while done < n_chunks:
            state, logs = nxt
            with guard.deferred():
                state = jax.block_until_ready(state)
                dt_wall = time.perf_counter() - t0
                t0 = time.perf_counter()
                done += 1
                if bar is not None:  # shown before the next chunk's dispatch, which on a CPU runs it
                    bar.chunk_done(dt_wall, fresh=first_in_process)
                # this chunk's gather (or with blocks, this process's runs) goes to the devices ahead of the next
                # chunk, its copy to the host and its checkpoint run beside that chunk (nothing is donated: the state
                # gathered stays valid)
                own = blocks is not None and done < n_chunks  # the last chunk is gathered whole for the results
                if own:
                    gathering = sp.own_start(state, dz.n, b.state_axes)
                else:
                    gathering = sp.gather_start((final_input(logs), state), dz.n, (0, b.state_axes),
                                                fetch=job.writer)
                nxt = step(state) if done < n_chunks else None
            marks.append(dict(chunk=done, wall_s=dt_wall, fresh_process=first_in_process))
            first_in_process = False
            if own:
                blocks.chunk_done(gathering, done, _meta(job, start, done, marks, t_run, None))
            elif job.writer:  # the other processes take part in the gather's collective only
                p_goal, gathered = _save(job, start, saver, gathering, done, marks, t_run)
            if done < n_chunks:
                after_chunk(done, n_chunks)
                guard.check()
    except BaseException:  # a signal, or the checkpoint's write failed
        if bar is not None:
            bar.close()
        if reporter is not None:
            reporter.close()
        with guard.deferred():
            saver.join()  # a finished chunk's checkpoint is complete before the run stops
            if blocks is not None:
                blocks.abandon()
        raise
    if bar is not None:
        bar.close()
    wall = start.wall_before + time.perf_counter() - t_run
    if sp.mode != "one":  # the last chunk's gathered state (process 0), or a collective when this session ran none
        state = gathered if start.done < n_chunks else sp.gather(state, dz.n, b.state_axes)
    return Rollout(state, p_goal, marks, wall, start.wall_before, t_run, start.sessions), reporter


def _write(job: Job, rollout: Rollout, clock: dict, report: bool, reporter, guard: interrupts.Guard,
           saver: checkpoint.Writer, blocks: Blocks | None = None) -> dict:
    """results.csv and manifest.json into DIR (atomically; a signal waits for them), then the last checkpoint's
    write (``saver``) cancelled, or completed where the results were not written, and the checkpoint deleted; then
    the report; the summary lines. ``blocks``: the last checkpoint completed first. Returns the manifest."""
    from wbc_jax.rollout import final_results

    sim, dz = job.built.sim, job.built.design
    res = final_results(sim, rollout.state, rollout.p_goal, dz.mu)
    df = results_table(job.spec, dz, res, sim.controller.extra_columns)
    summary = summarize(job.spec, df)
    rates = throughput(rollout.marks, dz.n, job.chunk_s, job.seconds, sim.dt_physics, rollout.wall_s)
    wall_before = rollout.wall_before
    timing = Timing(total=time.perf_counter() - clock["import"] + wall_before, rollout=rollout.wall_s,
                    imports=clock["start"] - clock["import"], setup=rollout.t_run - clock["start"],
                    compile_estimate=rates.compile_estimate, first_chunk=rates.first_chunk,
                    env_steps_per_s=rates.env_steps_per_s,
                    chunk_walls=tuple(mk["wall_s"] for mk in rollout.marks))
    files = ["manifest.json", "results.csv", *(["report"] if report else [])]
    manifest = campaign_manifest(job.spec, job.built, df, summary, timing, identity=job.identity, gains=job.gains,
                                 sensing=sensing_of(job.spec), spread_mode=job.spread.mode, chunk_s=job.chunk_s,
                                 sessions=rollout.sessions, files=files)
    if blocks is not None:
        with guard.deferred():
            saver.join()  # the last chunk saved whole, then the blocks it replaces go
            blocks.finish()
    try:
        with guard.deferred(), atomic_dir(job.out) as tmp:  # the finished simulation first: a failing report keeps it
            df.to_csv(tmp / "results.csv", index=False)
            manifest["wall_s_total"] = time.perf_counter() - clock["import"] + wall_before
            manifest.update(setup_figures(clock))
            write_json_atomic(tmp / "manifest.json", manifest)
    except BaseException as err:
        with guard.deferred():
            saver.join_keeping(err, job.out)  # no results: the last checkpoint keeps the finished simulation
        raise
    with guard.deferred():
        saver.cancel()  # the results hold the finished simulation
    shutil.rmtree(job.ckpt, ignore_errors=True)
    job.status.stage = "written"
    try:
        guard.check()
    except KeyboardInterrupt:
        if reporter is not None:
            reporter.close()
        raise
    if report:
        campaign_report(job.out, manifest, summary.warnings, reporter)
    for w in manifest["warnings"]:
        print(f"warning: {w}", flush=True)
    flagged = f" ({summary.qp_flagged_runs} QP-flagged on more than 1 % of steps)" if summary.qp_flagged_runs else ""
    print(f"{int(df.success.sum())}/{dz.n} runs succeeded{flagged}; wall {manifest['wall_s_total']:.1f} s, "
          f"{rates.env_steps_per_s:,.0f} env-steps per second; written to {job.status.out}", flush=True)
    return manifest


def run_campaign(spec_path: str | None, out: str, resume: bool = False, report: bool = True,
                 progress: bool = True, gains=None, *, force: bool = False, allow_large: bool = False,
                 inputs: tuple = (), backend: str | None = None) -> dict | None:
    """Run a campaign and write DIR (see module docstring). Returns the manifest.

    Args:
        spec_path: TOML spec; None: :func:`wbc_jax.campaign.spec.default_spec_path` for this machine.
        out: output directory: new or empty, or an earlier campaign's with ``force``.
        resume: continue from the checkpoint next to DIR if there is one.
        report: also write the ANOVA report (``report/``).
        progress: show a progress bar on stderr.
        gains: controller gains (unbatched TransportGains) instead of the defaults.
        force: replace DIR when it holds an earlier campaign.
        allow_large: run even when the memory estimate (:func:`wbc_jax.campaign.size.check_size`) exceeds what is
            available.
        inputs: further input files (e.g. the gains file) that DIR must not hold.
        backend: physics backend ("auto", "jax", "warp") instead of the spec's ``campaign.backend``.

    Returns:
        The manifest; None in a process other than process 0 of a multi-process run (it writes nothing).

    Raises:
        OutputError, LimitError, CheckpointError, SpecError: before anything is compiled (in every process of a
            multi-process run: process 0's checks are every process's).
        ReportError: the report failed after results.csv and manifest.json were written.
    """
    clock = {"import": time.perf_counter()}
    import wbc_jax.rollout.batch  # noqa: F401  (MJX, the controllers, the planner: timed apart from setup)

    clock["start"] = time.perf_counter()
    request = dict(spec_path=spec_path, out=out, resume=resume, report=report, progress=progress, gains=gains,
                   force=force, allow_large=allow_large, inputs=inputs, backend=backend)
    status = Status(str(out))
    with interrupts.Guard(COMMAND, status.describe) as guard:
        try:
            return _campaign(request, clock, status, guard)
        except KeyboardInterrupt as e:
            raise interrupts.as_interrupted(e, status.describe()) from None
        finally:
            try:
                release_out_dir(out)
            except OutputError:  # a path refused before any claim
                pass


def _campaign(request: dict, clock: dict, status: Status, guard: interrupts.Guard) -> dict | None:
    """:func:`run_campaign`'s steps (``request``: its arguments): checks, build, chunks, results."""
    r = request
    spec_path = r["spec_path"] if r["spec_path"] is not None else default_spec_path(has_accelerator())
    if distributed.is_writer():
        stage(f"reading the spec {spec_path} and checking the output folder")
    spec, physics_backend, identity = preflight.checked_spec(spec_path, r["backend"], r["gains"])
    status.writer = distributed.is_writer()
    sp = choose(physics_backend)  # several devices: each steps its own runs (wbc_jax.rollout.spread)
    out_p, ck = preflight.check_outputs(spec, r["out"], identity, resume=r["resume"], force=r["force"],
                                        allow_large=r["allow_large"], inputs=r["inputs"], backend_flag=r["backend"],
                                        parts=sp.parts)
    status.ckpt = ck
    status.saved, status.n_chunks = kept(ck)
    for line in preflight.notes(spec, physics_backend, r["allow_large"], sp.parts) if status.writer else []:
        print(line, flush=True)
    preload = warp_kernels.start_preload(physics_backend)  # Warp's kernels compile while the batch is built
    # Warp on one device, from the start: the chunk program is traced from the batch's shapes, then compiled while
    # the initial states' first MuJoCo Warp call compiles the model's kernels (build.states_and_program)
    ahead = physics_backend == "warp" and sp.mode == "one" and status.saved == 0
    if status.writer:
        stage(f"building {n_runs_of(spec)} runs on scene {spec.campaign['scene']} (initial states, plans, pushes)"
              + ("; MuJoCo Warp's kernels compiling meanwhile" if preload else ""))
    compiled = None
    with guard.deferred():  # the batch's initial states compile
        built, with_states = build_ahead(spec, r["gains"]) if ahead else (build(spec, r["gains"]), None)
        if ahead:
            if status.writer:
                stage(COMPILING)
            built, compiled, clock["chunk_ahead_s"] = states_and_program(built, with_states,
                                                                         preload and preload.ahead)
        if preload is not None:
            clock["warp_preload_s"] = preload.result()[1]
            clock["warp_ahead"] = preload.ahead
    guard.check()
    check_horizon(spec, built)
    job = Job(spec, built, sp.place(built.batch, own_contacts=True), sp, identity, r["gains"], status.writer, out_p,
              ck, status)
    start = start_point(job, built.batch.state, r["resume"])
    status.stage, status.n_chunks = "chunks", built.n_chunks
    _announce(job)
    saver = checkpoint.Writer()
    blocks = (Blocks(ck or checkpoint.ckpt_dir(Path(r["out"]).absolute()), sp, built.design.n, job.writer,
                     on_meta=lambda k: setattr(status, "saved", k)) if sp.mode == "blocks" else None)
    try:
        rollout, reporter = _run_chunks(job, start, r["progress"], r["report"], guard, saver, blocks, compiled)
        if not job.writer:
            if blocks is not None:
                with guard.deferred():
                    blocks.finish()  # once process 0 has saved the last chunk whole
            print(f"process {jax.process_index()}: done; process 0 writes {r['out']}", flush=True)
            return None
        return _write(job, rollout, clock, r["report"], reporter, guard, saver, blocks)
    finally:  # however the command ends, a finished chunk's checkpoint is complete first
        with guard.deferred():
            saver.join()


def run_in_fresh_process(spec_path, out: Path, report: bool = False, **env) -> Path:
    """``wbc-jax campaign --spec SPEC --out OUT`` (``--no-report`` unless ``report``) in a new Python process (``env``
    set on top of this one's environment); returns OUT. A failed run raises WbcJaxError with the end of its stderr."""
    cmd = [sys.executable, "-m", "wbc_jax", "campaign", "--spec", str(spec_path), "--out", str(out)]
    r = subprocess.run(cmd + ["--no-report"] * (not report), env={**os.environ, **env}, capture_output=True, text=True)
    if r.returncode != 0:
        extra = " ".join(f"{k}={v}" for k, v in env.items())
        raise WbcJaxError(f"campaign {spec_path} ({extra}) failed: {r.stderr.strip()[-800:]}")
    return Path(out)
