"""``wbc-jax trot``: the centroidal paper's trot study (Sec. 3.1) on the legged manipulator, flat ground.

One batched rollout (``lax.scan`` over control steps, ``vmap`` over runs): the runs share the robot and
the capture-point walking pattern and differ in the controller's model mass error (Fig. 12); the run
with error 0 is the nominal one of Figs. 6-11. Each control step: :func:`wbc_jax.physics.backend.sense` ->
walking pattern (:func:`wbc_jax.planner.capture_point.cp_walk_reference`) -> centroidal WBC
(:func:`wbc_jax.control.centroidal.centroidal_control`) -> :func:`wbc_jax.physics.backend.advance`.

Writes into DIR (atomically): ``summary.json`` (per run: mean forward speed, roll/pitch/yaw oscillation
amplitudes, max |torque| per joint against its limit, CP tracking error; plus the acceptance checks of
the nominal run and a manifest) and the figures ``fig6_capture_point.png``, ``fig7_speed.png``,
``fig8_attitude.png``, ``fig9_snapshots.png`` (the nominal run trotting: N frames side by side over one gait cycle
in the middle of the walk, :func:`wbc_jax.studies.trot_analysis.snapshot_times`; rendered offscreen, so without an
OpenGL backend it is left out and ``summary.json`` ``snapshots`` says why), ``fig10_torques.png``,
``fig11_phase.png``, ``fig12_mass_error.png`` (:mod:`wbc_jax.studies.trot_analysis`).
"""

from __future__ import annotations

import functools
import json
import platform
import time
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.campaign.manifest import study_manifest
from wbc_jax.control.centroidal import (
    CentroidalConfig,
    CentroidalGains,
    CentroidalRef,
    CentroidalState,
    centroidal_control,
    centroidal_qp_settings,
    default_gains,
    init_state,
)
from wbc_jax.errors import WbcJaxError
from wbc_jax.io_utils import atomic_dir, write_json_atomic
from wbc_jax.physics import backend as physics
from wbc_jax.physics import contacts
from wbc_jax.physics.contacts import contact_slots
from wbc_jax.physics.observe import dyn_terms, observe
from wbc_jax.planner.capture_point import CPWalkPlan, cp_walk_plan, cp_walk_reference
from wbc_jax.planner.gait import GaitParams
from wbc_jax.robot.model import Robot, mjx
from wbc_jax.runtime.static import ByValue
from wbc_jax.studies.trot_analysis import acceptance, analyse_run, plot_figures, write_snapshots

MASS_ERRORS = (-0.2, -0.1, 0.0, 0.1, 0.2)  # controller model mass error levels (Fig. 12)


@dataclass(frozen=True, eq=False)
class TrotSim(ByValue):
    """Static rollout structure: robot, controller config, log decimation, non-foot floor contact slots (hashed by
    value: the key of the compiled chunk functions)."""

    robot: Robot
    cfg: CentroidalConfig
    log_every: int
    nonfoot_slots: np.ndarray


class Accum(NamedTuple):
    """Online reductions over every control step (per run)."""

    min_trunk_z: jax.Array  # [m]
    nonfoot_floor: jax.Array  # bool
    nonfinite: jax.Array  # bool
    max_abs_tau: jax.Array  # (18,) [N m] applied torques
    max_tau_excess: jax.Array  # [N m] unclipped command over the limit (< 0: within)
    n_flag: jax.Array  # QPs not solved to tolerance
    n_steps: jax.Array


class TrotRun(NamedTuple):
    """Carried state of one run."""

    d: mjx.Data
    cs: CentroidalState
    p_lift: jax.Array  # (4, 3) foot positions at the last liftoff [m]
    acc: Accum


