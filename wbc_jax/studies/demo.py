"""``wbc-jax demo``: the transport WBC carrying the object through the course (or on flat ground), one
run or all 27 cells in one batch.

Writes ``summary.json`` (one entry per run, plus the batch's clock time and simulation rate), ``manifest.json``
(arguments, versions, git commit, device, clock times: :func:`wbc_jax.campaign.manifest.study_manifest`), ``runs.csv``,
``plots.png`` (object and CoM reference vs actual, object slip on the tray), ``trajectory.npz`` (logged
configurations of every run: t (T,), qpos (B, T, nq), factors) and ``video.gif`` (the first run, when
offscreen rendering is available) into DIR, atomically.
"""

from __future__ import annotations

import itertools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.analysis.video import render_gif
from wbc_jax.campaign.manifest import study_manifest
from wbc_jax.control.transport import TransportConfig, control_qp_settings, default_gains
from wbc_jax.io_utils import atomic_dir, write_json_atomic
from wbc_jax.metrics import paper as metrics
from wbc_jax.physics.backend import resolve_backend
from wbc_jax.planner.scene_geometry import scene_geometry
from wbc_jax.planner.transport import plan_duration
from wbc_jax.robot.model import Robot
from wbc_jax.robot.scenario import single_run_mj_model
from wbc_jax.rollout import make_push, make_sim, resolve_sensing, simulate
from wbc_jax.rollout.batch import broadcast, prepare_batch

LEVELS = dict(m=(0.2, 0.3, 0.4), mu=(0.4, 0.7, 1.0), d=(0.06, 0.08, 0.10))
DEFAULT = dict(m=0.3, mu=0.7, d=0.08)


def demo_backend(backend: str | None) -> str:
    """``--backend`` resolved for this machine ("auto" for None); a one-line InputError for a bad value."""
    from wbc_jax.errors import InputError

    try:
        return resolve_backend("auto" if backend is None else backend)
    except ValueError as e:
        raise InputError(f"--backend: {e}") from None


def run_demo(out: str, scene: str = "transport", seconds: float | None = None, all_cells: bool = False,
             push: bool = False, observer: bool = True, iters: int = 20, distance: float = 3.4,
             speed: float = 0.13, push_at: float = 0.35, video: bool = True, backend: str | None = None) -> dict:
    """Run the demo and write DIR. ``push_at``: push start as a fraction of the planned duration (0.35 is
    mid-course, before the wall). ``backend``: MJX physics implementation ("auto" for None; sensing as the
    campaign's default, ``wbc_jax.rollout.config.resolve_sensing``)."""
    arguments = dict(scene=scene, seconds=seconds, all_cells=all_cells, push=push, observer=observer, iters=iters,
                     distance=distance, speed=speed, push_at=push_at, video=video, backend=backend)
    t_start = time.perf_counter()
    backend = demo_backend(backend)
    robot = Robot(scene, backend=backend)
    sim = make_sim(robot, TransportConfig(qp=control_qp_settings(iters)), log_every=20,
                   sensing=resolve_sensing("auto", backend))
    cells = list(itertools.product(*LEVELS.values())) if all_cells else [tuple(DEFAULT.values())]
    m, mu, d = (np.array(c) for c in zip(*cells))
    gains = default_gains()
    if not observer:
        gains = gains._replace(k_obs=jnp.asarray(0.0))
    t0 = time.perf_counter()
    b = prepare_batch(sim, m, mu, d, gains=gains, plan_kwargs=dict(distance=distance, speed=speed))
    T = plan_duration(b.plan)
    seconds = T + 0.5 if seconds is None else float(seconds)
    p = make_push([40.0, 0.0, 0.0], push_at * T, 0.2) if push else None
    if p is not None:
        b = b._replace(push=broadcast(p, len(cells)))
    print(f"{len(cells)} run(s), {seconds:.1f} s simulated, scene {robot.path.name}", flush=True)
    tw = time.perf_counter()
    marks = []  # (simulated s, wall s) after each chunk; the first chunk includes compilation

    def progress(s):
        marks.append((s, time.perf_counter() - tw))
        print(f"  simulated {s:6.2f} / {seconds:.2f} s   clock time {marks[-1][1]:7.1f} s", flush=True)

    st, logs = simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground, seconds,
                        chunk_seconds=2.0, progress=progress)
    wall = time.perf_counter() - t0
    acc = jax.device_get(st.acc)
    n_steps = int(acc.n_steps[0])
    p_obj = np.asarray(st.d.xpos[:, robot.ids.obj_body])
    p_goal = np.asarray(logs.p_obj_ref[:, -1])
    err = np.linalg.norm(p_obj - p_goal, axis=1)
    res = metrics.finalize(acc, sim.dt_control, mu, course=scene_geometry(robot).is_course, final_err=err,
                           substeps=sim.n_substeps)
    runs = _run_rows(cells, res, acc, err, logs, n_steps)
    summary = dict(scene=str(robot.path), controller="transport WBC", physics_backend=backend,
                   sensing=sim.sensing, push=push, observer=observer,
                   qp_iters=iters, simulated_s=seconds, runs=runs, wall_time_s=wall,
                   env_steps_per_s=_steps_per_s(marks, len(cells), sim.dt_control),
                   compile_and_first_chunk_s=marks[0][1],
                   device=jax.devices()[0].device_kind)
    clock = dict(total=time.perf_counter() - t_start, batch_and_simulation=wall,
                 compile_and_first_chunk=marks[0][1])
    with atomic_dir(out, command="wbc-jax demo") as tmp:
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
        write_json_atomic(tmp / "manifest.json", study_manifest(
            "wbc-jax demo", arguments=arguments, clock_s=clock, physics_backend=backend, sensing=sim.sensing))
        import pandas as pd

        pd.DataFrame(runs).to_csv(tmp / "runs.csv", index=False)
        _plot(tmp / "plots.png", logs)
        np.savez_compressed(tmp / "trajectory.npz", t=np.asarray(logs.t[0]), qpos=np.asarray(logs.qpos, np.float32),
                            m=m, mu=mu, d=d)
        if video:
            mj = single_run_mj_model(robot.path, *cells[0])
            why = render_gif(tmp / "video.gif", mj, np.asarray(logs.qpos[0]), np.asarray(logs.t[0]),
                             track_body=robot.ids.trunk_body)
            if why:
                print(why)
    _print_table(runs)
    print(f"clock time {time.perf_counter() - t_start:.1f} s since the demo started ({wall:.1f} s building the batch "
          f"and simulating), {summary['env_steps_per_s']:,.0f} env-steps per second "
          f"{'after the first chunk' if len(marks) > 1 else 'with the compile (one chunk)'}; written to {out}")
    return summary


