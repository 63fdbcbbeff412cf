"""A campaign spec as one batched rollout: the Sim, the per-run design, the Batch and the chunk plan.

:func:`build` turns a validated spec (``wbc_jax.campaign.spec``) into a :class:`Built`: the cached Sim of the scene,
the design table (one row per run), a :class:`wbc_jax.rollout.batch.Batch` with each run's perturbed initial state,
push, metric window and controller variant, and how the simulated horizon is cut into chunks of whole log
intervals. :func:`wbc_jax.campaign.size.check_size` refuses a batch that cannot fit in memory before anything is
built.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import tempfile
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import numpy as np

from wbc_jax.campaign.design import Design, design
from wbc_jax.campaign.spec import BACKENDS, Spec
from wbc_jax.campaign.spec_controller import plugin_of
from wbc_jax.errors import SpecError
from wbc_jax.runtime import aot
from wbc_jax.runtime.transfer import to_device

LOG_EVERY = 20  # control steps per logged sample (the rollout's outer scan)
_SIMS: dict = {}
_FNS: dict = {}


class Built(NamedTuple):
    """A spec built for the rollout.

    Attributes:
        sim: the scene's Sim (static rollout structure).
        design: the design table, one row per run.
        batch: the Batch (model, state, plan, gains, pushes) of every run.
        planned_s: the longest planned duration over the runs [s].
        logs_per_chunk: logged samples (of LOG_EVERY control steps) per chunk.
        n_chunks: chunks that cover the simulated horizon.
    """

    sim: object
    design: Design
    batch: object
    planned_s: float
    logs_per_chunk: int
    n_chunks: int


def has_accelerator() -> bool:
    return jax.default_backend() != "cpu"


def backend_of(spec: Spec) -> str:
    """The spec's physics backend, "auto" resolved here (:func:`wbc_jax.physics.backend.resolve_backend`)."""
    from wbc_jax.physics.backend import resolve_backend

    try:
        return resolve_backend(spec.campaign["backend"])
    except ValueError as e:
        raise SpecError(f"{spec.path}: campaign.backend: {e}") from None


def with_backend(spec: Spec, backend: str | None) -> Spec:
    """``spec`` with ``campaign.backend`` replaced (a ``--backend`` flag); unchanged for None."""
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


def qp_changes(spec: Spec) -> tuple:
    """The spec's changes to its controller's QP settings (``campaign.qp_first_test``, ``qp_alpha``, ``qp_rho``,
    ``qp_max_iters``, ``qp_launch_order``, ``qp_reuse_factors``) as sorted ``(QPSettings field, value)`` pairs
    (hashable: part of the Sim's cache key); ``qp_reuse_factors`` only with Warp physics (docs/performance.md)."""
    c = spec.campaign
    reuse = c["qp_reuse_factors"] and backend_of(spec) == "warp"
    return tuple(sorted({"warm_first_test": c["qp_first_test"],
                         **({"alpha": c["qp_alpha"]} if c["qp_alpha"] > 0 else {}),
                         **({"rho": c["qp_rho"]} if c["qp_rho"] > 0 else {}),
                         **({"max_iters": c["qp_max_iters"]} if c["qp_max_iters"] > 0 else {}),
                         **({"launch_order": c["qp_launch_order"]} if c["qp_launch_order"] != "batch" else {}),
                         **({"reuse_factors": True} if reuse else {})}.items()))


def check_qp(spec: Spec) -> None:
    """SpecError naming ``campaign.qp_first_test`` where the spec's controller cannot use it: the solver's own rule
    (:func:`wbc_jax.qp.api.resolve_settings`: one QP factorization per control step), which the centroidal
    controller's QP breaks with ``qp_iters`` above its ``adapt_every``; and ``campaign.qp_reuse_factors`` and
    ``campaign.qp_rho`` but with the transport controller (whose warm start carries the factors, and its rho, which
    it does not adapt)."""
    from wbc_jax.control.centroidal import centroidal_qp_settings
    from wbc_jax.control.transport import control_qp_settings
    from wbc_jax.qp.api import resolve_settings

    c = spec.campaign
    if c["qp_reuse_factors"] and c["controller"] != "transport":
        raise SpecError(f"{spec.path}: campaign.qp_reuse_factors = 1 with the {c['controller']} controller: only the "
                        "transport controller's QP (the fused kernels) reuses its factors; use 0")
    if c["qp_rho"] and c["controller"] != "transport":
        raise SpecError(f"{spec.path}: campaign.qp_rho = {c['qp_rho']} with the {c['controller']} controller: its "
                        "QP adapts rho from its own start; use 0 (only the transport controller keeps a set rho)")
    iters, first = c["qp_iters"], c["qp_first_test"]
    s = (control_qp_settings if c["controller"] == "transport" else centroidal_qp_settings)(iters)
    try:
        resolve_settings(s._replace(warm_first_test=first), iters, np.float32, "cpu")
    except ValueError as e:
        raise SpecError(f"{spec.path}: campaign.qp_first_test = {first} with campaign.qp_iters = {iters} and the "
                        f"{c['controller']} controller: {e}") from None


