"""``wbc-jax demo``: one run at default factors.

Foundation stage: loads the scene, holds the robot in its home pose with a joint-space PD plus
gravity compensation computed from MJX's bias forces, steps MJX, and reports what happened
(trunk height, object slip on the tray). The transport controller replaces the PD hold.
"""

from __future__ import annotations

import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.io_utils import atomic_dir
from wbc_jax.model import Robot, mjx

KP, KD = 300.0, 10.0  # joint PD of the standing hold [N m / rad], [N m s / rad]


def run_demo(out: str, scene: str = "flat", seconds: float | None = None) -> dict:
    robot = Robot(scene)
    ids, mx = robot.ids, robot.mjx_model
    seconds = 1.0 if seconds is None else float(seconds)
    n = int(round(seconds / robot.mj_model.opt.timestep))
    q0 = jnp.asarray(robot.home_qpos())
    qa0 = q0[ids.act_qpos]
    tau_max = jnp.asarray(ids.tau_max)

    def step(d, _):
        d = mjx.forward(mx, d)
        qa, va = d.qpos[ids.act_qpos], d.qvel[ids.act_dof]
        tau = d.qfrc_bias[ids.act_dof] + KP * (qa0 - qa) - KD * va
        d = mjx.step(mx, d.replace(ctrl=jnp.clip(tau, -tau_max, tau_max)))
        rel = d.site_xmat[ids.tray_site].T @ (d.xpos[ids.obj_body] - d.site_xpos[ids.tray_site])
        return d, (d.xpos[ids.trunk_body, 2], rel)

    d0 = mjx.make_data(mx).replace(qpos=q0)
    t0 = time.perf_counter()
    _, (z, rel) = jax.jit(lambda d: jax.lax.scan(step, d, None, length=n))(d0)
    z, rel = np.asarray(z), np.asarray(rel)
    wall = time.perf_counter() - t0
    summary = {
        "scene": str(robot.path),
        "controller": "joint PD hold (foundation demo)",
        "simulated_s": seconds,
        "steps": n,
        "trunk_height_min_m": float(z.min()),
        "trunk_height_final_m": float(z[-1]),
        "max_slip_mm": float(np.linalg.norm(rel[:, :2] - rel[0, :2], axis=1).max() * 1e3),
        "wall_time_s_incl_compile": wall,
    }
    with atomic_dir(out) as tmp:
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return summary
