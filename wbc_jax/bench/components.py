"""``wbc-jax bench components``: the latency of each stage of one transport-WBC control step.

Each stage (sensing, observation, reference, QP assembly, QP solve, physics advance, metric integrands) runs as its
own jit(vmap) call on a batch state a few control steps into the run, next to the whole fused control step and
physics alone, so a stage's cost can be read without a profiler (each call adds one dispatch).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.bench.rollout import random_batch, timed, wbc_chunk_fn
from wbc_jax.control.transport import TransportConfig, assemble, control_qp_settings
from wbc_jax.metrics import paper as metrics
from wbc_jax.physics import backend as physics
from wbc_jax.physics import contacts
from wbc_jax.physics.contacts import CONTACT_DIST
from wbc_jax.physics.observe import observe
from wbc_jax.planner.transport import reference
from wbc_jax.qp import solve_qp
from wbc_jax.robot.model import Robot, mjx
from wbc_jax.rollout import control_step, make_sim


def _stages(sim, b, iters: int) -> list:
    """(name, jit(vmap) function, its arguments) per stage of one control step of batch ``b``, each stage's inputs
    computed by the stages before it from the state one chunk (``sim.log_every`` control steps) into the run."""
    ids, cfg, ax = sim.robot.ids, sim.cfg, b.in_axes
    chunk, args = wbc_chunk_fn(sim, b)
    rs, _ = chunk(*args)
    V = lambda f, n_run: jax.jit(jax.vmap(f, in_axes=(ax,) + (0,) * n_run))  # noqa: E731
    f_sense = V(physics.sense, 1)
    ds = f_sense(b.model, rs.d)
    f_obs = V(lambda m, d: observe(m, d, ids), 1)
    obs = f_obs(b.model, ds)

    def ref_fn(m, d, obs, plan, p_lift):
        contact = contacts.foot_dist(sim, m, d) < CONTACT_DIST
        return reference(plan, d.time, p_lift, contact, obs.robot.p_foot)

    f_ref = V(ref_fn, 4)
    ref = f_ref(b.model, ds, obs, b.plan, rs.p_lift)
    f_asm = jax.jit(jax.vmap(lambda obs, ref, om, g, cs, mg: assemble(obs, ref, om, g, cs, ids, cfg, mg)))
    _, (P, q, A, l, u, A_tau, h_a, _) = f_asm(obs, ref, b.om, b.gains, rs.cs, b.mu_ground)
    f_qp = jax.jit(jax.vmap(lambda P, q, A, l, u, w: solve_qp(P, q, A, l, u, warm=w, settings=cfg.qp)))
    res = f_qp(P, q, A, l, u, rs.cs.warm)
    tau = jnp.clip(jnp.einsum("bij,bj->bi", A_tau, res.x) + h_a, -ids.tau_max, ids.tau_max)
    f_adv = V(physics.finish, 2)
    d_next = f_adv(b.model, ds, tau)
    oa = ids.obj_dof_adr
    f_met = V(lambda m, d0, d1, mu: metrics.step_integrands(contacts.object_contacts(sim, m, d1)[0], mu,
                                                            d0.qvel[oa:oa + 3], d1.qvel[oa:oa + 3], sim.dt_control), 3)
    f_step = V(lambda m, rs, plan, om, g, push, mg: control_step(sim, m, rs, plan, om, g, push, mg), 6)
    f_phys = V(mjx.step, 1)
    return [("sense (fwd_position + fwd_velocity)", f_sense, (b.model, rs.d)),
            ("observe (dynamics terms, jacobians)", f_obs, (b.model, ds)),
            ("reference", f_ref, (b.model, ds, obs, b.plan, rs.p_lift)),
            ("assemble (observer, build_qp)", f_asm, (obs, ref, b.om, b.gains, rs.cs, b.mu_ground)),
            (f"solve_qp ({iters} iterations)", f_qp, (P, q, A, l, u, rs.cs.warm)),
            ("finish (actuation, constraint solve, integrate)", f_adv, (b.model, ds, tau)),
            ("metrics.step_integrands", f_met, (b.model, ds, d_next, b.om.mu)),
            ("whole control step", f_step, (b.model, rs, b.plan, b.om, b.gains, b.push, b.mu_ground)),
            ("physics only (mjx.step)", f_phys, (b.model, rs.d))]


def run_components(batch: int = 256, iters: int = 50, scene: str = "transport", warm_steps: int = 100,
                   reps: int = 20, json_path: str | None = None):
    """Latency of each stage of one control step, each stage its own jit(vmap) call on a state ``warm_steps`` into
    the run (median of ``reps`` calls; includes one dispatch per call, so the stages sum to more than the fused step).
    """
    robot = Robot(scene)
    cfg = TransportConfig(dt=float(robot.mj_model.opt.timestep), qp=control_qp_settings(iters))
    sim = make_sim(robot, cfg, log_every=warm_steps)
    b = random_batch(sim, batch)
    stages = _stages(sim, b, iters)
    device = jax.devices()[0].device_kind
    out = dict(device=device, scene=robot.path.name, batch=batch, iters=iters, stages_ms={})
    for name, f, args in stages:
        jax.block_until_ready(f(*args))
        ts = []
        for _ in range(reps):
            ts.append(timed(f, *args)[1])
        out["stages_ms"][name] = 1e3 * float(np.median(ts))
        print(f"{device} batch {batch}: {name:50s} {out['stages_ms'][name]:8.3f} ms per call", flush=True)
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=2)
    return out