def _sim(scene: str, iters: int, sensor_noise: bool = False, substeps: int = 1, backend: str = "jax",
         solver_iterations: int = 0, sensing: str = "exact", controller: str = "transport", qp: tuple = (),
         plugin: tuple = ()):
    """The (cached) Sim of a scene: ``controller`` (or its ``plugin``: :func:`plugin_of`) with ``iters`` ADMM
    iterations and its QP changed by ``qp`` (:func:`qp_changes`), control period ``substeps`` x the timestep."""
    from wbc_jax.control.centroidal import CentroidalConfig, centroidal_qp_settings
    from wbc_jax.control.transport import TransportConfig, control_qp_settings
    from wbc_jax.robot.model import Robot
    from wbc_jax.rollout import make_sim

    key = (scene, iters, sensor_noise, substeps, backend, solver_iterations, sensing, controller, qp, plugin)
    if key not in _SIMS:
        robot = Robot(scene, backend=backend, solver_iterations=solver_iterations)
        dt = float(robot.mj_model.opt.timestep) * substeps
        cfg = (TransportConfig(dt=dt, qp=control_qp_settings(iters)._replace(**dict(qp))) if controller == "transport"
               else CentroidalConfig(qp=centroidal_qp_settings(iters)._replace(**dict(qp)), dt=dt))
        _SIMS[key] = make_sim(robot, cfg, n_substeps=substeps, log_every=LOG_EVERY, sensor_noise=sensor_noise,
                              sensing=sensing, controller=controller, plugin=plugin[:2])
    return _SIMS[key]


def chunk_fn(sim, in_axes, n_logs: int, mesh=None, state_axes=0):
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
        _FNS[key] = (over_runs(fn, mesh, (in_axes, state_axes, 0, 0, 0, 0, 0), (state_axes, 0)) if mesh is not None
                     else aot.cached_jit("chunk", fn, aot.describe(sim, in_axes, n_logs), exportable=sim.exportable))
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
    sides, inverse = np.unique(np.asarray(dz.d, float), return_inverse=True)  # the home pose once per object side
    qpos = np.stack([robot.home_qpos(float(di)) for di in sides])[inverse.reshape(-1)]
    a = ids.obj_qpos_adr
    qpos[:, a] += dz.obj_dx
    qpos[:, a + 1] += dz.obj_dy
    qyaw = np.stack([np.cos(dz.obj_yaw / 2), np.zeros(dz.n), np.zeros(dz.n), np.sin(dz.obj_yaw / 2)], axis=1)
    qpos[:, a + 3:a + 7] = _quat_mul(qyaw, qpos[:, a + 3:a + 7])
    qvel = np.zeros((dz.n, robot.mj_model.nv))
    qvel[:, 0:2] = dz.v0
    qvel[:, ids.obj_dof_adr:ids.obj_dof_adr + 2] = dz.v0
    return qpos, qvel


def centroidal_gains(gains, dz: Design):
    """Per-run gains of the centroidal controller (leading run axis): ``gains`` (unbatched CentroidalGains; None: the
    defaults) with ``mass_scale`` = 1 + the run's mass error and ``load_mass`` = its object mass (the controller
    knows its payload)."""
    from wbc_jax.control.centroidal import default_gains

    base = default_gains() if gains is None else gains
    out = {name: np.broadcast_to(np.asarray(leaf), (dz.n,) + np.shape(leaf)) for name, leaf in zip(base._fields, base)}
    dtype = out["mass_scale"].dtype
    out["mass_scale"] = (1.0 + dz.mass_error).astype(dtype)
    out["load_mass"] = np.asarray(dz.m).astype(dtype)
    return type(base)(**{k: to_device(v) for k, v in out.items()})


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
        out[name] = to_device(x)
    return type(base)(**out)


def walk_steps(campaign: dict) -> int:
    """The centroidal trot's half-cycles: walk_seconds in half-cycles of step_time, at least 2."""
    return max(2, int(round(campaign["walk_seconds"] / campaign["step_time"])))


def _plan_kwargs(campaign: dict) -> dict:
    """The controller's planner keywords of a spec's ``campaign`` table."""
    if campaign["controller"] == "centroidal":
        return dict(speed=campaign["speed"], step_time=campaign["step_time"], four_foot=campaign["four_foot"],
                    n_steps=walk_steps(campaign))
    return dict(distance=campaign["distance"], speed=campaign["speed"], terrain=campaign["terrain"],
                com_plan=campaign["com_plan"])


