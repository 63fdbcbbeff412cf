"""How far the transport planner's CoM reference is from what per-footstep ZMP replanning would give (issue 23).

The transport paper replans the CoM at the start of every footstep with a cubic that ends over the support of the
coming swing phase, so that the ZMP stays inside the support polygon (``wbc_jax.planner.zmp.replan_com``). This
project's planner does not: the CoM follows the object path plus a constant offset. This tool evaluates the planned
reference of the obstacle course (no simulation) every 5 ms and reports, per two-foot (diagonal) support phase:

* the ZMP of the planned CoM (cart-table model, :func:`wbc_jax.planner.zmp.zmp_xy`) against the stance pair's
  support segment (their planned footholds): its largest distance from the segment;
* the planned CoM at the end of the phase against that segment: how far ``replan_com``'s goal clamp would move it.

Usage::

    PYTHONPATH=$PWD python tools/zmp_audit.py [--d 0.08] [--com-plan zmp]

``--com-plan zmp`` audits the replanned reference (``course_plan(com_plan="zmp")``) instead, and adds how far it
moves the CoM from the object-following one and the ZMP's margin in the four-foot phases.
"""

from __future__ import annotations

import argparse

import numpy as np


def _seg_dist(p, a, b):
    """Distance of points p (N, 2) from the segment a-b ((2,), (2,))."""
    ab = b - a
    s = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[:, None] * ab), axis=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--d", type=float, default=0.08, help="object side [m]")
    ap.add_argument("--dt", type=float, default=0.005, help="sampling step [s]")
    ap.add_argument("--verbose", action="store_true", help="every phase")
    ap.add_argument("--com-plan", default="spline", help="the planner's com_plan: spline (default) or zmp")
    a = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp

    from wbc_jax.planner.gait import gait_phase
    from wbc_jax.planner.transport import _landings, course_plan, reference
    from wbc_jax.planner.zmp import support_margin, zmp_xy
    from wbc_jax.robot.model import Robot

    robot = Robot("transport")
    plan = course_plan(robot, robot.home_qpos(a.d), side=a.d, com_plan=a.com_plan)
    base = plan._replace(com_xy=None)  # the object-following CoM
    t = np.arange(0.0, float(plan.gait.t_stop), a.dt)

    def one(tt):
        zero = jnp.zeros((4, 3))
        ref = reference(plan, tt, zero)
        g = gait_phase(plan.gait, tt)
        return ref.p_com, ref.a_com, _landings(plan, tt, g), g.swing, g.step_index, reference(base, tt, zero).p_com

    p_com, a_com, land, swing, step, p_base = (np.asarray(x) for x in jax.jit(jax.vmap(one))(jnp.asarray(t)))
    zmp = np.asarray(jax.vmap(zmp_xy)(jnp.asarray(p_com), jnp.asarray(a_com)))
    # each foot's planned foothold: its last swing's landing point, read in mid-swing (the start stance before the
    # first). Not the swing reference's last sample: it is still short of the landing by up to ~1 % of the swing's
    # length, and at a swing's last float32 sample the planner may already give the next landing.
    foot = np.empty((len(t), 4, 2))
    last = np.asarray(plan.foot_offset[:, :2]) + p_com[0, :2]
    pending = last.copy()
    mid = int(round(0.5 * float(plan.gait.t_swing) / a.dt))
    for k in range(len(t)):
        started = swing[k] & ((k == 0) | ~swing[k - 1])
        pending[started] = land[min(k + mid, len(t) - 1), started, :2]
        ended = (~swing[k]) & (k > 0) & swing[k - 1]
        last[ended] = pending[ended]
        foot[k] = last
    four = []  # ZMP margin in the four-foot phases of the walk (support_margin: > 0 inside the polygon)
    rows = []
    for s in np.unique(step[step >= 0]):
        k4 = np.flatnonzero((step == s) & ~swing.any(axis=1) & (t < plan.gait.t_stop))
        four += [float(support_margin(zmp[i], foot[i], np.ones(4, bool))) for i in k4[::4]]
        k = np.flatnonzero((step == s) & swing.any(axis=1))
        if len(k) < 2:
            continue
        st = ~swing[k[0]]
        if st.sum() != 2:
            continue
        i, j = np.flatnonzero(st)
        fa, fb = foot[k[0], i], foot[k[0], j]
        zd = _seg_dist(zmp[k], fa, fb)
        cd = _seg_dist(p_com[k[-1:], :2], fa, fb)[0]
        rows.append((t[k[0]], zd.max(), cd))
    r = np.array(rows)
    if a.verbose:
        for row in r:
            print(f"  phase at {row[0]:.3f} s: ZMP {1e3 * row[1]:.1f} mm, CoM at end {1e3 * row[2]:.1f} mm")
    print(f"course plan, d = {a.d}: {len(r)} two-foot support phases")
    print(f"ZMP of the planned CoM, largest distance from the support segment per phase [mm]: median "
          f"{1e3 * np.median(r[:, 1]):.1f}, p95 {1e3 * np.percentile(r[:, 1], 95):.1f}, max {1e3 * r[:, 1].max():.1f}")
    print(f"planned CoM at the phase's end, distance from the segment (replan_com's goal clamp) [mm]: median "
          f"{1e3 * np.median(r[:, 2]):.1f}, p95 {1e3 * np.percentile(r[:, 2], 95):.1f}, max {1e3 * r[:, 2].max():.1f}")
    dev = np.linalg.norm(p_com[:, :2] - p_base[:, :2], axis=1)
    print(f"CoM reference minus the object-following one, horizontal [mm]: max {1e3 * dev.max():.1f}, "
          f"mean {1e3 * dev.mean():.1f}; ZMP margin in the four-foot phases [mm]: min {1e3 * min(four):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
