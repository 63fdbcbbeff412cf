"""``wbc-jax bench rollout``: env steps per second of physics-only MJX and of physics + transport WBC.

Both are measured in the same process on the current device, on the flat scene (or ``scene``) with the object,
excluding compile time (reported separately); the ratio WBC / physics-only is printed next to the
absolute figures, and so is everything but physics per control step (the physics + WBC call's time less the
physics-only call's, over its control steps: what the controller, the QP and the rollout's bookkeeping add). The
WBC runs the loaded stand-and-walk plan from t = 0.

Each batch is timed in ``rounds`` rounds, a round being one physics-only call then one physics + WBC call, so slow
drifts of the device (clocks, other processes) reach both; the figures are the rounds' medians, and everything but
physics is also given as its smallest and largest round: one call of each is a single sample of a difference of
two timings, which varies between processes and rounds by more than most changes it is meant to measure.

Several devices: one process with several (JAX physics) also times the same batch with its runs over every
device (:func:`sharded_chunk_fn`, as a campaign runs it). Several processes (``--coordinator`` etc., one device
each; the layout of Warp physics on several GPUs, ``wbc_jax.rollout.spread``): process 0 first times the whole batch
alone on its device, then every process times a block of batch / processes runs on its own device, all starting
together; the slowest process's time gives the aggregate figure and the speed-up over the one-device time.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from jax.experimental import multihost_utils

from wbc_jax.bench.qp_audit import variants as variants_named
from wbc_jax.campaign.regress import compare_campaigns
from wbc_jax.campaign.runner import run_in_fresh_process
from wbc_jax.campaign.spec import load_spec
from wbc_jax.control.transport import TransportConfig, control_qp_settings
from wbc_jax.physics.backend import resolve_backend
from wbc_jax.robot.model import Robot, mjx
from wbc_jax.rollout import distributed, make_chunk_fn, make_sim, resolve_sensing
from wbc_jax.rollout.batch import chunk_args, prepare_batch
from wbc_jax.rollout.sharding import over_runs, run_mesh, shard_batch

ROUND_SPREAD = 1.10  # a call's slowest round over its fastest above which a round is reported as disturbed


def timed(f, *args):
    """(f(*args) once it is ready on the device, seconds it took)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    return out, time.perf_counter() - t0


def random_batch(sim, batch: int, seed: int = 0):
    """``batch`` runs in random (m, mu, d) cells of the paper's factor levels (seeded), prepared for ``sim``."""
    rng = np.random.default_rng(seed)
    return prepare_batch(sim, rng.choice([0.2, 0.3, 0.4], batch), rng.choice([0.4, 0.7, 1.0], batch),
                         rng.choice([0.06, 0.08, 0.10], batch))


def physics_only_fn(b, n_steps: int):
    """jit(vmap) of ``n_steps`` plain ``mjx.step`` calls per run (scope ``physics``), called as
    f(b.model, b.state.d)."""

    def phys(m, d):
        with jax.named_scope("physics"):
            return jax.lax.scan(lambda d, _: (mjx.step(m, d), None), d, None, length=n_steps)[0]

    return jax.jit(jax.vmap(phys, in_axes=(b.in_axes, 0)))


def wbc_chunk_fn(sim, b):
    """(f, args): jit(vmap) of one chunk of ``sim.log_every`` control steps per run, and its arguments from ``b``."""
    return jax.jit(make_chunk_fn(sim, 1, b.in_axes)), chunk_args(b)


def sharded_chunk_fn(sim, b):
    """(f, args): :func:`wbc_chunk_fn` with the run axis over every device, each device stepping its own runs
    (``wbc_jax.rollout.sharding.over_runs``, as a campaign on several devices), and ``b``'s arguments placed so."""
    f = over_runs(make_chunk_fn(sim, 1, b.in_axes), run_mesh(), (b.in_axes, b.state_axes, 0, 0, 0, 0, 0),
                  (b.state_axes, 0))
    bs, _ = shard_batch(b)
    return f, chunk_args(bs)


