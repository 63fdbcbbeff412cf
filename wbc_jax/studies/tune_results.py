"""What a gain search leaves (``wbc-jax tune``, :mod:`wbc_jax.studies.tune`): the rounds' log, the confirmation
of the best candidates next to the default gains, the manifest and the output folder."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.campaign.build import backend_of, sensing_of
from wbc_jax.campaign.gains import gains_toml
from wbc_jax.campaign.manifest import git_commit, versions
from wbc_jax.io_utils import atomic_dir, write_json_atomic
from wbc_jax.rollout import distributed
from wbc_jax.studies.tune_eval import Evaluator, candidate, rank_keys, score
from wbc_jax.studies.tune_report import SUMMARY, figures, paired_comparison, report_md, runs_table
from wbc_jax.studies.tune_search import CEMSearch, Space
from wbc_jax.studies.tune_spec import TuneSpec


class Tuning(NamedTuple):
    """A tuning ready to run: the spec, its search and the evaluators of the search and the confirmation."""

    spec: TuneSpec
    space: Space
    search: object  # a wbc_jax.studies.tune_search search: ask(r) -> (x, kinds), tell(x, keys)
    ev: Evaluator  # the tuning runs
    evc: Evaluator | None  # the confirmation campaign's runs (None: confirm on the tuning runs)
    total: float  # simulated run-seconds of the whole tuning (the progress bar's total)
    writer: bool  # this process writes DIR and prints


class SearchLog(NamedTuple):
    """What the search's rounds leave."""

    rows: list[dict]  # leaderboard rows of every candidate, in round order
    walls: list[float]  # [s] wall time per round
    variants: list  # compiled chunk-function variants before the first round and after each
    per_run: dict  # per-run results of the start ("start") and of the best candidate so far ("best")
    best: tuple  # (row, x (k,)) of the best candidate so far


class Confirmation(NamedTuple):
    """The default gains and the best distinct full-horizon candidates run again on the comparison runs."""

    picks: list[int]  # leaderboard indices of the confirmed candidates, search rank order
    xs: np.ndarray  # (len(picks), k) their ln multipliers
    evaluator: Evaluator  # the comparison runs
    results: dict  # per-run results of the gain sets (defaults first), (1 + len(picks)) * n runs
    win: int  # gain-set index of the confirmed best (1 .. len(picks); 0 would be the defaults)
    chosen: object  # its leaderboard row (pandas Series)
    comparison: list[dict]  # paired tests, defaults vs the confirmed best
    wall_s: float  # [s] wall time of the confirmation rollout
    gain_sets: list[dict]  # per gain set: label and score


def confirm(tuning: Tuning, df, bar) -> Confirmation:
    """Confirm the top ``confirm.top`` distinct candidates (1 without a confirmation campaign) next to the
    defaults on the same runs; the best of them by rank key wins."""
    space, obj = tuning.space, tuning.spec.objective
    full = df[df.sim_s >= df.sim_s.max() - 1e-9].sort_values("rank")
    n_top = tuning.spec.confirm["top"] if tuning.evc is not None else 1
    picks, seen = [], set()
    for rw in full.itertuples():
        key = tuple(round(getattr(rw, f"{n}_x"), 12) for n in space.names)
        if key not in seen:
            seen.add(key)
            picks.append(int(rw.Index))
        if len(picks) == n_top:
            break
    xs = np.stack([np.log([df.loc[i, f"{n}_x"] for n in space.names]) for i in picks])
    mult = {k: np.concatenate([[1.0], v]) for k, v in space.multipliers(xs).items()}
    ce = tuning.evc if tuning.evc is not None else tuning.ev
    t0 = time.perf_counter()
    cres, _ = ce.rollout(space.gains(None, mult), bar=bar)
    confirm_wall = time.perf_counter() - t0
    csc = score(cres, ce.mu, obj)
    ckeys = rank_keys(csc)
    win = 1 + max(range(len(picks)), key=lambda j: ckeys[1 + j])  # best confirmed candidate (0 = defaults)
    comparison = paired_comparison(candidate(cres, 0), candidate(cres, win), ce.mu, obj, tuning.spec.confirm["alpha"])
    gain_sets = [dict(label="default", **{k: float(v[0]) for k, v in csc.items()})] + [
        dict(label=f"rank {int(df.loc[i, 'rank'])}", **{k: float(v[1 + j]) for k, v in csc.items()})
        for j, i in enumerate(picks)]
    return Confirmation(picks, xs, ce, cres, win, df.loc[picks[win - 1]], comparison, confirm_wall, gain_sets)


