"""Leg clearance over the course's block edges, per leg and per block, for chosen runs of a campaign spec (issue 24).

Builds the chosen runs of a spec exactly as the campaign does (same design rows: factors, seeds, perturbations),
simulates them on the CPU with the qpos logged every ``--log-every`` control steps, and measures offline, with
MuJoCo C (``mj_geomDistance``), the distance of every shank and thigh to every block and the floor at each logged
sample. Prints, per run: the rollout's own ``min_clearance_mm`` (every physics step), and per leg the smallest
distance of its shank to each block with the time. Usage::

    PYTHONPATH=$PWD python tools/graze.py --spec sweeps/paper_campaign.toml --runs 260,268 [--seconds 15]
        [--save-state S.pkl --save-at 12.0] [--load-state S.pkl] [--window 12.5,15] [--out DIR]

``--save-state`` keeps the batch's state at the first chunk boundary at or after ``--save-at`` seconds;
``--load-state`` starts from such a state (the same runs; the planner may have changed since, which is the point:
iterate on what happens after that time without simulating the first 12 s again).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import time
from pathlib import Path

import numpy as np

LEGS = ("FL", "FR", "BL", "BR")


def subset_design(dz, idx):
    """The design rows ``idx`` (every per-run array and dict entry indexed)."""
    out = {}
    for f in dataclasses.fields(dz):
        v = getattr(dz, f.name)
        if isinstance(v, np.ndarray):
            out[f.name] = v[idx]
        elif isinstance(v, dict):
            out[f.name] = {k: np.asarray(x)[idx] for k, x in v.items()}
        else:
            out[f.name] = v
    return type(dz)(**out)


def build_runs(spec, idx, log_every: int):
    """campaign.build for the design rows ``idx``, with a Sim logging every ``log_every`` control steps."""
    from wbc_jax.control.transport import TransportConfig, control_qp_settings
    from wbc_jax.control.variants import Variant
    from wbc_jax.planner.transport import plan_duration
    from wbc_jax.rollout.batch import prepare_batch
    from wbc_jax.robot.model import Robot
    from wbc_jax.rollout.core import make_push, make_sim, with_metric_window, with_variant
    from wbc_jax.campaign.runner import initial_configuration
    from wbc_jax.campaign.spec import design

    c = spec.campaign
    dz = subset_design(design(spec), np.asarray(idx))
    robot = Robot(c["scene"], backend="jax")
    cfg = TransportConfig(dt=float(robot.mj_model.opt.timestep) * c["control_substeps"],
                          qp=control_qp_settings(c["qp_iters"]))
    sim = make_sim(robot, cfg, n_substeps=c["control_substeps"], log_every=log_every,
                   sensor_noise=bool(np.any(dz.qvel_noise_std > 0)))
    qpos0, qvel0 = initial_configuration(robot, dz)
    b = prepare_batch(sim, dz.m, dz.mu, dz.d, plan_kwargs=dict(distance=c["distance"], speed=c["speed"]),
                      qpos0=qpos0, qvel0=qvel0)
    T_plan = plan_duration(b.plan)
    push = make_push(dz.push_force, dz.push_frac * T_plan, dz.push_duration, dz.qvel_noise_std, dz.seed)
    state = with_variant(with_metric_window(b.state, T_plan + c["extra_seconds"]), Variant(*dz.variant.T))
    return sim, dz, b._replace(push=push, state=state), T_plan


def leg_distances(mj_model, qpos, blocks=("floor", "block1", "block2", "block3")):
    """(T, 4 legs, 2 parts (shank, thigh), n blocks) distances [m] of each logged configuration (MuJoCo C)."""
    import mujoco

    m, d = mj_model, mujoco.MjData(mj_model)
    gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    parts = [[gid(f"{leg}_shank"), gid(f"{leg}_thigh")] for leg in LEGS]
    env = [gid(n) for n in blocks]
    out = np.zeros((qpos.shape[0], 4, 2, len(env)))
    ft = np.zeros(6)
    for k, q in enumerate(qpos):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        for i in range(4):
            for j in range(2):
                for e, g in enumerate(env):
                    out[k, i, j, e] = mujoco.mj_geomDistance(m, d, parts[i][j], g, 0.5, ft)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default="sweeps/paper_campaign.toml")
    ap.add_argument("--runs", required=True, help="comma-separated design rows (0-based, as results.csv's run)")
    ap.add_argument("--seconds", type=float, default=0.0, help="simulated time (0: the campaign's horizon)")
    ap.add_argument("--chunk", type=float, default=1.0, help="simulated seconds per jit call")
    ap.add_argument("--log-every", type=int, default=5, help="control steps per logged qpos sample")
    ap.add_argument("--save-state"), ap.add_argument("--save-at", type=float, default=12.0)
    ap.add_argument("--load-state")
    ap.add_argument("--window", default="", help="t0,t1: report distances only inside this window [s]")
    ap.add_argument("--out", default="", help="folder for logs.npz and summary.json")
    a = ap.parse_args(argv)

    import jax

    from wbc_jax.rollout.core import final_results, simulate
    from wbc_jax.campaign.spec import load_spec

    idx = [int(x) for x in a.runs.split(",")]
    spec = load_spec(a.spec)
    t0 = time.perf_counter()
    sim, dz, b, T_plan = build_runs(spec, idx, a.log_every)
    horizon = a.seconds or (T_plan + spec.campaign["extra_seconds"])
    state, t_start = b.state, 0.0
    if a.load_state:
        with open(a.load_state, "rb") as fh:
            saved = pickle.load(fh)
        if saved["runs"] != idx:
            raise SystemExit(f"{a.load_state} holds runs {saved['runs']}, not {idx}")
        state = jax.tree_util.tree_map(lambda like, x: jax.numpy.asarray(x, like.dtype), state, saved["state"])
        t_start = saved["t"]
    print(f"built {len(idx)} runs in {time.perf_counter() - t0:.1f} s; simulating {t_start:.2f} -> {horizon:.2f} s",
          flush=True)
    logs_all, t = [], t_start
    while t < horizon - 1e-9:
        seg = min(a.chunk, horizon - t)
        state, logs = simulate(sim, b.model, b.in_axes, state, b.plan, b.om, b.gains, b.push, b.mu_ground, seg,
                               chunk_seconds=a.chunk)
        logs_all.append(logs)
        t += seg
        print(f"  t = {t:.2f} s ({time.perf_counter() - t0:.0f} s wall)", flush=True)
        if a.save_state and not a.load_state and t >= a.save_at - 1e-9:
            with open(a.save_state, "wb") as fh:
                pickle.dump(dict(runs=idx, t=t, state=jax.device_get(state)), fh)
            print(f"  state at {t:.2f} s saved to {a.save_state}", flush=True)
            a.save_state = None
    logs = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *logs_all)
    p_goal = np.asarray(logs.p_obj_ref[:, -1])
    res = final_results(sim, state, p_goal, dz.mu)
    tt = np.asarray(logs.t[0])
    sel = np.ones_like(tt, bool)
    if a.window:
        w0, w1 = (float(x) for x in a.window.split(","))
        sel = (tt >= w0) & (tt <= w1)
    summary = []
    for r, run in enumerate(idx):
        dist = leg_distances(sim.robot.mj_model, np.asarray(logs.qpos[r])[sel])
        row = dict(run=run, m=float(dz.m[r]), mu=float(dz.mu[r]), d=float(dz.d[r]), rep=int(dz.rep[r]),
                   success=bool(res["success"][r]), fail_reason=str(res["fail_reason"][r]),
                   min_clearance_mm=float(res["min_clearance_mm"][r]), min_clearance_s=float(res["min_clearance_s"][r]),
                   min_clearance_pair=str(res["min_clearance_pair"][r]),
                   R=float(res["R"][r]), T=float(res["T"][r]), S=float(res["S"][r]))
        for i, leg in enumerate(LEGS):
            for e, blk in enumerate(("floor", "block1", "block2", "block3")):
                k = int(np.argmin(dist[:, i, 0, e]))
                row[f"{leg}_shank_{blk}"] = (round(float(dist[k, i, 0, e]) * 1e3, 2), round(float(tt[sel][k]), 3))
        summary.append(row)
        print(json.dumps(row), flush=True)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "logs.npz", t=tt, qpos=np.asarray(logs.qpos), com=np.asarray(logs.com),
                            com_ref=np.asarray(logs.com_ref), trunk_z=np.asarray(logs.trunk_z))
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"wall {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
