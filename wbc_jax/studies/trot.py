"""``wbc-jax trot``: the centroidal paper's trot study (Sec. 3.1) on the legged manipulator, flat ground.

One batched rollout of the campaign engine (the shared rollout with the centroidal controller plug-in,
:class:`wbc_jax.rollout.controllers.centroidal.CentroidalController`): the runs share the robot and the
capture-point walking pattern and differ in the controller's model mass error (Fig. 12); the run with error 0 is
the nominal one of Figs. 6-11. Its per-run metrics are those of a centroidal campaign
(:mod:`wbc_jax.rollout.controllers.trot_metrics`), computed by the same code from the same batch
(:func:`trot_batch` builds what ``wbc_jax.campaign.build.build`` builds for the same settings).

Writes into DIR (atomically): ``summary.json`` (per run: the campaign's metric columns, the largest |torque| per
joint; the acceptance checks of the nominal run and a manifest) and the figures ``fig6_capture_point.png``,
``fig7_speed.png``, ``fig8_attitude.png``, ``fig9_snapshots.png`` (the nominal run trotting: N frames side by side
over one gait cycle in the middle of the walk, :func:`wbc_jax.studies.trot_analysis.snapshot_times`; rendered
offscreen, so without an OpenGL backend it is left out and ``summary.json`` ``snapshots`` says why),
``fig10_torques.png``, ``fig11_phase.png``, ``fig12_mass_error.png`` (:mod:`wbc_jax.studies.trot_analysis`).
"""

from __future__ import annotations

import json
import platform
import time
from typing import NamedTuple

import jax
import mujoco
import numpy as np

from wbc_jax.campaign.build import chunk_fn
from wbc_jax.campaign.manifest import study_manifest
from wbc_jax.campaign.spec import CAMPAIGN
from wbc_jax.control.centroidal import CentroidalConfig, CentroidalGains, centroidal_qp_settings, default_gains
from wbc_jax.errors import WbcJaxError
from wbc_jax.io_utils import atomic_dir, write_json_atomic
from wbc_jax.robot.model import Robot
from wbc_jax.rollout import final_results, make_sim, simulate, with_metric_window
from wbc_jax.rollout.batch import Batch, prepare_batch
from wbc_jax.studies.trot_analysis import acceptance, plot_figures, write_snapshots

MASS_ERRORS = (-0.2, -0.1, 0.0, 0.1, 0.2)  # controller model mass error levels (Fig. 12)
OBJECT = (CAMPAIGN["m"][1], CAMPAIGN["mu"][1], CAMPAIGN["d"][1])  # the cube on the tray: a campaign's default
#                                                                  mass [kg], tray friction and side [m]


class TrotSettings(NamedTuple):
    """One study's settings (the keys of a centroidal campaign with the same runs in brackets)."""

    stride: float = 0.10  # [m] virtual-leg advance per step (speed x step_time)
    step_time: float = 0.25  # [s] half-cycle (step_time)
    t_four: float = 0.08  # [s] its four-foot part (four_foot)
    n_steps: int = 40  # half-cycles (distance / (speed x step_time))
    mass_errors: tuple = MASS_ERRORS  # the runs' model mass errors (the mass_error factor)
    carry_object: bool = True  # the cube on the tray, its mass known to the controller (a campaign's case)
    iters: int = 40  # ADMM iterations per control step (qp_iters)
    log_every: int = 5  # control steps per log row (a campaign's: wbc_jax.campaign.build.LOG_EVERY)
    t_start: float = 0.5  # [s] standing before the walk
    t_settle: float = 0.5  # [s] simulated after it (extra_seconds)
    backend: str = "jax"  # physics backend


