"""Batched evaluation of gain candidates for ``wbc-jax tune``: candidates x runs -> per-run metrics -> score.

:class:`Evaluator` holds one campaign's runs (the chosen cells x reps, each with its seed and perturbations)
and rolls out any set of candidates on all of them. The candidates' runs (candidate-major: run i of a call
belongs to candidate i // n) are cut into **sub-batches of one fixed size** (``batch`` runs, the last one padded
with copies of its last run, which are dropped), so one compiled chunk function serves every round, rung and
confirmation, whatever the number of candidates, and the CPU never sees a batch larger than ``batch``.
Sub-batches run one after the other, each over the requested range of chunks; a run's state can be kept and
continued later (successive halving continues the survivors from their last rung).

Several devices (one process, or several processes joined by :mod:`wbc_jax.sim.distributed`): every sub-batch is
spread over all devices of all processes, each device stepping its own runs (the campaign's chunk function,
:func:`wbc_jax.sim.sharding.over_runs`). With several processes each sub-batch's final states are gathered to
every process after its last chunk (a collective), so every process scores the same runs, the search takes the
same steps everywhere, and continued states are placed again from the host copy.

:func:`score` turns per-run metrics into per-candidate aggregates (module docstring of
:mod:`wbc_jax.study.tune`).
"""

from __future__ import annotations

import numpy as np

from wbc_jax.control.transport import TransportGains
from wbc_jax.sim import distributed


def take(tree, idx, in_axes=0):
    """Rows ``idx`` of every batched leaf (``in_axes`` 0) of ``tree``; unbatched leaves (None) unchanged."""
    import jax

    leaves, treedef = jax.tree_util.tree_flatten(tree)
    axes = [in_axes] * len(leaves) if isinstance(in_axes, int) else treedef.flatten_up_to(in_axes)
    host = np.asarray(idx)  # host leaves (several processes' gathered states) are indexed on the host
    return jax.tree_util.tree_unflatten(treedef, [x if a is None else x[host] if isinstance(x, np.ndarray) else x[idx]
                                                  for x, a in zip(leaves, axes)])


def concat(trees: list):
    """Leafwise concatenation of pytrees along the run axis: device arrays stay on the device (the result keeps
    the chunk function's input types and placement, so feeding it back does not compile again), host arrays on
    the host."""
    import jax
    import jax.numpy as jnp

    def cat(*xs):
        return np.concatenate(xs) if isinstance(xs[0], np.ndarray) else jnp.concatenate(xs)

    return trees[0] if len(trees) == 1 else jax.tree_util.tree_map(cat, *trees)


