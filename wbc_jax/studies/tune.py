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
course) when an accelerator is present, else ``sweeps/gain_tuning_cpu.toml`` (sized for a CPU).

Physics backend: the campaign specs' ``campaign.backend`` (``--backend`` replaces it in both the tuning and the
confirmation campaign); the manifest records the resolved one. Several processes (``jax.distributed`` joined by the
command, :mod:`wbc_jax.rollout.distributed`, docs/cluster.md): every process runs the same search on the same gathered
results (the search is deterministic), each sub-batch spread over every device of every process; only process 0
checks and writes DIR and prints the progress, the others write nothing.
"""

from __future__ import annotations

import dataclasses
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.campaign.build import backend_of, has_accelerator, sensing_of, with_backend
from wbc_jax.campaign.design import object_levels
from wbc_jax.campaign.dry_run import layout_parts, memory_phrase
from wbc_jax.campaign.size import INPUT_BYTES, memory_need, n_runs_of, own_memories
from wbc_jax.errors import LimitError, WbcJaxError
from wbc_jax.io_utils import check_not_in_use, check_out_dir, output_path
from wbc_jax.rollout import distributed
from wbc_jax.rollout.runs import take
from wbc_jax.rollout.spread import choose
from wbc_jax.studies.tune_eval import Evaluator, candidate, rank_keys, score, selected_runs
from wbc_jax.studies.tune_report import leaderboard, make_rows, row_key
from wbc_jax.studies.tune_results import SearchLog, Tuning, confirm, manifest, print_summary, write_outputs
from wbc_jax.studies.tune_search import HalvingSearch, Space, halving_cost, halving_schedule, make_search
from wbc_jax.studies.tune_spec import CPU_BATCH, TuneSpec, default_tune_spec_path, load_tune_spec


def _bracket(ev: Evaluator, search: HalvingSearch, x: np.ndarray, obj: dict, bar):
    """One successive-halving bracket over the candidates x (C, k). Returns (per candidate: (sc row dict,
    sim_s, per-run dict) of its last rung, the full-horizon candidates' indices and keys)."""
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
        keys = rank_keys(sc)
        for j, c in enumerate(idx):
            last[int(c)] = (candidate(sc, j), h * ev.chunk_s, candidate(res, j))
        h0 = h
    return last, idx, keys


def _work(spec: TuneSpec, search, ev: Evaluator, evc: Evaluator | None) -> tuple[float, float]:
    """Simulated run-seconds of the search and of the confirmation; their sum is the progress bar's total."""
    C, t = search.C, spec.tune
    if t["method"] == "halving":
        work = search.rounds * halving_cost(C, search.eta, search.rungs, ev.n_chunks) * ev.n * ev.chunk_s
    else:
        work = search.rounds * C * ev.n * ev.seconds
    return work, _confirm_runs(spec, ev.n, evc.n if evc else 0) * (evc or ev).seconds


def _confirm_runs(spec: TuneSpec, n: int, n_confirm: int) -> int:
    """Runs of the confirmation, every gain set's: the default gains and ``confirm.top`` candidates on the
    ``[confirm]`` campaign's ``n_confirm`` runs, or (none) the default gains and the best on the ``n`` tuning runs."""
    return (1 + spec.confirm["top"]) * n_confirm if spec.confirm_campaign is not None else 2 * n


def _batch_size(spec: TuneSpec, runs: int) -> int:
    """Runs per rollout call: ``tune.batch``, or all of a round's runs on an accelerator, or CPU_BATCH on a CPU
    (see :mod:`wbc_jax.studies.tune_spec`: jaxlib's batched LAPACK kernels can deadlock the CPU thread pool)."""
    if spec.tune["batch"] > 0:
        return spec.tune["batch"]
    return max(1, runs) if has_accelerator() else CPU_BATCH


def _call_memory(spec: TuneSpec, size: int, parts: int | None = None) -> tuple[float, int | None, object]:
    """(a device's memory estimate [bytes], the available memory [bytes] or None, the campaign Spec it is for) of a
    rollout call of ``size`` runs of the tuning or the confirmation campaign, whichever needs more
    (:func:`wbc_jax.campaign.size.memory_need` over ``parts`` devices; None: those a call is spread over here), plus
    the campaigns' whole design batches the evaluators keep, INPUT_BYTES a run."""
    camps = [c for c in (spec.campaign, spec.confirm_campaign) if c is not None]
    needs = [memory_need(c, parts or choose(backend_of(c)).parts, runs=size) for c in camps]
    kept = sum(n_runs_of(c) for c in camps) * INPUT_BYTES
    k = int(np.argmax([n for n, _ in needs]))
    return needs[k][0] + kept, needs[k][1], camps[k]


def _memory_parts(spec: TuneSpec, layout: tuple) -> int | None:
    """The devices a rollout call's memory is counted over for ``layout`` = (processes, local devices or None): None
    for one process (each campaign's spread here, :func:`_call_memory`), else those of the processes to come
    (``wbc_jax.campaign.dry_run.layout_parts``)."""
    if layout[0] <= 1:
        return None
    physics = backend_of(spec.campaign)
    return layout_parts(choose(physics).parts, physics, *layout)


def _check_memory(spec: TuneSpec, size: int, parts: int | None = None) -> None:
    """Refuse a rollout call of ``size`` runs that would not fit in a device's memory (:func:`_call_memory`), before
    anything is built or compiled.

    Raises:
        LimitError: naming ``tune.batch``, ``--batch`` and the campaign.
    """
    need, avail, camp = _call_memory(spec, size, parts)
    if avail and need > avail:
        auto = " (0: a round's runs at once)" if spec.tune["batch"] == 0 else ""
        raise LimitError(f"{spec.path}: tune.batch{auto}: {size:,} runs per rollout call of {camp.path} need about "
                         f"{need / 2**30:,.1f} GiB, {avail / 2**30:,.1f} GiB available; a smaller tune.batch or "
                         "--batch")


def _with_backend(spec: TuneSpec, backend: str | None) -> TuneSpec:
    """``spec`` with ``campaign.backend`` of its tuning and confirmation campaigns replaced (``--backend``),
    each checked against its sensing setting; unchanged for None."""
    if backend is not None:
        cc = spec.confirm_campaign
        spec = dataclasses.replace(spec, campaign=with_backend(spec.campaign, backend),
                                   confirm_campaign=None if cc is None else with_backend(cc, backend))
    for camp in (spec.campaign, spec.confirm_campaign):
        if camp is not None:
            sensing_of(camp)  # a bad backend / sensing combination fails before anything is written
    return spec


def _say(writer: bool):
    """``print`` in the writing process, a no-op in the others."""
    return print if writer else (lambda *a, **k: None)


def _prepare(spec_path, out, candidates, rounds, batch, force, backend, dry: bool = False,
             layout: tuple = (1, None)) -> Tuning:
    """Load and check the spec, check DIR (process 0), build the search and both evaluators with one batch shape
    (``dry``: the runs planned, no initial state made; ``layout``: (processes, local devices or None) a dry run's
    memory check counts instead of this process's devices)."""
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
    space = Space(spec.leaves, spec.start)
    search = make_search(spec, space)
    # one shape for the search and the confirmation (one compilation when both use the same campaign settings),
    # fixed before the batches are built: Warp's shared contact list is sized for it
    n = len(selected_runs(*object_levels(spec.campaign), spec.cells))  # the runs' levels, not the whole design
    n_confirm = n_runs_of(spec.confirm_campaign) if spec.confirm_campaign is not None else 0
    size = _batch_size(spec, max(search.C * n, _confirm_runs(spec, n, n_confirm)))
    _check_memory(spec, size, _memory_parts(spec, layout))
    ev = Evaluator(spec.campaign, spec.cells, size, ahead=dry)
    evc = Evaluator(spec.confirm_campaign, None, size, ahead=dry) if spec.confirm_campaign is not None else None
    return Tuning(spec, space, search, ev, evc, sum(_work(spec, search, ev, evc)), writer)


def _announce(tuning: Tuning) -> None:
    """One line on what runs where (process 0), and the layout's note."""
    say, spec, ev, evc, t = _say(tuning.writer), tuning.spec, tuning.ev, tuning.evc, tuning.spec.tune
    search = tuning.search
    say(f"tune {t['name']!r} ({spec.path}): {t['method']}, {search.rounds} rounds x {search.C} candidates, "
        f"{tuning.space.k} tuned leaves; each candidate on {ev.n} runs ({ev.n // t['reps']} cells x {t['reps']} reps "
        f"of {spec.campaign.path}, {ev.seconds:.2f} s simulated), {ev.size} runs per rollout call, "
        f"{spec.campaign.campaign['qp_iters']} ADMM iterations, {backend_of(spec.campaign)} physics, device "
        f"{jax.devices()[0].device_kind}"
        + ev.spread.describe()
        + f"; {tuning.total:,.0f} run-seconds to simulate in all"
        + (f" (confirmation: {1 + spec.confirm['top']} gain sets x {evc.n} runs of {evc.camp.path})" if evc else ""),
        flush=True)
    if ev.spread.note:
        say(ev.spread.note, flush=True)


def _progress_bar(tuning: Tuning, progress: bool):
    """One tqdm bar over the whole tuning in run-seconds (stderr), or None."""
    if not (progress and tuning.writer):
        return None
    from tqdm import tqdm

    return tqdm(total=round(tuning.total, 3), unit="run-s", file=sys.stderr,
                bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} run-s [{elapsed}<{remaining}{postfix}]")


def _evaluate_round(tuning: Tuning, r: int, x: np.ndarray, kinds: list, bar):
    """Round ``r``'s candidates ``x`` (C, k) evaluated and told to the search. Returns (leaderboard rows, per-run
    results by slot)."""
    search, ev, obj = tuning.search, tuning.ev, tuning.spec.objective
    if isinstance(search, HalvingSearch):
        last, full, fkeys = _bracket(ev, search, x, obj, bar)
        search.tell(x[full], fkeys)
        new = []
        for c in sorted(last):
            sc1, sim_s, res1 = last[c]
            new += make_rows(r, x[c:c + 1], [kinds[c]], tuning.space, {k: np.atleast_1d(v) for k, v in sc1.items()},
                             sim_s, slots=[c])
        return new, {row["slot"]: last[row["slot"]][2] for row in new}
    res, _ = ev.rollout(tuning.space.gains(x), bar=bar)
    sc = score(res, ev.mu, obj)
    search.tell(x, rank_keys(sc))
    new = make_rows(r, x, kinds, tuning.space, sc, ev.seconds)
    return new, {row["slot"]: candidate(res, row["slot"]) for row in new}


def _search(tuning: Tuning, bar) -> SearchLog:
    """Every round of the search, one progress line per round."""
    ev, R = tuning.ev, tuning.search.rounds
    rows, walls, variants, per_run, best = [], [], [ev.compiled_variants()], {}, None
    for r in range(R):
        x, kinds = tuning.search.ask(r)
        t0 = time.perf_counter()
        new, results = _evaluate_round(tuning, r, x, kinds, bar)
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
        (bar.write if bar is not None else _say(tuning.writer))(line)
    return SearchLog(rows, walls, variants, per_run, best)


def dry_run_tune(spec_path: str | None, out: str, candidates: int | None = None, rounds: int | None = None,
                 batch: int | None = None, force: bool = False, backend: str | None = None, processes: int = 1,
                 local_devices: int | None = None) -> dict:
    """``wbc-jax tune --dry-run``: :func:`run_tune`'s checks (``out`` against a command using it, the spec,
    ``out``'s content, a rollout call's memory) and what it would simulate, printed and returned. The runs are
    planned (no initial state is made; nothing is compiled or simulated); ``out`` is not claimed and nothing is
    written in it. Arguments as :func:`run_tune`'s; ``processes`` (each with ``local_devices`` devices, None: this
    process's): the processes the tune will run as, whose devices the memory check counts; none is joined.

    Returns:
        dict: ``name``, ``spec``, ``method``, ``rounds``, ``candidates``, ``leaves`` (tuned), ``runs_per_candidate``,
        ``runs_per_call``, ``confirm_runs`` (the confirmation's runs of all its gain sets), ``search_run_s``,
        ``confirm_run_s`` (simulated run-seconds), ``physics_steps`` (of both, over the real runs: a last
        sub-batch's padding copies not counted), ``memory_bytes`` (a device's, :func:`_call_memory`),
        ``available_bytes`` (None where unknown), ``parts`` (the devices a call is spread over), ``backend``,
        ``device``, ``out``, ``out_state`` ("new", or "replaced": an earlier tune that ``force`` replaces).

    Raises:
        SpecError, OutputError, LimitError: what the tune would raise before it compiled.
    """
    check_not_in_use(out)  # the command's claim comes first (wbc_jax.cli), then the spec
    tuning = _prepare(spec_path, out, candidates, rounds, batch, force, backend, dry=True,
                      layout=(processes, local_devices))
    spec, ev, evc, search = tuning.spec, tuning.ev, tuning.evc, tuning.search
    search_s, confirm_s = _work(spec, search, ev, evc)
    steps = round(search_s / ev.sim.dt_physics + confirm_s / (evc or ev).sim.dt_physics)
    physics = backend_of(spec.campaign)
    parts = _memory_parts(spec, (processes, local_devices))  # the memory _prepare checked
    need, avail, _ = _call_memory(spec, ev.size, parts)
    parts = parts or ev.spread.parts
    out_p = output_path(out)
    plan = dict(name=spec.tune["name"], spec=str(spec.path), method=spec.tune["method"], rounds=search.rounds,
                candidates=search.C, leaves=list(spec.leaves), runs_per_candidate=ev.n, runs_per_call=ev.size,
                confirm_runs=_confirm_runs(spec, ev.n, evc.n if evc else 0), search_run_s=search_s,
                confirm_run_s=confirm_s, physics_steps=steps, memory_bytes=need, available_bytes=avail, parts=parts,
                backend=physics, device=jax.devices()[0].device_kind, out=str(out),
                out_state="replaced" if out_p.is_dir() and any(out_p.iterdir()) else "new")
    memory = memory_phrase(need, avail, parts if own_memories(parts) > 1 else 1)
    print(f"dry run of tune {plan['name']!r} ({spec.path}): nothing is simulated, nothing written in --out", flush=True)
    _announce(tuning)
    print(f"  search {search_s:,.1f} + confirmation {confirm_s:,.1f} run-seconds: {steps:,} physics steps; "
          f"a rollout call of {ev.size:,} run{'s' * (ev.size != 1)}: memory {memory}", flush=True)
    print(f"  --out {out}: " + ("holds an earlier tune, which --force replaces" if plan["out_state"] == "replaced"
                                else "a new folder"), flush=True)
    print("the tune would start: the same command without --dry-run runs it", flush=True)
    return plan


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
    t_start = time.perf_counter()
    tuning = _prepare(spec_path, out, candidates, rounds, batch, force, backend)
    _announce(tuning)
    bar = _progress_bar(tuning, progress)
    log = _search(tuning, bar)
    df = leaderboard(log.rows)
    conf = confirm(tuning, df, bar)
    if bar is not None:
        bar.close()
    variants = log.variants
    new_compiles = (variants[-1] - variants[1]) if None not in (variants[1], variants[-1]) else None
    if new_compiles:
        _say(tuning.writer)(f"warning: the chunk function compiled {new_compiles} more time(s) after round 1",
                            flush=True)
    record = manifest(tuning, log, df, conf, new_compiles)
    wall_tune = time.perf_counter() - t_start
    if not tuning.writer:
        print(f"process {jax.process_index()}: done; process 0 writes {out}", flush=True)
        return None
    write_outputs(out, tuning, log, df, conf, record, t_start, wall_tune)
    print_summary(out, tuning, log, record, conf)
    return record