def trot_batch(settings: TrotSettings, gains: CentroidalGains | None = None):
    """The Sim and the Batch of a study (one run per mass error): the arithmetic of
    ``wbc_jax.campaign.build.build`` for a centroidal spec with the same settings, zero perturbations and the
    default object. Returns (Sim, Batch, the first run's walk end [s])."""
    s = settings
    robot = Robot("flat", backend=s.backend)
    cfg = CentroidalConfig(qp=centroidal_qp_settings(s.iters), dt=float(robot.mj_model.opt.timestep))
    sim = make_sim(robot, cfg, log_every=s.log_every, controller="centroidal")
    B = len(s.mass_errors)
    m, mu, side = (np.full(B, v) for v in OBJECT)
    qpos0 = np.stack([robot.home_qpos(float(x)) for x in side])
    if not s.carry_object:  # the cube far from the robot, falling freely; the controller assumes no payload
        a = robot.ids.obj_qpos_adr
        qpos0[:, a:a + 3] = (2.0, 2.0, 1.0)
    base = gains or default_gains()
    leaves = {k: np.broadcast_to(np.asarray(v), (B,) + np.shape(v)) for k, v in base._asdict().items()}
    dtype = leaves["mass_scale"].dtype
    leaves["mass_scale"] = (1.0 + np.asarray(s.mass_errors, float)).astype(dtype)
    leaves["load_mass"] = (m if s.carry_object else np.zeros(B)).astype(dtype)
    gb = type(base)(**{k: jax.numpy.asarray(v) for k, v in leaves.items()})
    kw = dict(speed=s.stride / s.step_time, step_time=s.step_time, four_foot=s.t_four, n_steps=s.n_steps,
              t_start=s.t_start)
    b = prepare_batch(sim, m, mu, side, gains=gb, plan_kwargs=kw, qpos0=qpos0, qvel0=np.zeros((B, robot.mj_model.nv)))
    t_end = sim.controller.plan_end(b.plan)
    b = b._replace(state=with_metric_window(b.state, t_end + s.t_settle))
    return sim, b, float(np.max(t_end))


class StudyRun(NamedTuple):
    """A finished study: its Sim and Batch, the final state, the logs (run, time), the per-run results
    (:func:`wbc_jax.rollout.final_results`), the chunk marks (simulated s, wall s) and the walk's end [s]."""

    sim: object
    batch: Batch
    state: object
    logs: object
    results: dict
    marks: list
    t_end: float


def run_study(settings: TrotSettings, gains: CentroidalGains | None = None, chunk_seconds: float = 2.0,
              verbose: bool = True) -> StudyRun:
    """Build, simulate (the walk and ``t_settle``, in chunks of ``chunk_seconds`` [s]) and finalize a study."""
    sim, b, t_end = trot_batch(settings, gains)
    total = t_end + settings.t_settle
    tw = time.perf_counter()
    marks = []

    def progress(done):
        marks.append((done, time.perf_counter() - tw))
        if verbose:
            print(f"  simulated {done:6.2f} / {total:.2f} s   wall {marks[-1][1]:7.1f} s", flush=True)

    def program(sim, n_logs, in_axes):  # the campaign's chunk function: a trot campaign of these shapes shares it
        return chunk_fn(sim, in_axes, n_logs, state_axes=b.state_axes)

    state, logs = simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground, total,
                           chunk_seconds=chunk_seconds, progress=progress, program=program)
    res = final_results(sim, state, sim.controller.final_input(logs), np.asarray(b.om.mu))
    return StudyRun(sim, b, state, logs, res, marks, t_end)


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


def _manifest(t_wall: float, marks: list, n_runs: int, dt: float) -> dict:
    """``summary.json``'s ``manifest``: wall times, the rate after the first (compiling) chunk, versions."""
    steps_s = (n_runs * (marks[-1][0] - marks[0][0]) / dt / max(marks[-1][1] - marks[0][1], 1e-9)
               if len(marks) > 1 else float("nan"))
    return dict(wall_time_s=time.perf_counter() - t_wall, compile_and_first_chunk_s=marks[0][1],
                env_steps_per_s_after_compile=steps_s, device=jax.devices()[0].device_kind,
                jax=jax.__version__, mujoco=mujoco.__version__, python=platform.python_version())