class TrotLog(NamedTuple):
    """Logged every ``log_every`` control steps (per run), world frame unless noted."""

    t: jax.Array  # [s]
    com: jax.Array  # (3,) [m]
    com_vel: jax.Array  # (3,) [m/s]
    xi_d: jax.Array  # (2,) desired CP [m]
    P: jax.Array  # (2,) current virtual leg [m]
    v_des: jax.Array  # (2,) desired CoM velocity (eq. 19) [m/s]
    rpy: jax.Array  # (3,) trunk roll, pitch, yaw relative to its initial orientation [rad]
    trunk_z: jax.Array  # [m]
    tau: jax.Array  # (18,) applied torques [N m]
    tau_grf: jax.Array  # (18,) -J^T f part of the QP torques [N m]
    q_leg: jax.Array  # (12,) leg joint angles [rad]
    qd_leg: jax.Array  # (12,) leg joint velocities [rad/s]
    swing: jax.Array  # (4,) bool
    prim_res: jax.Array
    qpos: jax.Array  # (nq,) the full configuration (robot and cube), for the snapshots


def trunk_rpy(R0, R):
    """(3,) ZYX roll, pitch, yaw of R relative to R0 (trunk frame: x forward) [rad]."""
    E = R0.T @ R
    return jnp.array([jnp.arctan2(E[2, 1], E[2, 2]), -jnp.arcsin(jnp.clip(E[2, 0], -1.0, 1.0)),
                      jnp.arctan2(E[1, 0], E[0, 0])])


def make_plan(robot: Robot, qpos0, stride: float, step_time: float, t_four: float, n_steps: int,
              t_start: float = 0.5, swing_height: float = 0.06) -> tuple[CPWalkPlan, np.ndarray]:
    """Walking pattern along the trunk's forward axis from ``qpos0``; returns (plan, trunk R0 (3, 3))."""
    m, ids = robot.mj_model, robot.ids
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    R0 = d.xmat[ids.trunk_body].reshape(3, 3).copy()
    heading = float(np.arctan2(R0[1, 0], R0[0, 0]))
    gait = GaitParams(t_stance=t_four, t_swing=step_time - t_four, t_start=t_start)
    plan = cp_walk_plan(d.site_xpos[ids.foot_site].copy(), d.subtree_com[ids.trunk_body].copy(), heading, stride,
                        n_steps, gait, swing_height)
    return plan, R0


def init_run(sim: TrotSim, m, qpos0) -> TrotRun:
    ids = sim.robot.ids
    d = physics.sense(m, mjx.make_data(sim.robot.mjx_model).replace(qpos=qpos0))
    dyn = dyn_terms(m, d, ids)
    acc = Accum(min_trunk_z=dyn.p_base[2], nonfoot_floor=jnp.bool_(False), nonfinite=jnp.bool_(False),
                max_abs_tau=jnp.zeros(18), max_tau_excess=jnp.full((), -jnp.inf, jnp.result_type(float)),
                n_flag=jnp.zeros((), jnp.int32), n_steps=jnp.zeros((), jnp.int32))
    return TrotRun(d=d, cs=init_state(sim.cfg, d.qpos, ids), p_lift=dyn.p_foot, acc=acc)


def control_step(sim: TrotSim, m, rs: TrotRun, plan: CPWalkPlan, R0, gains: CentroidalGains):
    """One control period of one run: (new TrotRun, TrotLog entry)."""
    ids = sim.robot.ids
    d = physics.sense(m, rs.d)
    obs = observe(m, d, ids)
    dyn = obs.robot
    wr = cp_walk_reference(plan, d.time, dyn.com[:2], rs.p_lift)
    ref = CentroidalRef(v_xy=wr.v_xy, z=plan.z0, R_base=R0, heading=plan.heading, swing=wr.swing, p_sw=wr.p_sw,
                        v_sw=wr.v_sw, a_sw=wr.a_sw)
    tau, cs, dg = centroidal_control(obs, ref, gains, rs.cs, ids, sim.cfg)
    d_next = physics.advance(m, d, tau)
    finite = jnp.all(jnp.isfinite(d_next.qpos)) & jnp.all(jnp.isfinite(tau))
    a = rs.acc
    acc = Accum(
        min_trunk_z=jnp.minimum(a.min_trunk_z, dyn.p_base[2]),
        nonfoot_floor=a.nonfoot_floor | jnp.any(contacts.nonfoot_dist(sim, d) < 0.0),
        nonfinite=a.nonfinite | ~finite,
        max_abs_tau=jnp.maximum(a.max_abs_tau, jnp.abs(tau)),
        max_tau_excess=jnp.maximum(a.max_tau_excess, dg.tau_excess),
        n_flag=a.n_flag + (dg.flag != 0).astype(jnp.int32),
        n_steps=a.n_steps + 1,
    )
    d_next = physics.freeze(finite, d_next, rs.d)  # a non-finite run keeps its last finite state
    legs_v, legs_q = jnp.asarray(ids.act_dof[:12]), jnp.asarray(ids.act_qpos[:12])
    log = TrotLog(t=d.time, com=dyn.com, com_vel=dyn.com_vel, xi_d=wr.cp.xi, P=wr.cp.P, v_des=wr.v_xy,
                  rpy=trunk_rpy(R0, dyn.R_base), trunk_z=dyn.p_base[2], tau=tau, tau_grf=dg.tau_grf,
                  q_leg=d.qpos[legs_q], qd_leg=d.qvel[legs_v], swing=wr.swing, prim_res=dg.prim_res, qpos=d.qpos)
    p_lift = jnp.where(wr.swing[:, None], rs.p_lift, dyn.p_foot)
    return TrotRun(d=d_next, cs=cs, p_lift=p_lift, acc=acc), log