class Evaluator:
    """Rollouts of candidates x runs of one campaign in fixed-size sub-batches.

    Attributes:
        n: runs per candidate; m, mu, d, rep, seeds: (n,) factor values, repetition and seed of each run.
        size: runs per rollout call; n_chunks: chunks of the full horizon; chunk_s: simulated time per chunk [s];
        seconds: the full horizon [s]; sim: the Sim; fn: the compiled chunk function; calls: rollout calls made.
    """

    def __init__(self, camp, cells: list | None, size: int):
        """Args: camp: campaign Spec (reps, max_seconds, qp_iters applied); cells: [m, mu, d] cells to keep
        (None: all); size: runs per rollout call (>= 1)."""
        import jax

        from wbc_jax.study import campaign

        sim, dz, b, _, logs_per_chunk, n_chunks = campaign.build(camp)
        if cells is None:
            sel = np.arange(dz.n)
        else:
            have = np.stack([dz.m, dz.mu, dz.d], axis=1)
            sel = np.where(np.isclose(have[:, None, :], np.asarray(cells)[None]).all(-1).any(-1))[0]
        self.camp, self.sim, self.n, self.n_chunks = camp, sim, len(sel), n_chunks
        self.m, self.mu, self.d, self.rep, self.seeds = dz.m[sel], dz.mu[sel], dz.d[sel], dz.rep[sel], dz.seed[sel]
        self.chunk_s = logs_per_chunk * campaign.LOG_EVERY * sim.dt_control
        self.seconds = n_chunks * self.chunk_s
        self.size = int(size)
        self.batch, self.sel = b, np.asarray(sel)
        self.mesh = None
        if jax.device_count() > 1:  # spread every sub-batch over all devices of all processes (wbc_jax.sim.sharding)
            from wbc_jax.sim.sharding import run_mesh

            self.mesh = run_mesh()
        self.multiprocess = distributed.is_multiprocess()
        self.fn = campaign._chunk_fn(sim, b.in_axes, logs_per_chunk, self.mesh)
        self.calls = 0

    def compiled_variants(self) -> int | None:
        """Number of compiled variants of the chunk function so far (None if this JAX does not say)."""
        size = getattr(self.fn, "_cache_size", None)
        return int(size()) if callable(size) else None

    def calls_for(self, n_candidates: int) -> int:
        """Sub-batches needed for ``n_candidates`` candidates' runs."""
        return -(-n_candidates * self.n // self.size)

    def rollout(self, gains: TransportGains, chunks: tuple[int, int] = (0, -1), states=None, bar=None):
        """Roll out every run of every candidate over chunks [c0, c1).

        Args:
            gains: TransportGains with leading axis C (host numpy).
            chunks: (c0, c1): first chunk and end chunk (-1: the full horizon); c0 > 0 continues ``states``.
            states: pytree of RunState with C n runs (candidate-major), as returned by an earlier call (None: the
                initial states): device arrays, or host arrays with several processes.
            bar: progress bar advanced by simulated run-seconds after every call (``update``), or None.

        Returns:
            (res, states): ``wbc_jax.sim.metrics.finalize``'s per-run dict at chunk c1, every array (C, n), the
            same in every process; the runs' states at chunk c1 (C n runs, candidate-major; a device pytree, or
            the host copy with several processes).
        """
        import jax
        import jax.numpy as jnp

        from wbc_jax.sim.rollout import final_results

        c0, c1 = chunks[0], self.n_chunks if chunks[1] < 0 else chunks[1]
        C = int(np.shape(gains.kp_com)[0])
        total = C * self.n
        cand = np.repeat(np.arange(C), self.n)  # candidate of each run
        run = self.sel[np.tile(np.arange(self.n), C)]  # design row of each run
        b = self.batch
        outs, finals = [], []
        for s0 in range(0, total, self.size):
            real = min(self.size, total - s0)
            idx = np.arange(s0, s0 + self.size).clip(max=total - 1)  # padded with the last run
            rows = jnp.asarray(run[idx])
            sub = b._replace(model=take(b.model, rows, b.in_axes), plan=take(b.plan, rows), om=take(b.om, rows),
                             push=take(b.push, rows), mu_ground=take(b.mu_ground, rows),
                             state=take(b.state if states is None else states, rows if states is None else
                                        jnp.asarray(idx)),
                             gains=jax.tree_util.tree_map(jnp.asarray, take(gains, cand[idx])))
            if self.mesh is not None:
                from wbc_jax.sim.sharding import shard_batch

                sub, _ = shard_batch(sub, self.mesh)
            state, logs = sub.state, None
            for _ in range(c0, c1):
                state, logs = self.fn(sub.model, state, sub.plan, sub.om, sub.gains, sub.push, sub.mu_ground)
                state = jax.block_until_ready(state)
                self.calls += 1
                if bar is not None:
                    bar.update(real * self.chunk_s)
            p_goal = logs.p_obj_ref[:, -1]
            if self.multiprocess:  # every process: the whole sub-batch on the host (a collective)
                state, p_goal = distributed.gather((state, p_goal))
            finals.append(final_results(self.sim, state, p_goal, np.tile(self.mu, C)[idx], n=real))
            outs.append(jax.tree_util.tree_map(lambda x: x[:real], state))
        res = {k: np.concatenate([f[k] for f in finals]).reshape(C, self.n) for k in finals[0]}
        return res, concat(outs)


def score(res: dict, mu: np.ndarray, obj: dict) -> dict[str, np.ndarray]:
    """Per-candidate aggregates from per-run results.

    Args:
        res: per-run metrics, each (C, n) (R [rad^2], S [s^2/m], T [m], success); mu: (n,) runs' tray friction;
        obj: the spec's [objective] table.

    Returns:
        (C,) arrays: success_rate, R, R_norm, S, S_norm, T_mm (means over the successful runs, NaN when none),
        objective, violation, feasible.
    """
    ok = res["success"].astype(bool)
    n_ok = ok.sum(1)

    def mean_ok(v):
        v = np.where(ok, np.asarray(v, float), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n_ok > 0, v.sum(1) / np.maximum(n_ok, 1), np.nan)

    R, S, T_mm = mean_ok(res["R"]), mean_ok(res["S"]), mean_ok(res["T"] * 1e3)
    R_norm = mean_ok(res["R"] / np.arctan(mu)[None] ** 2)
    S_norm = S / obj["s_ref"]
    objective = obj["w_R"] * R_norm + obj["w_S"] * S_norm - obj["w_T"] * T_mm
    rate = ok.mean(1)
    viol = np.maximum(0.0, obj["min_success"] - rate)
    if obj["t_max_mm"] > 0:
        viol = viol + np.where(n_ok > 0, np.maximum(0.0, T_mm - obj["t_max_mm"]) / obj["t_max_mm"], 1.0)
    viol = np.where(n_ok > 0, viol, np.maximum(viol, 1.0))  # no successful run is never feasible
    return dict(success_rate=rate, R=R, R_norm=R_norm, S=S, S_norm=S_norm, T_mm=T_mm, objective=objective,
                violation=viol, feasible=viol <= 0.0)


def per_run_objective(res: dict, mu: np.ndarray, obj: dict) -> np.ndarray:
    """Per-run objective J_i = w_R R_i / atan(mu_i)^2 + w_S S_i / s_ref - w_T T_i [mm] (any run, successful or
    not; each (C, n) -> (C, n)). Its mean over the successful runs is :func:`score`'s objective."""
    return (obj["w_R"] * np.asarray(res["R"], float) / np.arctan(mu)[None] ** 2
            + obj["w_S"] * np.asarray(res["S"], float) / obj["s_ref"] - obj["w_T"] * np.asarray(res["T"], float) * 1e3)
