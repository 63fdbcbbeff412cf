"""Batched evaluation of gain candidates for ``wbc-jax tune``: candidates x runs -> per-run metrics -> score.

:class:`Evaluator` holds one campaign's runs (the chosen cells x reps, each with its seed and perturbations)
and rolls out any set of candidates on all of them. The candidates' runs (candidate-major: run i of a call
belongs to candidate i // n) are cut into **sub-batches of one fixed size** (``batch`` runs, the last one padded
with copies of its last run, which are dropped), so one compiled chunk function serves every round, rung and
confirmation, whatever the number of candidates, and the CPU never sees a batch larger than ``batch``.
Sub-batches run one after the other, each over the requested range of chunks; a run's state can be kept and
continued later (successive halving continues the survivors from their last rung).

Several devices (one process, or several processes joined by :mod:`wbc_jax.rollout.distributed`): every sub-batch is
spread as a campaign spreads its batch (:mod:`wbc_jax.rollout.spread`: over every device of every process on JAX
physics, a block per process on Warp). Each sub-batch's final states are then gathered to every process's host
after its last chunk (a collective), so every process scores the same runs, the search takes the same steps
everywhere, and continued states are placed again from the host copy.

:func:`score` turns per-run metrics into per-candidate aggregates (module docstring of
:mod:`wbc_jax.studies.tune`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.campaign.build import build, build_ahead, chunk_fn
from wbc_jax.campaign.job import chunk_seconds
from wbc_jax.control.transport import TransportGains
from wbc_jax.rollout import final_results
from wbc_jax.rollout.batch import take_runs, with_contact_list
from wbc_jax.rollout.runs import concat, take
from wbc_jax.rollout.spread import choose
from wbc_jax.studies.tune_search import rank_key


def selected_runs(m, mu, d, cells: list | None) -> np.ndarray:
    """Design rows (int, ascending) of the runs in ``cells`` ([m, mu, d] each; None: every run) of a design whose
    runs have the (B,) levels ``m``, ``mu``, ``d`` (:func:`wbc_jax.campaign.design.object_levels`)."""
    if cells is None:
        return np.arange(len(m))
    have = np.stack([m, mu, d], axis=1)
    return np.where(np.isclose(have[:, None, :], np.asarray(cells)[None]).all(-1).any(-1))[0]


class Evaluator:
    """Rollouts of candidates x runs of one campaign in fixed-size sub-batches.

    Attributes:
        n: runs per candidate; m, mu, d, rep, seeds: (n,) factor values, repetition and seed of each run.
        size: runs per rollout call; n_chunks: chunks of the full horizon; chunk_s: simulated time per chunk [s];
        seconds: the full horizon [s]; sim: the Sim; fn: the compiled chunk function; calls: rollout calls made.
    """

    def __init__(self, camp, cells: list | None, size: int, ahead: bool = False):
        """Args: camp: campaign Spec (reps, max_seconds, qp_iters applied); cells: [m, mu, d] cells to keep
        (None: all); size: runs per rollout call (>= 1); ahead: the runs planned but no initial state made and no
        chunk function (``batch`` and ``fn`` None: a dry run's figures, no rollout)."""
        built = build_ahead(camp)[0] if ahead else build(camp)
        sim, dz, b = built.sim, built.design, built.batch
        logs_per_chunk, n_chunks = built.logs_per_chunk, built.n_chunks
        sel = selected_runs(dz.m, dz.mu, dz.d, cells)
        self.camp, self.sim, self.n, self.n_chunks = camp, sim, len(sel), n_chunks
        self.m, self.mu, self.d, self.rep, self.seeds = dz.m[sel], dz.mu[sel], dz.d[sel], dz.rep[sel], dz.seed[sel]
        self.chunk_s = chunk_seconds(built)
        self.seconds = n_chunks * self.chunk_s
        self.size = int(size)
        self.sel = np.asarray(sel)
        self.spread = choose(sim.robot.backend)  # every sub-batch over every device (wbc_jax.rollout.spread)
        self.batch = self.fn = None
        if not ahead:  # every sub-batch has `size` runs taken from b: Warp's contact list sized for them, not b's
            self.batch = with_contact_list(b, self.size)
            self.fn = chunk_fn(sim, b.in_axes, logs_per_chunk, self.spread.mesh, self.batch.state_axes)
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
            (res, states): ``wbc_jax.metrics.paper.finalize``'s per-run dict at chunk c1, every array (C, n), the
            same in every process; the runs' states at chunk c1 (C n runs, candidate-major; a device pytree, or
            the host copy with several processes).
        """
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
            sub = take_runs(b, rows, state=None if states is None else take(states, jnp.asarray(idx), b.state_axes),
                            gains=jax.tree_util.tree_map(jnp.asarray, take(gains, cand[idx])))
            sub = self.spread.place(sub)
            state, logs = sub.state, None
            for _ in range(c0, c1):
                state, logs = self.fn(sub.model, state, sub.plan, sub.om, sub.gains, sub.push, sub.mu_ground)
                state = jax.block_until_ready(state)
                self.calls += 1
                if bar is not None:
                    bar.update(real * self.chunk_s)
            p_goal = self.sim.controller.final_input(logs)
            if self.spread.mode != "one":  # every process: the whole sub-batch on the host (one collective)
                state, p_goal = self.spread.gather((state, p_goal), self.size, (b.state_axes, 0))
            finals.append(final_results(self.sim, state, p_goal, np.tile(self.mu, C)[idx], n=real))
            outs.append(take(state, np.arange(real), b.state_axes))
        res = {k: np.concatenate([f[k] for f in finals]).reshape(C, self.n) for k in finals[0]}
        return res, concat(outs, b.state_axes)


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


def candidate(res: dict, i) -> dict:
    """Entry ``i`` (a candidate, or an index array of them) of every field of :meth:`Evaluator.rollout`'s or
    :func:`score`'s dict."""
    return {k: v[i] for k, v in res.items()}


def rank_keys(sc: dict) -> list[tuple]:
    """Every candidate's ranking key (:func:`wbc_jax.studies.tune_search.rank_key`) of :func:`score`'s dict."""
    return [rank_key(sc["feasible"][i], sc["violation"][i], sc["objective"][i]) for i in range(len(sc["feasible"]))]


def per_run_objective(res: dict, mu: np.ndarray, obj: dict) -> np.ndarray:
    """Per-run objective J_i = w_R R_i / atan(mu_i)^2 + w_S S_i / s_ref - w_T T_i [mm] (any run, successful or
    not; each (C, n) -> (C, n)). Its mean over the successful runs is :func:`score`'s objective."""
    return (obj["w_R"] * np.asarray(res["R"], float) / np.arctan(mu)[None] ** 2
            + obj["w_S"] * np.asarray(res["S"], float) / obj["s_ref"] - obj["w_T"] * np.asarray(res["T"], float) * 1e3)