_CHUNKS: dict = {}


def simulate(sim: TrotSim, rs: TrotRun, plan: CPWalkPlan, R0, gains: CentroidalGains, seconds: float,
             chunk_seconds: float = 2.0, progress=None):
    """Run ``seconds`` (rounded up to whole chunks) for a batch of runs (leading axis of rs and gains).

    The model, plan and R0 are shared. Returns (final TrotRun, TrotLog with axes (run, time)).
    """
    dt = sim.cfg.dt
    n_chunks = max(1, int(np.ceil(seconds / chunk_seconds - 1e-9)))
    n_logs = max(1, int(np.ceil(seconds / n_chunks / (dt * sim.log_every) - 1e-9)))
    key = (sim, n_logs)
    if key not in _CHUNKS:  # the runs batched inside each step, traced once (wbc_jax.rollout.loop.make_chunk_fn)
        step = jax.vmap(functools.partial(control_step, sim), in_axes=(None, 0, None, None, 0))

        def chunk(m, rs, plan, R0, gains):
            def inner(rs, _):
                return step(m, rs, plan, R0, gains)

            def outer(rs, _):
                rs, logs = jax.lax.scan(inner, rs, None, length=sim.log_every)
                return rs, jax.tree_util.tree_map(lambda x: x[-1], logs)

            rs, logs = jax.lax.scan(outer, rs, None, length=n_logs)
            return rs, jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), logs)  # (log, run) -> (run, log)

        _CHUNKS[key] = jax.jit(chunk)
    m = sim.robot.mjx_model
    out = []
    for c in range(n_chunks):
        rs, logs = _CHUNKS[key](m, rs, plan, R0, gains)
        out.append(jax.device_get(logs))
        if progress is not None:
            progress((c + 1) * n_logs * sim.log_every * dt)
    return rs, jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *out)


def validate(seconds, stride, step_time, t_four, mass_errors, iters, snapshots: int = 6):
    """Raise WbcJaxError on values the study cannot run with."""
    if not 0 < seconds <= 600:  # finite and bounded: a day of simulated walking would not fit in memory
        raise WbcJaxError(f"--seconds = {seconds}: expected 0 < value <= 600 [s]")
    if not 0 < stride <= 0.2:
        raise WbcJaxError(f"--stride = {stride}: expected 0 < stride <= 0.2 m")
    if not 0.02 <= step_time <= 2.0:
        raise WbcJaxError(f"--step-time = {step_time}: expected 0.02 <= value <= 2.0 [s]")
    if not 0 < t_four < step_time:
        raise WbcJaxError(f"--step-time = {step_time}, --four-foot = {t_four}: expected 0 < four-foot < step time")
    if not mass_errors or any(not -0.5 < e < 1.0 for e in mass_errors):
        raise WbcJaxError(f"--mass-errors = {list(mass_errors)}: expected one or more values in (-0.5, 1.0)")
    if not 1 <= iters <= 1000:
        raise WbcJaxError(f"--iters = {iters}: expected 1 <= value <= 1000")
    if not 0 <= snapshots <= 24:
        raise WbcJaxError(f"--snapshots = {snapshots}: expected 0 <= value <= 24")


