"""``wbc-jax campaign``: a spec's whole factorial design (cells x repetitions) as one batched rollout.

spec (``wbc_jax.campaign.spec``) -> design table with per-run seeds and perturbations -> one :class:`wbc_jax.rollout.batch.Batch`
(all runs) -> chunked, jitted, vmapped rollout (``chunk_seconds`` of simulated time per call; the state is
checkpointed after every chunk) -> per-run metrics and flags (``wbc_jax.metrics.paper``) ->
``results.csv`` and ``manifest.json`` in DIR (written atomically), then the ANOVA report
(``wbc_jax.analysis.report``) in ``DIR/report/``. A report that fails leaves the results, writes
``DIR/report_error.txt`` and ends the command with a one-line error (rerun ``wbc-jax report DIR/results.csv``).

DIR must be new or empty, or (``--force``) hold an earlier campaign (``wbc_jax.io_utils.check_out_dir``); it is
checked, with the spec's size against the machine's memory (:func:`check_size`), before anything is compiled.

Checkpoint (``wbc_jax.campaign.checkpoint``): ``.<DIR name>.campaign-ckpt/`` next to DIR holds the state after the last finished chunk
(``state_K.npz``: every leaf of the batched RunState after chunk K) and ``meta.json`` (the run's identity,
:func:`run_identity`: spec hash, gains hash, backend, numerics package versions, run count; chunks done, the state
file's SHA-256, wall time so far). Ctrl-C keeps it; ``--resume`` continues from it (the chunks are the same, so the
results equal an uninterrupted run's) after checking the identity and the checksum: a mismatch or damage is a
one-line error; it is deleted once the results are written. A run that goes non-finite is frozen by the
rollout and reported failed; the others continue.

Several devices or processes (``wbc_jax.rollout.distributed``: ``jax.distributed`` initialised by the CLI): the runs
are spread over them (``wbc_jax.rollout.spread``: on JAX physics one program over every device of every process, on
Warp physics a block of runs per process); every process builds the same batch and steps its own runs; the
states are gathered after each chunk and only process 0 writes (DIR, the checkpoint; the others write nothing).
The checkpoint holds the real runs only (no padding), so a run can resume on another layout; process 0 reads it
and hands it to the others. ``manifest.json``'s ``layout`` records the processes and devices.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

import jax
import numpy as np

from wbc_jax.campaign import checkpoint
from wbc_jax.campaign.spec import Design, Spec, default_spec_path, design, load_spec
from wbc_jax.errors import LimitError, ReportError, SpecError, WbcJaxError
from wbc_jax.io_utils import atomic_dir, check_out_dir, write_json_atomic
from wbc_jax.rollout import distributed, runs
from wbc_jax.rollout.spread import choose
from wbc_jax.runtime import aot

LOG_EVERY = 20  # control steps per logged sample (the rollout's outer scan)
PACKAGES = ("wbc_jax", "jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy", "scipy", "statsmodels", "pandas")
NUMERICS = ("wbc_jax", "jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy")  # their versions can change a rollout
COMMAND = "wbc-jax campaign"
# memory estimate of a batched rollout, per run [bytes]: state, model, plan and QP workspace, plus the logged samples
# of one chunk; deliberately generous round numbers (not measured), only meant to stop batches that cannot fit
RUN_BYTES = 4 << 20
LOG_SAMPLE_BYTES = 64 << 10
_SIMS: dict = {}
_FNS: dict = {}


def has_accelerator() -> bool:
    return jax.default_backend() != "cpu"


def backend_of(spec: Spec) -> str:
    """The spec's physics backend, "auto" resolved for this machine (:func:`wbc_jax.physics.backend.resolve_backend`)."""
    from wbc_jax.physics.backend import resolve_backend

    try:
        return resolve_backend(spec.campaign["backend"])
    except ValueError as e:
        raise SpecError(f"{spec.path}: campaign.backend: {e}") from None


def with_backend(spec: Spec, backend: str | None) -> Spec:
    """``spec`` with ``campaign.backend`` replaced (a ``--backend`` flag); unchanged for None."""
    import dataclasses

    from wbc_jax.campaign.spec import BACKENDS

    if backend is None:
        return spec
    if backend not in BACKENDS:
        raise SpecError(f"--backend {backend!r}: expected one of {', '.join(BACKENDS)}")
    return dataclasses.replace(spec, campaign={**spec.campaign, "backend": backend})