def manifest(tuning: Tuning, log: SearchLog, df, conf: Confirmation, new_compiles) -> dict:
    """``manifest.json``'s record (without ``wall_s_total``, set when the folder is written)."""
    spec, space, ev, search, t = tuning.spec, tuning.space, tuning.ev, tuning.search, tuning.spec.tune
    C, walls, ce, chosen = search.C, log.walls, conf.evaluator, conf.chosen
    start, top = log.rows[0], log.best[0]
    round_s = float(np.median(walls[1:] if len(walls) > 1 else walls))
    sim_steps = ev.calls * ev.size * ev.chunk_s * (1.0 / ev.sim.dt_physics)
    record = dict(
        command="wbc-jax tune", spec_path=spec.path, spec_hash=spec.hash, spec_file_sha256=spec.text_sha256,
        spec=spec.canonical(), campaign_spec_path=spec.campaign.path, method=t["method"], candidates_per_round=C,
        rounds=search.rounds, candidates_evaluated=len(log.rows), tuned_leaves=list(space.names),
        runs_per_candidate=ev.n, runs_per_call=ev.size, rollout_calls=ev.calls, batch_runs=C * ev.n,
        cells=[[float(a), float(b), float(c)] for a, b, c in zip(ev.m, ev.mu, ev.d)][::t["reps"]],
        seeds=[int(s) for s in ev.seeds], search_seed=t["seed"], simulated_s=ev.seconds, chunk_s=ev.chunk_s,
        control_dt_s=ev.sim.dt_control, versions=versions(), git_commit=git_commit(),
        device=dict(backend=jax.default_backend(), kind=jax.devices()[0].device_kind, count=jax.device_count(),
                    host=platform.node(), cpu_count=os.cpu_count()),
        round_wall_s=walls, first_round_s=walls[0], steady_round_s=round_s, candidates_per_s=C / round_s,
        env_steps_per_s=sim_steps / max(sum(walls), 1e-9), compiled_variants_per_round=log.variants,
        new_compilations_after_round_1=new_compiles, planned_run_seconds=tuning.total,
        compiled_variants_after_confirmation=ce.compiled_variants(),
        start={k: start[k] for k in SUMMARY}, best={k: top[k] for k in SUMMARY},
        best_multipliers={n: top[f"{n}_x"] for n in space.names},
        improvement={k: top[k] - start[k] for k in ("objective", "R", "R_norm", "S", "T_mm", "success_rate")},
        n_feasible=int(df.feasible.sum()), n_pareto=int(df.pareto.sum()), objective=spec.objective,
        confirmation=dict(campaign=ce.camp.path, runs=ce.n, seeds=[int(s) for s in ce.seeds], wall_s=conf.wall_s,
                          gain_sets=conf.gain_sets, chosen_rank=int(chosen["rank"]),
                          chosen_multipliers={n: float(chosen[f"{n}_x"]) for n in space.names}),
        comparison=conf.comparison, physics_backend=backend_of(spec.campaign), sensing=sensing_of(spec.campaign),
        layout=dict(distributed.layout_record(), spread=ev.spread.mode))
    if isinstance(search, CEMSearch):
        record["cem_history"] = search.history
    return record


def _gains_info(tuning: Tuning, conf: Confirmation) -> dict:
    """``best_gains.toml``'s ``[info]``: where the gains come from and how they scored."""
    spec, chosen = tuning.spec, conf.chosen
    return dict(source="wbc-jax tune", spec=spec.path, spec_hash=spec.hash,
                qp_iters=spec.campaign.campaign["qp_iters"], search_rank=int(chosen["rank"]),
                confirmed_on=conf.evaluator.camp.path,
                **{k: chosen[k] for k in ("round", "objective", "feasible", "R", "S", "T_mm", "success_rate")},
                **{f"{n}_x": float(chosen[f"{n}_x"]) for n in tuning.space.names})


def gain_set_runs(conf: Confirmation) -> dict:
    """Per gain set of the confirmation ("default", then the confirmed candidates' labels), its per-run results."""
    return {"default": candidate(conf.results, 0),
            **{g["label"]: candidate(conf.results, 1 + j) for j, g in enumerate(conf.gain_sets[1:])}}