def _timed_together(f, *args):
    """:func:`timed` in every process at once (a barrier first): (output, the slowest process's seconds)."""
    multihost_utils.sync_global_devices("bench rollout")
    out, t = timed(f, *args)
    return out, float(np.max(multihost_utils.process_allgather(np.array([t]))))


class _Timings(NamedTuple):
    """Seconds of the physics-only and the physics + WBC calls of :func:`_physics_and_wbc`."""

    first_physics_s: float  # the first physics-only call (compiles)
    first_wbc_s: float  # the first physics + WBC call (compiles)
    physics_s: np.ndarray  # (rounds,) physics-only calls
    wbc_s: np.ndarray  # (rounds,) physics + WBC calls
    qp_iters_per_step: float  # the QP's mean ADMM iterations per control step in a physics + WBC call
    solver_cap_share: float  # its share of physics steps at the constraint solver's cap (solver_cap_share)


def _counted(before, after, field: str) -> np.ndarray:
    """Per run, what accumulator ``field`` (``Accum``) counted between RunStates ``before`` and ``after``
    (float64)."""
    return np.asarray(getattr(after.acc, field), np.float64) - np.asarray(getattr(before.acc, field), np.float64)


def qp_iterations(before, after, steps: int) -> float:
    """Mean ADMM iterations per control step over the runs between RunStates ``before`` and ``after``, ``steps``
    control steps apart (``Accum.sum_qp_iters``; a run that has failed, frozen, counts none)."""
    return float(np.mean(_counted(before, after, "sum_qp_iters"))) / steps


def solver_cap_share(before, after, physics_steps: int) -> float:
    """Share of the runs' physics steps between RunStates ``before`` and ``after`` (``physics_steps`` apart) whose
    constraint solve stopped at ``opt.iterations`` (``Accum.n_solver_cap``; MuJoCo Warp only: MJX's JAX solver
    reports no count, so 0). Warp's solver loop runs until the batch's last world has converged: one capped world
    holds every world's step at the cap's iterations."""
    return float(np.mean(_counted(before, after, "n_solver_cap"))) / physics_steps


def _physics_and_wbc(sim, b, n_env: int, timer, rounds: int) -> _Timings:
    """Physics only and physics + WBC on batch ``b``, timed with ``timer`` (:func:`timed` or
    :func:`_timed_together`): each called once (the call that compiles), then ``rounds`` rounds of one physics call
    and one physics + WBC call."""
    f_phys = physics_only_fn(b, n_env)
    f_wbc, args = wbc_chunk_fn(sim, b)
    c_phys = timer(f_phys, b.model, b.state.d)[1]
    (state, _), c_wbc = timer(f_wbc, *args)
    t = np.array([(timer(f_phys, b.model, b.state.d)[1], timer(f_wbc, *args)[1]) for _ in range(rounds)])
    return _Timings(c_phys, c_wbc, t[:, 0], t[:, 1], qp_iterations(b.state, state, sim.log_every),
                    solver_cap_share(b.state, state, n_env))


def round_figures(t_phys, t_wbc, batch: int, n_env: int, steps: int) -> dict:
    """The reported figures of timed rounds: (rounds,) seconds of the physics-only and of the physics + WBC call
    (``batch`` runs, ``n_env`` env-steps each, ``steps`` control steps). Rates and their ratio from the medians;
    everything but physics [ms per control step] the median over rounds of each round's difference, with the
    smallest and largest round."""
    t_phys, t_wbc = np.asarray(t_phys, float), np.asarray(t_wbc, float)
    diff = 1e3 * (t_wbc - t_phys) / steps
    tp, tw = float(np.median(t_phys)), float(np.median(t_wbc))
    return dict(rounds=len(diff), physics_steps_per_s=batch * n_env / tp, wbc_steps_per_s=batch * n_env / tw,
                ratio=tp / tw, non_physics_ms_per_step=float(np.median(diff)),
                non_physics_ms_per_step_range=[float(diff.min()), float(diff.max())],
                physics_round_s=t_phys.tolist(), wbc_round_s=t_wbc.tolist())