def sensing_of(spec: Spec) -> str:
    """The spec's ``campaign.sensing`` resolved for its backend (:func:`wbc_jax.rollout.config.resolve_sensing`)."""
    from wbc_jax.rollout import resolve_sensing

    c = spec.campaign
    backend = backend_of(spec)
    try:
        return resolve_sensing(c["sensing"], backend, c["control_substeps"])
    except ValueError:
        raise SpecError(f"{spec.path}: campaign.sensing = {c['sensing']!r}: needs campaign.backend 'warp' (here "
                        f"{backend!r}) and control_substeps 1 (here {c['control_substeps']})") from None


def _sim(scene: str, iters: int, sensor_noise: bool = False, substeps: int = 1, backend: str = "jax",
         solver_iterations: int = 0, sensing: str = "exact"):
    """The (cached) Sim of a scene: ``iters`` ADMM iterations, control period ``substeps`` x the scene's timestep."""
    from wbc_jax.control.transport import TransportConfig, control_qp_settings
    from wbc_jax.robot.model import Robot
    from wbc_jax.rollout import make_sim

    key = (scene, iters, sensor_noise, substeps, backend, solver_iterations, sensing)
    if key not in _SIMS:
        robot = Robot(scene, backend=backend, solver_iterations=solver_iterations)
        cfg = TransportConfig(dt=float(robot.mj_model.opt.timestep) * substeps, qp=control_qp_settings(iters))
        _SIMS[key] = make_sim(robot, cfg, n_substeps=substeps, log_every=LOG_EVERY, sensor_noise=sensor_noise,
                              sensing=sensing)
    return _SIMS[key]


def _chunk_fn(sim, in_axes, n_logs: int, mesh=None, state_axes=0):
    """The jitted chunk function (:func:`wbc_jax.rollout.loop.make_chunk_fn`); with a ``mesh`` (several devices),
    each device steps its own runs. ``in_axes``, ``state_axes``: the batch's model and state run axes
    (``Batch.in_axes``, ``Batch.state_axes``)."""
    from wbc_jax.rollout import make_chunk_fn
    from wbc_jax.rollout.sharding import over_runs

    leaves, tree = jax.tree_util.tree_flatten(state_axes, is_leaf=lambda v: v is None)
    key = (sim, n_logs, mesh, tuple(leaves), tree)
    if key not in _FNS:  # jit, with the lowered program kept on disk for the next process (wbc_jax.runtime.aot)
        # (vmap takes the Warp data whole: MJX batches its shared contact list itself)
        fn = make_chunk_fn(sim, n_logs, in_axes)
        _FNS[key] = (aot.cached_jit("chunk", fn, aot.describe(sim, in_axes, n_logs),
                                     exportable=sim.robot.backend != "warp") if mesh is None
                     else over_runs(fn, mesh, (in_axes, state_axes, 0, 0, 0, 0, 0), (state_axes, 0)))
    return _FNS[key]


def _quat_mul(a, b):
    w1, x1, y1, z1 = a.T
    w2, x2, y2, z2 = b.T
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)


def initial_configuration(robot, dz: Design):
    """Perturbed initial (qpos (B, nq), qvel (B, nv)): the object shifted by (obj_dx, obj_dy) in the world's
    horizontal plane (the tray is level at home) and yawed by obj_yaw about world z; robot base and object
    moving horizontally at v0."""
    ids = robot.ids
    qpos = np.stack([robot.home_qpos(float(di)) for di in dz.d])
    a = ids.obj_qpos_adr
    qpos[:, a] += dz.obj_dx
    qpos[:, a + 1] += dz.obj_dy
    qyaw = np.stack([np.cos(dz.obj_yaw / 2), np.zeros(dz.n), np.zeros(dz.n), np.sin(dz.obj_yaw / 2)], axis=1)
    qpos[:, a + 3:a + 7] = _quat_mul(qyaw, qpos[:, a + 3:a + 7])
    qvel = np.zeros((dz.n, robot.mj_model.nv))
    qvel[:, 0:2] = dz.v0
    qvel[:, ids.obj_dof_adr:ids.obj_dof_adr + 2] = dz.v0
    return qpos, qvel