def failure_summary(per_set: dict) -> str:
    """One line on the failed runs of each gain set: per set (label -> per-run dict with ``success`` and
    ``fail_reason``, :func:`wbc_jax.metrics.paper.finalize`) how many of its runs failed and why, e.g. "failed runs:
    default 2 of 270 (body contact 2), rank 1 none"."""
    parts = []
    for label, runs in per_set.items():
        ok = np.asarray(runs["success"], bool)
        reasons, counts = np.unique(np.asarray(runs["fail_reason"])[~ok].astype(str), return_counts=True)
        why = ", ".join(f"{r or 'unnamed'} {c}" for r, c in sorted(zip(reasons, counts), key=lambda x: -x[1]))
        parts.append(f"{label} {(~ok).sum()} of {ok.size} ({why})" if (~ok).any() else f"{label} none")
    return "failed runs: " + ", ".join(parts)


def write_outputs(out: str, tuning: Tuning, log: SearchLog, df, conf: Confirmation, record: dict, t_start: float,
                  wall_tune: float) -> None:
    """DIR, atomically: leaderboard, per-run tables, best gains, report, figures and the manifest."""
    spec, ev, ce, t, obj = tuning.spec, tuning.ev, conf.evaluator, tuning.spec.tune, tuning.spec.objective
    chosen, rows = conf.chosen, log.rows
    best_gains = jax.tree_util.tree_map(lambda v: v[0], tuning.space.gains(conf.xs[conf.win - 1:conf.win]))
    where = f"{ce.camp.path}: {ce.n} runs, seeds of its design"
    search = tuning.search
    lines = [f"Spec `{spec.path}` ({t['method']}, {search.rounds} rounds x {search.C} candidates on {ev.n} "
             f"runs of `{spec.campaign.path}`, {ev.seconds:.2f} s simulated each); {len(rows)} candidates; wall "
             f"{wall_tune:.0f} s on {jax.devices()[0].device_kind} ({ev.size} runs per rollout call).", "",
             "Confirmed gain sets (on the comparison runs): " + "; ".join(
                 f"{g['label']}: J {g['objective']:.4f}, success {g['success_rate']:.0%}, T {g['T_mm']:.2f} mm"
                 for g in conf.gain_sets) + f". best_gains.toml = search rank {int(chosen['rank'])}.",
             "", failure_summary(gain_set_runs(conf)) + ".",
             "", f"Replay: `wbc-jax campaign --spec {ce.camp.path} --gains {Path(out) / 'best_gains.toml'}`."]
    with atomic_dir(Path(out).absolute()) as tmp:
        df.to_csv(tmp / "leaderboard.csv", index=False)
        runs_table(ev, log.per_run, obj).to_csv(tmp / "best_runs.csv", index=False)
        runs_table(ce, gain_set_runs(conf), obj).to_csv(tmp / "confirm_runs.csv", index=False)
        (tmp / "best_gains.toml").write_text(gains_toml(
            best_gains, f"wbc-jax tune: best gains of {spec.path} (search rank {int(chosen['rank'])} of {len(rows)}, "
                        f"best of {len(conf.picks)} confirmed on {ce.camp.path})\n"
                        "use: wbc-jax campaign --gains best_gains.toml", _gains_info(tuning, conf)))
        (tmp / "report.md").write_text(report_md(f"wbc-jax tune: {t['name']}", lines, conf.comparison, where,
                                                 spec.confirm["alpha"]))
        for name, png in figures(df, int(df["rank"].to_numpy().argmin())).items():
            (tmp / name).write_bytes(png)
        record["wall_s_total"] = time.perf_counter() - t_start
        write_json_atomic(tmp / "manifest.json", record)


def print_summary(out: str, tuning: Tuning, log: SearchLog, record: dict, conf: Confirmation) -> None:
    """The closing lines: candidates, wall time, start vs search best, the paired comparison, the confirmation's
    failed runs and why."""
    start, top = log.rows[0], log.best[0]
    print(f"{len(log.rows)} candidates in {record['wall_s_total']:.1f} s ({tuning.ev.calls} rollout calls of "
          f"{tuning.ev.size} runs); feasible {record['n_feasible']}, Pareto front {record['n_pareto']}", flush=True)
    print(f"start: J {start['objective']:.4f}, success {start['success_rate']:.0%}; search best (round "
          f"{top['round']}): J {top['objective']:.4f}, success {top['success_rate']:.0%}, T {top['T_mm']:.2f} mm",
          flush=True)
    for c in conf.comparison:
        print(f"  {c['metric']}: default {c['default']:.4g}, tuned {c['tuned']:.4g} ({c['test']}, p = {c['p']:.3g})",
              flush=True)
    print(f"confirmation ({conf.evaluator.camp.path}), {failure_summary(gain_set_runs(conf))}", flush=True)
    print(f"written to {out}", flush=True)


