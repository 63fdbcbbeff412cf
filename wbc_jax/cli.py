"""The ``wbc-jax`` console script.

Subcommands import their modules lazily so that ``wbc-jax report`` does not pay for JAX.
User errors (:class:`wbc_jax.errors.WbcJaxError`) become one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import sys

from wbc_jax.errors import WbcJaxError

MAX_SECONDS = 600.0  # longest simulated time of demo / trot [s] (a campaign's max_seconds has the same bound)
DISTANCE_RANGE = (0.05, 10.0)  # demo --distance [m], as a campaign spec's campaign.distance
CPU_BATCHES = {"rollout": (1, 4, 16), "profile": 16, "components": 16, "trace": 16}  # bench defaults on a CPU


def _cmd_report(args: argparse.Namespace) -> int:
    from wbc_jax.analysis.render import Workers

    workers = Workers.for_machine()  # they import matplotlib while this process imports the statistics
    try:
        from wbc_jax.analysis.report import run_report

        factors = args.factors.split(",") if args.factors else None
        metrics = args.metrics.split(",") if args.metrics else None
        run_report(args.results, args.out, alpha=args.alpha, factors=factors, metrics=metrics, force=args.force,
                   workers=workers)
    finally:
        if workers is not None:
            workers.close()
    print(f"report written to {args.out}")
    return 0


def _check_bench_args(args: argparse.Namespace) -> list[int] | None:
    """The ``--batches`` sizes (None when not given); bad ``bench`` arguments as user errors (flag, value, expected
    range) before anything is compiled."""
    from wbc_jax.errors import InputError

    sizes = None
    if args.batches is not None:
        try:
            sizes = [int(x) for x in args.batches.split(",")]
        except ValueError:
            sizes = []
        if not sizes or min(sizes) < 1:
            raise InputError(f"--batches {args.batches!r}: expected comma-separated integers >= 1, e.g. 1,1024")
    for flag in ("steps", "iters", "substeps", "rounds"):
        if getattr(args, flag) is not None and getattr(args, flag) < 1:
            raise InputError(f"--{flag} {getattr(args, flag)}: expected an integer >= 1")
    if args.qp is not None:
        from wbc_jax.bench.qp_audit import variants

        try:
            variants([args.qp])
        except ValueError as e:
            raise InputError(f"--qp: {e}") from None
    if args.what in ("rollout", "trace"):
        from wbc_jax.physics.backend import BACKENDS, resolve_backend
        from wbc_jax.rollout import resolve_sensing

        names = [x for x in str(args.backend).split(",") if x]
        try:
            if not names:
                raise ValueError("empty list")
            if args.what == "trace" and len(names) > 1:
                raise ValueError("trace takes one backend")
            for x in names:
                name, _, sensing = x.partition(":")
                resolve_sensing(sensing or "auto", resolve_backend(name), args.substeps)
        except ValueError as e:
            raise InputError(f"--backend {args.backend!r}: {e} (expected a comma-separated list of "
                             f"{', '.join(BACKENDS)}, each optionally with :auto, :exact or :delayed)") from None
    return sizes


def _cmd_bench(args: argparse.Namespace) -> int:
    sizes = _check_bench_args(args)
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
        run_rollout_bench(batches=batches, steps=args.steps, iters=args.iters, json_path=args.json, scene=args.scene,
                          qp=args.qp, substeps=args.substeps, campaign=args.campaign, backends=backends,
                          rounds=args.rounds or (3 if cpu else 5))
        return 0
    if args.what == "profile":
        from wbc_jax.bench.rollout import run_profile

        batch = sizes[-1] if sizes else (4 if args.quick else CPU_BATCHES["profile"] if cpu else 16384)
        run_profile(batch=batch, steps=args.steps, iters=args.iters, scene=args.scene, json_path=args.json,
                    variants=args.variants.split(",") if args.variants else None)
        return 0
    if args.what == "components":
        from wbc_jax.bench.rollout import run_components

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


def _check_demo_args(args: argparse.Namespace) -> None:
    """Bounded, finite demo arguments (user errors before anything is built)."""
    from wbc_jax.errors import LimitError

    lo, hi = DISTANCE_RANGE
    bounds = {"seconds": (0.0, MAX_SECONDS, "0 < value <= 600 [s]"), "distance": (lo, hi, f"{lo} <= value <= {hi} [m]"),
              "push_at": (0.0, 1.0, "0 < value < 1 (fraction of the planned duration)")}
    for name, (a, b, text) in bounds.items():
        v = getattr(args, name)
        if v is not None and not (a < v <= b if name == "seconds" else a <= v <= b if name == "distance"
                                  else a < v < b):
            raise LimitError(f"--{name.replace('_', '-')} = {v}: expected {text}")
    if not 1 <= args.iters <= 1000:
        raise LimitError(f"--iters = {args.iters}: expected 1 <= value <= 1000")


def _check_out(args: argparse.Namespace, inputs=()) -> None:
    """The ``--out`` folder of ``args.command`` (new, empty, or an earlier run of it with ``--force``)."""
    from wbc_jax.io_utils import check_out_dir

    check_out_dir(args.out, f"wbc-jax {args.command}", force=args.force, inputs=inputs)


def _cmd_demo(args: argparse.Namespace) -> int:
    _check_demo_args(args)
    from wbc_jax.studies.demo import demo_backend

    demo_backend(args.backend)  # a bad --backend before anything is written
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
    from wbc_jax.rollout import distributed

    distributed.initialize(distributed.resolve(args.coordinator, args.num_processes, args.process_id,
                                               args.local_device_ids))


def _cmd_campaign(args: argparse.Namespace) -> int:
    _join_processes(args)
    from wbc_jax.campaign.runner import run_campaign

    gains = None
    if args.gains is not None:
        from wbc_jax.campaign.gains import load_gains

        gains = load_gains(args.gains)  # validated before anything runs or is written
        print(f"gains from {args.gains}", flush=True)
    run_campaign(args.spec, args.out, resume=args.resume, report=not args.no_report, gains=gains, force=args.force,
                 allow_large=args.allow_large, inputs=(args.gains,) if args.gains else (), backend=args.backend)
    return 0


def _cmd_tune(args: argparse.Namespace) -> int:
    _join_processes(args)
    from wbc_jax.studies.tune import run_tune

    run_tune(args.spec, args.out, candidates=args.candidates, rounds=args.rounds, batch=args.batch,
             progress=not args.no_progress, force=args.force, backend=args.backend)
    return 0


def _cmd_regress(args: argparse.Namespace) -> int:
    from wbc_jax.campaign.regress import run_regress

    code, _ = run_regress(args.baseline, update=args.update)
    return code


def _backend_flag(parser: argparse.ArgumentParser, default: str) -> None:
    """``--backend auto|jax|warp``: the MJX physics implementation (``wbc_jax.physics.backend.resolve_backend``)."""
    parser.add_argument("--backend", choices=("auto", "jax", "warp"), default=None,
                        help=f"MJX physics implementation (default: {default}; 'auto' = MuJoCo Warp on a CUDA GPU "
                             "with warp-lang installed (pip install -e '.[cuda]'), else MJX's JAX implementation)")


def _process_flags(parser: argparse.ArgumentParser) -> None:
    """The flags that join a multi-process run (``wbc_jax.rollout.distributed``, docs/cluster.md)."""
    parser.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                        help="several processes (one per host or GPU; docs/cluster.md): process 0's address, the "
                             "same in every process (default: $JAX_COORDINATOR_ADDRESS, or the first node of a "
                             "SLURM step)")
    parser.add_argument("--num-processes", default=None, metavar="N",
                        help="number of processes (default: $JAX_NUM_PROCESSES or SLURM's task count; none: one "
                             "process)")
    parser.add_argument("--process-id", default=None, metavar="I",
                        help="this process's id, 0 to N-1; process 0 writes everything (default: $JAX_PROCESS_ID "
                             "or $SLURM_PROCID)")
    parser.add_argument("--local-device-ids", default=None, metavar="IDS",
                        help="comma-separated ids of the local devices this process uses, e.g. 0 (default: all it "
                             "sees)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="wbc-jax", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("report", help="ANOVA report of a results table (one row per run)")
    r.add_argument("results", help="results CSV (one row per run)")
    r.add_argument("--out", required=True, help="output directory (new or empty; never the input's)")
    r.add_argument("--alpha", type=float, default=0.05, help="significance level (default 0.05)")
    r.add_argument("--factors", default=None, help="comma-separated factor columns (default: the campaign's, "
                                                        "from manifest.json beside the results; else m,mu,d)")
    r.add_argument("--metrics", default=None, help="comma-separated metric columns (default: inferred)")
    r.set_defaults(func=_cmd_report)

    b = sub.add_parser("bench", help="benchmarks on the current device")
    b.add_argument("what", choices=["qp", "rollout", "profile", "components", "trace", "qp-rollout"],
                   help="what to benchmark (profile: where a control step's time goes, at the last --batches size, "
                        "from variants; components: latency of each stage of a control step; trace: a device trace "
                        "of --steps control steps at the last --batches size (default 270, the paper campaign's), "
                        "kernels and device time per stage; qp-rollout: control-loop "
                        "ADMM variants (--variants it50,it20_a0,...) against OSQP on QPs sampled from their own "
                        "closed-loop rollouts, CPU)")
    b.add_argument("--batches", default=None, help="rollout: comma-separated batch sizes (default 1,1024,4096,16384 "
                                                   "on an accelerator, 1,4,16 on a CPU)")
    b.add_argument("--steps", type=int, default=200, help="rollout: control steps per timed call")
    b.add_argument("--rounds", type=int, default=None, help="rollout: timed rounds per batch, each a physics-only "
                   "and a physics + WBC call; the figures are the rounds' medians (default 5; 3 on a CPU)")
    b.add_argument("--iters", type=int, default=4, help="rollout: ADMM iterations per control step before the "
                                                         "convergence checks (the control loop's default: 4)")
    b.add_argument("--qp", default=None, help="rollout: control-loop ADMM variant it<N>[_a<K>][_b<B>][_rho<R>][_r<R>]"
                                          "[_pol<P>][_e<E>][_m<M>][_c<C>][_tol<T>] (N iterations, rho adapted every K "
                                          "(0: never), adaptation bias B, rho R, R Ruiz passes, P polishing passes, "
                                          "E rows held exactly, up to M iterations while unconverged, tested every "
                                          "C, tolerance "
                                          "10^-T; unnamed parts: the control loop's); overrides --iters")
    b.add_argument("--substeps", type=int, default=1, help="rollout: physics steps per control step (default 1)")
    b.add_argument("--backend", default="jax",
                   help="rollout: MJX physics implementation(s), comma-separated, each measured in this one run: "
                        "'jax' (default), 'warp', 'auto', e.g. jax,warp; each with campaign.sensing's default "
                        "('auto': delayed on Warp) or ':exact' / ':delayed', e.g. warp:exact,warp")
    b.add_argument("--scene", default="flat", help="rollout: 'flat' (default), 'transport' or a scene XML path")
    b.add_argument("--variants", default=None, help="profile: comma-separated variants (default wbc_1,wbc_n,"
                                                    "wbc_n_norefactor,wbc_n_chol,wbc_n_pallas; also wbc_n_inv, "
                                                    "wbc_n_pallas_norefactor, wbc_n_unroll, wbc_n_unroll_norefactor)")
    b.add_argument("--campaign", default=None, help="rollout: also run this campaign spec end to end twice in fresh "
                                                    "processes with a new compilation cache (wall time, compile "
                                                    "cold and warm), e.g. sweeps/paper_campaign.toml")
    b.add_argument("--warmup", type=float, default=0.0,
                   help="trace: simulated seconds run untraced first, so that the traced steps come from the walk "
                        "(default 0: the first standing steps)")
    b.add_argument("--quick", action="store_true", help="small sizes (CPU smoke run)")
    b.add_argument("--json", default=None, help="also write the results as JSON here")
    _process_flags(b)
    b.set_defaults(func=_cmd_bench)

    d = sub.add_parser("demo", help="the transport course, one run at default factors or all 27 cells; summary, "
                                    "plots, video")
    d.add_argument("--out", default="out/demo", help="output directory")
    d.add_argument("--scene", default="transport", help="'transport' (default), 'flat' or a scene XML path")
    d.add_argument("--seconds", type=float, default=None, help="simulated time [s] (default: whole path + 0.5)")
    d.add_argument("--all-cells", action="store_true", help="all 27 (m, mu, d) cells in one batch")
    d.add_argument("--push", action="store_true", help="push the trunk 40 N sideways for 0.2 s mid-walk")
    d.add_argument("--push-at", type=float, default=0.35,
                   help="push start as a fraction of the planned duration (default 0.35: before the wall)")
    d.add_argument("--no-video", action="store_true", help="skip video.gif")
    d.add_argument("--no-observer", action="store_true", help="disable the momentum observer")
    d.add_argument("--iters", type=int, default=20, help="ADMM iterations per control step")
    d.add_argument("--distance", type=float, default=3.4, help="transport distance [m]")
    _backend_flag(d, "auto")
    d.set_defaults(func=_cmd_demo)

    c = sub.add_parser("campaign", help="a spec's factorial design (cells x repetitions) as one batched rollout; "
                                        "results.csv, ANOVA report, manifest.json")
    c.add_argument("--spec", default=None, help="TOML spec (default: sweeps/quick.toml on a CPU-only machine, "
                                                "sweeps/paper_campaign.toml when an accelerator is present)")
    c.add_argument("--out", default="out/campaign", help="output directory (default out/campaign)")
    c.add_argument("--resume", action="store_true", help="continue from the checkpoint of an interrupted run")
    c.add_argument("--no-report", action="store_true", help="skip the ANOVA report")
    c.add_argument("--gains", default=None, help="controller gains TOML (e.g. best_gains.toml of wbc-jax tune) "
                                                 "instead of the defaults")
    _backend_flag(c, "the spec's campaign.backend")
    c.add_argument("--allow-large", action="store_true", help="run even when the memory estimate of the batch "
                                                              "exceeds the available memory")
    _process_flags(c)
    c.set_defaults(func=_cmd_campaign)

    u = sub.add_parser("tune", help="batched gain search (grid, random, cross-entropy method, successive halving) "
                                    "over factor cells; leaderboard.csv, best_gains.toml, report.md (paired test "
                                    "against the default gains), figures, manifest.json")
    u.add_argument("--spec", default=None, help="tuning spec (default: sweeps/gain_tuning_course.toml, the obstacle "
                                                "course, with an accelerator; sweeps/gain_tuning_cpu.toml on a CPU)")
    u.add_argument("--out", default="out/tune", help="output directory (default out/tune)")
    u.add_argument("--candidates", type=int, default=None, help="candidates per round (overrides tune.candidates)")
    u.add_argument("--rounds", type=int, default=None, help="rounds (overrides tune.rounds; not used by grid)")
    u.add_argument("--batch", type=int, default=None, help="runs per rollout call (overrides tune.batch; 0: all "
                                                           "of a round's runs on an accelerator, 1 on a CPU)")
    u.add_argument("--no-progress", action="store_true", help="no progress bar")
    _backend_flag(u, "the campaign specs' campaign.backend (tuning and confirmation)")
    _process_flags(u)
    u.set_defaults(func=_cmd_tune)

    g = sub.add_parser("regress", help="CI regression: rerun a stored baseline's spec, compare per-cell metric means "
                                       "with its tolerance band; exit 1 with a table of what moved")
    g.add_argument("--baseline", default="reports/baseline", help="baseline directory with spec.toml and "
                                                                  "baseline.json (default reports/baseline)")
    g.add_argument("--update", action="store_true", help="rewrite baseline.json from this run")
    g.set_defaults(func=_cmd_regress)

    t = sub.add_parser("trot", help="centroidal WBC trot study on flat ground (one batch over controller mass "
                                    "errors); summary.json and the paper's figures")
    t.add_argument("--out", default="out/trot", help="output directory")
    t.add_argument("--seconds", type=float, default=10.0, help="walking time [s] (default 10)")
    t.add_argument("--stride", type=float, default=0.10, help="advance per step [m] (default 0.10)")
    t.add_argument("--step-time", type=float, default=0.25, help="step (half-cycle) duration [s] (default 0.25)")
    t.add_argument("--four-foot", type=float, default=0.08, help="four-foot support per step [s] (default 0.08)")
    t.add_argument("--mass-errors", default="-0.2,-0.1,0,0.1,0.2",
                   help="controller model mass errors, comma-separated fractions; write --mass-errors=-0.2,0,0.2")
    t.add_argument("--no-object", action="store_true", help="take the cube off the tray")
    t.add_argument("--iters", type=int, default=40, help="ADMM iterations per control step")
    t.add_argument("--snapshots", type=int, default=6, help="frames of the Fig. 9 snapshot strip over one gait "
                                                            "cycle (default 6; 0: none)")
    t.set_defaults(func=_cmd_trot)
    for cmd in (r, d, c, u, t):
        cmd.add_argument("--force", action="store_true", help="replace --out when it holds an earlier run of this "
                                                              "command (never another folder)")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from wbc_jax.runtime import jaxcfg

    if args.command != "report":
        jaxcfg.configure()
    try:
        return int(args.func(args) or 0)
    except WbcJaxError as e:
        print(f"wbc-jax {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"wbc-jax {args.command}: interrupted", file=sys.stderr)
        return 130


def run() -> None:
    """The console script and ``python -m wbc_jax``: :func:`main`, then the process ends without tearing down the
    interpreter.

    Once a command has returned, what it wrote is closed (files are written atomically and closed before the
    command returns). Python's exit handlers (``atexit``: logging, JAX's clean-up, ``weakref.finalize``) still run,
    stdout and stderr are flushed, and threads that are not daemons are waited for. What is skipped is the
    interpreter's finalization, which frees every module and the GPU client's and MuJoCo Warp's objects one by
    one, where the operating system frees a process's memory and device context at once: after a GPU campaign it
    took 2.2 s after the exit handlers on one H100 host, and the time from the report's last file to the end of
    the process was 2.3-3.5 s on another (0.4-0.9 s on others; 2026-11-27). An exception escaping :func:`main`
    (``--help`` included) takes Python's normal exit.
    """
    import atexit
    import os
    import threading

    code = main()
    for t in threading.enumerate():
        if t is not threading.main_thread() and not t.daemon:
            t.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or a broken pipe: nothing left to flush there
            pass
    os._exit(code)


if __name__ == "__main__":
    run()