def run_gains(gains, dz: Design):
    """Per-run gains of a design: ``gains`` (unbatched TransportGains; None: the defaults) with each ``gain.*``
    factor's multiplier applied (leaves with a leading run axis); unbatched as given without such factors."""
    from wbc_jax.control.transport import default_gains

    if not dz.gain_scale:
        return gains
    base = default_gains() if gains is None else gains
    out = {}
    for name, leaf in zip(base._fields, base):
        x = np.broadcast_to(np.asarray(leaf), (dz.n,) + np.shape(leaf))
        scale = dz.gain_scale.get(name)
        if scale is not None:
            x = x * scale.reshape((dz.n,) + (1,) * np.ndim(leaf)).astype(x.dtype)
        out[name] = jax.numpy.asarray(x)
    return type(base)(**out)


def build(spec: Spec, gains=None):
    """Spec -> (sim, design, Batch with perturbed initial states and pushes, simulated seconds, chunk plan).
    ``gains``: controller gains (TransportGains, unbatched) instead of the defaults."""
    from wbc_jax.control.variants import Variant
    from wbc_jax.planner.transport import plan_duration
    from wbc_jax.rollout.batch import prepare_batch
    from wbc_jax.rollout import make_push, with_metric_window, with_variant

    c = spec.campaign
    dz = design(spec)
    backend = backend_of(spec)
    sim = _sim(c["scene"], c["qp_iters"], bool(np.any(dz.qvel_noise_std > 0)), c["control_substeps"],
               backend, c["solver_iterations"], sensing_of(spec))
    qpos0, qvel0 = initial_configuration(sim.robot, dz)
    b = prepare_batch(sim, dz.m, dz.mu, dz.d, gains=run_gains(gains, dz),
                      plan_kwargs=dict(distance=c["distance"], speed=c["speed"], terrain=c["terrain"],
                                       com_plan=c["com_plan"]),
                      qpos0=qpos0, qvel0=qvel0,
                      speed=dz.speed if "speed" in spec.factors else None,
                      ground_mu=dz.ground_mu if np.all(dz.ground_mu > 0) else None)
    T_plan = plan_duration(b.plan)
    t_plan = np.asarray(b.plan.obj_path.t_knots)[:, -1]  # (B,) each run's plan end [s]
    # push start: a fraction of the planned duration (each run's own when the speed is varied)
    push = make_push(dz.push_force, dz.push_frac * (t_plan if "speed" in spec.factors else T_plan),
                     dz.push_duration, dz.qvel_noise_std, dz.seed)
    # metric window (wbc_jax.metrics.paper): each run's own plan end + the settling time, capped like the horizon
    t_end = t_plan + c["extra_seconds"]
    if c["max_seconds"] > 0:
        t_end = np.minimum(t_end, c["max_seconds"])
    state = with_variant(with_metric_window(b.state, t_end), Variant(*dz.variant.T))
    b = b._replace(push=push, state=state)
    log_dt = sim.dt_control * LOG_EVERY
    logs_per_chunk = max(1, int(round(c["chunk_seconds"] / log_dt)))
    horizon = T_plan + c["extra_seconds"]
    if c["max_seconds"] > 0:
        horizon = min(horizon, c["max_seconds"])
    n_chunks = max(1, int(np.ceil(horizon / (logs_per_chunk * log_dt) - 1e-9)))
    return sim, dz, b, T_plan, logs_per_chunk, n_chunks


def run_identity(spec: Spec, gains=None, n_runs: int | None = None, backend: str = "jax") -> dict:
    """Everything that determines a campaign's results, as the dict a checkpoint must match.

    Args:
        spec: the validated spec (its hash).
        gains: controller gains (None: the defaults, hashed as such).
        n_runs: number of runs (default: the spec's design size).
        backend: the simulation backend ("jax").

    Returns:
        dict with ``spec_hash``, ``gains_hash`` (SHA-256 of every gains leaf, shape, dtype and value), ``backend``,
        ``platform`` (jax's default backend: cpu, gpu, ...), ``versions`` (of :data:`NUMERICS`) and ``n_runs``.
    """
    from wbc_jax.control.transport import default_gains

    h = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(default_gains() if gains is None else gains):
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    versions = _versions()
    return dict(spec_hash=spec.hash, gains_hash=h.hexdigest(), backend=backend, platform=jax.default_backend(),
                versions={p: versions.get(p) for p in NUMERICS},
                n_runs=int(n_runs if n_runs is not None else n_runs_of(spec)))