def build(spec: Spec, gains=None) -> Built:
    """Spec -> :class:`Built` (the Sim, the design, the Batch with perturbed initial states and pushes, the chunk
    plan). ``gains``: controller gains (unbatched, of the spec's controller) instead of the defaults."""
    return _build(spec, gains, states=True)[0]


def build_ahead(spec: Spec, gains=None) -> tuple[Built, Callable[[], Built]]:
    """:func:`build` with the batch's initial states as shapes only (``jax.ShapeDtypeStruct`` leaves: nothing of
    them runs), and a function returning the Built with them made; :func:`states_and_program` calls it and compiles
    the chunk program (on the Warp backend the initial states are MuJoCo Warp's first call, which compiles the
    model's kernels)."""
    return _build(spec, gains, states=False)


def _build(spec: Spec, gains, states: bool) -> tuple[Built, Callable[[], Built] | None]:
    from wbc_jax.control.variants import Variant
    from wbc_jax.rollout import make_push, with_metric_window, with_plugin_params, with_variant
    from wbc_jax.rollout.batch import initial_states, prepare_batch

    c = spec.campaign
    check_qp(spec)
    dz = design(spec)
    transport = c["controller"] == "transport"
    sim = _sim(contact_scene(c), c["qp_iters"], bool(np.any(dz.qvel_noise_std > 0)), c["control_substeps"],
               backend_of(spec), c["solver_iterations"], sensing_of(spec), c["controller"], qp_changes(spec),
               plugin_of(spec))
    qpos0, qvel0 = initial_configuration(sim.robot, dz)
    gains = run_gains(gains, dz) if transport else centroidal_gains(gains, dz)
    b = prepare_batch(sim, dz.m, dz.mu, dz.d, gains=gains, plan_kwargs=_plan_kwargs(c), qpos0=qpos0, qvel0=qvel0,
                      speed=dz.speed if "speed" in spec.factors else None,
                      ground_mu=dz.ground_mu if np.all(dz.ground_mu > 0) else None,
                      ramp=speed_ramps(spec, dz), shapes_only=not states)
    planned_s = sim.controller.planned_s(b.plan)
    t_plan = sim.controller.plan_end(b.plan)  # (B,) each run's plan end [s]
    # push start: a fraction of the planned duration (each run's own when the speed or the ramps are varied)
    own = "speed" in spec.factors or "obj_accel" in spec.factors
    push = make_push(dz.push_force, dz.push_frac * (t_plan if own else planned_s),
                     dz.push_duration, dz.qvel_noise_std, dz.seed)
    # metric window (wbc_jax.metrics.paper): each run's own plan end + the settling time, capped like the horizon
    t_end = t_plan + c["extra_seconds"]
    if c["max_seconds"] > 0:
        t_end = np.minimum(t_end, c["max_seconds"])

    def finish(state):
        state = with_plugin_params(with_metric_window(state, t_end), dz.plugin_params, sim.controller)
        return with_variant(state, Variant(*dz.variant.T), sim.controller) if transport else state

    b = b._replace(push=push, state=finish(b.state))  # shapes stay shapes (Packed._replace, placed_like)
    built = Built(sim, dz, b, planned_s, *chunk_plan(c, sim.dt_control, planned_s))

    def with_states() -> Built:
        state = finish(initial_states(sim, b.model, b.in_axes, qpos0, qvel0))
        return built._replace(batch=b._replace(state=state))

    return built, None if states else with_states


def lower_chunk(built: Built):
    """The chunk program (:func:`chunk_fn`, one device) traced and lowered for ``built``'s batch from its arguments'
    shapes (``jax.stages.Lowered``; the initial states may be shapes only: :func:`build_ahead`). Raises ValueError
    where the chunk program cannot be lowered ahead (the JAX backend's is exported instead:
    :func:`wbc_jax.runtime.aot.cached_jit`)."""
    from wbc_jax.rollout.batch import chunk_args

    b = built.batch
    fn = chunk_fn(built.sim, b.in_axes, built.logs_per_chunk, None, b.state_axes)
    if not hasattr(fn, "lower"):
        raise ValueError("lower_chunk: the chunk program of this backend is exported, not lowered ahead")
    return fn.lower(*chunk_args(b))


def states_and_program(built: Built, with_states: Callable[[], Built], ahead=None):
    """``(with_states(), the chunk program compiled, seconds)`` for a :func:`build_ahead` pair (the program:
    ``jax.stages.Compiled``, called instead of tracing it again): the chunk program traced first
    (:func:`lower_chunk`), then the initial states made (on Warp, MuJoCo Warp's first call) and the program compiled,
    XLA's compile in the window of ``ahead``'s next first call when given (a
    ``wbc_jax.physics.warp_kernels.CompileAhead``: beside the model's kernels' compile), else after the states.
    ``seconds``: the program's trace and compile [s]."""
    t0 = time.perf_counter()
    lowered = lower_chunk(built)
    traced_s = time.perf_counter() - t0
    if ahead is None:
        states = with_states()
        t0 = time.perf_counter()
        return states, lowered.compile(), traced_s + time.perf_counter() - t0
    beside = ahead.open_window(lowered.compile)
    try:
        made = with_states()
        jax.block_until_ready(made.batch.state)  # the first call has run, also where XLA runs it on its own thread
        return made, beside.result(), traced_s + beside.seconds
    finally:
        ahead.close_window()


