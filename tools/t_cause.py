"""Why the tracking metric T depends on the object's mass, the tray friction and the object's size (issue 23).

Runs a small batch on flat ground without perturbations (one factor varied at a time around the centre cell
m 0.3 kg, mu 0.7, d 0.08 m), standing still for ``--stand`` seconds before a short straight walk, logs the object
and the tray every ``--log-every`` control steps, and decomposes the tracking error e = p_ref - p (object CoM vs
its planned path, the integrand of T) into:

* components: along the path (+: the object behind its reference), lateral, vertical (+: below its reference);
* where it sits: the tray (e_tray = p_ref - (p_tray + R_tray rel0), the error of the tray point that carried the
  object's CoM at t = 0) and the object on the tray (e_rel = R_tray (rel0 - rel), slip and sinking);
* constant offset (the phase's mean vector) vs the dynamic part (mean norm of e minus that mean);

per phase: standing, walking (the path's motion), settling (after the path ends). Usage::

    PYTHONPATH=$PWD python tools/t_cause.py [--stand 1.0] [--distance 0.2] [--iters 20] [--object-lever]
        [--wrench] [--scale w_obj_f=100,w_obj_t=100] [--course] [--out DIR]

``--object-lever`` runs the controller as before issue 23; ``--wrench`` adds the trace of the object wrench the QP
plans vs the one the cube's motion needs (``wrench_trace``), the mechanism (docs/method.md, "T's dependence on m,
mu, d"). About 1.5 min on a 2-core CPU without ``--wrench``, 3 min with it (compiles included).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

CENTRE = (0.3, 0.7, 0.08)
LEVELS = dict(m=(0.2, 0.4), mu=(0.4, 1.0), d=(0.06, 0.10))


def one_at_a_time():
    """The centre cell and each factor's other two levels with the rest at the centre: 7 (m, mu, d) cells."""
    cells = [CENTRE]
    for k, name in enumerate(("m", "mu", "d")):
        for v in LEVELS[name]:
            c = list(CENTRE)
            c[k] = v
            cells.append(tuple(c))
    return cells


def _batch(cells, stand, distance, speed, iters, gains, lever, course, log_every=20):
    """(robot, cfg, sim, batch) of the cells: flat ground (a ``distance`` walk) or the course's full plan."""
    from wbc_jax.control.transport import TransportConfig, control_qp_settings
    from wbc_jax.planner.gait import GaitParams
    from wbc_jax.rollout.batch import prepare_batch
    from wbc_jax.robot.model import Robot
    from wbc_jax.rollout.core import make_sim

    robot = Robot("transport" if course else "flat")
    cfg = TransportConfig(dt=float(robot.mj_model.opt.timestep), qp=control_qp_settings(iters), object_lever=lever)
    sim = make_sim(robot, cfg, log_every=log_every)
    m, mu, d = (np.array(x, float) for x in zip(*cells))
    walk = {} if course else dict(distance=distance)
    b = prepare_batch(sim, m, mu, d, gains=gains,
                      plan_kwargs=dict(speed=speed, gait=GaitParams(t_start=stand), **walk))
    return robot, cfg, sim, b


