"""The ``wbc-jax`` argument parser: one subparser per command, each built by its ``_add_*`` function."""

from __future__ import annotations

import argparse

from wbc_jax.errors import UsageError
from wbc_jax.studies import replay, warmup

DESCRIPTION = ("Batched whole-body control of a legged manipulator carrying an object, simulated in MuJoCo MJX: "
               "factorial campaigns as one batched rollout with their ANOVA report, gain tuning, a single-run demo, "
               "a trot study, regression checks against a baseline and benchmarks.")


class HelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to an optional argument's help unless the help already states its default, the
    argument is required, or it has no value default (a flag that is off, or None explained in the help)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (not action.option_strings or action.required or "default" in text
                or action.default in (None, False, argparse.SUPPRESS)):
            return text
        return f"{text} (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line: :class:`wbc_jax.errors.UsageError` (the CLI prints it) instead
    of a usage block and ``sys.exit``."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        raise UsageError(f"{message} ({self.prog} --help lists the arguments)", prog=self.prog)


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


def _add_report(sub) -> argparse.ArgumentParser:
    r = sub.add_parser("report", help="ANOVA report of a results table (one row per run)")
    r.add_argument("results", help="results CSV (one row per run)")
    r.add_argument("--out", required=True, help="output directory (new or empty; never the input's)")
    r.add_argument("--alpha", type=float, default=0.05, help="significance level (default 0.05)")
    r.add_argument("--factors", default=None, help="comma-separated factor columns (default: the campaign's, "
                                                        "from manifest.json beside the results; else m,mu,d)")
    r.add_argument("--metrics", default=None, help="comma-separated metric columns (default: inferred)")
    return r


def _add_bench(sub) -> argparse.ArgumentParser:
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
                   "and a physics + WBC call (with --campaign also each program's calls per state); the figures "
                   "are the rounds' medians (default 5; 3 on a CPU)")
    b.add_argument("--iters", type=int, default=4, help="rollout: ADMM iterations per control step before the "
                                                         "convergence checks (the control loop's default: 4)")
    b.add_argument("--qp", default=None, help="rollout: control-loop ADMM variant it<N>[_a<K>][_b<B>][_rho<R>][_r<R>]"
                                          "[_pol<P>][_e<E>][_m<M>][_c<C>][_tol<T>] (N iterations, rho adapted every K "
                                          "(0: never), adaptation bias B, rho R, R Ruiz passes, P polishing passes, "
                                          "E rows held exactly, up to M iterations while unconverged, tested every "
                                          "C, tolerance 10^-T; unnamed parts: the control loop's); overrides "
                                          "--iters (default: none, --iters with the control loop's settings)")
    b.add_argument("--substeps", type=int, default=1, help="rollout: physics steps per control step (default 1)")
    b.add_argument("--backend", default="jax",
                   help="rollout: MJX physics implementation(s), comma-separated, each measured in this one run: "
                        "'jax' (default), 'warp', 'auto', e.g. jax,warp; each with campaign.sensing's default "
                        "('auto': delayed on Warp) or ':exact' / ':delayed', e.g. warp:exact,warp")
    b.add_argument("--scene", default="flat", help="rollout: 'flat' (default), 'transport' or a scene XML path")
    b.add_argument("--variants", default=None, help="profile: comma-separated variants (default wbc_1,wbc_n,"
                                                    "wbc_n_norefactor,wbc_n_chol,wbc_n_pallas; also wbc_n_inv, "
                                                    "wbc_n_pallas_norefactor, wbc_n_unroll, wbc_n_unroll_norefactor)")
    b.add_argument("--campaign", default=None, help="rollout: also time this campaign spec's own control step at "
                                                    "each --batches size (its runs repeated; from --snapshots states "
                                                    "along its horizon; monitors' share), e.g. "
                                                    "sweeps/paper_campaign.toml (default: none)")
    b.add_argument("--snapshots", type=int, default=3, help="rollout --campaign: states along the horizon each "
                                                            "timed call starts from")
    b.add_argument("--breakdown", default=None, help="rollout --campaign: comma-separated batch sizes at which the "
                                                     "step is also timed without clearance and without monitors "
                                                     "(default: every --batches size)")
    b.add_argument("--cold-warm", action="store_true", help="rollout --campaign: also run the whole campaign command "
                                                            "twice, each a new process, with JAX's, Warp's and CUDA's "
                                                            "caches new and empty before the first: a fresh machine's "
                                                            "wall time, then a warm one's, and their regress "
                                                            "comparison")
    b.add_argument("--warmup", type=float, default=0.0,
                   help="trace: simulated seconds run untraced first, so that the traced steps come from the walk "
                        "(default 0: the first standing steps)")
    b.add_argument("--quick", action="store_true", help="small sizes (CPU smoke run)")
    b.add_argument("--json", default=None, help="also write the results as JSON here (a new file; an existing one "
                                                "only with --force; default: none)")
    b.add_argument("--force", action="store_true", help="overwrite an existing --json file")
    _process_flags(b)
    return b


