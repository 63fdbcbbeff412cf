"""S's dependence on the tray friction: closed-loop runs with a dense per-step log of the object and the robot.

The paper's smoothness S = T_win / int ||vdot_b|| dt (``wbc_jax.metrics.paper``) is a property of the object's
acceleration, which the tray's motion and the object/tray contact law make together. :func:`record` runs a small
batch of a campaign spec with *common random numbers* (every cell's repetition r draws the perturbations and the
velocity noise of the first cell's repetition r, so a difference between cells is the factor's, not the draws') and
keeps, for every control step, the full state after the step, the torques and the object's contact forces; the
campaign's accumulators are not touched. A scene variant (:func:`wbc_jax.robot.scenario.scene_variant`) changes
MuJoCo's contact law (cone, impratio, solver iterations, the object pairs' solref/solimp) without a new file in
``mjcf/``.

The offline decomposition and the contact-law replay in MuJoCo C: :mod:`wbc_jax.studies.s_cause_replay`; the
command line: :mod:`wbc_jax.studies.s_cause_cli`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.campaign.build import initial_configuration, run_gains, speed_ramps
from wbc_jax.campaign.design import Design, design
from wbc_jax.campaign.spec import Spec
from wbc_jax.control.transport import TransportConfig, control_qp_settings
from wbc_jax.control.variants import Variant
from wbc_jax.physics import contacts
from wbc_jax.robot.model import Robot, scene_path

# perturbation draws of a Design, per run: the fields common random numbers copy from the first cell
_DRAWN = ("seed", "obj_dx", "obj_dy", "obj_yaw", "v0", "push_force", "push_frac")


class Recording(NamedTuple):
    """A batch's dense log, one row per control step (the state *after* the step), runs on axis 0.

    Attributes:
        t: (S,) time after each step [s]; dt: the physics timestep [s] (one physics step per control step).
        qpos0, qvel0: (B, nq), (B, nv) the state before the first step.
        qpos, qvel: (B, S, nq), (B, S, nv) the state after each step.
        tau: (B, S, nu) the step's joint torques [N m]; f_obj: (B, S, 4, 3) the object's contact forces after
            the step (contact frame, normal first) [N].
        design: the batch's design table (the run's factors, seeds and draws).
        scene: the scene file simulated.
    """

    t: np.ndarray
    dt: float
    qpos0: np.ndarray
    qvel0: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    tau: np.ndarray
    f_obj: np.ndarray
    design: Design
    scene: str


def common_draws(dz: Design, reps: int) -> Design:
    """``dz`` with every run's seed and perturbation draws replaced by those of the first cell's run of the same
    repetition (runs ordered cells x ``reps``), so all cells share their random numbers repetition by repetition."""
    first = np.arange(dz.n) % reps
    return dataclasses.replace(dz, **{k: np.asarray(getattr(dz, k))[first] for k in _DRAWN})


def _step_fn(sim, in_axes, n_steps: int):
    """jit: ``n_steps`` control steps of every run -> (state, (qpos, qvel, tau, f_obj) per step)."""
    from wbc_jax.rollout import control_step

    step = jax.vmap(functools.partial(control_step, sim), in_axes=(in_axes, 0, 0, 0, 0, 0, 0))
    forces = jax.vmap(lambda m, d: contacts.object_contacts(sim, m, d)[0], in_axes=(in_axes, 0))

    def chunk(m, run_state, plan, obj_model, gains, push, mu_ground):
        def body(state, _):
            new, log = step(m, state, plan, obj_model, gains, push, mu_ground)
            return new, (new.d.qpos, new.d.qvel, log.tau, forces(m, new.d), new.d.time[0])

        return jax.lax.scan(body, run_state, None, length=n_steps)

    return jax.jit(chunk)


def record(spec: Spec, seconds: float, scene_file: str | None = None, chunk_steps: int = 500,
           crn: bool = True, overrides: dict | None = None, controller_mu=None, sensor_noise: bool | None = None
           ) -> Recording:
    """Run the batch of ``spec`` for ``seconds`` [s] with a dense log (module docstring).

    Args:
        spec: a validated campaign spec (its design, perturbations and plan; ``campaign.scene`` unless
            ``scene_file``); control at the physics rate (``control_substeps`` 1) on the JAX backend.
        seconds: simulated time [s]; chunk_steps: control steps per compiled call.
        crn: common random numbers across cells (:func:`common_draws`).
        overrides: Design field -> (B,) values replacing the design's (e.g. ``mu``, ``variant`` (B, 3),
            ``qvel_noise_std``), after the common draws.
        controller_mu: (B,) the tray friction the controller assumes (its ObjectModel) instead of the physics'.
        sensor_noise: compile the noisy controller view even where every run's noise is 0 (so a batch shares
            its program with a noisy one); None: where some run has noise.
    """
    from wbc_jax.rollout import make_push, make_sim, with_variant
    from wbc_jax.rollout.batch import prepare_batch

    c = spec.campaign
    dz = design(spec)
    if crn:
        dz = common_draws(dz, spec.reps)
    dz = dataclasses.replace(dz, **{k: np.asarray(v) for k, v in (overrides or {}).items()})
    scene = scene_file or str(scene_path(c["scene"]))
    robot = Robot(scene, backend="jax")
    cfg = TransportConfig(dt=float(robot.mj_model.opt.timestep), qp=control_qp_settings(c["qp_iters"]))
    noisy = bool(np.any(dz.qvel_noise_std > 0)) if sensor_noise is None else sensor_noise
    sim = make_sim(robot, cfg, sensor_noise=noisy)
    qpos0, qvel0 = initial_configuration(robot, dz)
    b = prepare_batch(sim, dz.m, dz.mu, dz.d, gains=run_gains(None, dz), qpos0=qpos0, qvel0=qvel0,
                      plan_kwargs=dict(distance=c["distance"], speed=c["speed"], terrain=c["terrain"],
                                       com_plan=c["com_plan"]),
                      speed=dz.speed if "speed" in spec.factors else None, ramp=speed_ramps(spec, dz))
    if controller_mu is not None:
        b = b._replace(om=b.om._replace(mu=jax.numpy.asarray(controller_mu, b.om.mu.dtype)))
    t_plan = np.asarray(b.plan.obj_path.t_knots)[:, -1]
    push = make_push(dz.push_force, dz.push_frac * t_plan, dz.push_duration, dz.qvel_noise_std, dz.seed)
    state = with_variant(b.state, Variant(*dz.variant.T), sim.controller)
    steps = min(chunk_steps, int(round(seconds / sim.dt_control)))
    fn = _step_fn(sim, b.in_axes, steps)
    parts = []
    for _ in range(int(np.ceil(seconds / sim.dt_control / steps - 1e-9))):  # whole chunks: one compiled program
        state, out = fn(b.model, state, b.plan, b.om, b.gains, push, b.mu_ground)
        parts.append(jax.device_get(out))
    qpos, qvel, tau, f_obj = (np.concatenate([p[k] for p in parts], axis=0).swapaxes(0, 1) for k in range(4))
    t = np.concatenate([p[4] for p in parts])
    return Recording(t, sim.dt_physics, np.asarray(qpos0), np.asarray(qvel0), qpos, qvel, tau, f_obj, dz, scene)


def save(rec: Recording, path: str) -> None:
    """Write a recording as one ``.npz`` (the design's per-run columns as ``design_<name>``)."""
    cols = {f"design_{k}": np.asarray(v) for k, v in rec.design.asdict().items() if not isinstance(v, dict)}
    np.savez_compressed(path, t=rec.t, dt=rec.dt, qpos0=rec.qpos0, qvel0=rec.qvel0, qpos=rec.qpos, qvel=rec.qvel,
                        tau=rec.tau, f_obj=rec.f_obj, scene=rec.scene, **cols)


def load(path: str) -> Recording:
    """A recording written by :func:`save` (the design without its ``gain_scale`` and ``levels``)."""
    z = np.load(path)
    cols = {k[len("design_"):]: z[k] for k in z.files if k.startswith("design_")}
    dz = Design(**cols, gain_scale={}, plugin_params={}, levels={})
    return Recording(z["t"], float(z["dt"]), z["qpos0"], z["qvel0"], z["qpos"], z["qvel"], z["tau"], z["f_obj"], dz,
                     str(z["scene"]))
