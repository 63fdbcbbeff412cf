"""MJX physics on either backend, split so the controller reads fresh kinematics once per control step.

Two MJX implementations (``Robot(backend=...)``): **JAX** (``impl="jax"``, any device, the CPU path) and **Warp**
(``impl="warp"``, MuJoCo Warp kernels called through XLA; NVIDIA GPUs, and the CPU for tests). :func:`sense` runs
the forward pass's position and velocity stages (the controller reads M, bias forces, Jacobians and contacts from
its output); :func:`finish` completes that forward pass with the controller's torques and integrates: one physics
step, both exact (on Warp ``sensing = "delayed"`` drops :func:`sense`, ``wbc_jax.rollout.config.resolve_sensing``).
On Warp both are MJX's own generated XLA calls running other MuJoCo Warp functions (:func:`_mjx_warp_call`):
``step1``, then the rest of ``step``; the same arithmetic as ``mjx.forward`` then ``mjx.step``. A control period
of ``n_substeps`` physics steps is :func:`finish` then ``n_substeps - 1`` plain ``mjx.step`` calls
(``wbc_jax.rollout.step.physics_period``). :func:`resolve_backend` turns "auto" into Warp on a CUDA GPU with
warp-lang installed, else JAX.

After any of these steps, ``d.contact`` (and ``efc_force``) belong to the positions at the *start* of that
step (collision runs before integration): after :func:`finish` they are the sensed ``d``'s contacts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import threading
import types

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

with contextlib.redirect_stdout(io.StringIO()):
    # MJX prints a notice on stdout when the optional Warp backend (warp-lang) is absent.
    from mujoco import mjx

BACKENDS = ("auto", "jax", "warp")
NACON_PER_RUN = 32  # Warp: contacts listed per run on average (the list is shared: naconmax = runs x this); a
#                     standing or walking robot with the object lists 8-12 (feet, object spheres)
NJMAX_PER_CONTACT = 4  # constraint rows of one pyramidal condim-3 contact

# MuJoCo Warp's import-time kernel modules that a forward step of a rigid-body model with contacts launches
# (kinematics, sensors, constraints, the solver, and MJX's FFI glue; not the passive forces, which the scenes turn
# off where they are zero: wbc_jax.robot.sensors.zero_stages): what wbc_jax.physics.warp_kernels compiles ahead
WARP_STEP_MODULES = tuple(f"mujoco.mjx.third_party.mujoco_warp._src.{name}" for name in (
    "forward", "smooth", "sensor", "constraint", "solver", "support")) + ("mujoco.mjx.warp.ffi",)


def warp_available() -> bool:
    """warp-lang importable (MJX's Warp implementation can run)."""
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(name: str) -> str:
    """"auto" -> "warp" on a CUDA GPU with warp-lang, else "jax" (module docstring); "jax", "warp" unchanged.

    Raises:
        ValueError: an unknown name, or "warp" without warp-lang.
    """
    if name not in BACKENDS:
        raise ValueError(f"backend {name!r}: expected one of {', '.join(BACKENDS)}")
    if name == "auto":
        return "warp" if jax.default_backend() == "gpu" and warp_available() else "jax"
    if name == "warp" and not warp_available():
        raise ValueError("backend 'warp' needs warp-lang (pip install -e '.[cuda]', or pip install warp-lang)")
    return name


def is_warp(d) -> bool:
    """``d`` is MuJoCo Warp data (static: the type of its implementation part)."""
    return type(d._impl).__name__ == "DataWarp"


def make_data(robot, n_runs: int = 1):
    """A fresh mjx.Data of ``robot``'s backend. Warp: the contact list is shared by the ``n_runs`` runs of a batch
    (``naconmax = n_runs x NACON_PER_RUN``), constraint rows are per run (``njmax``); call it inside the vmap
    over runs, as MJX's Warp examples do."""
    if robot.backend != "warp":
        return mjx.make_data(robot.mjx_model, device=jax.local_devices()[0])  # (several processes: not process 0's)
    m = robot.mj_model
    njmax = NJMAX_PER_CONTACT * NACON_PER_RUN + 2 * m.njnt
    return mjx.make_data(m, impl="warp", naconmax=NACON_PER_RUN * max(int(n_runs), 1), njmax=njmax,
                         device=jax.local_devices()[0])


_DATA_AXES: dict = {}


def data_axes(robot, d):
    """The run axes of ``d``, a batched mjx.Data of ``robot``'s backend (``vmap`` of :func:`make_data`): a pytree
    of ``d``'s structure, 0 where a leaf has the run axis first, None where the runs share it (Warp: the contact
    list and its counters, scratch every ``step`` rebuilds, placed whole on every device and left as they are when
    runs are taken or padded). Found from the shapes of :func:`make_data` vmapped over 2 and 3 runs."""
    if not is_warp(d):
        return jax.tree_util.tree_map(lambda _: 0, d)
    n_runs = int(d._impl.naconmax) // NACON_PER_RUN
    key = (robot, n_runs)  # Robots hash by value
    if key not in _DATA_AXES:
        two, three = (jax.eval_shape(jax.vmap(lambda _: make_data(robot, n_runs)), np.zeros(k)) for k in (2, 3))
        _DATA_AXES[key] = jax.tree_util.tree_map(lambda a, b: 0 if a.shape != b.shape else None, two, three)
    return _DATA_AXES[key]


def size_contact_list(d, axes, n_runs: int):
    """(``d``, ``axes``) with Warp's shared contact list sized for ``n_runs`` runs as :func:`make_data` sizes it:
    ``d`` a batched mjx.Data (run axes ``axes``, :func:`data_axes`) whose runs were taken from another batch. The
    list is scratch every step rebuilds: cut, or grown with zeros (else more runs' contacts would overflow it)."""
    if not is_warp(d):
        return d, axes
    impl, slots = d._impl, NACON_PER_RUN * max(int(n_runs), 1)
    have = int(impl.naconmax)
    if slots == have:
        return d, axes
    names = [f.name for f in dataclasses.fields(impl) if getattr(axes._impl, f.name) is None
             and np.ndim(getattr(impl, f.name)) and np.shape(getattr(impl, f.name))[0] == have]

    def sized(x):  # on the host (an eager slice on the device compiles a program per shape), placed back as x was
        h = np.asarray(x)
        h = h[:slots] if slots < have else np.concatenate([h, np.zeros((slots - have, *h.shape[1:]), h.dtype)])
        return jax.device_put(h, x.sharding) if isinstance(x, jax.Array) else h

    sizes = dict(naconmax=slots, naccdmax=slots)  # make_data: naccdmax = naconmax
    d = d.replace(_impl=impl.replace(**sizes, **{k: sized(getattr(impl, k)) for k in names}))
    return d, axes.replace(_impl=axes._impl.replace(**sizes))


STATE_FIELDS = ("time", "qpos", "qvel", "act", "qacc_warmstart", "history", "plugin_state")
"""The fields of mjx.Data a physics step reads that it does not recompute (the integrated state, the solver's warm
start); every other field is derived from them and the inputs ``ctrl``, ``xfrc_applied`` (set every step)."""


def freeze(ok, new, old):
    """``new`` with its :data:`STATE_FIELDS` taken from ``old`` where ``ok`` is False (per run, under ``vmap``): a
    run whose step went non-finite keeps its last finite state, so its next step recomputes every derived field from
    it (Warp's shared contact list gets no garbage). Cheaper than ``Data.where`` over every field (Warp's in-place
    ``step`` would copy each field of ``old`` still read)."""
    return new.replace(**{f: jnp.where(ok, getattr(new, f), getattr(old, f)) for f in STATE_FIELDS
                          if hasattr(new, f)})


def overflow(d) -> jax.Array:
    """() bool: this step's contacts or constraint rows may not all fit (Warp: candidate pairs or listed contacts
    reached ``naconmax``, or this run's rows ``njmax``); always False on JAX (fixed slots)."""
    if not is_warp(d):
        return jnp.bool_(False)
    i = d._impl
    full = (jnp.max(i.nacon) >= i.naconmax) | (jnp.max(i.ncollision) >= i.naconmax)
    return full | (i.nefc >= i.njmax)


def solver_capped(m, d) -> jax.Array:
    """() bool: the physics step that produced ``d`` ended its constraint solve at the iteration cap
    (``opt.iterations``) instead of at its tolerance (Warp's ``solver_niter``; counted per run, ``Accum.n_solver_cap``,
    its console warning being off). MJX's JAX solver does not count: False (:func:`reports_solver_cap`)."""
    if not is_warp(d):
        return jnp.bool_(False)
    return d._impl.solver_niter >= m.opt.iterations


def contact_sensor_slots(m) -> int | None:
    """The contacts MuJoCo Warp's contact sensors of ``m`` (an MJX model) hold per run and sensor
    (``contact_sensor_maxmatch``: the model's numeric of that name, else 64); None on JAX (no sensors read)."""
    impl = getattr(m.opt, "_impl", None)
    return getattr(impl, "contact_sensor_maxmatch", None)


def reports_solver_cap(robot) -> bool:
    """Whether :func:`solver_capped` is measured on ``robot``'s backend (Warp) rather than always False (JAX)."""
    return robot.backend == "warp"


def sense(m, d):
    """The forward pass's position and velocity stages: MJX ``fwd_position`` + ``fwd_velocity`` (JAX), MuJoCo
    Warp's ``step1`` (Warp, :func:`_warp_stages`); the later stages are left to :func:`finish`."""
    if is_warp(d):
        return _warp_stages()(m, d)
    d = mjx.fwd_position(m, d)
    return mjx.fwd_velocity(m, d)


def initial(m, d, sensed: bool = False):
    """A run's first data: :func:`sense` (JAX), ``mjx.forward`` (Warp: every field; its first call compiles the
    step's kernels ahead, ``wbc_jax.physics.warp_kernels``). ``sensed`` (exact sensing): on Warp the same forward
    pass through MJX's generated call whose skipped pass (:func:`skipped_pass`) also walks :func:`sense` and
    :func:`finish`, so their own kernels (the mass matrix's separate factor and solve) compile ahead too."""
    if not is_warp(d):
        return sense(m, d)
    return _warp_forward()(m, d) if sensed and _splits(m) else mjx.forward(m, d)


_PASS = threading.local()  # on: this thread runs a skipped pass (skipped_pass)


@contextlib.contextmanager
def skipped_pass():
    """Marks this thread's MuJoCo Warp calls as a pass whose kernel launches are skipped, run to find the kernels a
    call launches (``wbc_jax.physics.warp_kernels.launched_modules``)."""
    _PASS.on = True
    try:
        yield
    finally:
        _PASS.on = False


def sense_with_view(m, d, qvel_seen=None):
    """:func:`sense` of ``d``, and the controller's view of it with generalized velocities ``qvel_seen`` (positions,
    hence kinematics and contacts, exact; None: the view is the sensed data itself).

    Returns:
        (sensed d, view). JAX: the view recomputes the velocity stage. Warp: one :func:`sense` call on the view;
        the sensed d is the view with the true velocities put back (:func:`finish` recomputes what depends on them).
    """
    if qvel_seen is None:
        d = sense(m, d)
        return d, d
    if is_warp(d):
        view = sense(m, d.replace(qvel=qvel_seen))
        return view.replace(qvel=d.qvel), view
    d = sense(m, d)
    return d, mjx.fwd_velocity(m, d.replace(qvel=qvel_seen))


def finish(m, d, ctrl, sensed: bool = True):
    """One physics step from ``d``: finish its forward pass with ``ctrl`` and integrate.

    Args:
        m: mjx.Model; d: mjx.Data; ctrl: (nu,) actuator torques [N m]; sensed: ``d``'s position stage is
            :func:`sense`'s of its positions (Warp then skips it, :func:`_warp_finish`; False, delayed sensing:
            ``mjx.step``).

    Returns:
        mjx.Data one timestep later (``ctrl`` kept, contacts and constraint forces of the step's start).
    """
    d = d.replace(ctrl=ctrl)
    if is_warp(d):
        return _warp_finish()(m, d) if sensed and _splits(m) else mjx.step(m, d)
    d = mjx.fwd_actuation(m, d)
    d = mjx.fwd_acceleration(m, d)
    d = mjx.solve(m, d)
    return mjx.euler(m, d)


# ---- the package's only reads of MJX internals (``mujoco.mjx._src``, ``Data._impl``, ``Option._impl``, MuJoCo Warp)


def _mjx_warp_call(kind: str, body):
    """MJX's generated XLA call of MuJoCo Warp's ``kind`` ("forward" or "step", ``mujoco.mjx.warp.forward``) running
    ``body(m, d)`` (Warp Model, Data) instead, with its own argument holders and FFI target."""
    from mujoco.mjx.warp import ffi
    from mujoco.mjx.warp import forward as mjxw

    def clone(fn, **names):  # fn with module globals replaced
        out = types.FunctionType(fn.__code__, dict(fn.__globals__, **names), fn.__name__, fn.__defaults__)
        out.__annotations__ = dict(fn.__annotations__)
        return out

    held = {k: type(v)(**{f.name: None for f in dataclasses.fields(v) if f.init})
            for k, v in vars(mjxw).items() if k in ("_m", "_d", "_o", "_c", "_e", "_cb")}
    shim = clone(getattr(mjxw, f"_{kind}_shim").__wrapped__, mjwarp=types.SimpleNamespace(**{kind: body}), **held)
    impl = clone(getattr(mjxw, f"_{kind}_jax_impl"), **{f"_{kind}_shim": ffi.format_args_for_warp(shim)})

    @jax.custom_batching.custom_vmap
    @ffi.marshal_jax_warp_callable
    def call(m, d):
        return impl(m, d)

    call.def_vmap(ffi.marshal_custom_vmap(lambda _, batched, m, d: (call(m, d), batched[1])))
    return call


def _splits(m) -> bool:
    """Warp: :func:`finish` runs the rest of ``step`` after :func:`sense` (Euler or implicitfast, no sleeping)."""
    euler_like = (mujoco.mjtIntegrator.mjINT_EULER, mujoco.mjtIntegrator.mjINT_IMPLICITFAST)
    return not int(m.opt.enableflags) & mujoco.mjtEnableBit.mjENBL_SLEEP and int(m.opt.integrator) in euler_like


def _mjwarp():
    from mujoco.mjx.third_party import mujoco_warp

    return mujoco_warp


def _step1(m, d):
    """MuJoCo Warp's ``step1`` (position and velocity stages, their sensors); the later stages' pure outputs
    (actuator forces, constraint forces and states) zeroed."""
    _mjwarp().step1(m, d)
    for a in (d.act_dot, d.actuator_force, d.efc.force, d.efc.Ma, d.efc.state):
        a.zero_()


def _step_rest(m, d):
    """MuJoCo Warp's ``step`` after the position stage: the constraint rows made again (their reference
    accelerations use the velocities, which the sensed data may have seen with noise), the velocity stage, then
    ``step2`` (actuation to the integrator)."""
    from mujoco.mjx.third_party.mujoco_warp._src import constraint, forward, sensor

    constraint.make_constraint(m, d)
    forward.fwd_velocity(m, d)
    sensor.sensor_vel(m, d)
    forward._energy_vel(m, d)
    _mjwarp().step2(m, d)


def _forward(m, d):
    """MuJoCo Warp's ``forward``; in a skipped pass also :func:`_step1` and :func:`_step_rest` (launches skipped)."""
    _mjwarp().forward(m, d)
    if getattr(_PASS, "on", False):
        _step1(m, d)
        _step_rest(m, d)


_warp_stages = functools.cache(lambda: _mjx_warp_call("forward", _step1))  # sense, as one call like mjx.forward
_warp_finish = functools.cache(lambda: _mjx_warp_call("step", _step_rest))  # finish, as one call like mjx.step
_warp_forward = functools.cache(lambda: _mjx_warp_call("forward", _forward))  # initial(sensed=True)


def put_model(mj_model, impl: str, device):
    """``mjx.put_model`` on ``device``; a Warp model does not print "solver/linesearch iterations limit reached"
    (the scenes cap the solver at ``opt.iterations`` on purpose; :func:`solver_capped` counts it); overflows do."""
    if impl != "warp":
        return mjx.put_model(mj_model, device=device)
    from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType

    mx = mjx.put_model(mj_model, impl="warp", device=device)
    opt = mx.opt
    quiet = int(opt._impl.warn_overflow) & ~int(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
    return mx.replace(opt=opt.replace(_impl=dataclasses.replace(opt._impl, warn_overflow=quiet)))


def contact_list(d):
    """Warp: MuJoCo Warp's contact list of the step that made ``d``, shared by the runs (unbatched under their vmap):
    ``(dist (L,) [m], geom (L, 2) ids, world (L,) run index, listed (L,) bool)``, ``listed`` where the entry is one
    of the ``nacon`` contacts and a constraint (the contacts MuJoCo Warp's contact sensors match)."""
    from mujoco.mjx.third_party.mujoco_warp._src.types import ContactType
    i = d._impl
    listed = (jnp.arange(i.contact__dist.shape[0]) < i.nacon[0]) & (i.contact__type & int(ContactType.CONSTRAINT) > 0)
    return i.contact__dist, i.contact__geom, i.contact__worldid, listed


def motion_cross(u, v):
    """MJX's spatial motion cross product u x v of two (6,) motion vectors [angular; linear]."""
    from mujoco.mjx._src.math import motion_cross as _motion_cross

    return _motion_cross(u, v)


def slot_dist(d, slots) -> jax.Array:
    """JAX backend: the distances [m] of MJX's contact slots ``slots`` (static ints; filled whether or not the pair
    touches)."""
    return d._impl.contact.dist[slots]


def slot_friction(d, slots) -> jax.Array:
    """JAX backend: the tangential friction coefficient of MJX's contact slots ``slots``."""
    return d._impl.contact.friction[slots, 0]


def slot_geoms(d) -> jax.Array:
    """JAX backend: (ncon, 2) geom ids of every MJX contact slot of ``d``."""
    return d._impl.contact.geom


def slot_forces(m, d, slots) -> jax.Array:
    """JAX backend: (n, 3) [N] simulator forces at contact slots ``slots`` in their contact frames, normal first."""
    from mujoco.mjx._src.support import contact_force

    return jnp.stack([contact_force(m, d, int(s))[:3] for s in slots])


def slot_geoms_static(mjx_model) -> np.ndarray | None:
    """(ncon, 2) geom ids of MJX's contact slots (JAX backend) from the model alone, as MJX's collision driver lays
    them out (one function per group of geom pairs, ``_geom_groups``; each group's rows repeated by its contact
    count; groups by ascending condim). None where that is not static (a broad phase) or does not add up
    (:func:`wbc_jax.physics.contacts.compiled_contact_geoms` reads a compiled step instead; a test compares them)."""
    from mujoco.mjx._src import collision_driver as cd

    if cd._numeric(mjx_model, "max_geom_pairs") > -1 or cd._numeric(mjx_model, "max_contact_points") > -1:
        return None
    by_condim: dict[int, list[np.ndarray]] = {}
    for key, ids in cd._geom_groups(mjx_model).items():
        func = cd._COLLISION_FUNC.get(key.types)
        if func is None:  # SDF and other groups whose count is not the function's
            return None
        geom = np.asarray(ids, dtype=np.int64)[:, :2]
        by_condim.setdefault(int(key.condim), []).append(np.repeat(geom, func.ncon, axis=0))
    if not by_condim:
        return None
    dims = np.concatenate([np.full(len(g), c) for c in sorted(by_condim) for g in by_condim[c]])
    if not np.array_equal(dims, cd.make_condim(mjx_model)):  # MJX's own count of the slots and their dims
        return None
    return np.concatenate([g for c in sorted(by_condim) for g in by_condim[c]])