def disturbed(what: str, t) -> str | None:
    """With two rounds (``t``: (2,) seconds of a call), whose median is their mean, where the slower took more than
    :data:`ROUND_SPREAD` times the faster: a phrase naming ``what`` (e.g. "physics-only call") and the range (a
    round was disturbed: another process on the device, its clocks). None otherwise: from three rounds the median
    leaves one disturbed round out, and the range of everything but physics is printed."""
    t = np.asarray(t, float)
    if len(t) != 2 or t.max() <= ROUND_SPREAD * t.min():
        return None
    return (f"the {what}'s rounds took {t.min():.3f} to {t.max():.3f} s ({t.max() / t.min():.2f}x): a round was "
            "disturbed and with 2 rounds the figures are their mean: rerun with --rounds 3 or more")


def spread_warning(t_phys, t_wbc, batch: int) -> str | None:
    """The warning line of a batch whose physics-only or physics + WBC rounds disagree (:func:`disturbed`), else
    None."""
    phrase = disturbed("physics-only call", t_phys) or disturbed("physics + WBC call", t_wbc)
    return f"warning: batch {batch}: {phrase}" if phrase else None


def _peak_bytes() -> int | None:
    """Peak device memory in use so far [bytes] (None where the backend does not report it, e.g. the CPU)."""
    stats = jax.local_devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


class _Case(NamedTuple):
    """One measured configuration of :func:`run_bench`: the simulation and the row's fixed fields."""

    sim: object  # wbc_jax.rollout.config.Sim
    device: str
    label: str  # "<backend>:<sensing>"
    batch: int
    n_env: int  # env-steps per run per timed call
    steps: int  # control steps per timed call
    rounds: int


def _make_case(spec: str, scene: str, qs, substeps: int, steps: int):
    """(sim, backend, sensing) for one ``backends`` entry ("jax", "warp:exact", ...)."""
    name, _, sensing = spec.partition(":")  # "warp:exact": campaign.sensing
    backend = resolve_backend(name)
    sensing = resolve_sensing(sensing or "auto", backend, substeps)
    robot = Robot(scene, backend=backend)
    sim = make_sim(robot, TransportConfig(dt=float(robot.mj_model.opt.timestep) * substeps, qp=qs),
                   n_substeps=substeps, log_every=steps, sensing=sensing)
    return sim, backend, sensing


def _time_one_device(case: _Case, row: dict):
    """The whole batch on this process's device: figures into ``row``, printed. Returns (batch, median physics +
    WBC call [s], the base of the speed-ups)."""
    B, rounds = case.batch, case.rounds
    b = random_batch(case.sim, B)
    c_phys, c_wbc, phys_rounds, wbc_rounds, qp_iters, caps = _physics_and_wbc(case.sim, b, case.n_env, timed, rounds)
    t_phys, t_wbc = float(np.median(phys_rounds)), float(np.median(wbc_rounds))
    row.update(round_figures(phys_rounds, wbc_rounds, B, case.n_env, case.steps), peak_device_bytes=_peak_bytes(),
               compile_physics_s=c_phys - t_phys, compile_wbc_s=c_wbc - t_wbc, qp_iters_per_step=qp_iters,
               solver_cap_share=caps)
    lo, hi = row["non_physics_ms_per_step_range"]
    print(f"{case.device} {case.label:4s} batch {B:6d}: physics {row['physics_steps_per_s']:12.0f} steps/s   "
          f"physics+WBC {row['wbc_steps_per_s']:12.0f} steps/s   ratio {row['ratio']:.3f}   everything but "
          f"physics {row['non_physics_ms_per_step']:.3f} ms per control step ({rounds} rounds: {lo:.3f} to "
          f"{hi:.3f}), QP iterations per step {qp_iters:.1f}, physics steps at the solver's cap {caps:.1%}   "
          f"compile {row['compile_wbc_s']:.1f} s"
          + (f"   peak memory {row['peak_device_bytes'] / 2**30:.2f} GiB" if row["peak_device_bytes"] else ""),
          flush=True)
    warning = spread_warning(phys_rounds, wbc_rounds, B)
    if warning:
        print(warning, flush=True)
    return b, t_wbc