def _add_demo(sub) -> argparse.ArgumentParser:
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
    return d


def _add_campaign(sub) -> argparse.ArgumentParser:
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
    c.add_argument("--dry-run", action="store_true", help="check everything the campaign checks and print what it "
                                                          "would simulate (runs, chunks, steps, memory, --out); "
                                                          "nothing is simulated or written in or beside --out")
    _process_flags(c)
    return c


def _add_tune(sub) -> argparse.ArgumentParser:
    u = sub.add_parser("tune", help="batched gain search (grid, random, cross-entropy method, successive halving) "
                                    "over factor cells; leaderboard.csv, best_gains.toml, report.md (paired test "
                                    "against the default gains), figures, manifest.json")
    u.add_argument("--spec", default=None, help="tuning spec (default: sweeps/gain_tuning_course.toml, the obstacle "
                                                "course, with an accelerator; sweeps/gain_tuning_cpu.toml on a CPU)")
    u.add_argument("--out", default="out/tune", help="output directory (default out/tune)")
    u.add_argument("--candidates", type=int, default=None, help="candidates per round (default: the spec's "
                                                                "tune.candidates)")
    u.add_argument("--rounds", type=int, default=None, help="rounds, not used by grid (default: the "
                                                            "spec's tune.rounds)")
    u.add_argument("--batch", type=int, default=None, help="runs per rollout call; 0: all of a round's "
                                                           "runs on an accelerator, 1 on a CPU (default: the spec's "
                                                           "tune.batch)")
    u.add_argument("--no-progress", action="store_true", help="no progress bar")
    u.add_argument("--dry-run", action="store_true", help="check the spec, --out and a rollout call's memory, print "
                                                          "what the tune would simulate, and exit: nothing "
                                                          "simulated, nothing written in --out")
    _backend_flag(u, "the campaign specs' campaign.backend (tuning and confirmation)")
    _process_flags(u)
    return u


def _add_regress(sub) -> argparse.ArgumentParser:
    g = sub.add_parser("regress", help="CI regression: rerun a stored baseline's spec, compare per-cell metric means "
                                       "with its tolerance band; exit 1 with a table of what moved")
    g.add_argument("--baseline", default="reports/baseline", help="baseline directory with spec.toml and "
                                                                  "baseline.json (default reports/baseline)")
    g.add_argument("--update", action="store_true", help="rewrite baseline.json from this run")
    g.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"), default=None,
                   help="instead: compare two finished campaigns' folders (AFTER against BEFORE) with the regress "
                        "bands of their controller; nothing is rerun (default: none)")
    return g


def _add_trot(sub) -> argparse.ArgumentParser:
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
    return t


def build_parser() -> argparse.ArgumentParser:
    """The ``wbc-jax`` parser: one subparser per command (each built by its ``_add_*`` function)."""
    p = Parser(prog="wbc-jax", description=DESCRIPTION)
    sub = p.add_subparsers(dest="command", required=True)
    writers = [_add_report(sub)]
    _add_bench(sub)
    writers.append(_add_demo(sub))
    writers.append(_add_campaign(sub))
    writers.append(_add_tune(sub))
    _add_regress(sub)
    replay.add_parser(sub)  # its own --force
    warmup.add_parser(sub)
    writers.append(_add_trot(sub))
    for cmd in writers:
        cmd.add_argument("--force", action="store_true", help="replace --out when it holds an earlier run of this "
                                                              "command (never another folder)")
    return p
