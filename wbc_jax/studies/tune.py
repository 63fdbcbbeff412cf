"""``wbc-jax tune``: batched search over the transport controller's gains.

A **candidate** is a :class:`~wbc_jax.control.transport.TransportGains` whose tuned leaves are the default gains
times a multiplier; the search works on x = ln(multiplier), one coordinate per tuned leaf (a vector leaf such as
``kp_com`` (3,) is scaled as a whole). Leaves that are not tuned keep their *start* value (default x the spec's
start scale). Every round evaluates C candidates on n runs each (the chosen factor cells x reps of a campaign
spec); their C n runs go through one compiled chunk function in sub-batches of one fixed size
(:mod:`wbc_jax.studies.tune_eval`), so no round, rung or confirmation compiles again (the manifest records it).

Methods (``tune.method``, :mod:`wbc_jax.studies.tune_search`): ``grid``, ``random``, ``cem`` (cross-entropy method)
and ``halving`` (successive halving over candidates x simulated time: the survivors of each rung continue their
runs to the next, longer horizon). Round 0 slot 0 is always the start.

**Objective** (``[objective]``), per candidate over its successful runs (cells x reps):

    J = w_R mean(R / atan(mu)^2) + w_S mean(S / s_ref) - w_T mean(T) [mm]

R / atan(mu)^2 is R as a fraction of its maximum (see ``wbc_jax.metrics.paper``), in [0, 1] for every friction
level; S / s_ref (s_ref [s^2/m]) puts S on the same O(1) scale. **Constraints**: success rate >= ``min_success``
and mean T <= ``t_max_mm`` (0: no bound); violation = (min_success - success rate)+ + ((T - t_max) / t_max)+ (the
T term is 1 when no run succeeded); on the obstacle course a success also means no body contact with the blocks
or the wall (``wbc_jax.metrics.paper``). **Ranking**: longer simulated horizon first (successive halving), then
feasible candidates by J descending, then infeasible ones by violation ascending.

**Confirmation and comparison**: after the search the default gains and the ``confirm.top`` best candidates
(full horizon, best first) run on the ``[confirm]`` campaign (e.g. the full paper campaign; without one: the
default gains and the best candidate on the tuning runs). ``best_gains.toml`` holds the candidate that ranks first
there; ``report.md`` compares it with the default gains run by run on the same seeds (paired tests named there,
:mod:`wbc_jax.studies.tune_report`).

Outputs (DIR, written atomically): ``leaderboard.csv`` (one row per candidate: round, slot, kind, sim_s,
multipliers ``<leaf>_x`` and values ``<leaf>``, R, R_norm, S, S_norm, T_mm, success_rate, objective, violation,
feasible, rank, pareto), ``best_gains.toml`` (for ``wbc-jax campaign --gains``), ``best_runs.csv`` (per run: the
start and the search's best on the tuning runs), ``confirm_runs.csv`` (per run: default and confirmed candidates),
``report.md``, ``objective_per_round.png``, ``pareto.png`` and ``manifest.json``.

Spec format: :mod:`wbc_jax.studies.tune_spec`. With no ``--spec``: ``sweeps/gain_tuning_course.toml`` (the obstacle
course) when an accelerator is present, else ``sweeps/gain_tuning_cpu.toml`` (minutes on a 2-core CPU).

Physics backend: the campaign specs' ``campaign.backend`` (``--backend`` replaces it in both the tuning and the
confirmation campaign); the manifest records the resolved one. Several processes (``jax.distributed`` joined by the
command, :mod:`wbc_jax.rollout.distributed`, docs/cluster.md): every process runs the same search on the same gathered
results (the search is deterministic), each sub-batch spread over every device of every process; only process 0
checks and writes DIR and prints the progress, the others write nothing.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from wbc_jax.rollout.runs import take
from wbc_jax.studies.tune_eval import Evaluator, score
from wbc_jax.studies.tune_report import (
    SUMMARY,
    leaderboard,
    make_rows,
    paired_comparison,
    report_md,
    row_key,
    runs_table,
)
from wbc_jax.studies.tune_search import (
    CEMSearch,
    HalvingSearch,
    Space,
    halving_cost,
    halving_schedule,
    make_search,
    rank_key,
)
from wbc_jax.studies.tune_spec import CPU_BATCH, TuneSpec, default_tune_spec_path, load_tune_spec


def _keys(sc: dict) -> list:
    return [rank_key(sc["feasible"][i], sc["violation"][i], sc["objective"][i]) for i in range(len(sc["feasible"]))]


def _pick(res: dict, i) -> dict:
    return {k: v[i] for k, v in res.items()}


def _bracket(ev: Evaluator, search: HalvingSearch, x: np.ndarray, obj: dict, bar):
    """One successive-halving bracket over the candidates x (C, k). Returns (per candidate: (sc row dict,
    sim_s, per-run dict) of its last rung, the full-horizon candidates' indices and keys)."""
    import jax.numpy as jnp

    alive, horizons = halving_schedule(len(x), search.eta, search.rungs, ev.n_chunks)
    idx, states, h0, last, keys = np.arange(len(x)), None, 0, {}, None
    for a, h in zip(alive, horizons):
        if keys is not None:  # keep the best a of the previous rung, continue their runs
            keep = HalvingSearch.survivors(keys, a)
            states = take(states, jnp.asarray((keep[:, None] * ev.n + np.arange(ev.n)[None]).ravel()),
                          ev.batch.state_axes)
            idx = idx[keep]
        res, states = ev.rollout(search.space.gains(x[idx]), (h0, h), states, bar)
        sc = score(res, ev.mu, obj)
        keys = _keys(sc)
        for j, c in enumerate(idx):
            last[int(c)] = (_pick(sc, j), h * ev.chunk_s, _pick(res, j))
        h0 = h
    return last, idx, keys


def _plan(spec: TuneSpec, search, ev: Evaluator, evc: Evaluator | None) -> float:
    """Simulated run-seconds of the whole tuning (search + confirmation): the progress bar's total."""
    C, t = search.C, spec.tune
    if t["method"] == "halving":
        work = search.rounds * halving_cost(C, search.eta, search.rungs, ev.n_chunks) * ev.n * ev.chunk_s
    else:
        work = search.rounds * C * ev.n * ev.seconds
    if evc is not None:
        return work + (1 + spec.confirm["top"]) * evc.n * evc.seconds
    return work + 2 * ev.n * ev.seconds


def _batch_size(spec: TuneSpec, runs: int) -> int:
    """Runs per rollout call: ``tune.batch``, or all of a round's runs on an accelerator, or CPU_BATCH on a CPU
    (see :mod:`wbc_jax.studies.tune_spec`: jaxlib's batched LAPACK kernels can deadlock the CPU thread pool)."""
    from wbc_jax.campaign.runner import has_accelerator

    if spec.tune["batch"] > 0:
        return spec.tune["batch"]
    return max(1, runs) if has_accelerator() else CPU_BATCH


def _with_backend(spec: TuneSpec, backend: str | None) -> TuneSpec:
    """``spec`` with ``campaign.backend`` of its tuning and confirmation campaigns replaced (``--backend``),
    each checked against its sensing setting; unchanged for None."""
    import dataclasses

    from wbc_jax.campaign.runner import sensing_of, with_backend

    if backend is not None:
        cc = spec.confirm_campaign
        spec = dataclasses.replace(spec, campaign=with_backend(spec.campaign, backend),
                                   confirm_campaign=None if cc is None else with_backend(cc, backend))
    for camp in (spec.campaign, spec.confirm_campaign):
        if camp is not None:
            sensing_of(camp)  # a bad backend / sensing combination fails before anything is written
    return spec


def run_tune(spec_path: str | None, out: str, candidates: int | None = None, rounds: int | None = None,
             batch: int | None = None, progress: bool = True, force: bool = False,
             backend: str | None = None) -> dict | None:
    """Run a gain search and write DIR (module docstring). Returns the manifest; None in a process other than
    process 0 of a multi-process run (it writes nothing).

    Args:
        spec_path: tuning spec (None: :func:`wbc_jax.studies.tune_spec.default_tune_spec_path` for this machine).
        out: output directory (replaced atomically).
        candidates, rounds, batch: override the spec's ``tune.candidates`` / ``tune.rounds`` / ``tune.batch``.
        progress: show one progress bar over the whole tuning with the time left (stderr).
        force: replace DIR when it holds an earlier tune.
        backend: physics backend ("auto", "jax", "warp") instead of the campaign specs' ``campaign.backend``.
    """
    import jax

    from wbc_jax.campaign import runner as campaign
    from wbc_jax.campaign.gains import gains_toml
    from wbc_jax.campaign.runner import backend_of, has_accelerator, sensing_of
    from wbc_jax.errors import WbcJaxError
    from wbc_jax.io_utils import atomic_dir, check_out_dir, write_json_atomic
    from wbc_jax.rollout import distributed

    t_start = time.perf_counter()
    path = spec_path if spec_path is not None else default_tune_spec_path(has_accelerator())
    spec = _with_backend(load_tune_spec(path).with_overrides(candidates, rounds, batch), backend)
    writer = distributed.is_writer()
    problem = None
    try:  # process 0's output folder (the others write nothing)
        if writer:
            check_out_dir(out, "wbc-jax tune", force=force, inputs=[spec.path])  # force: replace an earlier tune's
    except WbcJaxError as e:
        problem = e
    distributed.agree(problem)
    say = print if writer else (lambda *a, **k: None)
    space = Space(spec.leaves, spec.start)
    search = make_search(spec, space)
    C, R, t, obj = search.C, search.rounds, spec.tune, spec.objective
    ev = Evaluator(spec.campaign, spec.cells, 1)
    evc = Evaluator(spec.confirm_campaign, None, 1) if spec.confirm_campaign is not None else None
    # one shape for the search and the confirmation (one compilation when both use the same campaign settings)
    ev.size = _batch_size(spec, max(C * ev.n, (1 + spec.confirm["top"]) * evc.n if evc else 2 * ev.n))
    if evc is not None:
        evc.size = ev.size
    total = _plan(spec, search, ev, evc)
    steps_per_s = 1.0 / ev.sim.dt_physics
    say(f"tune {t['name']!r} ({spec.path}): {t['method']}, {R} rounds x {C} candidates, {space.k} tuned leaves; "
        f"each candidate on {ev.n} runs ({ev.n // t['reps']} cells x {t['reps']} reps of {spec.campaign.path}, "
        f"{ev.seconds:.2f} s simulated), {ev.size} runs per rollout call, "
        f"{spec.campaign.campaign['qp_iters']} ADMM iterations, {backend_of(spec.campaign)} physics, device "
        f"{jax.devices()[0].device_kind}"
        + ev.spread.describe()
        + f"; {total:,.0f} run-seconds to simulate in all"
        + (f" (confirmation: {1 + spec.confirm['top']} gain sets x {evc.n} runs of {evc.camp.path})" if evc else ""),
        flush=True)
    if ev.spread.note:
        say(ev.spread.note, flush=True)
    bar = None
    if progress and writer:
        from tqdm import tqdm

        bar = tqdm(total=round(total, 3), unit="run-s", file=sys.stderr,
                   bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} run-s [{elapsed}<{remaining}{postfix}]")

    rows, walls, variants, per_run, best = [], [], [ev.compiled_variants()], {}, None
    for r in range(R):
        x, kinds = search.ask(r)
        t0 = time.perf_counter()
        if isinstance(search, HalvingSearch):
            last, full, fkeys = _bracket(ev, search, x, obj, bar)
            search.tell(x[full], fkeys)
            new = []
            for c in sorted(last):
                sc1, sim_s, res1 = last[c]
                new += make_rows(r, x[c:c + 1], [kinds[c]], space, {k: np.atleast_1d(v) for k, v in sc1.items()},
                                 sim_s, slots=[c])
            results = {row["slot"]: last[row["slot"]][2] for row in new}
        else:
            res, _ = ev.rollout(space.gains(x), bar=bar)
            sc = score(res, ev.mu, obj)
            search.tell(x, _keys(sc))
            new = make_rows(r, x, kinds, space, sc, ev.seconds)
            results = {row["slot"]: _pick(res, row["slot"]) for row in new}
        walls.append(time.perf_counter() - t0)
        variants.append(ev.compiled_variants())
        for row in new:
            if r == 0 and row["slot"] == 0:
                per_run["start"] = results[0]
            if best is None or row_key(row) > row_key(best[0]):
                best = (row, x[row["slot"]].copy())
                per_run["best"] = results[row["slot"]]
        rows += new
        full_rows = [w for w in new if w["sim_s"] >= ev.seconds - 1e-9]
        rb = max(full_rows, key=row_key)
        line = (f"round {r + 1}/{R}: {walls[-1]:.1f} s, feasible {sum(w['feasible'] for w in full_rows)}/"
                f"{len(full_rows)} at the full horizon; round best J {rb['objective']:.4f} (success "
                f"{rb['success_rate']:.0%}, T {rb['T_mm']:.2f} mm); best so far J {best[0]['objective']:.4f} "
                f"({'feasible' if best[0]['feasible'] else 'infeasible'})")
        (bar.write if bar is not None else say)(line)

    df = leaderboard(rows)
    start, top = rows[0], best[0]
    # ---- confirmation / comparison: default gains and the top candidates on the same runs (paired)
    full = df[df.sim_s >= df.sim_s.max() - 1e-9].sort_values("rank")
    n_top = spec.confirm["top"] if evc is not None else 1
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
    ce = evc if evc is not None else ev
    t0 = time.perf_counter()
    cres, _ = ce.rollout(space.gains(None, mult), bar=bar)
    confirm_wall = time.perf_counter() - t0
    csc = score(cres, ce.mu, obj)
    ckeys = _keys(csc)
    win = 1 + max(range(len(picks)), key=lambda j: ckeys[1 + j])  # best confirmed candidate (0 = defaults)
    chosen = df.loc[picks[win - 1]]
    comparison = paired_comparison(_pick(cres, 0), _pick(cres, win), ce.mu, obj, spec.confirm["alpha"])
    if bar is not None:
        bar.close()
    best_gains = jax.tree_util.tree_map(lambda v: v[0], space.gains(xs[win - 1:win]))
    round_s = float(np.median(walls[1:] if len(walls) > 1 else walls))
    new_compiles = (variants[-1] - variants[1]) if None not in (variants[1], variants[-1]) else None
    if new_compiles:
        say(f"warning: the chunk function compiled {new_compiles} more time(s) after round 1", flush=True)
    sim_steps = ev.calls * ev.size * ev.chunk_s * steps_per_s
    confirmed = [dict(label="default", **{k: float(v[0]) for k, v in csc.items()})] + [
        dict(label=f"rank {int(df.loc[i, 'rank'])}", **{k: float(v[1 + j]) for k, v in csc.items()})
        for j, i in enumerate(picks)]
    manifest = dict(
        command="wbc-jax tune", spec_path=spec.path, spec_hash=spec.hash, spec_file_sha256=spec.text_sha256,
        spec=spec.canonical(), campaign_spec_path=spec.campaign.path, method=t["method"], candidates_per_round=C,
        rounds=R, candidates_evaluated=len(rows), tuned_leaves=list(space.names), runs_per_candidate=ev.n,
        runs_per_call=ev.size, rollout_calls=ev.calls, batch_runs=C * ev.n,
        cells=[[float(a), float(b), float(c)] for a, b, c in zip(ev.m, ev.mu, ev.d)][::t["reps"]],
        seeds=[int(s) for s in ev.seeds], search_seed=t["seed"], simulated_s=ev.seconds, chunk_s=ev.chunk_s,
        control_dt_s=ev.sim.dt_control, versions=campaign._versions(), git_commit=campaign._git_commit(),
        device=dict(backend=jax.default_backend(), kind=jax.devices()[0].device_kind, count=jax.device_count(),
                    host=platform.node(), cpu_count=os.cpu_count()),
        round_wall_s=walls, first_round_s=walls[0], steady_round_s=round_s, candidates_per_s=C / round_s,
        env_steps_per_s=sim_steps / max(sum(walls), 1e-9), compiled_variants_per_round=variants,
        new_compilations_after_round_1=new_compiles, planned_run_seconds=total,
        compiled_variants_after_confirmation=ce.compiled_variants(),
        start={k: start[k] for k in SUMMARY}, best={k: top[k] for k in SUMMARY},
        best_multipliers={n: top[f"{n}_x"] for n in space.names},
        improvement={k: top[k] - start[k] for k in ("objective", "R", "R_norm", "S", "T_mm", "success_rate")},
        n_feasible=int(df.feasible.sum()), n_pareto=int(df.pareto.sum()), objective=obj,
        confirmation=dict(campaign=ce.camp.path, runs=ce.n, seeds=[int(s) for s in ce.seeds], wall_s=confirm_wall,
                          gain_sets=confirmed, chosen_rank=int(chosen["rank"]),
                          chosen_multipliers={n: float(chosen[f"{n}_x"]) for n in space.names}),
        comparison=comparison, physics_backend=backend_of(spec.campaign), sensing=sensing_of(spec.campaign),
        layout=dict(distributed.layout_record(), spread=ev.spread.mode))
    if isinstance(search, CEMSearch):
        manifest["cem_history"] = search.history
    info = dict(source="wbc-jax tune", spec=spec.path, spec_hash=spec.hash,
                qp_iters=spec.campaign.campaign["qp_iters"], search_rank=int(chosen["rank"]),
                confirmed_on=ce.camp.path, **{k: chosen[k] for k in ("round", "objective", "feasible", "R", "S",
                                                                      "T_mm", "success_rate")},
                **{f"{n}_x": float(chosen[f"{n}_x"]) for n in space.names})
    wall_tune = time.perf_counter() - t_start
    if not writer:
        print(f"process {jax.process_index()}: done; process 0 writes {out}", flush=True)
        return None
    where = f"{ce.camp.path}: {ce.n} runs, seeds of its design"
    lines = [f"Spec `{spec.path}` ({t['method']}, {R} rounds x {C} candidates on {ev.n} runs of "
             f"`{spec.campaign.path}`, {ev.seconds:.2f} s simulated each); {len(rows)} candidates; wall "
             f"{wall_tune:.0f} s on {jax.devices()[0].device_kind} ({ev.size} runs per rollout call).", "",
             "Confirmed gain sets (on the comparison runs): " + "; ".join(
                 f"{g['label']}: J {g['objective']:.4f}, success {g['success_rate']:.0%}, T {g['T_mm']:.2f} mm"
                 for g in confirmed) + f". best_gains.toml = search rank {int(chosen['rank'])}.",
             "", f"Replay: `wbc-jax campaign --spec {ce.camp.path} --gains {Path(out) / 'best_gains.toml'}`."]
    with atomic_dir(Path(out).absolute()) as tmp:
        df.to_csv(tmp / "leaderboard.csv", index=False)
        runs_table(ev, per_run, obj).to_csv(tmp / "best_runs.csv", index=False)
        runs_table(ce, {"default": _pick(cres, 0), **{g["label"]: _pick(cres, 1 + j)
                                                      for j, g in enumerate(confirmed[1:])}}, obj) \
            .to_csv(tmp / "confirm_runs.csv", index=False)
        (tmp / "best_gains.toml").write_text(gains_toml(
            best_gains, f"wbc-jax tune: best gains of {spec.path} (search rank {int(chosen['rank'])} of {len(rows)}, "
                        f"best of {len(picks)} confirmed on {ce.camp.path})\n"
                        "use: wbc-jax campaign --gains best_gains.toml", info))
        (tmp / "report.md").write_text(report_md(f"wbc-jax tune: {t['name']}", lines, comparison, where,
                                                 spec.confirm["alpha"]))
        from wbc_jax.studies.tune_report import figures

        for name, png in figures(df, int(df["rank"].to_numpy().argmin())).items():
            (tmp / name).write_bytes(png)
        manifest["wall_s_total"] = time.perf_counter() - t_start
        write_json_atomic(tmp / "manifest.json", manifest)
    print(f"{len(rows)} candidates in {manifest['wall_s_total']:.1f} s ({ev.calls} rollout calls of {ev.size} runs); "
          f"feasible {manifest['n_feasible']}, Pareto front {manifest['n_pareto']}", flush=True)
    print(f"start: J {start['objective']:.4f}, success {start['success_rate']:.0%}; search best (round "
          f"{top['round']}): J {top['objective']:.4f}, success {top['success_rate']:.0%}, T {top['T_mm']:.2f} mm",
          flush=True)
    for c in comparison:
        print(f"  {c['metric']}: default {c['default']:.4g}, tuned {c['tuned']:.4g} ({c['test']}, p = {c['p']:.3g})",
              flush=True)
    print(f"written to {out}", flush=True)
    return manifest