def n_runs_of(spec: Spec) -> int:
    """Number of runs of a spec (cells x reps), without building the design."""
    return int(np.prod([len(v) for v in spec.factors.values()])) * spec.reps


def check_size(spec: Spec, allow_large: bool = False) -> None:
    """Refuse a campaign whose batch would not fit in memory (an estimate, before the design is built).

    Raises:
        LimitError: runs x (RUN_BYTES + a chunk's log samples x LOG_SAMPLE_BYTES) exceeds the available memory,
            unless ``allow_large``.
    """
    c = spec.campaign
    n = n_runs_of(spec)
    samples = max(1.0, c["chunk_seconds"] / (0.002 * c["control_substeps"] * LOG_EVERY))  # 2 ms physics step
    need = n * (RUN_BYTES + samples * LOG_SAMPLE_BYTES)
    avail = _available_memory()
    if avail and need > avail and not allow_large:
        raise LimitError(f"{spec.path}: {n:,} runs need about {need / 2**30:,.1f} GiB, "
                         f"{avail / 2**30:,.1f} GiB available; fewer levels or reps, a smaller "
                         "campaign.chunk_seconds, or --allow-large to try anyway")


def _available_memory() -> int | None:
    """Available memory [bytes]: the accelerator's free memory, else the host's MemAvailable; None if unknown."""
    try:
        st = jax.local_devices()[0].memory_stats() or {}
        if "bytes_limit" in st:
            return int(st["bytes_limit"] - st.get("bytes_in_use", 0))
    except Exception:  # noqa: BLE001  (CPU devices have no memory stats)
        pass
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _versions() -> dict:
    out = {"python": platform.python_version()}
    for p in PACKAGES:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = None
    return out