def run(cells, stand=1.0, distance=0.2, speed=0.13, settle=0.5, iters=20, log_every=10, gains=None, lever=False,
        course=False):
    """Simulate the cells (list of (m, mu, d)) and return (logs dict of host arrays, info dict). ``course``: the
    obstacle course (its full plan, ``distance`` unused) instead of flat ground."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.planner.spline import eval_path
    from wbc_jax.planner.transport import plan_duration
    from wbc_jax.rollout.core import final_results, simulate, with_metric_window

    robot, cfg, sim, b = _batch(cells, stand, distance, speed, iters, gains, lever, course, log_every)
    mu = np.array([c[1] for c in cells], float)
    T_plan = plan_duration(b.plan)
    t_end = T_plan + settle
    state = with_metric_window(b.state, np.full(len(cells), t_end))
    t0 = time.time()
    state, logs = simulate(sim, b.model, b.in_axes, state, b.plan, b.om, b.gains, b.push, b.mu_ground, t_end,
                           chunk_seconds=t_end)
    wall = time.time() - t0
    p_goal = np.asarray(jax.vmap(lambda pth: eval_path(pth, jnp.asarray(t_end))[0])(b.plan.obj_path))
    res = final_results(sim, state, p_goal, np.asarray(mu))
    info = dict(T_plan=T_plan, t_start=stand, t_end=t_end, wall_s=wall, T_metric_mm=(res["T"] * 1e3).tolist(),
                R=res["R"].tolist(), S=res["S"].tolist(), max_slip_mm=res["max_slip_mm"].tolist(),
                success=res["success"].tolist(),
                rel0=np.asarray(state.rel0).tolist(), heading=np.asarray(b.plan.heading).tolist())
    return robot, {k: np.asarray(v) for k, v in logs._asdict().items()}, info


def wrench_trace(cells, stand=1.0, distance=0.2, speed=0.13, settle=0.5, iters=20, gains=None, lever=False,
                 course=False):
    """Every control step of the cells: the object wrench the QP plans (W = G F_c of its Lambda_b), the one the
    object's motion needs (F_b,ref = [m (a_b + g); I alpha_b], the cost's target) and the force the simulated
    object actually receives (m (a + g), a its CoM acceleration over the period), plus how close the planned
    contact forces are to their friction pyramids. Returns a dict of (B, N, ...) host arrays."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.spatial import GRAVITY, cone_edges
    from wbc_jax.physics.observe import wrench_map
    from wbc_jax.control.transport import N_FEET, assemble, contact_points, object_state
    from wbc_jax.planner.transport import plan_duration
    from wbc_jax.rollout.core import control_step, controller_inputs

    robot, cfg, sim, b = _batch(cells, stand, distance, speed, iters, gains, lever, course)
    ids = robot.ids
    n_steps = int(round((plan_duration(b.plan) + settle) / cfg.dt))
    k, nv = cfg.k, ids.nv_robot
    ib = slice(nv + k * N_FEET, nv + k * N_FEET + 4 * k)
    oa = ids.obj_dof_adr
    g = jnp.array([0.0, 0.0, GRAVITY])

    def one(mdl, rs, plan, om, gn, push, mu_g):
        def step(rs, _):
            d, d_ctl, dyn, ref, mu_f = controller_inputs(sim, mdl, rs, plan, push, mu_g)
            new, _log = control_step(sim, mdl, rs, plan, om, gn, push, mu_g)
            lam = new.cs.warm.x[ib]
            obj = object_state(d_ctl, ids)
            Ec = jax.scipy.linalg.block_diag(*([cone_edges(om.mu, k, dyn.R_tray)] * 4))
            F = (Ec @ lam).reshape(4, 3)
            W = wrench_map(contact_points(obj, om), obj.p) @ F.reshape(12)
            a_b = ref.a_obj + gn.kd_obj * (ref.v_obj - obj.v) + gn.kp_obj * (ref.p_obj - obj.p)
            target = jnp.concatenate([om.mass * (a_b + g), jnp.zeros(3)])
            a_act = (new.d.qvel[oa:oa + 3] - d.qvel[oa:oa + 3]) / cfg.dt
            Fl = F @ dyn.R_tray  # tray frame: column 2 normal
            use = jnp.linalg.norm(Fl[:, :2], axis=1) / (om.mu * jnp.maximum(Fl[:, 2], 1e-9))
            _obs, qp = assemble(mdl, d_ctl, dyn, ref, om, gn, rs.cs, ids, cfg, mu_f)
            res = qp[2] @ new.cs.warm.x - qp[3]  # rows 0:6 floating base (9), 18:24 tray (11): equalities
            return new, (d.time, W, target, om.mass * (a_act + g), jnp.max(use), jnp.min(lam), a_act - a_b,
                         res[0:6], res[18:24], ref.p_obj - obj.p, ref.v_obj - obj.v, ref.a_obj)

        return jax.lax.scan(step, rs, None, length=n_steps)[1]

    fn = jax.jit(jax.vmap(one, in_axes=(b.in_axes, 0, 0, 0, 0, 0, 0)))
    t, W, target, f_act, use, lam_min, acc_err, res9, res11, e, ev, a_ref = (
        np.asarray(x) for x in fn(b.model, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground))
    return dict(t=t[0], W=W, target=target, f_act=f_act, cone_use=use, lam_min=lam_min, acc_err=acc_err,
                res9=res9, res11=res11, e=e, e_v=ev, a_ref=a_ref,
                t_start=stand, T_plan=plan_duration(b.plan))


