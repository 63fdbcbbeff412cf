"""A finished batch's per-run results (:func:`final_results`) and readable names of its contact and clearance
pairs."""

from __future__ import annotations

import jax
import numpy as np

from wbc_jax.physics import backend as physics
from wbc_jax.physics.clearance import clearance_pairs
from wbc_jax.planner.scene_geometry import scene_geometry
from wbc_jax.rollout.config import Sim
from wbc_jax.rollout.state import RunState


def final_results(sim: Sim, state: RunState, final_input, mu, n: int | None = None) -> dict[str, np.ndarray]:
    """The per-run results of a batch's final state: the controller's (``Controller.finalize``; the transport's:
    :func:`wbc_jax.metrics.paper.finalize`) and the shared ones (constraint-solver cap, first non-foot contact,
    closest clearance pair).

    Args:
        state: batched RunState at the end of the runs; final_input: ``Controller.final_input`` of the last logs
            (the transport's: (B, 3) the object's goal position [m], the reference's last point); mu: (n or B,)
            tray friction of each run.
        n: keep the first n runs (drops the padding of a sharded batch); None: all.
    """
    acc = jax.device_get(state.acc)
    if n is not None:
        acc = jax.tree_util.tree_map(lambda x: np.asarray(x)[:n], acc)
    out = sim.controller.finalize(sim, acc, state, final_input, mu, n, scene_geometry(sim.robot).is_course)
    if not physics.reports_solver_cap(sim.robot):  # MJX's JAX solver does not report its iteration count
        out["solver_cap_fraction"] = np.full(len(out["success"]), np.nan)
    out["first_contact_s"] = np.asarray(acc.first_contact_t, float)
    out["first_contact"] = np.array([contact_name(sim, k) for k in np.asarray(acc.first_contact_k)], dtype=object)
    out["min_clearance_pair"] = np.array([clearance_name(sim, k) for k in np.asarray(acc.min_clear_k)], dtype=object)
    return out


def _pair_name(sim: Sim, g1, g2) -> str:
    """``"robot geom (body B) / scene geom"``: the geom not on the world body (floor, blocks, walls) first."""
    m = sim.robot.mj_model

    def name(g):
        return m.geom(int(g)).name or f"geom{int(g)}"

    robot_g, env_g = (g1, g2) if int(m.geom_bodyid[g1]) != 0 else (g2, g1)
    return f"{name(robot_g)} (body {m.body(int(m.geom_bodyid[robot_g])).name}) / {name(env_g)}"


def clearance_name(sim: Sim, k: int) -> str:
    """Readable pair of clearance index ``k`` (Accum.min_clear_k, an index into
    ``wbc_jax.physics.clearance.clearance_pairs(sim.robot)``; -1: ""), e.g. ``"FL_shank (body FL_calf) / block3"``."""
    if k < 0:
        return ""
    pairs = clearance_pairs(sim.robot)
    return _pair_name(sim, pairs.robot[int(k)], pairs.env[int(k)])


def contact_name(sim: Sim, k: int) -> str:
    """Readable pair of non-foot slot ``k`` (index into ``sim.nonfoot_slots``; -1: "" ), e.g.
    ``"BR_shank (body BR_calf) / block3"``: the robot geom with its body, then the floor or terrain geom."""
    if k < 0:
        return ""
    g1, g2 = sim.nonfoot_geoms[int(k)]
    return _pair_name(sim, g1, g2)
