"""Planned footholds at every block edge of the course, per leg (issue 24): each touchdown near a block, where it
lands relative to the edge, and the planar leg's clearance over the far edge it stepped off (the hip as planned,
and HIP_DROP lower), for the course plan of each object side. Usage::

    PYTHONPATH=$PWD python tools/edge_audit.py [--sides 0.06,0.08,0.10]
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", default="0.06,0.08,0.10")
    a = ap.parse_args(argv)
    import jax
    import jax.numpy as jnp

    from wbc_jax.planner.gait import FOOT_NAMES, FOOT_PAIR, half_cycle
    from wbc_jax.planner.scene_geometry import HIP_DROP, scene_geometry, shin_clearance
    from wbc_jax.planner.spline import eval_path
    from wbc_jax.planner.transport import _com_from_object, course_plan, reference
    from wbc_jax.robot.model import Robot

    robot = Robot("transport")
    geo = scene_geometry(robot)
    for side in (float(x) for x in a.sides.split(",")):
        plan = course_plan(robot, robot.home_qpos(side), side=side, distance=3.4, speed=0.13)
        H = float(half_cycle(plan.gait))
        g = plan.gait
        ks = np.arange(int((float(g.t_stop) - float(g.t_start)) / H))
        t_td = float(g.t_start) + (ks + 1) * H - 1e-4  # just before each touchdown: p_sw = the landing target
        land = jax.jit(jax.vmap(lambda t: reference(plan, t, jnp.zeros((4, 3))).p_sw))(jnp.asarray(t_td))
        com = jax.jit(jax.vmap(lambda t: _com_from_object(plan, *eval_path(plan.obj_path, t))[0]))(jnp.asarray(t_td))
        land, com = np.asarray(land), np.asarray(com)
        u = np.asarray(plan.heading)
        print(f"d = {side}: touchdowns within 0.3 m of a block edge (s = distance along the walk past the edge)")
        rows = []
        for j, k in enumerate(ks):
            for i in range(4):
                if FOOT_PAIR[i] != k % 2:
                    continue
                p = land[j, i]
                hip = com[j] + np.asarray(plan.hip_offset[i])
                for b, box in enumerate(geo.terrain):
                    e_in, e_out = sorted([box[0, :2] @ u, box[1, :2] @ u])
                    s = p[:2] @ u
                    if not (e_in - 0.3 < s < e_out + 0.3):
                        continue
                    hs = hip[:2] @ u
                    edge = jnp.array([e_out, box[1, 2]])
                    cl = [float(shin_clearance(jnp.array([hs, hip[2] - dz]), jnp.array([s, p[2]]), edge,
                                               plan.leg)) for dz in (0.0, HIP_DROP)]
                    where = ("before" if s < e_in else "on" if s <= e_out else "beyond")
                    rows.append((t_td[j] + 1e-4, FOOT_NAMES[i], f"block{b + 1}", where, s - e_in, s - e_out,
                                 hs - e_out, hip[2], cl[0], cl[1]))
        print(" t [s]   leg block   lands  s-e_in  s-e_out  hip-e_out  hip_z  far-edge clear (plan, drop) [mm]")
        for r in rows:
            far = f"{r[8] * 1e3:7.1f} {r[9] * 1e3:7.1f}" if r[3] == "beyond" else ""
            print(f"{r[0]:6.3f}  {r[1]}  {r[2]}  {r[3]:6s} {r[4]:7.3f} {r[5]:8.3f} {r[6]:9.3f}  {r[7]:.3f}  {far}")


if __name__ == "__main__":
    main()