def _time_processes(case: _Case, row: dict, t_wbc: float | None, writer: bool) -> None:
    """Every process its block of batch / processes runs on its own device, all at once (wbc_jax.rollout.spread):
    the aggregate figures and the speed-up over ``t_wbc`` into ``row``."""
    B, n_env, n_proc = case.batch, case.n_env, jax.process_count()
    b = random_batch(case.sim, B // n_proc, seed=1 + jax.process_index())
    timings = _physics_and_wbc(case.sim, b, n_env, _timed_together, case.rounds)
    tp, tw = float(np.median(timings.physics_s)), float(np.median(timings.wbc_s))
    n = B // n_proc * n_proc
    row.update(processes=n_proc, physics_steps_per_s_processes=n * n_env / tp,
               wbc_steps_per_s_processes=n * n_env / tw, process_speedup=n / B * t_wbc / tw if t_wbc else None)
    if writer:
        print(f"{'':>{len(case.device)}} batch {B:6d}: on {n_proc} processes (one device each, {B // n_proc} runs "
              f"each): physics {n * n_env / tp:12.0f} steps/s   physics+WBC {n * n_env / tw:12.0f} steps/s   "
              f"speed-up {row['process_speedup']:.2f}x", flush=True)


def _time_sharded(case: _Case, row: dict, b, t_wbc: float) -> None:
    """The same batch with the run axis over every device, as a campaign runs it: figures into ``row``."""
    B, n_env = case.batch, case.n_env
    f_sh, sargs = sharded_chunk_fn(case.sim, b)
    timed(f_sh, *sargs)
    t_sh = float(np.median([timed(f_sh, *sargs)[1] for _ in range(case.rounds)]))
    n_dev = jax.device_count()
    row.update(n_devices=n_dev, wbc_steps_per_s_sharded=B * n_env / t_sh, sharded_speedup=t_wbc / t_sh)
    print(f"{'':>{len(case.device)}} batch {B:6d}: physics+WBC on {n_dev} devices {B * n_env / t_sh:12.0f} "
          f"steps/s   speed-up {t_wbc / t_sh:.2f}x", flush=True)


def run_bench(batches=(1, 1024, 4096, 16384), steps: int = 200, iters: int = 30, json_path: str | None = None,
              scene: str = "flat", qp: str | None = None, substeps: int = 1, cold_warm: dict | None = None,
              backends=("jax",), rounds: int = 5):
    """Physics-only and physics + WBC env steps per second per batch size (see module docstring).

    An env-step is one physics step (``robot``'s timestep); with ``substeps`` > 1 the controller runs once per
    ``substeps`` physics steps (zero-order hold), so ``steps`` control steps are ``steps * substeps`` env-steps.

    Args:
        backends: MJX physics implementations to measure, each at every batch size ("jax", "warp"; "auto"
            resolved; with ``:exact`` / ``:delayed`` / ``:auto`` (the default): ``campaign.sensing``), in this one
            process, so their ratios are read from one run.
        qp: control-loop ADMM variant name (``wbc_jax.bench.qp_audit.variants``, e.g. ``"it20_a0"``); None:
            ``iters`` iterations with the control loop's default settings.
        rounds: timed rounds per batch (module docstring); the figures are their medians.
        cold_warm: :func:`campaign_cold_warm`'s result, run before this process took a device: kept in the
            result and the JSON as ``campaign``.

    Returns:
        dict: device, ``batches`` (one row per batch size) and ``campaign`` (``cold_warm``); also written
        to ``json_path``.
    """
    qs = variants_named([qp])[qp] if qp else control_qp_settings(iters)
    iters = qs.iters
    device = jax.devices()[0].device_kind
    n_env = steps * substeps  # env-steps per run per timed call
    rows = []
    n_proc, writer = jax.process_count(), distributed.is_writer()
    distributed.check_own_gpus()  # before the first collective: each process its own GPUs
    for k, B in [(k, B) for k in backends for B in batches]:
        sim, backend, sensing = _make_case(k, scene, qs, substeps, steps)
        row = dict(device=device, backend=backend, sensing=sensing, scene=sim.robot.path.name, batch=B, steps=steps,
                   substeps=substeps, qp_iters=iters, qp=qp or f"it{iters}", adapt_every=qs.adapt_every,
                   ruiz_iters=qs.ruiz_iters)
        case = _Case(sim, device, f"{backend}:{sensing}", B, n_env, steps, rounds)
        t_wbc = None
        if writer:  # the whole batch on one device (with several processes: process 0's, the others wait)
            b, t_wbc = _time_one_device(case, row)
        if n_proc > 1:
            _time_processes(case, row, t_wbc, writer)
        elif jax.device_count() > 1 and backend == "warp":
            print(f"{'':>{len(device)}} batch {B:6d}: Warp on several devices needs one process per device "
                  f"(wbc_jax.rollout.spread; --coordinator, --num-processes, --process-id, --local-device-ids)",
                  flush=True)
        elif jax.device_count() > 1:
            _time_sharded(case, row, b, t_wbc)
        rows.append(row)
    out = dict(device=device, batches=rows, campaign=cold_warm)
    if json_path and writer:
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=2)
    return out