class _Study(NamedTuple):
    """The batch of one study: simulation structure, walking pattern and per-run controller gains."""

    robot: Robot
    sim: TrotSim
    plan: CPWalkPlan
    R0: np.ndarray  # (3, 3) trunk orientation at the start
    gains: CentroidalGains  # the nominal gains (mass_scale 1)
    batch_gains: CentroidalGains  # leading run axis, mass_scale = 1 + mass error
    runs0: TrotRun  # initial state, leading run axis
    n_steps: int
    t_end: float  # [s] end of the walk
    total: float  # [s] simulated time


def _build(stride, step_time, t_four, mass_errors, carry_object, iters, log_every, gains, t_start, seconds,
           t_settle) -> _Study:
    """Robot, controller config, plan and the batch's initial state (one run per mass error)."""
    robot = Robot("flat")
    ids = robot.ids
    cfg = CentroidalConfig(qp=centroidal_qp_settings(iters), dt=float(robot.mj_model.opt.timestep))
    sim = TrotSim(robot=robot, cfg=cfg, log_every=log_every, nonfoot_slots=contact_slots(robot)[0])
    qpos0 = robot.home_qpos()
    obj_mass = float(robot.mj_model.body_mass[ids.obj_body])
    if not carry_object:
        qpos0[ids.obj_qpos_adr : ids.obj_qpos_adr + 3] = (2.0, 2.0, 1.0)
    n_steps = max(2, int(round(seconds / step_time)))
    plan, R0 = make_plan(robot, qpos0, stride, step_time, t_four, n_steps, t_start=t_start)
    B = len(mass_errors)
    g0 = gains or default_gains(load_mass=obj_mass if carry_object else 0.0)
    gb = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (B,) + jnp.shape(x)), g0)
    gb = gb._replace(mass_scale=1.0 + jnp.asarray(mass_errors))
    runs0 = jax.jit(jax.vmap(lambda q: init_run(sim, robot.mjx_model, q)))(
        jnp.broadcast_to(jnp.asarray(qpos0), (B,) + qpos0.shape))
    t_end = t_start + n_steps * step_time
    return _Study(robot=robot, sim=sim, plan=plan, R0=R0, gains=g0, batch_gains=gb, runs0=runs0, n_steps=n_steps,
                  t_end=t_end, total=t_end + t_settle)


def _simulate_with_progress(study: _Study):
    """:func:`simulate` printing the simulated and wall time after each chunk. Returns (final TrotRun, TrotLog,
    marks: (simulated s, wall s) after each chunk, the first one including compilation)."""
    tw = time.perf_counter()
    marks = []

    def progress(s):
        marks.append((s, time.perf_counter() - tw))
        print(f"  simulated {s:6.2f} / {study.total:.2f} s   wall {marks[-1][1]:7.1f} s", flush=True)

    final, logs = simulate(study.sim, study.runs0, study.plan, jnp.asarray(study.R0), study.batch_gains, study.total,
                           progress=progress)
    return final, logs, marks


def _manifest(t_wall: float, marks: list, n_runs: int, dt: float) -> dict:
    """``summary.json``'s ``manifest``: wall times, the rate after the first (compiling) chunk, versions."""
    steps_s = (n_runs * (marks[-1][0] - marks[0][0]) / dt / max(marks[-1][1] - marks[0][1], 1e-9)
               if len(marks) > 1 else float("nan"))
    return dict(wall_time_s=time.perf_counter() - t_wall, compile_and_first_chunk_s=marks[0][1],
                env_steps_per_s_after_compile=steps_s, device=jax.devices()[0].device_kind,
                jax=jax.__version__, mujoco=mujoco.__version__, python=platform.python_version())


def _print_runs(runs: list[dict], summary: dict, checks: dict, out: str) -> None:
    for r in runs:
        print(f"  mass error {r['mass_error']:+.2f}: walked {r['walked']}, speed {r['mean_forward_speed_mps']:.3f} "
              f"m/s, CP x-error rms {1e3 * r['cp_x_error_rms_m']:.1f} mm, attitude amp "
              + ", ".join(f"{k} {v:.4f}" for k, v in r["attitude_amplitude_rad"].items())
              + f" rad, max |tau|/limit {r['max_tau_ratio']:.2f}")
    if summary["snapshots"]["written"] is None:
        print(f"  {summary['snapshots']['reason']}")
    print(f"acceptance: {checks}; written to {out}")


