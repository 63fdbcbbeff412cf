"""The ``wbc-jax`` console script.

Subcommands import their modules lazily so that ``wbc-jax report`` does not pay for JAX.
User errors (:class:`wbc_jax.errors.WbcJaxError`) become one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import sys

from wbc_jax.campaign import interrupts
from wbc_jax.campaign.progress import stage
from wbc_jax.cli import checks
from wbc_jax.cli import parser as parser_module
from wbc_jax.errors import UsageError, WbcJaxError
from wbc_jax.io_utils import check_file_target, check_out_dir, claim_out_dir, release_out_dir
from wbc_jax.rollout import distributed
from wbc_jax.runtime import jaxcfg
from wbc_jax.studies import replay, warmup

CPU_BATCHES = {"rollout": (1, 4, 16), "profile": 16, "components": 16, "trace": 16}  # bench defaults on a CPU


def _cmd_report(args: argparse.Namespace) -> int:
    from wbc_jax.analysis.render import Workers

    workers = Workers.for_machine()  # they import matplotlib while this process imports the statistics
    try:
        from wbc_jax.analysis.report import run_report

        factors = args.factors.split(",") if args.factors else None
        metrics = args.metrics.split(",") if args.metrics else None
        claim_out_dir(args.out, "wbc-jax report")
        run_report(args.results, args.out, alpha=args.alpha, factors=factors, metrics=metrics, force=args.force,
                   workers=workers)
    finally:
        if workers is not None:
            workers.close()
    print(f"report written to {args.out}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    sizes = checks.bench_args(args)
    if args.json is not None:  # before anything is measured: a result never overwrites a file by surprise
        check_file_target(args.json, "--json", force=args.force)
    cold_warm = None
    if args.cold_warm:  # first: the runs are whole processes, each taking the GPU's memory as a user's run does
        from wbc_jax.bench.rollout import campaign_cold_warm

        cold_warm = campaign_cold_warm(args.campaign)
    _join_processes(args)  # rollout: one process per device (wbc_jax.bench.rollout)
    import jax

    cpu = jax.default_backend() == "cpu"  # GPU-sized default batches would run for hours on a CPU
    if args.what == "qp":
        from wbc_jax.bench.qp import run_bench

        run_bench(quick=args.quick, json_path=args.json)
        return 0
    if args.what == "rollout":
        from wbc_jax.bench.rollout import run_bench as run_rollout_bench

        backends = tuple(x for x in args.backend.split(",") if x)
        batches = sizes or ((1, 4) if args.quick else CPU_BATCHES["rollout"] if cpu else (1, 1024, 4096, 16384))
        kw = dict(batches=batches, steps=args.steps, iters=args.iters, json_path=args.json, scene=args.scene,
                  qp=args.qp, substeps=args.substeps, cold_warm=cold_warm,
                  backends=backends, rounds=args.rounds or (3 if cpu else 5))
        if args.campaign is None:
            run_rollout_bench(**kw)
            return 0
        from wbc_jax.bench.campaign_step import run_bench_with_campaign

        breakdown = checks.bench_args(argparse.Namespace(**{**vars(args), "batches": args.breakdown}))
        if args.snapshots < 1:
            raise WbcJaxError(f"--snapshots {args.snapshots}: expected an integer >= 1")
        run_bench_with_campaign(args.campaign, snapshots=args.snapshots, breakdown=breakdown, **kw)
        return 0
    if args.what == "profile":
        from wbc_jax.bench.rollout import run_profile

        batch = sizes[-1] if sizes else (4 if args.quick else CPU_BATCHES["profile"] if cpu else 16384)
        run_profile(batch=batch, steps=args.steps, iters=args.iters, scene=args.scene, json_path=args.json,
                    variants=args.variants.split(",") if args.variants else None)
        return 0
    if args.what == "components":
        from wbc_jax.bench.components import run_components

        batch = sizes[-1] if sizes else (4 if args.quick else CPU_BATCHES["components"] if cpu else 256)
        run_components(batch=batch, iters=args.iters, scene=args.scene, json_path=args.json)
        return 0
    if args.what == "trace":
        from wbc_jax.bench.trace import run_trace

        batch = sizes[-1] if sizes else (4 if args.quick else CPU_BATCHES["trace"] if cpu else 270)
        run_trace(batch=batch, steps=args.steps, scene=args.scene, qp=args.qp, substeps=args.substeps,
                  json_path=args.json, backend=(args.backend or "jax").split(",")[0], warmup_s=args.warmup)
        return 0
    if args.what == "qp-rollout":
        from wbc_jax.bench.qp_audit import audit

        audit(args.variants.split(",") if args.variants else None, scene=args.scene,
              seconds=0.4 if args.quick else 1.2, json_path=args.json)
        return 0
    raise WbcJaxError(f"bench: unknown target {args.what!r}")


def _check_out(args: argparse.Namespace, inputs=()) -> None:
    """The ``--out`` folder of ``args.command``, claimed for this command (new, empty, or an earlier run of it with
    ``--force``)."""
    claim_out_dir(args.out, f"wbc-jax {args.command}")
    check_out_dir(args.out, f"wbc-jax {args.command}", force=args.force, inputs=inputs)


def _cmd_demo(args: argparse.Namespace) -> int:
    checks.demo_args(args)
    from wbc_jax.studies.demo import demo_backend

    if demo_backend(args.backend) == "warp":  # a bad --backend fails here, before anything is written
        import jax

        if jax.default_backend() == "cpu":
            print("warning: --backend warp on a CPU: MuJoCo Warp's kernels run on the CPU here, many times slower "
                  "than --backend jax", flush=True)
    _check_out(args, [args.scene if args.scene.endswith(".xml") else None])
    from wbc_jax.studies.demo import run_demo

    run_demo(out=args.out, scene=args.scene, seconds=args.seconds, all_cells=args.all_cells, push=args.push,
             observer=not args.no_observer, iters=args.iters, distance=args.distance, push_at=args.push_at,
             video=not args.no_video, backend=args.backend)
    return 0


def _cmd_trot(args: argparse.Namespace) -> int:
    from wbc_jax.studies.trot import run_trot, validate

    try:
        errors = [float(x) for x in args.mass_errors.split(",")]
    except ValueError:
        raise WbcJaxError(f"--mass-errors = {args.mass_errors!r}: expected comma-separated numbers, "
                          "e.g. --mass-errors=-0.2,0,0.2") from None
    validate(args.seconds, args.stride, args.step_time, args.four_foot, errors, args.iters, args.snapshots)
    _check_out(args)
    run_trot(out=args.out, seconds=args.seconds, stride=args.stride, step_time=args.step_time, t_four=args.four_foot,
             mass_errors=errors, carry_object=not args.no_object, iters=args.iters, snapshots=args.snapshots)
    return 0


def _join_processes(args: argparse.Namespace) -> None:
    """``jax.distributed`` from the ``--coordinator`` / ``--num-processes`` / ``--process-id`` flags or the
    environment (``wbc_jax.rollout.distributed``), before anything touches a device; nothing when none is set."""
    distributed.initialize(distributed.resolve(args.coordinator, args.num_processes, args.process_id,
                                               args.local_device_ids))


def _layout_to_come(args: argparse.Namespace) -> dict:
    """A dry run's ``processes`` and ``local_devices``: the processes the command will run as, from the
    ``--coordinator`` / ``--num-processes`` / ``--process-id`` / ``--local-device-ids`` flags or the environment,
    resolved without joining them."""
    layout = distributed.resolve(args.coordinator, args.num_processes, args.process_id, args.local_device_ids)
    return dict(processes=layout.num_processes if layout else 1,
                local_devices=len(layout.local_device_ids) if layout and layout.local_device_ids else None)


def _cmd_campaign(args: argparse.Namespace) -> int:
    if args.spec is not None:  # a bad spec fails in a second, before JAX and MuJoCo MJX load (seconds)
        from wbc_jax.campaign.spec import load_spec

        load_spec(args.spec)
    stage("loading JAX, MuJoCo MJX and the controllers")
    if not args.dry_run:  # a dry run checks this process's devices alone
        _join_processes(args)
    jaxcfg.start_backend()  # the device's client starts while MJX imports
    from wbc_jax.campaign.runner import run_campaign

    gains = None
    if args.gains is not None:
        from wbc_jax.campaign.gains import load_gains

        gains = load_gains(args.gains)  # validated before anything runs or is written
        print(f"gains from {args.gains}", flush=True)
    inputs = (args.gains,) if args.gains else ()
    if args.dry_run:  # the processes the campaign will run as, from the flags or the environment, not joined
        from wbc_jax.campaign.dry_run import dry_run

        dry_run(args.spec, args.out, resume=args.resume, force=args.force, allow_large=args.allow_large, gains=gains,
                inputs=inputs, backend=args.backend, **_layout_to_come(args))
        return 0
    run_campaign(args.spec, args.out, resume=args.resume, report=not args.no_report, gains=gains, force=args.force,
                 allow_large=args.allow_large, inputs=inputs, backend=args.backend)
    return 0


def _cmd_tune(args: argparse.Namespace) -> int:
    if not args.dry_run:  # a dry run joins no process (it counts them)
        _join_processes(args)
    jaxcfg.start_backend()
    from wbc_jax.studies.tune import dry_run_tune, run_tune

    if args.dry_run:  # the processes the tune will run as, from the flags or the environment, not joined
        dry_run_tune(args.spec, args.out, candidates=args.candidates, rounds=args.rounds, batch=args.batch,
                     force=args.force, backend=args.backend, **_layout_to_come(args))
        return 0
    if distributed.is_writer():  # process 0 writes --out
        claim_out_dir(args.out, "wbc-jax tune")
    run_tune(args.spec, args.out, candidates=args.candidates, rounds=args.rounds, batch=args.batch,
             progress=not args.no_progress, force=args.force, backend=args.backend)
    return 0


def _cmd_regress(args: argparse.Namespace) -> int:
    from wbc_jax.campaign.regress import compare_campaigns, run_regress

    if args.compare:
        if args.update:
            raise UsageError("--compare takes two campaigns' folders and writes nothing; drop --update")
        return compare_campaigns(*args.compare)[0]
    code, _ = run_regress(args.baseline, update=args.update)
    return code


COMMANDS = {"report": _cmd_report, "bench": _cmd_bench, "demo": _cmd_demo, "campaign": _cmd_campaign,
            "tune": _cmd_tune, "regress": _cmd_regress, "trot": _cmd_trot, "replay": replay.main,
            "warmup": warmup.main}


def main(argv: list[str] | None = None) -> int:
    """Run one ``wbc-jax`` command; returns its exit code: 0, 1 (regress: a metric moved), 2 (a user error, one line
    on stderr), 130 (SIGINT) or 143 (SIGTERM; one line saying what the command left)."""
    try:
        args, extra = parser_module.build_parser().parse_known_args(argv)
        if extra:
            raise UsageError(f"unrecognized arguments: {' '.join(extra)} (wbc-jax {args.command} --help lists the "
                             "arguments)", prog=f"wbc-jax {args.command}")
    except UsageError as e:
        print(f"{e.prog}: error: {e}", file=sys.stderr)
        return 2
    if args.command != "report":
        jaxcfg.configure()
    name = f"wbc-jax {args.command}"
    with interrupts.Guard(name):
        try:
            return int(COMMANDS[args.command](args) or 0)
        except WbcJaxError as e:
            print(f"{name}: error: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as e:
            stop = interrupts.as_interrupted(e)
            print(f"{name}: {stop}", file=sys.stderr)
            return stop.exit_code
        finally:
            release_out_dir()


def run() -> None:
    """The console script and ``python -m wbc_jax``: :func:`main`, then the process ends without tearing down the
    interpreter.

    Once a command has returned, what it wrote is closed (files are written atomically and closed before the
    command returns). Threads that are not daemons are waited for, a process of a multi-process run that succeeded
    leaves it (:func:`wbc_jax.rollout.distributed.leave`), Python's exit handlers (``atexit``: logging, JAX's
    clean-up, ``weakref.finalize``) still run, and stdout and stderr are flushed. What is skipped is the
    interpreter's finalization, which frees every module and the GPU client's and MuJoCo Warp's objects one by
    one, where the operating system frees a process's memory and device context at once. An exception escaping
    :func:`main` (``--help`` included) takes Python's normal exit.
    """
    import atexit
    import os
    import threading

    code = main()
    for t in threading.enumerate():
        if t is not threading.main_thread() and not t.daemon:
            t.join()
    if code == 0:  # a failing process leaves as before (JAX's exit handler), without waiting here for its partners
        distributed.leave()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or a broken pipe: nothing left to flush there
            pass
    os._exit(code)


if __name__ == "__main__":
    run()
