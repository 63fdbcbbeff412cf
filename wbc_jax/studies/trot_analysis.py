"""The trot study's per-run metrics, acceptance checks and figures (numpy and matplotlib, after the rollout).

The logs are :class:`wbc_jax.rollout.controllers.trot_metrics.TrotLog` with axes (run, time); the figures follow
the centroidal paper's Figs. 6-12.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from wbc_jax.planner.capture_point import CPWalkPlan
from wbc_jax.robot.model import Robot

SPEED_TARGET, SPEED_TOL = 0.4, 0.05  # [m/s] acceptance of the nominal run
ATTITUDE_TARGET = 0.02  # [rad] oscillation amplitude target (paper: < 0.01 on its lighter robot)
SNAPSHOT_SIZE = (240, 320)  # [px] (height, width) of one frame of fig9_snapshots.png


def snapshot_times(t_start: float, t_end: float, step_time: float, n: int) -> np.ndarray:
    """(n,) times [s] of the Fig. 9 strip: one gait cycle (two steps, both diagonal pairs swinging) in n equal
    parts, starting at the first step boundary at or after the middle of the walk [t_start, t_end]."""
    k = np.ceil(((t_start + t_end) / 2 - t_start) / step_time - 1e-9)
    t0 = min(t_start + k * step_time, max(t_start, t_end - 2 * step_time))
    return t0 + 2 * step_time * np.arange(n) / max(n, 1)


def write_snapshots(path, robot: Robot, logs, i: int, plan: CPWalkPlan, t_start, t_end, step_time,
                    n: int) -> dict:
    """Fig. 9: ``n`` frames of run ``i`` side by side at :func:`snapshot_times`, a side view from the robot's right
    (camera tracking the trunk). Returns ``summary.json``'s ``snapshots``: file written (or None), the frame times
    [s] and the reason when nothing was written (no frames asked for, or no offscreen OpenGL backend)."""
    from wbc_jax.analysis.video import render_strip

    at = snapshot_times(t_start, t_end, step_time, n)
    if n == 0:
        return dict(written=None, times_s=[], reason="no snapshots: --snapshots 0")
    h = np.asarray(plan.heading)
    azimuth = float(np.degrees(np.arctan2(h[1], h[0]))) + 120.0  # looks across the walking direction, from ahead-right
    why = render_strip(path, robot.mj_model, np.asarray(logs.qpos[i]), np.asarray(logs.t[i]), at, size=SNAPSHOT_SIZE,
                       track_body=robot.ids.trunk_body, azimuth=azimuth)
    return dict(written=None if why else Path(path).name, times_s=[round(float(t), 4) for t in at], reason=why or "")


def forward(xy, heading):
    """Component of ``xy`` (..., 2) along the walking direction ``heading`` (2,)."""
    return xy @ np.asarray(heading)


def acceptance(runs: list[dict], mass_errors: tuple, i0: int) -> dict:
    """The acceptance checks: the nominal run ``i0`` walks at ``SPEED_TARGET`` +- ``SPEED_TOL`` with attitude
    amplitudes within ``ATTITUDE_TARGET``, no run exceeds a torque limit, every mass error walks. ``runs``: per
    run a dict of its results (``wbc_jax.rollout.controllers.trot_metrics.finalize`` columns)."""
    nom = runs[i0]
    amplitude = max(nom[k] for k in ("roll_amp_deg", "pitch_amp_deg", "yaw_amp_deg"))
    return dict(
        nominal_mass_error=mass_errors[i0],
        speed_ok=bool(abs(nom["speed_mps"] - SPEED_TARGET) <= SPEED_TOL and nom["walked"]),
        torques_within_limits=bool(all(r["max_tau_ratio"] <= 1.0 for r in runs) and nom["max_qp_tau_excess_Nm"] <= 0),
        attitude_amplitude_ok=bool(amplitude <= np.rad2deg(ATTITUDE_TARGET)),
        all_mass_errors_walk=bool(all(r["walked"] for r in runs)),
    )


class _FigureData(NamedTuple):
    """What every figure of the nominal run reads: its logs in the heading frame."""

    logs: object  # TrotLog, axes (run, time)
    i0: int  # the nominal run
    h: np.ndarray  # (2,) walking direction
    lat: np.ndarray  # (2,) its left normal
    t: np.ndarray  # (T,) [s] the nominal run's log times
    o: np.ndarray  # (2,) [m] the nominal run's first CoM position: the figures' origin
    w: float  # [1/s] the LIP's natural frequency
    xi: np.ndarray  # (T, 2) [m] the nominal run's actual capture point


def _save(plt, fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _fig6_capture_point(plt, f: _FigureData, plan: CPWalkPlan):
    """Fig. 6: footprints, desired and actual CP (forward vs time, and top view in the heading frame)."""
    logs, i0, h, lat, o, xi = f.logs, f.i0, f.h, f.lat, f.o, f.xi
    fig, ax = plt.subplots(1, 2, figsize=(13, 4.5))
    ax[0].step(f.t, forward(logs.P[i0] - o, h), "k", where="post", lw=1, label="virtual leg P (footprint)")
    ax[0].plot(f.t, forward(logs.xi_d[i0] - o, h), "C0", label="desired CP")
    ax[0].plot(f.t, forward(xi - o, h), "C1--", label="actual CP")
    ax[0].set_xlabel("t [s]"), ax[0].set_ylabel("forward [m]"), ax[0].legend()
    feet = np.asarray(plan.feet) - o
    for k, name in enumerate(("FL", "FR", "BL", "BR")):
        ax[1].plot(feet[:, k] @ h, feet[:, k] @ lat, "s", ms=3, label=f"{name} footholds")
    ax[1].plot((logs.xi_d[i0] - o) @ h, (logs.xi_d[i0] - o) @ lat, "C0", lw=1, label="desired CP")
    ax[1].plot((xi - o) @ h, (xi - o) @ lat, "C1--", lw=1, label="actual CP")
    ax[1].set_xlabel("forward [m]"), ax[1].set_ylabel("lateral [m]"), ax[1].legend(fontsize=7)
    return fig


def _fig7_speed(plt, f: _FigureData):
    """Fig. 7: CoM forward speed, desired (eq. 19) and actual."""
    fig, ax = plt.subplots(figsize=(9, 3.5))
    ax.plot(f.t, forward(f.logs.v_des[f.i0], f.h), "k", lw=0.8, label="desired (eq. 19)")
    ax.plot(f.t, forward(f.logs.com_vel[f.i0, :, :2], f.h), "C1", lw=0.8, label="actual")
    ax.axhline(SPEED_TARGET, color="gray", ls=":")
    ax.set_xlabel("t [s]"), ax.set_ylabel("CoM forward speed [m/s]"), ax.legend()
    return fig


def _fig8_attitude(plt, f: _FigureData):
    """Fig. 8: trunk roll, pitch and yaw."""
    fig, ax = plt.subplots(figsize=(9, 3.5))
    for j, k in enumerate(("roll", "pitch", "yaw")):
        ax.plot(f.t, f.logs.rpy[f.i0, :, j], lw=0.8, label=k)
    ax.set_xlabel("t [s]"), ax.set_ylabel("[rad]"), ax.legend()
    return fig


def _fig10_torques(plt, f: _FigureData, ids):
    """Fig. 10: FL joint torques against the limit: tau_m = tau_star + tau_grf."""
    logs, i0 = f.logs, f.i0
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    lim = float(np.asarray(ids.tau_max)[0])
    for j, k in enumerate(("roll", "pitch", "knee")):
        ax[j].plot(f.t, logs.tau[i0, :, j], "k", lw=0.8, label="tau_m (applied)")
        ax[j].plot(f.t, logs.tau_grf[i0, :, j], "C0", lw=0.6, label="-J^T f")
        ax[j].plot(f.t, logs.tau[i0, :, j] - logs.tau_grf[i0, :, j], "C1", lw=0.6, label="tau_* = tau_m + J^T f")
        for s in (-lim, lim):
            ax[j].axhline(s, color="r", ls=":")
        ax[j].set_ylabel(f"FL {k} [N m]")
    ax[0].legend(fontsize=7, ncol=3), ax[-1].set_xlabel("t [s]")
    return fig


def _fig11_phase(plt, f: _FigureData, t_start, t_end):
    """Fig. 11: phase portraits of the FL hip (pitch) and knee joints while walking."""
    walk = (f.t >= t_start) & (f.t <= t_end)
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for a, j, k in ((ax[0], 1, "hip (pitch)"), (ax[1], 2, "knee")):
        a.plot(f.logs.q_leg[f.i0, walk, j], f.logs.qd_leg[f.i0, walk, j], lw=0.5)
        a.set_xlabel(f"FL {k} [rad]"), a.set_ylabel("[rad/s]")
    return fig


def _fig12_mass_error(plt, f: _FigureData, mass_errors):
    """Fig. 12: CP forward error per controller mass error (every run)."""
    logs = f.logs
    fig, ax = plt.subplots(figsize=(9, 3.5))
    for i, e in enumerate(mass_errors):
        x_i = logs.com[i, :, :2] + logs.com_vel[i, :, :2] / f.w
        ax.plot(logs.t[i], forward(x_i - logs.xi_d[i], f.h), lw=0.7, label=f"mass error {100 * e:+.0f} %")
    ax.set_xlabel("t [s]"), ax.set_ylabel("CP x-error [m]"), ax.legend(fontsize=7)
    return fig


def plot_figures(folder, logs, plan: CPWalkPlan, mass_errors, i0: int, ids, t_start, t_end):
    """The paper's Figs. 6, 7, 8, 10, 11 (nominal run ``i0``) and 12 (all mass errors) as PNG files in ``folder``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = np.asarray(plan.heading)
    w = float(plan.w)
    f = _FigureData(logs=logs, i0=i0, h=h, lat=np.array([-h[1], h[0]]), t=logs.t[i0],
                    o=np.asarray(logs.com[i0, 0, :2]), w=w, xi=logs.com[i0, :, :2] + logs.com_vel[i0, :, :2] / w)
    folder = Path(folder)
    _save(plt, _fig6_capture_point(plt, f, plan), folder / "fig6_capture_point.png")
    _save(plt, _fig7_speed(plt, f), folder / "fig7_speed.png")
    _save(plt, _fig8_attitude(plt, f), folder / "fig8_attitude.png")
    _save(plt, _fig10_torques(plt, f, ids), folder / "fig10_torques.png")
    _save(plt, _fig11_phase(plt, f, t_start, t_end), folder / "fig11_phase.png")
    _save(plt, _fig12_mass_error(plt, f, mass_errors), folder / "fig12_mass_error.png")