def tray_poses(robot, qpos):
    """Tray-top site positions (..., 3) and orientations (..., 3, 3) of logged configurations (MuJoCo C)."""
    import mujoco

    m, ids = robot.mj_model, robot.ids
    data = mujoco.MjData(m)
    flat = qpos.reshape(-1, qpos.shape[-1])
    p = np.empty((len(flat), 3))
    R = np.empty((len(flat), 3, 3))
    for i, q in enumerate(flat):
        data.qpos[:] = q
        mujoco.mj_kinematics(m, data)
        p[i] = data.site_xpos[ids.tray_site]
        R[i] = data.site_xmat[ids.tray_site].reshape(3, 3)
    return p.reshape(qpos.shape[:-1] + (3,)), R.reshape(qpos.shape[:-1] + (3, 3))


def decompose(robot, logs, info):
    """Per run and phase: T's integrand and its parts (see the module docstring). Lengths in mm."""
    t = logs["t"][0]
    p, pr = logs["p_obj"], logs["p_obj_ref"]  # (B, N, 3)
    p_top, R = tray_poses(robot, logs["qpos"])
    rel0 = np.asarray(info["rel0"])  # (B, 3) object in the tray frame at t = 0
    rel = np.einsum("bnji,bnj->bni", R, p - p_top)
    e = pr - p
    e_rel = np.einsum("bnij,bnj->bni", R, rel0[:, None] - rel)
    e_tray = e - e_rel
    u = np.asarray(info["heading"])[0]
    lat = np.array([-u[1], u[0]])

    def comps(v):  # along (+: behind the reference), lateral, vertical
        return np.stack([v[..., :2] @ u, v[..., :2] @ lat, v[..., 2]], -1)

    tilt = np.degrees(np.arccos(np.clip(R[..., 2, 2], -1, 1)))
    phases = dict(stand=(0.0, info["t_start"]), walk=(info["t_start"], info["T_plan"]),
                  settle=(info["T_plan"], info["t_end"]), window=(0.0, info["t_end"]))
    out = []
    for b in range(p.shape[0]):
        row = {}
        # on the course: the walk split where the object's reference dips under the wall (> 1 mm below its start)
        dip = pr[b, :, 2] < pr[b, 0, 2] - 1e-3
        for ph, (a, z) in list(phases.items()) + ([("level", phases["walk"]), ("dip", phases["walk"])]
                                                  if dip.any() else []):
            k = (t >= a) & (t < z) & {"level": ~dip, "dip": dip}.get(ph, True)
            E, Et, Er = comps(e[b, k]), comps(e_tray[b, k]), comps(e_rel[b, k])
            mean = E.mean(0)
            row[ph] = dict(
                T_mm=float(np.linalg.norm(E, axis=1).mean() * 1e3),
                mean_mm=(mean * 1e3).round(4).tolist(),  # constant offset [along, lateral, vertical]
                dyn_mm=float(np.linalg.norm(E - mean, axis=1).mean() * 1e3),
                rms_mm=(np.sqrt((E**2).mean(0)) * 1e3).round(4).tolist(),
                tray_mean_mm=(Et.mean(0) * 1e3).round(4).tolist(),
                rel_mean_mm=(Er.mean(0) * 1e3).round(4).tolist(),
                tilt_deg=float(tilt[b, k].mean()),
            )
        out.append(row)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stand", type=float, default=1.0, help="standing time before the walk [s]")
    ap.add_argument("--distance", type=float, default=0.2, help="walk length [m]")
    ap.add_argument("--speed", type=float, default=0.13)
    ap.add_argument("--iters", type=int, default=20, help="ADMM iterations of the control-loop QP")
    ap.add_argument("--log-every", type=int, default=10)
    ap.add_argument("--scale", default="", help="gain multipliers, e.g. w_obj_f=100,w_obj_t=100")
    ap.add_argument("--object-lever", action="store_true",
                    help="the CoM-wrench row before issue 23 (object reaction through Lambda_b)")
    ap.add_argument("--wrench", action="store_true",
                    help="also trace the planned vs needed object wrench every control step (a second compile)")
    ap.add_argument("--out", type=Path, default=None, help="write decomposition.json and logs.npz here")
    ap.add_argument("--course", action="store_true",
                    help="the obstacle course's full plan, d varied only (m 0.3, mu 0.7); the walk also split into "
                         "'level' and 'dip' (the object's reference under the wall)")
    a = ap.parse_args(argv)
    cells = [(0.3, 0.7, d) for d in (0.06, 0.08, 0.10)] if a.course else one_at_a_time()
    gains = None
    if a.scale:
        from wbc_jax.control.transport import default_gains

        gains = default_gains()
        for kv in a.scale.split(","):
            k, v = kv.split("=")
            gains = gains._replace(**{k: getattr(gains, k) * float(v)})
    robot, logs, info = run(cells, a.stand, a.distance, a.speed, iters=a.iters, log_every=a.log_every, gains=gains,
                            lever=a.object_lever, course=a.course)
    rows = decompose(robot, logs, info)
    print(f"plan end {info['T_plan']:.2f} s, window {info['t_end']:.2f} s, rollout {info['wall_s']:.1f} s")
    hdr = "m    mu   d    | phase  | T [mm] | offset along/lat/vert [mm] | dyn [mm] | tray offset a/l/v | on-tray a/l/v"
    print(hdr)
    for (m, mu, d), row, Tm in zip(cells, rows, info["T_metric_mm"]):
        for ph, r in row.items():
            f = lambda v: "/".join(f"{x:+.3f}" for x in v)  # noqa: E731
            print(f"{m:.1f} {mu:.1f} {d:.2f} | {ph:6s} | {r['T_mm']:.3f} | {f(r['mean_mm'])} | {r['dyn_mm']:.3f} | "
                  f"{f(r['tray_mean_mm'])} | {f(r['rel_mean_mm'])}")
        i = cells.index((m, mu, d))
        print(f"  T (rollout metric) = {Tm:.3f} mm, R {info['R'][i]:.4f}, S {info['S'][i]:.3f}, "
              f"max slip {info['max_slip_mm'][i]:.2f} mm, success {info['success'][i]}")
    if a.wrench:
        wr = wrench_trace(cells, a.stand, a.distance, a.speed, iters=a.iters, gains=gains, lever=a.object_lever,
                          course=a.course)
        print("walk phase: planned object wrench G F_c minus the needed F_b,ref; tray acceleration error")
        print("m    mu   d    | mean dF x/y/z [N] | rms |dF| [N] | rms |dtau| [N mm] | mean a - a_b along [m/s^2]")
        t = wr["t"]
        k = (t >= wr["t_start"]) & (t < wr["T_plan"])
        u = np.asarray(info["heading"])[0]
        for i, (m, mu, d) in enumerate(cells):
            dW = wr["W"][i, k] - wr["target"][i, k]
            rms = lambda v: float(np.sqrt((v**2).sum(1).mean()))  # noqa: E731
            print(f"{m:.1f} {mu:.1f} {d:.2f} | " + "/".join(f"{x:+.3f}" for x in dW[:, :3].mean(0)) +
                  f" | {rms(dW[:, :3]):.3f} | {1e3 * rms(dW[:, 3:]):.1f} | "
                  f"{float(wr['acc_err'][i, k, :2].mean(0) @ u):+.4f}")
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "decomposition.json").write_text(json.dumps(dict(cells=cells, info=info, rows=rows), indent=1))
        np.savez_compressed(a.out / "logs.npz", **logs)


if __name__ == "__main__":
    main()