def contact_scene(campaign: dict) -> str:
    """The campaign's scene with its contact options (``cone``, ``impratio``) applied: a copy in a folder of the
    system's temporary directory named by the options (:func:`wbc_jax.robot.scenario.scene_variant`), or the scene
    itself when both keep the scene's."""
    from wbc_jax.robot.scenario import scene_variant

    options = {k: campaign[k] for k, keep in (("cone", "scene"), ("impratio", 0.0)) if campaign[k] != keep}
    if not options:
        return campaign["scene"]
    name = hashlib.sha256(json.dumps([campaign["scene"], options], sort_keys=True).encode()).hexdigest()[:16]
    return scene_variant(campaign["scene"], options, out_dir=str(Path(tempfile.gettempdir()) / f"wbc_jax_scene_{name}"))


def speed_ramps(spec: Spec, dz: Design):
    """(B,) each run's speed-ramp duration [s] from its peak object acceleration (``obj_accel``, a factor or the
    campaign's value): 2 speed / obj_accel (:func:`wbc_jax.planner.spline.straight_path`: peak 2 speed / ramp);
    None where no run sets one (the planner's default ramps)."""
    accel = dz.levels.get("obj_accel", np.full(dz.n, spec.campaign["obj_accel"]))
    if not np.any(accel > 0):
        return None
    return np.where(accel > 0, 2 * dz.speed / np.where(accel > 0, accel, 1.0), 1.0)


def chunk_plan(campaign: dict, dt_control: float, planned_s: float) -> tuple[int, int]:
    """(logged samples per chunk, chunks) of a spec's ``campaign`` table: as few chunks of at most
    ``chunk_seconds`` (rounded to whole log intervals of LOG_EVERY control steps of ``dt_control`` [s]) as cover the
    horizon (``planned_s`` + ``extra_seconds`` [s]), each made as short as still covers it, so the simulation ends
    less than one log interval per chunk past the horizon instead of rounding it up to whole chunks of
    ``chunk_seconds``. A ``max_seconds`` cap below the horizon is met exactly when it is a whole number of log
    intervals: the fewest equal chunks that divide it (:func:`check_horizon` refuses the others)."""
    log_dt = dt_control * LOG_EVERY
    most = max(1, int(round(campaign["chunk_seconds"] / log_dt)))
    horizon = planned_s + campaign["extra_seconds"]
    cap = campaign["max_seconds"]
    if cap > 0:
        horizon = min(horizon, cap)
    logs = horizon / log_dt
    n_chunks = max(1, int(np.ceil(logs / most - 1e-9)))
    per_chunk = max(1, int(np.ceil(logs / n_chunks - 1e-9)))
    whole = int(round(cap / log_dt))
    if cap > 0 and n_chunks * per_chunk * log_dt > cap + 1e-9 and whole >= 1 and abs(cap / log_dt - whole) < 1e-6:
        n_chunks = next(k for k in range(-(-whole // most), whole + 1) if whole % k == 0)
        per_chunk = whole // n_chunks
    return per_chunk, n_chunks


def check_horizon(spec: Spec, built: Built) -> None:
    """Refuse a ``campaign.max_seconds`` that the chunks cannot honour exactly (before anything is compiled).

    Raises:
        SpecError: the cap is shorter than one logged interval (no metric could be computed), or not a whole number
            of logged intervals (the chunks would simulate past it); the line names a cap that fits.
    """
    c = spec.campaign
    cap = c["max_seconds"]
    if cap <= 0:
        return
    log_dt = built.sim.dt_control * LOG_EVERY
    if cap < log_dt - 1e-9:
        raise SpecError(f"{spec.path}: campaign.max_seconds = {cap:g}: shorter than one logged interval ({log_dt:g} s "
                        f"= {LOG_EVERY} control steps), too short for any metric; use at least {log_dt:g}")
    simulated = built.n_chunks * built.logs_per_chunk * log_dt
    if simulated <= cap + 1e-9:
        return
    raise SpecError(f"{spec.path}: campaign.max_seconds = {cap:g} is not a whole number of logged intervals "
                    f"({log_dt:g} s = {LOG_EVERY} control steps), so {simulated:g} s would be simulated; use a "
                    f"multiple of {log_dt:g} s, e.g. {int(cap / log_dt + 1e-9) * log_dt:g}")
