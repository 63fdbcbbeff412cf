"""What a replay writes per run: ``trajectory.npz`` and ``plots.png`` (the video: :mod:`~.replay_video`).

``plots.png`` shows, against simulated time, the object's slip on the tray, the object's and the CoM's tracking
errors, the trunk height with the fall height, every joint's torque as a fraction of its limit, the clearance of
the robot's non-foot geoms to the floor, blocks and walls, and the QP's primal residual, with the trunk push, the
failure instant (the run is frozen after it) and the video's window marked. The clearance is recomputed from the
logged configurations with MuJoCo C (``mj_geomDistance``, the pairs of
:func:`wbc_jax.physics.clearance.clearance_pairs`) at the log's rate, so a contact between two logged samples can be
missed. Contact forces against the friction cone are not plotted: the rollout's log does not hold them (nor the
velocities they would be recomputed from).
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

CLEARANCE_MAX = 1.0  # [m] distances beyond this are reported as this (mj_geomDistance's distmax)


def sample_times(n_samples: int, log_every: int, dt_control: float) -> np.ndarray:
    """(n_samples,) [s] the simulated time of each logged sample: the start of the last control step of each log
    interval (the log's own clock ``t`` stops at a failed run's failure, as the run is frozen there)."""
    return ((np.arange(n_samples) + 1) * log_every - 1) * dt_control


def clearance(mj_model: mujoco.MjModel, pairs, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) the smallest signed distance [m] over ``pairs`` (``ClearancePairs``: robot and scene geom ids) at each
    configuration of ``qpos`` (T, nq), capped at :data:`CLEARANCE_MAX`, and (T,) the index of the closest pair
    (-1 without pairs)."""
    robot, env = np.asarray(pairs.robot, int), np.asarray(pairs.env, int)
    out = np.full(len(qpos), CLEARANCE_MAX)
    which = np.full(len(qpos), -1)
    if robot.size == 0:
        return out, which
    data = mujoco.MjData(mj_model)
    for i, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(mj_model, data)
        dist = [mujoco.mj_geomDistance(mj_model, data, int(a), int(b), CLEARANCE_MAX, None) for a, b in zip(robot, env)]
        which[i] = int(np.argmin(dist))
        out[i] = dist[which[i]]
    return out, which


def write_trajectory(path: Path, logs, time: np.ndarray, extra: dict) -> None:
    """``trajectory.npz``: ``time`` (T,) [s] and every field of the rollout's Log (``t``: the run's own clock, frozen
    after a failure; positions [m], slip [m], torques [N m], qpos (T, nq)), then ``extra`` (arrays or scalars)."""
    arrays = {"time": time, **{name: np.asarray(getattr(logs, name)) for name in logs._fields}, **extra}
    np.savez_compressed(path, **arrays)


def _mark(ax, events: dict, end: float, label: bool) -> None:
    """On one axis (in its legend where ``label``): the push (shaded orange), the failure instant (a red line) and
    the frozen time after it (shaded red) up to ``end`` [s], the video's window (shaded grey)."""
    t0, duration, force = events["push"]
    if duration > 0 and force > 0:
        ax.axvspan(t0, t0 + duration, color="tab:orange", alpha=0.15, lw=0, label=f"push {force:.0f} N" if label
                   else None)
    failure_s = events["failure_s"]
    if np.isfinite(failure_s):
        ax.axvline(failure_s, color="tab:red", lw=1.2, ls="--", label=f"failure {failure_s:.3f} s" if label else None)
        ax.axvspan(failure_s, end, color="tab:red", alpha=0.05, lw=0, label="frozen" if label else None)
    if events["window"] is not None:
        ax.axvspan(*events["window"], color="0.9", zorder=0, label="video window" if label else None)


def _panels(axes, time, logs, limits: dict, clear_mm) -> None:
    """The six panels' curves (module docstring); ``limits``: tau_max (nu,) [N m] and fall_z [m]."""
    ax = axes.ravel()
    ax[0].plot(time, np.asarray(logs.slip) * 1e3)
    ax[0].set_ylabel("object slip on the tray [mm]")
    ax[1].plot(time, np.linalg.norm(np.asarray(logs.p_obj) - np.asarray(logs.p_obj_ref), axis=1) * 1e3,
               label="object")
    ax[1].plot(time, np.linalg.norm(np.asarray(logs.com) - np.asarray(logs.com_ref), axis=1) * 1e3, label="CoM")
    ax[1].set_ylabel("tracking error ‖p_ref − p‖ [mm]")
    ax[2].plot(time, np.asarray(logs.trunk_z), label="trunk")
    ax[2].axhline(limits["fall_z"], color="k", lw=0.8, ls=":", label="fall height")
    ax[2].set_ylabel("trunk height [m]")
    ratio = np.abs(np.asarray(logs.tau)) / np.asarray(limits["tau_max"])
    ax[3].plot(time, ratio, lw=0.6, color="0.6")
    ax[3].plot(time, ratio.max(axis=1), color="tab:blue", label="largest joint")
    ax[3].axhline(1.0, color="k", lw=0.8, ls=":", label="limit")
    ax[3].set_ylabel("|torque| / limit")
    ax[4].plot(time, clear_mm, label="smallest over the pairs")
    ax[4].axhline(0.0, color="k", lw=0.8, ls=":")
    ax[4].set_ylabel("clearance, non-foot geoms [mm]")
    ax[5].semilogy(time, np.maximum(np.asarray(logs.prim_res), 1e-12))
    ax[5].set_ylabel("QP primal residual")


def write_plots(path: Path, time: np.ndarray, logs, limits: dict, clear_mm: np.ndarray, events: dict,
                title: str) -> None:
    """``plots.png``: the six panels of the module docstring, each with the push, the failure and the video window.

    Args:
        time: (T,) [s] sample times; logs: the run's Log (host, axis 0 the samples).
        limits: ``tau_max`` (nu,) [N m] and ``fall_z`` [m]; clear_mm: (T,) clearance [mm].
        events: ``push`` (start [s], duration [s], force [N]), ``failure_s`` (the failure instant [s], NaN: none)
            and ``window`` ((start, end) [s] of the video, or None: not shaded, e.g. the whole run).
        title: the figure's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5), sharex=True)
    _panels(axes, time, logs, limits, clear_mm)
    for i, ax in enumerate(axes.ravel()):
        _mark(ax, events, float(time[-1]), label=i == 0)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="best")
    for ax in axes[1]:
        ax.set_xlabel("simulated time [s]")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