def run_trot(out: str, seconds: float = 10.0, stride: float = 0.10, step_time: float = 0.25, t_four: float = 0.08,
             mass_errors=MASS_ERRORS, carry_object: bool = True, iters: int = 40, log_every: int = 5,
             gains: CentroidalGains | None = None, t_start: float = 0.5, t_settle: float = 0.5,
             snapshots: int = 6) -> dict:
    """Run the study (one batch over ``mass_errors``) and write DIR.

    Args:
        seconds: walking time [s] (``round(seconds / step_time)`` steps); the rollout adds ``t_start``
            standing before and ``t_settle`` after.
        stride: virtual-leg advance per step [m]; step_time: half-cycle [s]; t_four: its four-foot part [s].
        mass_errors: controller model mass errors (fractions, e.g. -0.2 = model 20 % too light).
        carry_object: keep the cube on the tray (the controller knows its mass); otherwise the cube is
            moved off the robot (it falls freely, touching nothing) and the controller assumes no payload.
        iters: ADMM iterations per control step; log_every: control steps per log sample.
        snapshots: frames of ``fig9_snapshots.png`` (0: none).
    """
    mass_errors = tuple(float(e) for e in mass_errors)
    validate(seconds, stride, step_time, t_four, mass_errors, iters, snapshots)
    t_wall = time.perf_counter()
    study = _build(stride, step_time, t_four, mass_errors, carry_object, iters, log_every, gains, t_start, seconds,
                   t_settle)
    ids, t_end = study.robot.ids, study.t_end
    print(f"trot: {len(mass_errors)} run(s) (mass errors {list(mass_errors)}), {study.n_steps} steps of {step_time} s, "
          f"stride {stride} m, {study.total:.2f} s simulated, object {'on the tray' if carry_object else 'removed'}",
          flush=True)
    final, logs, marks = _simulate_with_progress(study)
    acc = jax.device_get(final.acc)
    runs = [analyse_run(logs, acc, i, e, study.plan, t_start, t_end, stride, ids) for i, e in enumerate(mass_errors)]
    i0 = int(np.argmin(np.abs(np.asarray(mass_errors))))
    checks = acceptance(runs, mass_errors, i0)
    summary = dict(
        study="centroidal WBC trot (centroidal paper Sec. 3.1)", scene=str(study.robot.path), controller="centroidal",
        stride_m=stride, step_time_s=step_time, four_foot_s=t_four, n_steps=study.n_steps, walk_s=t_end - t_start,
        simulated_s=study.total, carry_object=carry_object, qp_iters=iters, control_dt_s=study.sim.cfg.dt,
        gains={k: np.asarray(v).tolist() for k, v in study.gains._asdict().items() if k != "mass_scale"},
        acceptance=checks, runs=runs, manifest=_manifest(t_wall, marks, len(mass_errors), study.sim.cfg.dt),
    )
    with atomic_dir(out, command="wbc-jax trot") as tmp:
        summary["snapshots"] = write_snapshots(tmp / "fig9_snapshots.png", study.robot, logs, i0, study.plan, t_start,
                                               t_end, step_time, snapshots)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
        write_json_atomic(tmp / "manifest.json", study_manifest("wbc-jax trot", arguments=dict(
            seconds=seconds, stride=stride, step_time=step_time, t_four=t_four, mass_errors=list(mass_errors),
            carry_object=carry_object, iters=iters, log_every=log_every, default_gains=gains is None,
            t_start=t_start, t_settle=t_settle, snapshots=snapshots), clock_s=dict(
            total=summary["manifest"]["wall_time_s"], compile_and_first_chunk=marks[0][1]),
            physics_backend=study.robot.backend))
        plot_figures(tmp, logs, study.plan, mass_errors, i0, ids, t_start, t_end)
    _print_runs(runs, summary, checks, out)
    return summary