def _git_commit(package_dir: Path | None = None) -> str | None:
    """HEAD of this project's checkout, with ``-dirty`` when tracked files differ from it; None when the package
    is not in its own repository (outside git, or inside another repository that does not track this package).

    Args:
        package_dir: the ``wbc_jax`` folder (default: this package's).
    """
    pkg = (package_dir or Path(__file__).resolve().parents[1]).resolve()
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=pkg, capture_output=True, text=True,
                             timeout=5)
        root = Path(top.stdout.strip()).resolve() if top.returncode == 0 and top.stdout.strip() else None
        if root is None or pkg.parent != root:  # the project's root holds wbc_jax/ (pyproject.toml beside it)
            return None
        tracked = subprocess.run(["git", "ls-files", "--error-unmatch", "wbc_jax/__init__.py", "pyproject.toml"],
                                 cwd=root, capture_output=True, text=True, timeout=5)
        if tracked.returncode != 0:
            return None
        r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
        head = r.stdout.strip()
        if r.returncode != 0 or not head:
            return None
        st = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True,
                            text=True, timeout=10)
        return head + ("-dirty" if st.returncode != 0 or st.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def zero_noise_warning(spec: Spec) -> str | None:
    """The warning for a spec without perturbations, or None: only with reps > 1 are identical repetitions a problem
    (one run per cell, e.g. sweeps/paper_exact.toml, is a deliberate deterministic design)."""
    if spec.zero_noise and spec.reps > 1:
        return ("all perturbations are zero: repetitions are identical, within-cell variance is zero and the F "
                "tests are meaningless")
    return None


def factor_columns(spec: Spec) -> list[str]:
    """The results table's factor columns: the spec's factors in design order (m, mu, d for the paper's)."""
    return list(spec.factors)


def results_table(spec: Spec, dz: Design, res: dict):
    """One row per run: run, m, mu, d, the other factors' levels (one column each, named like the factor),
    rep, seed, success, the metrics and flags, the perturbations."""
    import pandas as pd

    extra = {k: v for k, v in dz.levels.items() if k not in ("m", "mu", "d", "push_N")}
    df = pd.DataFrame(dict(run=np.arange(dz.n), m=dz.m, mu=dz.mu, d=dz.d, **extra, rep=dz.rep, seed=dz.seed,
                           success=res["success"]))
    for k in ("R", "T", "S", "R_plan", "max_slip_mm", "fell", "trunk_low", "body_contact", "dropped", "slid", "hit_wall",
              "qp_flagged", "qp_flag_fraction", "qp_iters_mean", "qp_iters_max", "nonfinite", "overflow", "solver_cap_fraction", "boundary_fraction",
              "boundary_cone_fraction",
              "boundary_fraction_plan", "boundary_cone_fraction_plan", "final_err_mm", "fail_reason", "first_contact_s",
              "first_contact", "window_s", "min_clearance_mm", "min_clearance_s", "min_clearance_pair"):
        df[k] = res[k]
    df["obj_dx_mm"] = dz.obj_dx * 1e3
    df["obj_dy_mm"] = dz.obj_dy * 1e3
    df["obj_yaw_deg"] = np.rad2deg(dz.obj_yaw)
    df["push_N"] = dz.levels["push_N"] if "push_N" in dz.levels else np.linalg.norm(dz.push_force, axis=1)
    return df


def _shared_resume(state, done: int, spread, n: int, axes):
    """Process 0's resume point (its loaded state of ``n`` runs, run axes ``axes``, and chunk count) in every
    process, the state placed as ``spread`` (:class:`wbc_jax.rollout.spread.Spread`) places the batch."""
    from jax.experimental import multihost_utils

    if distributed.is_multiprocess():
        state, done = multihost_utils.broadcast_one_to_all((runs.first(jax.device_get(state), n, axes),
                                                            np.int32(done)))
    return spread.place_state(state, n, axes), int(done)


def run_campaign(spec_path: str | None, out: str, resume: bool = False, report: bool = True,
                 progress: bool = True, gains=None, _interrupt_after: int | None = None, *, force: bool = False,
                 allow_large: bool = False, inputs: tuple = (), backend: str | None = None) -> dict:
    """Run a campaign and write DIR (see module docstring). Returns the manifest.

    Args:
        spec_path: TOML spec; None: :func:`wbc_jax.campaign.spec.default_spec_path` for this machine.
        out: output directory: new or empty, or an earlier campaign's with ``force``.
        resume: continue from the checkpoint next to DIR if there is one.
        report: also write the ANOVA report (``report/``).
        gains: controller gains (unbatched TransportGains) instead of the defaults.
        _interrupt_after: testing hook: raise KeyboardInterrupt after this many chunks (checkpoint kept).
        force: replace DIR when it holds an earlier campaign.
        allow_large: run even when the memory estimate (:func:`check_size`) exceeds what is available.
        inputs: further input files (e.g. the gains file) that DIR must not hold.
        backend: physics backend ("auto", "jax", "warp") instead of the spec's ``campaign.backend``.

    Returns:
        The manifest; None in a process other than process 0 of a multi-process run (it writes nothing).

    Raises:
        OutputError, LimitError, CheckpointError, SpecError: before anything is compiled (in every process of a
            multi-process run: process 0's checks are every process's).
        ReportError: the report failed after results.csv and manifest.json were written.
    """
    t_import = time.perf_counter()
    import wbc_jax.rollout.batch  # noqa: F401  (MJX, the controllers, the planner: timed apart from setup)

    t_start = time.perf_counter()
    spec = load_spec(spec_path if spec_path is not None else default_spec_path(has_accelerator()))
    spec = with_backend(spec, backend)
    physics_backend = backend_of(spec)
    sensing_of(spec)  # a bad combination fails here, before anything is written
    writer = distributed.is_writer()
    identity = run_identity(spec, gains, backend=physics_backend)
    out_p = ck = problem = None
    try:  # process 0's output folder and checkpoint (the others write nothing and read neither)
        if writer:
            out_p = check_out_dir(out, COMMAND, force=force, inputs=[spec.path, *inputs])
            ck = checkpoint.ckpt_dir(out_p)
            if resume:  # meta.json and the identity before the build and the compile; the state file after it
                checkpoint.read_meta(ck, identity, checkpoint.n_chunks_hint(ck))
        check_size(spec, allow_large)
    except WbcJaxError as e:
        problem = e
    distributed.agree(problem)
    sim, dz, b, T_plan, logs_per_chunk, n_chunks = build(spec, gains)
    chunk_s = logs_per_chunk * LOG_EVERY * sim.dt_control
    seconds = n_chunks * chunk_s
    sp, state0 = choose(sim.robot.backend), b.state  # several devices: each steps its own runs (wbc_jax.rollout.spread)
    b = sp.place(b)
    state, done, wall_before, marks, p_goal = b.state, 0, 0.0, [], None
    if resume:
        st = meta = problem = None
        if writer:
            try:
                st, meta = checkpoint.load_state(ck, state0, identity, n_chunks)
            except WbcJaxError as e:
                problem = e
        distributed.agree(problem)
        if sp.mode != "one":  # every process: process 0's resume point, placed as the batch
            state, done = _shared_resume(state0 if st is None else st, meta["chunks_done"] if meta else 0, sp,
                                         dz.n, b.state_axes)
        elif st is not None:
            state, done = st, meta["chunks_done"]
        if meta is not None:
            wall_before, marks = meta["wall_s"], meta["marks"]
            p_goal = np.asarray(meta["p_goal"]) if meta.get("p_goal") is not None else None
        if writer:
            print(f"resuming from {ck}: {done} of {n_chunks} chunks done" if meta is not None else
                  f"no checkpoint at {ck}: starting from the beginning", flush=True)
    elif writer and ck.exists():
        shutil.rmtree(ck)
    if zero_noise_warning(spec) and writer:
        print("warning: all perturbations are zero: repetitions are identical (deterministic runs)", flush=True)
    if sp.note and writer:
        print(sp.note, flush=True)
    print(f"{'' if writer else f'process {jax.process_index()}: '}campaign {spec.campaign['name']!r} ({spec.path}): "
          f"{dz.n} runs = {dz.n // spec.reps} cells x {spec.reps} reps, {seconds:.2f} s simulated in {n_chunks} "
          f"chunks of {chunk_s:.2f} s, scene {spec.campaign['scene']}, device {jax.devices()[0].device_kind}{sp.describe()}",
          flush=True)
    fn = _chunk_fn(sim, b.in_axes, logs_per_chunk, sp.mesh, b.state_axes)
    bar = None
    if progress and writer:
        from tqdm import tqdm

        bar = tqdm(total=round(seconds, 3), initial=round(done * chunk_s, 3), unit="sim-s", file=sys.stderr,
                   bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} sim-s [{elapsed}<{remaining}{postfix}]")
    t_run = time.perf_counter()
    first_in_process = True  # that chunk's wall time includes compilation
    step = lambda st: fn(b.model, st, b.plan, b.om, b.gains, b.push, b.mu_ground)  # noqa: E731  (dispatch only)
    reporter = None
    try:
        nxt, t0 = (step(state) if done < n_chunks else None), t_run
        if report and writer:  # the report's process gets ready during the rollout (wbc_jax.analysis.render),
            from wbc_jax.analysis.render import ReportWorker  # started once the first chunk is traced and compiled

            reporter = ReportWorker.for_machine()
        while done < n_chunks:
            state, logs = nxt
            state = jax.block_until_ready(state)
            dt_wall = time.perf_counter() - t0
            t0 = time.perf_counter()
            done += 1
            # the next chunk runs on the device while this one's checkpoint is written (nothing is donated: the
            # state saved below stays valid)
            nxt = step(state) if done < n_chunks else None
            marks.append(dict(chunk=done, wall_s=dt_wall, fresh_process=first_in_process))
            first_in_process = False
            if sp.mode == "one":
                p_goal, saved = np.asarray(logs.p_obj_ref[:, -1]), state
            else:  # every process takes part in the gathers; process 0 writes
                p_goal, saved = sp.gather((logs.p_obj_ref[:, -1], state), dz.n, (0, b.state_axes))  # one collective
            if writer:
                checkpoint.save_state(ck, saved, dict(identity=identity, chunks_done=done, n_chunks=n_chunks,
                                           wall_s=wall_before + time.perf_counter() - t_run, marks=marks,
                                           p_goal=p_goal.tolist()))
            if bar is not None:
                bar.update(chunk_s)
                bar.set_postfix_str(f"{dz.n} runs, {dz.n * chunk_s / sim.dt_physics / dt_wall:,.0f} env-steps/s")
            if _interrupt_after is not None and done >= _interrupt_after and done < n_chunks:
                raise KeyboardInterrupt
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        if reporter is not None:
            reporter.close()
        if writer:
            print(f"interrupted after {done} of {n_chunks} chunks; finished chunks kept in {ck}; "
                  f"continue with --resume", file=sys.stderr, flush=True)
        raise
    if bar is not None:
        bar.close()
    wall_sim = wall_before + time.perf_counter() - t_run
    if sp.mode != "one":
        state = sp.gather(state, dz.n, b.state_axes)
    if not writer:
        print(f"process {jax.process_index()}: done; process 0 writes {out}", flush=True)
        return None

    from wbc_jax.rollout import final_results

    res = final_results(sim, state, p_goal, dz.mu)
    df = results_table(spec, dz, res)
    # env-steps/s from chunks that did not compile (the first chunk of each process does)
    steady = [mk["wall_s"] for mk in marks if not mk["fresh_process"]]
    per_chunk = float(np.median(steady)) if steady else None
    first = [mk["wall_s"] for mk in marks if mk["fresh_process"]]
    compile_s = (first[0] - per_chunk) if (first and per_chunk) else None
    eps = dz.n * chunk_s / sim.dt_physics / per_chunk if per_chunk else dz.n * seconds / sim.dt_physics / wall_sim
    cols = list(dict.fromkeys(["m", "mu", "d", *factor_columns(spec)]))  # a cell's values, the paper's first
    cells = df.groupby(cols)["success"].agg(["size", "sum"]).reset_index()
    failures = [dict(**{k: _plain(r[k]) for k in cols}, failed=int(r["size"] - r["sum"]), runs=int(r["size"]))
                for _, r in cells.iterrows() if r["size"] != r["sum"]]
    failed_runs = [{"run": int(r.run), "push_N": float(r.push_N),  # the drawn push; a push_N factor's level agrees
                    **{k: _plain(r[k]) for k in cols}, "rep": int(r.rep), "seed": int(r.seed),
                    "reason": r.fail_reason, "first_contact": r.first_contact or None,
                    "first_contact_s": _nan_none(r.first_contact_s)}
                   for _, r in df[~df.success].iterrows()]
    warnings = [w for w in [zero_noise_warning(spec)] if w]
    if failures:
        warnings.append(f"{int((~df.success).sum())} of {dz.n} runs failed: " + "; ".join(
            f"run {f['run']} ({', '.join(f'{k} {f[k]}' for k in cols)}, rep {f['rep']}): {f['reason']}"
            + (f" (first at {f['first_contact_s']:.3f} s: {f['first_contact']})" if f["first_contact"] else "")
            for f in failed_runs[:10]) + (" ..." if len(failed_runs) > 10 else "") + " (all: manifest failed_runs)")
    manifest = dict(
        command="wbc-jax campaign", spec_path=str(spec.path), spec_hash=spec.hash, spec_file_sha256=spec.text_sha256,
        spec=spec.canonical(), default_gains=gains is None, gains_hash=identity["gains_hash"], versions=_versions(), git_commit=_git_commit(),
        physics_backend=physics_backend,
        sensing=sensing_of(spec),
        device=dict(backend=jax.default_backend(), kind=jax.devices()[0].device_kind, count=jax.device_count(),
                    host=platform.node(), cpu_count=os.cpu_count()),
        layout=dict(distributed.layout_record(), spread=sp.mode),  # wbc_jax.rollout.spread: one, mesh, blocks
        n_runs=dz.n, n_cells=int(len(cells)), reps=spec.reps, seeds=[int(s) for s in dz.seed],
        simulated_s=seconds, planned_s=T_plan, chunk_s=chunk_s, n_chunks=n_chunks, control_dt_s=sim.dt_control,
        wall_s_total=time.perf_counter() - t_import + wall_before, wall_s_rollout=wall_sim,
        import_s=t_start - t_import, setup_s=t_run - t_start, compile_s_estimate=compile_s,
        first_chunk_s=first[0] if first else None, env_steps_per_s=eps,
        resumed=bool(resume and wall_before > 0), n_success=int(df.success.sum()), failures_per_cell=failures, failed_runs=failed_runs,
        warnings=warnings, metric_means={k: float(df.loc[df.success, k].mean()) if df.success.any() else None
                                         for k in ("R", "T", "S", "max_slip_mm")},
        constraint_solver=dict(iterations=int(sim.robot.mj_model.opt.iterations),
                               cap_fraction_mean=_nan_none(df.solver_cap_fraction.mean()),
                               cap_fraction_max=_nan_none(df.solver_cap_fraction.max())))
    with atomic_dir(out_p) as tmp:  # the finished simulation first: a failing report cannot lose it
        df.to_csv(tmp / "results.csv", index=False)
        manifest["wall_s_total"] = time.perf_counter() - t_import + wall_before
        write_json_atomic(tmp / "manifest.json", manifest)
    shutil.rmtree(ck, ignore_errors=True)
    if report:
        _campaign_report(out_p, manifest, warnings, reporter)
    for w in manifest["warnings"]:
        print(f"warning: {w}", flush=True)
    print(f"{int(df.success.sum())}/{dz.n} runs succeeded; wall {manifest['wall_s_total']:.1f} s, "
          f"{eps:,.0f} env-steps/s; written to {out}", flush=True)
    return manifest


def _nan_none(x) -> float | None:
    """A float for JSON; None for NaN (e.g. a figure the JAX backend does not report)."""
    x = float(x)
    return None if np.isnan(x) else x


def _plain(x):
    """A numpy scalar as the Python number or string it holds (for JSON)."""
    return x.item() if isinstance(x, np.generic) else x


def _campaign_report(out: Path, manifest: dict, warnings: list[str], reporter=None) -> None:
    """The ANOVA report of ``out/results.csv`` into ``out/report`` (the spec's factors and ``[analysis]``; written
    by ``reporter``, a :class:`wbc_jax.analysis.render.ReportWorker`, when given; closed here); a failure is written
    to ``out/report_error.txt`` and the manifest, and raised as a one-line ReportError (the results stay)."""
    from wbc_jax.analysis.report import CAMPAIGN_METRICS, run_report

    write = run_report if reporter is None else reporter.run_report  # the same function, in the worker
    spec = manifest.get("spec", {})
    analysis = spec.get("analysis", {})
    try:
        write(str(out / "results.csv"), str(out / "report"), metrics=list(CAMPAIGN_METRICS),
                   factors=list(spec["factors"]) if "factors" in spec else None, order=analysis.get("order", 2),
                   alpha=analysis.get("alpha", 0.05))
        if warnings:
            md = out / "report" / "report.md"
            md.write_text("".join(f"> **Campaign warning:** {w}\n\n" for w in warnings) + md.read_text())
    except Exception as e:  # noqa: BLE001  (any failure of the statistics: the finished simulation is kept)
        why = " ".join(f"{type(e).__name__ + ': ' if not isinstance(e, WbcJaxError) else ''}{e}".split())
        (out / "report_error.txt").write_text(why + "\n")
        manifest["warnings"].append(f"no report: {why}")
        write_json_atomic(out / "manifest.json", manifest)
        raise ReportError(f"the simulation finished and {out}/results.csv and manifest.json are written, but the "
                          f"report failed ({why}); retry with wbc-jax report {out}/results.csv --out "
                          f"{out}/report") from None
    finally:
        if reporter is not None:
            reporter.close()


def run_in_fresh_process(spec_path, out: Path, **env) -> Path:
    """``wbc-jax campaign --spec SPEC --out OUT --no-report`` in a new Python process (environment variables
    ``env`` set on top of this one's); returns OUT. A failed run raises WbcJaxError with the end of its stderr."""
    r = subprocess.run([sys.executable, "-m", "wbc_jax", "campaign", "--spec", str(spec_path), "--out", str(out),
                        "--no-report"], env=dict(os.environ, **env), capture_output=True, text=True)
    if r.returncode != 0:
        extra = " ".join(f"{k}={v}" for k, v in env.items())
        raise WbcJaxError(f"campaign {spec_path} ({extra}) failed: {r.stderr.strip()[-800:]}")
    return Path(out)