def _run_rows(cells, res: dict, acc, err, logs, n_steps: int) -> list[dict]:
    """``summary.json``'s ``runs``: one dict per (m, mu, d) cell from the finalized metrics ``res``, the
    accumulators ``acc``, the final object error ``err`` (B,) [m] and the logs."""
    runs = []
    for i, (mi, mui, di) in enumerate(cells):
        runs.append(dict(
            m=float(mi), mu=float(mui), d=float(di), completed=bool(res["success"][i]), fell=bool(res["fell"][i]),
            dropped=bool(res["dropped"][i]), hit_wall=bool(res["hit_wall"][i]),
            max_slip_mm=float(res["max_slip_mm"][i]),
            max_off_tray_ms=float(acc.max_off_s[i] * 1e3), final_object_error_m=float(err[i]),
            T_mean_tracking_m=float(res["T"][i]),
            min_trunk_z_m=float(acc.min_trunk_z[i]), max_tau_ratio=float(acc.max_tau_ratio[i]),
            max_qp_tau_excess_Nm=float(acc.max_tau_excess[i]),
            qp_prim_res_median=float(np.median(logs.prim_res[i])), qp_flag_fraction=float(acc.n_flag[i] / n_steps)))
    return runs


# the console table of the runs: (header, summary.json key, format); headers name the quantity and its unit
TABLE = [("m [kg]", "m", "{:.1f}"), ("mu", "mu", "{:.1f}"), ("d [m]", "d", "{:.2f}"),
         ("delivered", "completed", "{}"), ("fell", "fell", "{}"), ("dropped", "dropped", "{}"),
         ("wall contact", "hit_wall", "{}"), ("max slip [mm]", "max_slip_mm", "{:.2f}"),
         ("off tray [ms]", "max_off_tray_ms", "{:.0f}"), ("final err [cm]", "final_object_error_m", "{:.2f}"),
         ("T [mm]", "T_mean_tracking_m", "{:.2f}"), ("min trunk z [m]", "min_trunk_z_m", "{:.3f}"),
         ("tau over limit [Nm]", "max_qp_tau_excess_Nm", "{:.1f}"), ("QP residual", "qp_prim_res_median", "{:.1e}"),
         ("QP flagged [%]", "qp_flag_fraction", "{:.1f}")]
TABLE_SCALE = {"final_object_error_m": 100.0, "T_mean_tracking_m": 1e3, "qp_flag_fraction": 100.0}
TABLE_LEGEND = ("off tray: the longest spell of the object off the tray; final err: object to goal at the end; T: "
                "mean object tracking error; tau over limit: the largest unclipped joint torque over its limit; QP "
                "residual: median primal residual; QP flagged: control steps whose QP was flagged")


def _print_table(runs):
    """One line per run under :data:`TABLE`'s headers (each column as wide as its header), then the legend."""
    widths = [max(len(h), 6) for h, _, _ in TABLE]
    print("  ".join(f"{h:>{w}}" for (h, _, _), w in zip(TABLE, widths)))
    for r in runs:
        print("  ".join(f"{f.format(r[k] * TABLE_SCALE.get(k, 1.0) if isinstance(r[k], float) else r[k]):>{w}}"
                        for (_, k, f), w in zip(TABLE, widths)))
    print(TABLE_LEGEND)


def _steps_per_s(marks, n_runs, dt):
    """Env-steps/s after the first (compiling) chunk; over the whole run if there is only one chunk."""
    (s0, w0), (s1, w1) = (marks[0], marks[-1]) if len(marks) > 1 else ((0.0, 0.0), marks[-1])
    return n_runs * (s1 - s0) / dt / max(w1 - w0, 1e-9)


def _plot(path, logs):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = logs.t[0]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    ax[0].plot(t, logs.p_obj_ref[0, :, 1], "k--", label="object ref y")
    ax[0].plot(t, logs.p_obj[0, :, 1], label="object y")
    ax[0].plot(t, logs.com_ref[0, :, 1], "k:", label="CoM ref y")
    ax[0].plot(t, logs.com[0, :, 1], label="CoM y")
    ax[0].set_xlabel("t [s]"), ax[0].set_ylabel("[m]"), ax[0].legend()
    ax[1].plot(t, logs.p_obj[0, :, 2] - logs.p_obj_ref[0, :, 2], label="object z error")
    ax[1].plot(t, logs.trunk_z[0] - logs.trunk_z[0, 0], label="trunk z - z0")
    ax[1].set_xlabel("t [s]"), ax[1].set_ylabel("[m]"), ax[1].legend()
    ax[2].plot(t, logs.slip.T * 1e3)
    ax[2].set_xlabel("t [s]"), ax[2].set_ylabel("object slip on the tray [mm]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