def _runs(study: StudyRun, mass_errors: tuple) -> list[dict]:
    """``summary.json``'s ``runs``: per run its mass error, the results row and the largest |torque| per joint."""
    joints = [f"{leg}_{j}" for leg in ("FL", "FR", "BL", "BR") for j in ("roll", "pitch", "knee")] + [
        f"arm_j{k}" for k in range(1, 7)]
    max_tau = np.asarray(jax.device_get(study.state.metrics.max_abs_tau))
    out = []
    for i, e in enumerate(mass_errors):
        row = {k: (v[i].item() if isinstance(v[i], np.generic) else v[i]) for k, v in study.results.items()}
        out.append(dict(mass_error=e, **row, max_abs_tau_Nm={j: float(v) for j, v in zip(joints, max_tau[i])}))
    return out


def _print_runs(runs: list[dict], summary: dict, checks: dict, out: str) -> None:
    for r in runs:
        print(f"  mass error {r['mass_error']:+.2f}: walked {r['walked']}, speed {r['speed_mps']:.3f} m/s, CP x-error "
              f"rms {r['cp_err_x_rms_mm']:.1f} mm, attitude amp roll {r['roll_amp_deg']:.3f}, pitch "
              f"{r['pitch_amp_deg']:.3f}, yaw {r['yaw_amp_deg']:.3f} deg, max |tau|/limit {r['max_tau_ratio']:.2f}")
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
    settings = TrotSettings(stride=stride, step_time=step_time, t_four=t_four,
                            n_steps=max(2, int(round(seconds / step_time))), mass_errors=mass_errors,
                            carry_object=carry_object, iters=iters, log_every=log_every, t_start=t_start,
                            t_settle=t_settle)
    print(f"trot: {len(mass_errors)} run(s) (mass errors {list(mass_errors)}), {settings.n_steps} steps of "
          f"{step_time} s, stride {stride} m, object {'on the tray' if carry_object else 'removed'}", flush=True)
    study = run_study(settings, gains)
    ids, t_end = study.sim.robot.ids, study.t_end
    plan = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], study.batch.plan.walk)  # the same for every run
    runs = _runs(study, mass_errors)
    i0 = int(np.argmin(np.abs(np.asarray(mass_errors))))
    checks = acceptance(runs, mass_errors, i0)
    nominal = jax.tree_util.tree_map(lambda x: np.asarray(x)[i0], study.batch.gains)
    summary = dict(
        study="centroidal WBC trot (centroidal paper Sec. 3.1)", scene=str(study.sim.robot.path),
        controller="centroidal", stride_m=stride, step_time_s=step_time, four_foot_s=t_four,
        n_steps=settings.n_steps, walk_s=t_end - t_start, simulated_s=study.marks[-1][0], carry_object=carry_object,
        qp_iters=iters, control_dt_s=study.sim.dt_control,
        gains={k: np.asarray(v).tolist() for k, v in nominal._asdict().items() if k != "mass_scale"},
        acceptance=checks, runs=runs, manifest=_manifest(t_wall, study.marks, len(mass_errors), study.sim.dt_control),
    )
    with atomic_dir(out, command="wbc-jax trot") as tmp:
        summary["snapshots"] = write_snapshots(tmp / "fig9_snapshots.png", study.sim.robot, study.logs, i0, plan,
                                               t_start, t_end, step_time, snapshots)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        write_json_atomic(tmp / "manifest.json", study_manifest("wbc-jax trot", arguments=dict(
            seconds=seconds, stride=stride, step_time=step_time, t_four=t_four, mass_errors=list(mass_errors),
            carry_object=carry_object, iters=iters, log_every=log_every, default_gains=gains is None,
            t_start=t_start, t_settle=t_settle, snapshots=snapshots), clock_s=dict(
            total=summary["manifest"]["wall_time_s"], compile_and_first_chunk=study.marks[0][1]),
            physics_backend=study.sim.robot.backend, sensing=study.sim.sensing))
        plot_figures(tmp, study.logs, plan, mass_errors, i0, ids, t_start, t_end)
    _print_runs(runs, summary, checks, out)
    return summary
