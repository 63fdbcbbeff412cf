"""``wbc-jax demo``: the transport WBC carrying the object on flat ground, one run or all 27 cells.

Writes ``summary.json`` (one entry per run, plus the batch's wall time and env-steps/s), ``runs.csv``
and ``plots.png`` (object and CoM reference vs actual, object slip on the tray) into DIR, atomically.
"""

from __future__ import annotations

import itertools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.batch import broadcast, prepare_batch
from wbc_jax.control.transport import TransportConfig, default_gains
from wbc_jax.io_utils import atomic_dir
from wbc_jax.model import Robot
from wbc_jax.planner.transport import plan_duration
from wbc_jax.qp import QPSettings
from wbc_jax.rollout import Push, make_sim, simulate

LEVELS = dict(m=(0.2, 0.3, 0.4), mu=(0.4, 0.7, 1.0), d=(0.06, 0.08, 0.10))
DEFAULT = dict(m=0.3, mu=0.7, d=0.08)
FALL_Z = 0.3  # [m] trunk height below which a run counts as fallen
DROP_LIFT = 0.01  # [m] object lifted this far off the tray counts as dropped
DONE_TOL = 0.05  # [m] final object error for a completed transport


def run_demo(out: str, scene: str = "flat", seconds: float | None = None, all_cells: bool = False,
             push: bool = False, observer: bool = True, iters: int = 50, distance: float = 3.4,
             speed: float = 0.13) -> dict:
    robot = Robot(scene)
    sim = make_sim(robot, TransportConfig(qp=QPSettings(iters=iters)), log_every=20)
    cells = list(itertools.product(*LEVELS.values())) if all_cells else [tuple(DEFAULT.values())]
    m, mu, d = (np.array(c) for c in zip(*cells))
    gains = default_gains()
    if not observer:
        gains = gains._replace(k_obs=jnp.asarray(0.0))
    t0 = time.perf_counter()
    b = prepare_batch(sim, m, mu, d, gains=gains, plan_kwargs=dict(distance=distance, speed=speed))
    T = plan_duration(b.plan)
    seconds = T + 0.5 if seconds is None else float(seconds)
    p = Push(jnp.array([40.0, 0.0, 0.0]), jnp.asarray(0.5 * T), jnp.asarray(0.2)) if push else None
    if p is not None:
        b = b._replace(push=broadcast(p, len(cells)))
    print(f"{len(cells)} run(s), {seconds:.1f} s simulated, scene {robot.path.name}", flush=True)
    tw = time.perf_counter()
    marks = []  # (simulated s, wall s) after each chunk; the first chunk includes compilation

    def progress(s):
        marks.append((s, time.perf_counter() - tw))
        print(f"  simulated {s:6.2f} / {seconds:.2f} s   wall {marks[-1][1]:7.1f} s", flush=True)

    st, logs = simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground, seconds,
                        chunk_seconds=2.0, progress=progress)
    wall = time.perf_counter() - t0
    acc = jax.device_get(st.acc)
    n_steps = int(acc.n_steps[0])
    p_obj = np.asarray(st.d.xpos[:, robot.ids.obj_body])
    p_goal = np.asarray(logs.p_obj_ref[:, -1])
    runs = []
    for i, (mi, mui, di) in enumerate(cells):
        fell = bool(acc.min_trunk_z[i] < FALL_Z or acc.nonfoot_floor[i] or acc.nonfinite[i])
        dropped = bool(acc.max_lift[i] > DROP_LIFT)
        err = float(np.linalg.norm(p_obj[i] - p_goal[i]))
        runs.append(dict(
            m=float(mi), mu=float(mui), d=float(di), completed=bool(not fell and not dropped and err < DONE_TOL),
            fell=fell, dropped=dropped, hit_wall=bool(acc.wall_contact[i]), max_slip_mm=float(acc.max_slip[i] * 1e3),
            final_object_error_m=err, T_mean_tracking_m=float(acc.sum_track[i] / (n_steps * sim.dt_control)),
            min_trunk_z_m=float(acc.min_trunk_z[i]), max_tau_ratio=float(acc.max_tau_ratio[i]),
            max_qp_tau_excess_Nm=float(acc.max_tau_excess[i]),
            qp_prim_res_median=float(np.median(logs.prim_res[i])), qp_flag_fraction=float(acc.n_flag[i] / n_steps)))
    summary = dict(scene=str(robot.path), controller="transport WBC", push=push, observer=observer,
                   qp_iters=iters, simulated_s=seconds, runs=runs, wall_time_s=wall,
                   env_steps_per_s=_steps_per_s(marks, len(cells), sim.dt_control),
                   compile_and_first_chunk_s=marks[0][1],
                   device=jax.devices()[0].device_kind)
    with atomic_dir(out) as tmp:
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
        import pandas as pd

        pd.DataFrame(runs).to_csv(tmp / "runs.csv", index=False)
        _plot(tmp / "plots.png", logs)
    for r in runs:
        print(json.dumps(r))
    print(f"wall {wall:.1f} s, {summary['env_steps_per_s']:.0f} env-steps/s; written to {out}")
    return summary


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