FRESH_MACHINE_CACHES = {"WBC_JAX_CACHE": "jax", "WARP_CACHE_PATH": "warp", "CUDA_CACHE_PATH": "cuda"}


def campaign_cold_warm(spec: str) -> dict:
    """Run ``wbc-jax campaign --spec SPEC`` (the whole command, with its report) twice, each in a new process (call
    it before this process holds a GPU: the runs' memory pools take most of its memory, as a user's run does),
    with every cache a run can fill new and empty before the first (JAX's compilation and the plans in
    ``WBC_JAX_CACHE``, MuJoCo Warp's kernels in ``WARP_CACHE_PATH``, the CUDA driver's in ``CUDA_CACHE_PATH``) and
    shared by both: the first is a fresh machine's first run (but for its first disk reads), the second a warm one.
    Prints and returns, per run, the process's wall time [s] (``process_s``: start to exit, measured here) and the
    manifest's wall time, import / setup / compile estimate [s], rollout env steps per second and successes; and
    whether the warm run's cell means lie within the fresh one's regress bands (``regress --compare``).

    Raises:
        WbcJaxError: a run failed (the end of its stderr).
    """
    load_spec(spec)  # a bad spec fails here (file, key, range), before anything runs
    keys = ("wall_s_total", "wall_s_rollout", "import_s", "setup_s", "compile_s_estimate", "env_steps_per_s",
            "n_success", "n_runs")
    out = dict(spec=str(spec))
    with tempfile.TemporaryDirectory() as td:
        caches = {var: str(Path(td) / "caches" / name) for var, name in FRESH_MACHINE_CACHES.items()}
        for label in ("cold", "warm"):
            t0 = time.perf_counter()
            run = run_in_fresh_process(spec, Path(td) / label, report=True, **caches)
            man = json.loads((run / "manifest.json").read_text())
            m = out[label] = {"process_s": time.perf_counter() - t0, **{k: man.get(k) for k in keys}}
            print(f"campaign {spec}, {label} caches: the whole command {m['process_s']:.1f} s (manifest: wall "
                  f"{m['wall_s_total']:.1f} s, import {m['import_s']:.1f} s, setup {m['setup_s']:.1f} s, compile "
                  f"about {m['compile_s_estimate'] or 0:.1f} s, rollout {m['wall_s_rollout']:.1f} s, "
                  f"{m['env_steps_per_s']:,.0f} env steps/s), {m['n_success']}/{m['n_runs']} runs succeed", flush=True)
        out["warm_within_cold_bands"] = compare_campaigns(str(Path(td) / "cold"), str(Path(td) / "warm"))[0] == 0
    return out


