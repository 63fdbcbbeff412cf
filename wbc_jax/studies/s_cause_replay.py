"""The object's acceleration of a :class:`wbc_jax.studies.s_cause.Recording`, decomposed, and replayed in MuJoCo C.

:func:`decompose` splits the integrand of S, ||vdot_b|| (the object CoM's acceleration over each physics step), into
the part normal to the tray and the tangential part, into the tray's own acceleration at the object and the object's
relative to it, and by time segment (standing before the walk, walking) and frequency (a moving average over
:data:`SMOOTH_S` and the rest). :func:`replay_object` re-simulates only the object in MuJoCo C (float64): every
physics step the robot's state and torques are set to the recording's, the object keeps its own state, so the
tray's motion is the closed loop's and only the contact law (the scene file's options, the run's mu) acts on the
object. Plain numpy and MuJoCo C (no JAX).
"""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

from wbc_jax.robot.model import resolve_ids
from wbc_jax.robot.scenario import single_run_mj_model

SMOOTH_S = 0.02  # [s] moving-average window separating the slow part of the acceleration from the jitter


class Parts(NamedTuple):
    """Mean magnitudes [m/s^2] of one run's object acceleration and its parts over a time span (1/S is
    ``total``)."""

    total: float
    normal: float  # |a . n|, n the tray's normal
    tangential: float  # ||a - (a . n) n||
    tray: float  # ||a_tray||: the tray's acceleration at the object's CoM (rigidly attached point)
    relative: float  # ||a - a_tray||
    slow: float  # ||moving average of a||
    jitter: float  # ||a - moving average of a||


def object_acceleration(qvel0, qvel, adr: int, dt: float) -> np.ndarray:
    """(S, 3) the object CoM's linear acceleration over each physics step [m/s^2]; qvel0 (nv,), qvel (S, nv)."""
    v = np.concatenate([qvel0[None, adr:adr + 3], qvel[:, adr:adr + 3]])
    return np.diff(v, axis=0) / dt


def tray_kinematics(mj_model, qpos, qvel, obj_body: int, tray_body: int):
    """Per step: (S, 3) velocity of the tray point at the object's CoM [m/s] and (S, 3) the tray's normal."""
    data = mujoco.MjData(mj_model)
    vel = np.zeros((len(qpos), 3))
    normal = np.zeros((len(qpos), 3))
    six = np.zeros(6)
    for k in range(len(qpos)):
        data.qpos[:], data.qvel[:] = qpos[k], qvel[k]
        mujoco.mj_fwdPosition(mj_model, data)
        mujoco.mj_fwdVelocity(mj_model, data)
        mujoco.mj_objectVelocity(mj_model, data, mujoco.mjtObj.mjOBJ_BODY, tray_body, six, 0)
        arm = data.xpos[obj_body] - data.xpos[tray_body]
        vel[k] = six[3:] + np.cross(six[:3], arm)
        normal[k] = data.xmat[tray_body].reshape(3, 3)[:, 2]
    return vel, normal


def _moving_average(a: np.ndarray, n: int) -> np.ndarray:
    kernel = np.ones(n) / n
    return np.stack([np.convolve(a[:, i], kernel, mode="same") for i in range(a.shape[1])], axis=1)


def parts(acc, tray_acc, normal, dt: float, span=slice(None)) -> Parts:
    """:class:`Parts` of accelerations ``acc`` (S, 3), ``tray_acc`` (S, 3) and tray normals (S, 3) over ``span``."""
    a_n = np.sum(acc * normal, axis=1)
    slow = _moving_average(acc, max(1, int(round(SMOOTH_S / dt))))
    norm = np.linalg.norm

    def mean(x):
        return float(np.mean(x[span]))

    return Parts(total=mean(norm(acc, axis=1)), normal=mean(np.abs(a_n)),
                 tangential=mean(norm(acc - a_n[:, None] * normal, axis=1)), tray=mean(norm(tray_acc, axis=1)),
                 relative=mean(norm(acc - tray_acc, axis=1)), slow=mean(norm(slow, axis=1)),
                 jitter=mean(norm(acc - slow, axis=1)))


def decompose(rec, run: int, walk_start_s: float = 1.0) -> dict[str, Parts]:
    """{"all", "standing", "walking"}: :class:`Parts` of run ``run`` of a recording (``walk_start_s``: the plan's
    start of motion [s])."""
    dz = rec.design
    model = single_run_mj_model(rec.scene, float(dz.m[run]), float(dz.mu[run]), float(dz.d[run]))
    ids = resolve_ids(model)
    acc = object_acceleration(rec.qvel0[run], rec.qvel[run], ids.obj_dof_adr, rec.dt)
    vel, normal = tray_kinematics(model, rec.qpos[run], rec.qvel[run], ids.obj_body, ids.tray_body)
    vel0, _ = tray_kinematics(model, rec.qpos0[run][None], rec.qvel0[run][None], ids.obj_body, ids.tray_body)
    tray_acc = np.diff(np.concatenate([vel0, vel]), axis=0) / rec.dt
    standing = rec.t <= walk_start_s
    return {"all": parts(acc, tray_acc, normal, rec.dt), "standing": parts(acc, tray_acc, normal, rec.dt, standing),
            "walking": parts(acc, tray_acc, normal, rec.dt, ~standing)}


def replay_object(rec, run: int, scene_file: str | None = None, mu: float | None = None) -> np.ndarray:
    """(S, nv) the state after each step of run ``run`` re-simulated in MuJoCo C with only the object free.

    Every physics step starts from the recording's robot state (qpos, qvel of every dof but the object's) and
    torques; the object's qpos and qvel are the replay's own (from the recording's initial state).

    Args:
        scene_file: the scene (its contact options) to replay in; None: the recording's.
        mu: the tray friction; None: the run's.
    """
    dz = rec.design
    model = single_run_mj_model(scene_file or rec.scene, float(dz.m[run]),
                                float(dz.mu[run] if mu is None else mu), float(dz.d[run]))
    ids = resolve_ids(model)
    qa, va = ids.obj_qpos_adr, ids.obj_dof_adr
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = rec.qpos0[run], rec.qvel0[run]
    out = np.zeros_like(rec.qvel[run])
    for k in range(len(rec.t)):
        data.ctrl[:] = rec.tau[run, k]
        mujoco.mj_step(model, data)
        out[k] = data.qvel
        robot_q, robot_v = rec.qpos[run, k].copy(), rec.qvel[run, k].copy()
        robot_q[qa:qa + 7], robot_v[va:va + 6] = data.qpos[qa:qa + 7], data.qvel[va:va + 6]
        data.qpos[:], data.qvel[:] = robot_q, robot_v
    return out


def smoothness(qvel0, qvel, adr: int, dt: float, span=slice(None)) -> float:
    """S = 1 / mean ||vdot_b|| [s^2/m] over ``span`` of the steps (the metric of ``wbc_jax.metrics.paper`` over a
    window of whole physics steps)."""
    return 1.0 / float(np.mean(np.linalg.norm(object_acceleration(qvel0, qvel, adr, dt), axis=1)[span]))