PROFILE_VARIANTS = ("wbc_1", "wbc_n", "wbc_n_norefactor", "wbc_n_chol")


def run_profile(batch: int = 16384, steps: int = 100, iters: int = 50, scene: str = "flat",
                json_path: str | None = None, variants=None):
    """Where the time of one control step goes, from timings of variants compiled in one process.

    Times (per env-step, excluding compile) physics only; physics + WBC with 1 ADMM iteration; with ``iters``
    iterations (the default rho adaptation, i.e. a refactor every ``adapt_every``); with ``iters`` iterations and
    no refactor; with the Cholesky solve (``variants`` picks others, e.g. the unrolled solver ``wbc_n_unroll``;
    the default linear solve is the backend's, see ``control_qp_settings``). Differences give the controller's
    fixed cost (sensing, QP assembly, equilibration, one factorization), the cost of one ADMM iteration and of one
    refactor.
    """
    robot = Robot(scene)
    device = jax.devices()[0].device_kind
    base = control_qp_settings(iters)
    known = dict(wbc_1=base._replace(iters=1), wbc_n=base, wbc_n_norefactor=base._replace(adapt_every=0),
                 wbc_n_inv=base._replace(linsolve="inv"), wbc_n_chol=base._replace(linsolve="chol"),
                 wbc_n_unroll=base._replace(unroll=True),
                 wbc_n_unroll_norefactor=base._replace(unroll=True, adapt_every=0))
    variants = [(k, known[k] if k in known else variants_named([k])[k]) for k in (variants or PROFILE_VARIANTS)]
    out = dict(device=device, scene=robot.path.name, batch=batch, steps=steps, iters=iters)
    b = None
    for label, qs in [("physics", None)] + variants:
        sim = make_sim(robot, TransportConfig(dt=float(robot.mj_model.opt.timestep), qp=qs or base), log_every=steps)
        if b is None:
            b = random_batch(sim, batch)
        if qs is None:
            f, args = physics_only_fn(b, steps), (b.model, b.state.d)
        else:
            f, args = wbc_chunk_fn(sim, b)
        _, c = timed(f, *args)
        _, t = timed(f, *args)
        out[label + "_us"] = 1e6 * t / (batch * steps)
        out[label + "_compile_s"] = c - t
        print(f"{device} batch {batch}: {label:18s} {out[label + '_us']:8.3f} us/env-step "
              f"({batch * steps / t:10.0f} env steps/s), compile {c - t:.1f} s", flush=True)
    if all(k in out for k in ("wbc_1_us", "wbc_n_us", "wbc_n_norefactor_us")):
        _split(out, iters, base)
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=2)
    return out


def _split(out: dict, iters: int, base) -> None:
    """Controller fixed cost, per-iteration and per-refactor cost from the variants' timings (in place)."""
    n_ref = max(0, (iters - 1) // base.adapt_every) if base.adapt_every else 0
    out["controller_fixed_us"] = out["wbc_1_us"] - out["physics_us"]
    out["per_iteration_us"] = (out["wbc_n_norefactor_us"] - out["wbc_1_us"]) / max(iters - 1, 1)
    out["per_refactor_us"] = (out["wbc_n_us"] - out["wbc_n_norefactor_us"]) / max(n_ref, 1)
    print(f"controller fixed cost {out['controller_fixed_us']:.3f} us, one ADMM iteration "
          f"{out['per_iteration_us']:.4f} us, one refactor {out['per_refactor_us']:.3f} us (per env-step; physics "
          f"{out['physics_us']:.3f} us)", flush=True)
