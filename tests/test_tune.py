"""`wbc-jax tune`: spec and gains-file validation, search bookkeeping (CEM, grid, successive halving), the paired
comparison, the CPU batch that keeps jaxlib's LAPACK kernels off the thread pool (where they can hang), one tiny
end-to-end CEM run from deliberately poor gains (every Kp x 0.2) with the best gains replayed by
`wbc-jax campaign --gains`, and one tiny successive-halving run through the command line in a subprocess with a
time limit (a hang fails the test instead of stalling CI).

The tiny runs use the CI baseline campaign (reports/baseline/spec.toml: flat ground, 0.12 s, 20 ADMM iterations)
on 2 of its cells. The CEM run sets batch = 8 runs per call, the shape of tests/test_campaign.py's campaign and of
the replay below: float32 results depend on the batch a run is computed in (a sliding cube at mu 0.4 moves R by
several per cent between batch 1 and 8), so an exact replay needs the same batch. The halving run uses the
machine's default (one run per call on a CPU, tune_spec.CPU_BATCH).
"""

import json

import numpy as np
import pandas as pd
import pytest

from wbc_jax import cli
from wbc_jax.campaign.gains import gains_toml, load_gains
from wbc_jax.campaign.spec import SWEEPS
from wbc_jax.errors import SpecError
from wbc_jax.studies.tune_eval import score
from wbc_jax.studies.tune_report import paired_comparison
from wbc_jax.studies.tune_search import (
    CEMSearch,
    GridSearch,
    Space,
    halving_cost,
    halving_schedule,
    pareto_mask,
    rank_key,
)
from wbc_jax.studies.tune_spec import load_tune_spec

BASELINE_SPEC = SWEEPS.parent / "reports" / "baseline" / "spec.toml"
CELLS = [[0.2, 0.4, 0.06], [0.4, 1.0, 0.10]]
C, ROUNDS = 4, 3
TINY = f"""
[tune]
name = "tiny"
campaign = "{BASELINE_SPEC}"
method = "cem"
candidates = {C}
rounds = {ROUNDS}
seed = 5
cells = {CELLS}
batch = {C * len(CELLS)}
[start]
kp = 0.2
[leaves]
kp_com = [0.1, 4.0]
kp_obj = [0.1, 4.0]
kd_obj = [0.2, 4.0]
[objective]
t_max_mm = 1.6
[cem]
init_std = 0.6
"""
METRIC_RTOL = 1e-4  # same runs in another batch position / batch: float32 rounding at most


def _write(tmp_path, text, name="tune.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from wbc_jax.studies.tune import run_tune

    d = tmp_path_factory.mktemp("tune")
    spec = _write(d, TINY)
    man = run_tune(str(spec), str(d / "out"), progress=False)
    return d / "out", man, load_tune_spec(spec)


# ---------------------------------------------------------------- specs


def test_shipped_spec_loads():
    s = load_tune_spec(SWEEPS / "gain_tuning.toml")
    assert s.tune["method"] == "cem" and s.cells is None and s.campaign.campaign["reps"] == 1
    assert s.campaign.factors == dict(m=[0.2, 0.3, 0.4], mu=[0.4, 0.7, 1.0], d=[0.06, 0.08, 0.10])
    assert all(s.start[k] == 0.2 for k in s.start if k.startswith("kp_"))
    assert all(s.start[k] == 1.0 for k in s.start if not k.startswith("kp_"))
    assert s.with_overrides(candidates=1024).tune["candidates"] == 1024  # the GPU run's size
    course = load_tune_spec(SWEEPS / "gain_tuning_course.toml")  # the accelerator default: the paper's course
    assert course.campaign.campaign["scene"] == "transport" and course.cells is None
    assert course.campaign.campaign["max_seconds"] == 0 and course.objective["min_success"] == 1.0
    assert course.confirm_campaign.path.endswith("paper_campaign.toml") and course.confirm_campaign.reps == 10
    cpu = load_tune_spec(SWEEPS / "gain_tuning_cpu.toml")  # the CPU default
    assert cpu.tune["method"] == "halving" and cpu.confirm_campaign.reps == 1
    from wbc_jax.studies.tune_spec import CPU_SPEC, GPU_SPEC, default_tune_spec_path

    assert default_tune_spec_path(True) == GPU_SPEC and default_tune_spec_path(False) == CPU_SPEC


@pytest.mark.parametrize("edit, key, expect", [
    (("[tune]\n", "[tune]\nmethd = 'cem'\n"), "tune.methd", "unknown key"),
    (("candidates = 4", "candidates = 'four'"), "tune.candidates", "integer"),
    (("candidates = 4", "candidates = 1"), "tune.candidates", "needs >= 2"),
    (("method = \"cem\"", "method = \"anneal\""), "tune.method", "grid, random, cem, halving"),
    (("[cem]\n", "[halving]\neta = 1\n[cem]\n"), "halving.eta", "2 <= value <= 10"),
    (("[cem]\n", "[confirm]\nalpha = 1.5\n[cem]\n"), "confirm.alpha", "0.0 < value <= 1.0"),
    (("kp_com = [0.1, 4.0]", "kp_cmo = [0.1, 4.0]"), "leaves.kp_cmo", "unknown leaf"),
    (("kp_com = [0.1, 4.0]", "kp_com = [4.0, 0.1]"), "leaves.kp_com", "lo < hi"),
    (("kp_obj = [0.1, 4.0]", "kp_obj = [0.5, 4.0]"), "leaves.kp_obj", "start scale 0.2"),
    (("kp = 0.2", "kp = -1"), "start.kp", "0.0 < value"),
    (("cells = [[0.2, 0.4, 0.06]", "cells = [[0.25, 0.4, 0.06]"), "tune.cells[0]", "not a level"),
    (("t_max_mm = 1.6", "t_max_mm = -1"), "objective.t_max_mm", "0.0 <= value <= 1000.0"),
    (("[cem]\n", "[cem]\nelite = 3\n"), "cem.elite", "unknown key"),
    (("[tune]\n", "[tunes]\n"), "tunes", "unknown table"),
])
def test_bad_tune_spec_names_file_and_key(tmp_path, edit, key, expect):
    text = TINY.replace(*edit)
    assert text != TINY
    p = _write(tmp_path, text)
    with pytest.raises(SpecError) as e:
        load_tune_spec(p)
    msg = str(e.value)
    assert str(p) in msg and key in msg and expect in msg and "\n" not in msg


def test_cells_of_a_campaign_without_a_factor(tmp_path):
    """A campaign that does not vary d: a cell's d is checked against its fixed value (0.08 by default)."""
    camp = _write(tmp_path, "\n".join(x for x in BASELINE_SPEC.read_text().splitlines() if not x.startswith("d = ")),
                  "camp.toml")
    text = TINY.replace(str(BASELINE_SPEC), str(camp)).replace(f"cells = {CELLS}", "cells = [[0.2, 0.4, 0.08]]")
    assert load_tune_spec(_write(tmp_path, text)).cells == [[0.2, 0.4, 0.08]]
    with pytest.raises(SpecError) as e:
        load_tune_spec(_write(tmp_path, text.replace("0.4, 0.08]", "0.4, 0.06]"), "bad.toml"))
    msg = str(e.value)
    assert "tune.cells[0]" in msg and "d = 0.06 is not the fixed value of the campaign ([0.08])" in msg


def test_bad_tune_spec_cli_exit_2_nothing_written(tmp_path, capsys):
    p = _write(tmp_path, TINY.replace("rounds = 3", "rounds = 0"))
    out = tmp_path / "out"
    assert cli.main(["tune", "--spec", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("wbc-jax tune: error:") and str(p) in err[0] and "tune.rounds" in err[0]
    # a bad campaign reference names the campaign file
    q = _write(tmp_path, TINY.replace(str(BASELINE_SPEC), "nowhere.toml"), "ref.toml")
    assert cli.main(["tune", "--spec", str(q), "--out", str(out), "--candidates", "8"]) == 2
    assert "nowhere.toml" in capsys.readouterr().err
    assert cli.main(["tune", "--spec", str(_write(tmp_path, TINY, "ok.toml")), "--out", str(out),
                     "--candidates", "0"]) == 2
    assert "--candidates" in capsys.readouterr().err
    assert not out.exists() and sorted(f.name for f in tmp_path.iterdir()) == ["ok.toml", "ref.toml", "tune.toml"]


def test_a_rollout_call_too_large_for_memory_is_refused_before_compiling(tmp_path, capsys):
    """A million runs per rollout call (``--batch``): one line naming tune.batch, --batch and the campaign with its
    memory estimate (wbc_jax.campaign.size), exit 2, nothing written."""
    out = tmp_path / "out"
    assert cli.main(["tune", "--spec", str(_write(tmp_path, TINY)), "--out", str(out), "--batch", "1000000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"tune.batch: 1,000,000 runs per rollout call of {BASELINE_SPEC} need about" in err[0]
    assert "--batch" in err[0] and not out.exists()


@pytest.mark.parametrize("text, key, expect", [
    ("[gains]\nkp_cmo = 1.0\n", "gains.kp_cmo", "unknown leaf"),
    ("[gains]\nkp_com = [1.0, 2.0]\n", "gains.kp_com", "list of 3 numbers"),
    ("[gains]\nkp_obj = -5.0\n", "gains.kp_obj", "0.0 <= value"),
    ("[gains]\ntau_margin = 1.5\n", "gains.tau_margin", "0.0 < value <= 1.0"),
    ("[gains]\nkp_obj = 'high'\n", "gains.kp_obj", "expected a number"),
    ("[gain]\nkp_obj = 1.0\n", "gain", "unknown table"),
    ("kp_obj = 1.0\n", "kp_obj", "unknown table"),
])
def test_bad_gains_file_names_file_and_key(tmp_path, text, key, expect):
    p = _write(tmp_path, text, "g.toml")
    with pytest.raises(SpecError) as e:
        load_gains(p)
    msg = str(e.value)
    assert str(p) in msg and key in msg and expect in msg and "\n" not in msg


def test_gains_file_round_trip_and_defaults(tmp_path, capsys):
    from wbc_jax.control.transport import default_gains

    g0 = default_gains()
    g = g0._replace(kp_com=g0.kp_com * np.float32(0.3137), r_vdot=g0.r_vdot * np.float32(7.1), k_obs=g0.k_obs * 0)
    back = load_gains(_write(tmp_path, gains_toml(g, "header\nline 2", dict(note="x", n=3, R=0.5)), "g.toml"))
    for name, a, b in zip(g._fields, g, back):
        assert np.asarray(a).dtype == np.asarray(b).dtype and np.array_equal(np.asarray(a), np.asarray(b)), name
    part = load_gains(_write(tmp_path, "[gains]\nkp_com = 100.0\n", "p.toml"))  # scalar for a vector leaf
    assert np.array_equal(np.asarray(part.kp_com), [100.0] * 3) and np.array_equal(part.kd_com, g0.kd_com)
    bad = _write(tmp_path, "[gains]\nkp_obj = -1.0\n", "bad.toml")
    out = tmp_path / "camp"
    assert cli.main(["campaign", "--spec", str(BASELINE_SPEC), "--gains", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "gains.kp_obj" in err[0] and not out.exists()


# ---------------------------------------------------------------- search pieces


def test_rank_pareto_and_score():
    keys = [rank_key(False, 0.5, 9.0), rank_key(True, 0.0, 1.0), rank_key(True, 0.0, 2.0), rank_key(False, 0.1, 0.0),
            rank_key(True, 0.0, np.nan)]
    assert sorted(range(5), key=lambda i: keys[i], reverse=True) == [2, 1, 4, 3, 0]
    pts = np.array([[1, 1, -1], [2, 2, -1], [3, 0, -1], [2, 2, -2], [np.nan, 5, 0]])
    assert pareto_mask(pts).tolist() == [False, True, True, False, False]
    mu = np.array([0.5, 1.0])
    res = dict(success=np.array([[True, True], [True, False], [False, False]]), R=np.full((3, 2), 0.2),
               S=np.full((3, 2), 3.0), T=np.array([[1e-3, 3e-3], [1e-3, 1e-3], [1e-3, 1e-3]]))
    obj = dict(w_R=1.0, w_S=2.0, w_T=0.0, s_ref=3.0, min_success=1.0, t_max_mm=2.5)
    sc = score(res, mu, obj)
    want_r = np.mean(0.2 / np.arctan(mu) ** 2)
    np.testing.assert_allclose(sc["objective"][0], want_r + 2.0)
    np.testing.assert_allclose(sc["T_mm"][:2], [2.0, 1.0])
    assert sc["feasible"].tolist() == [True, False, False]
    np.testing.assert_allclose(sc["violation"][1], 0.5)  # half the runs failed
    assert sc["violation"][2] >= 1.0 and np.isnan(sc["objective"][2])
    sc = score(res, mu, dict(obj, t_max_mm=1.5))
    np.testing.assert_allclose(sc["violation"][0], (2.0 - 1.5) / 1.5)


def test_cem_carries_the_best_and_grid_covers_the_box(tmp_path):
    spec = load_tune_spec(_write(tmp_path, TINY))
    space = Space(spec.leaves, spec.start)
    cem = CEMSearch(space, 6, 3, np.random.default_rng(0), **spec.cem)
    x, kinds = cem.ask(0)
    assert kinds[0] == "start" and np.allclose(np.exp(x[0]), [0.2, 0.2, 1.0])
    assert np.all(x >= space.lo) and np.all(x <= space.hi)
    keys = [rank_key(True, 0.0, float(v)) for v in [1, 5, 2, 0, 3, 4]]
    cem.tell(x, keys)
    x2, kinds2 = cem.ask(1)
    assert kinds2[0] == "elite" and np.array_equal(x2[0], x[1])
    assert np.allclose(cem.mean, 0.7 * x[[1, 5]].mean(0) + 0.3 * space.x0)
    grid = GridSearch(space, 4, 0, None, points=2)
    xs = np.concatenate([grid.ask(r)[0] for r in range(grid.rounds)])
    assert grid.rounds == 3 and grid.ask(2)[1] == ["grid"] * 1 + ["padding"] * 3  # 1 start + 8 corners
    assert {tuple(np.round(np.exp(v), 6)) for v in xs[1:9]} == {(a, b, c) for a in (0.1, 4.0) for b in (0.1, 4.0)
                                                                for c in (0.2, 4.0)}
    g = space.gains(x[:2])
    assert g.kp_com.shape == (2, 3) and np.allclose(g.kp_rot, 600.0 * 0.2)  # untuned Kp stays at the start scale


def test_halving_schedule_and_survivors():
    from wbc_jax.studies.tune_search import HalvingSearch

    assert halving_schedule(32, 3, 3, 14) == ([32, 11, 4], [2, 5, 14])
    assert halving_schedule(6, 3, 2, 6) == ([6, 2], [2, 6])
    assert halving_schedule(5, 2, 4, 2) == ([5, 1], [1, 2])  # rungs with equal horizons merge
    assert halving_schedule(4, 2, 1, 6) == ([4], [6])  # one rung: plain random search at the full horizon
    # survivors continue their states: every candidate-chunk is simulated once
    assert halving_cost(32, 3, 3, 14) == 32 * 2 + 11 * 3 + 4 * 9
    keys = [rank_key(True, 0.0, v) for v in (0.1, 0.9, 0.5)] + [rank_key(False, 0.2, 5.0)]
    assert HalvingSearch.survivors(keys, 2).tolist() == [1, 2]


def test_paired_comparison_names_the_test_and_finds_a_shift():
    """Tuned runs better by a fixed shift plus noise on every run: Wilcoxon finds it; a zero shift is not
    significant; a failure only the tuned set has is counted by McNemar's pairs."""
    rng = np.random.default_rng(0)
    n = 40
    mu = np.tile([0.4, 0.7, 1.0], n)[:n]
    base = dict(success=np.ones(n, bool), R=rng.uniform(0.1, 0.3, n), S=rng.uniform(2, 4, n),
                T=rng.uniform(1e-3, 2e-3, n))
    obj = dict(w_R=1.0, w_S=1.0, w_T=0.0, s_ref=3.0, min_success=1.0, t_max_mm=2.0)
    tuned = dict(base, S=base["S"] + 0.3 + 0.05 * rng.standard_normal(n))
    cmp = {r["metric"]: r for r in paired_comparison(base, tuned, mu, obj, 0.01)}
    assert cmp["J"]["improved"] and cmp["J"]["p"] < 1e-6 and "Wilcoxon" in cmp["J"]["test"]
    assert cmp["S"]["improved"] and np.isclose(cmp["S"]["diff"], np.mean(tuned["S"] - base["S"]))
    assert not cmp["R_norm"]["improved"] and not cmp["R_norm"]["worse"] and cmp["R_norm"]["p"] == 1.0
    worse = dict(base, success=np.r_[False, np.ones(n - 1, bool)])
    c = {r["metric"]: r for r in paired_comparison(base, worse, mu, obj, 0.01)}
    assert c["success"]["tuned"] < c["success"]["default"] and c["success"]["n"] == n and not c["success"]["worse"]
    assert c["J"]["n"] == n - 1 and "McNemar" in c["success"]["test"]


def test_compare_replay_pairs_by_seed(tmp_path):
    """`python -m wbc_jax.studies.tune_report TUNE_DIR CAMPAIGN_DIR`: the replay's results.csv paired with the tuning's
    default-gain runs by seed; a replay of another campaign is an error naming the file."""
    from wbc_jax.errors import WbcJaxError
    from wbc_jax.studies.tune_report import compare_replay

    rng = np.random.default_rng(1)
    n = 30
    cells = dict(m=np.full(n, 0.2), mu=np.tile([0.4, 0.7, 1.0], 10), d=np.full(n, 0.06), rep=np.arange(n),
                 seed=rng.integers(0, 2**32, n))
    t_dir, c_dir = tmp_path / "tune", tmp_path / "camp"
    t_dir.mkdir()
    c_dir.mkdir()
    S = rng.uniform(2, 4, n)
    pd.DataFrame(dict(candidate="default", **cells, success=True, R=0.2, S=S, T_mm=1.5)).to_csv(
        t_dir / "confirm_runs.csv", index=False)
    obj = dict(w_R=1.0, w_S=1.0, w_T=0.0, s_ref=3.0, min_success=1.0, t_max_mm=2.0)
    (t_dir / "manifest.json").write_text(json.dumps(dict(objective=obj, spec=dict(confirm=dict(alpha=0.01)),
                                                         confirmation=dict(campaign="paper.toml"))))
    res = pd.DataFrame(dict(run=np.arange(n), **cells, success=True, R=0.2, S=S + 0.5 + 0.01 * rng.random(n),
                            T=1.5e-3))
    res.sample(frac=1.0, random_state=0).to_csv(c_dir / "results.csv", index=False)  # order does not matter
    md = compare_replay(t_dir, c_dir)
    assert "30 runs paired by seed" in md and "| J | Wilcoxon signed-rank (two-sided) | 30 |" in md
    assert "| S |" in md and md.count("improved") >= 2
    res.assign(seed=res.seed + 1).to_csv(c_dir / "results.csv", index=False)
    with pytest.raises(WbcJaxError, match="results.csv"):
        compare_replay(t_dir, c_dir)


def test_cpu_batch_keeps_lapack_kernels_inline(monkeypatch):
    """The hang of `wbc-jax tune --candidates 4` on 2 cores: jaxlib 0.10's batched Cholesky / triangular solve
    hand pieces of a batch to XLA's intra-op pool when batch x n^3 / 3 >= 200,000 and block their own pool thread
    until the pieces finish; two at once on a 2-thread pool deadlock. With CPU_BATCH runs per call, every LAPACK
    kernel of the chunk program stays below that work and runs inline. Traces the real chunk function (no
    compile) and checks every factorisation in it, so a larger QP or model breaks this test, not a user's run."""
    import jax

    from wbc_jax.campaign.build import build
    from wbc_jax.campaign.spec import load_spec, parse_spec
    from wbc_jax.rollout import batch as batch_module
    from wbc_jax.rollout import make_chunk_fn
    from wbc_jax.studies.tune_eval import take
    from wbc_jax.studies.tune_spec import CPU_BATCH

    paper = load_spec(SWEEPS / "paper_campaign.toml")  # the course scene (the larger model), 8 runs to build
    spec = parse_spec(dict(campaign=dict(paper.campaign, reps=1), perturbations=paper.perturbations,
                           factors={k: v[:2] for k, v in paper.factors.items()}))
    # the batch's initial states as shapes and types only (jax.eval_shape of the real init function): the trace
    # below reads nothing else of them, and compiling the course scene's init program is slow on a CPU
    real_init = batch_module._init_fn
    monkeypatch.setattr(batch_module, "_init_fn", lambda *a: lambda *x: jax.eval_shape(real_init(*a), *x))
    built = build(spec)
    sim, b = built.sim, built.batch
    assert all(isinstance(x, jax.ShapeDtypeStruct) for x in jax.tree_util.tree_leaves(b.state.d))  # not computed
    rows = np.arange(CPU_BATCH)
    sub = b._replace(model=take(b.model, rows, b.in_axes), state=jax.eval_shape(lambda s: take(s, rows), b.state),
                     **{k: take(getattr(b, k), rows) for k in ("plan", "om", "gains", "push", "mu_ground")})
    f = make_chunk_fn(sim, 1, b.in_axes)
    jaxpr = jax.make_jaxpr(f)(sub.model, sub.state, sub.plan, sub.om, sub.gains, sub.push, sub.mu_ground)
    found = []

    def walk(j):
        for e in j.eqns:
            if e.primitive.name in ("cholesky", "triangular_solve", "lu", "qr", "eigh", "svd"):
                found.append((e.primitive.name, e.invars[0].aval.shape))
            for p in e.params.values():
                for v in (p if isinstance(p, (list, tuple)) else [p]):
                    inner = getattr(v, "jaxpr", None)
                    if inner is not None:
                        walk(getattr(inner, "jaxpr", inner))

    walk(jaxpr.jaxpr)
    names = {k for k, _ in found}
    assert "cholesky" in names and names <= {"cholesky", "triangular_solve"}, names  # the kernels it was checked on
    for name, shape in found:
        batch, n = int(np.prod(shape[:-2])), shape[-1]
        assert batch == CPU_BATCH and batch * n ** 3 / 3 < 200_000, (name, shape)


# ---------------------------------------------------------------- one tiny tuning run


def test_tune_end_to_end_from_poor_gains(tiny_run):
    out, man, spec = tiny_run
    df = pd.read_csv(out / "leaderboard.csv")
    assert len(df) == C * ROUNDS and sorted(df["rank"]) == list(range(1, C * ROUNDS + 1))
    for col in ("round", "kind", "kp_com_x", "kp_com", "kd_obj_x", "R", "S", "T_mm", "success_rate", "objective",
                "feasible", "pareto"):
        assert col in df.columns
    start = df.iloc[0]
    assert start.kind == "start" and np.isclose(start.kp_com_x, 0.2) and np.isclose(start.kp_com, 400.0)
    key = lambda r: rank_key(r.feasible, r.violation, r.objective)  # noqa: E731
    best = df.sort_values("rank").iloc[0]
    # improvement where it is certain: the start is a candidate, so the best ranks at least as high
    assert key(best) >= key(start)
    if start.feasible:
        assert best.feasible and best.objective >= start.objective
    # CEM carries the best so far in slot 0: the round best never ranks lower, and the carried elite's second
    # evaluation equals its first (same compiled function, state reset each round)
    round_best = [max(key(r) for r in df[df["round"] == k].itertuples()) for k in range(1, ROUNDS + 1)]
    assert all(b >= a for a, b in zip(round_best, round_best[1:])), round_best
    for k in range(2, ROUNDS + 1):
        elite = df[(df["round"] == k) & (df.slot == 0)].iloc[0]
        assert elite.kind == "elite"
        prev = df[(df["round"] < k) & np.isclose(df.kp_com_x, elite.kp_com_x) & np.isclose(df.kp_obj_x, elite.kp_obj_x)]
        assert len(prev) >= 1
        np.testing.assert_allclose(prev[["R", "S", "T_mm"]].to_numpy()[0], elite[["R", "S", "T_mm"]].to_numpy(float),
                                   rtol=METRIC_RTOL)
    # the gain leaves do change the rollout (candidates differ) and every run is scored
    assert df.T_mm.nunique() > 1 and np.isfinite(df.objective).all()
    assert man["new_compilations_after_round_1"] in (0, None) and man["candidates_per_s"] > 0
    assert man["candidates_evaluated"] == C * ROUNDS and man["batch_runs"] == C * len(CELLS)
    m = json.loads((out / "manifest.json").read_text())
    for k in ("versions", "device", "spec_hash", "wall_s_total", "candidates_per_s", "round_wall_s", "best", "start"):
        assert k in m
    assert m["spec_hash"] == spec.hash and len(m["round_wall_s"]) == ROUNDS
    for f in ("objective_per_round.png", "pareto.png"):
        assert (out / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if df.feasible.any():
        assert df.pareto.any() and not (df.pareto & ~df.feasible).any()


def test_best_gains_replayed_by_campaign(tiny_run, tmp_path):
    """best_gains.toml holds the best candidate's gains; `wbc-jax campaign --gains` with them on the same campaign
    reproduces that candidate's per-run metrics on the tuned cells."""
    from wbc_jax.control.transport import default_gains

    out, _, spec = tiny_run
    df = pd.read_csv(out / "leaderboard.csv")
    best = df.sort_values("rank").iloc[0]
    g = load_gains(out / "best_gains.toml")
    g0 = default_gains()
    np.testing.assert_allclose(np.asarray(g.kp_com), np.asarray(g0.kp_com) * best.kp_com_x, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(g.kd_obj), np.asarray(g0.kd_obj) * best.kd_obj_x, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(g.kp_rot), np.asarray(g0.kp_rot) * 0.2, rtol=1e-6)  # untuned: start
    np.testing.assert_array_equal(np.asarray(g.w_com), np.asarray(g0.w_com))
    camp = tmp_path / "camp"
    assert cli.main(["campaign", "--spec", str(BASELINE_SPEC), "--gains", str(out / "best_gains.toml"),
                     "--out", str(camp), "--no-report"]) == 0
    res = pd.read_csv(camp / "results.csv")
    runs = pd.read_csv(out / "best_runs.csv")
    runs = runs[runs.candidate == "best"]
    got = res.merge(runs, on=["m", "mu", "d", "rep"], suffixes=("", "_tune"))
    assert len(got) == len(CELLS) and (got.seed == got.seed_tune).all()
    np.testing.assert_allclose(got.R, got.R_tune, rtol=METRIC_RTOL)
    np.testing.assert_allclose(got["T"] * 1e3, got.T_mm, rtol=METRIC_RTOL)
    np.testing.assert_allclose(got.S, got.S_tune, rtol=METRIC_RTOL)
    assert json.loads((camp / "manifest.json").read_text())["default_gains"] is False


def test_dry_run_describes_the_tune_it_would_run(tiny_run, tmp_path, capsys):
    """`wbc-jax tune --dry-run`: the tiny tune's own figures (runs per candidate and per rollout call, the planned
    run-seconds of its manifest) and a hand count of its physics steps; nothing written; an earlier tune's folder
    refused without --force and named as what --force replaces (and left as it was); a folder another command holds
    refused; exit 0 and 2 as the tune's."""
    from wbc_jax.campaign.spec import load_spec
    from wbc_jax.io_utils import claim_out_dir, release_out_dir
    from wbc_jax.studies.tune import dry_run_tune

    out, man, spec = tiny_run
    new = tmp_path / "new"
    assert cli.main(["tune", "--spec", spec.path, "--out", str(new), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "nothing is simulated" in text and "the tune would start" in text and f"--out {new}: a new folder" in text
    assert not new.exists() and list(tmp_path.iterdir()) == []
    plan = dry_run_tune(spec.path, str(new))
    assert (plan["runs_per_candidate"], plan["runs_per_call"]) == (man["runs_per_candidate"], man["runs_per_call"])
    assert plan["search_run_s"] + plan["confirm_run_s"] == pytest.approx(man["planned_run_seconds"], rel=1e-12)
    n, seconds = len(CELLS), man["simulated_s"]  # reps 1; no [confirm]: default and best on the tuning runs
    assert plan["search_run_s"] == pytest.approx(ROUNDS * C * n * seconds)
    assert plan["confirm_run_s"] == pytest.approx(2 * n * seconds) and plan["confirm_runs"] == 2 * n
    dt = man["control_dt_s"] / load_spec(BASELINE_SPEC).campaign["control_substeps"]
    assert plan["physics_steps"] == round((ROUNDS * C + 2) * n * seconds / dt)
    assert plan["parts"] == 1 and dry_run_tune(spec.path, str(new), processes=3)["parts"] == 3  # JAX: a mesh over
    # the 3 processes' devices (one CPU device each here)
    before = sorted((f.name, f.stat().st_mtime_ns) for f in out.iterdir())
    assert cli.main(["tune", "--spec", spec.path, "--out", str(out), "--dry-run"]) == 2
    assert "--force" in capsys.readouterr().err
    assert cli.main(["tune", "--spec", spec.path, "--out", str(out), "--dry-run", "--force"]) == 0
    assert "holds an earlier tune, which --force replaces" in capsys.readouterr().out
    assert sorted((f.name, f.stat().st_mtime_ns) for f in out.iterdir()) == before
    claim_out_dir(new, "wbc-jax campaign")
    try:
        assert cli.main(["tune", "--spec", spec.path, "--out", str(new), "--dry-run"]) == 2
        assert "in use by" in capsys.readouterr().err
    finally:
        release_out_dir(new)


def test_failure_summary_counts_runs_and_reasons():
    """The tune's line on the confirmation's failed runs: per gain set the failed runs and their reasons, most
    frequent first (hand count)."""
    from wbc_jax.studies.tune_results import failure_summary

    per = {"default": dict(success=np.array([True, False, False, True, False]),
                           fail_reason=np.array(["", "fell", "body contact", "", "body contact"])),
           "rank 1": dict(success=np.ones(5, bool), fail_reason=np.array([""] * 5))}
    assert failure_summary(per) == "failed runs: default 3 of 5 (body contact 2, fell 1), rank 1 none"


@pytest.mark.slow  # a fresh process compiles the one-run programs; the CEM run above covers the search end to end
#                   and test_halving_schedule_and_survivors the halving bookkeeping
def test_tiny_successive_halving_end_to_end(tmp_path):
    """`wbc-jax tune` with method = "halving" through the command line, in a subprocess under a time limit (a
    hang fails here instead of stalling CI): 4 candidates per bracket, 2 brackets, rungs at 1 and 3 chunks; the
    survivors' runs continue their states, and their full-horizon metrics equal the confirmation's
    uninterrupted rollout of the same gains on the same seeds."""
    import subprocess
    import sys

    spec = _write(tmp_path, TINY.replace('method = "cem"', 'method = "halving"').replace("rounds = 3", "rounds = 2")
                  .replace(f"batch = {C * len(CELLS)}\n", "")
                  .replace("[cem]\n", f"[halving]\neta = 3\nrungs = 2\n[confirm]\ncampaign = \"{BASELINE_SPEC}\"\n"
                                      "top = 2\n[cem]\n"))
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "wbc_jax", "tune", "--spec", str(spec), "--out", str(out),
                        "--no-progress"], capture_output=True, text=True, timeout=420)
    assert r.returncode == 0, r.stderr[-2000:]
    df = pd.read_csv(out / "leaderboard.csv")
    man = json.loads((out / "manifest.json").read_text())
    assert man["method"] == "halving" and len(df) == 2 * C and set(np.round(df.sim_s, 6)) == {0.04, 0.12}
    full = df[np.isclose(df.sim_s, 0.12)]
    assert len(full) == 2 * 2  # ceil(4 / 3) = 2 survivors per bracket reach the full horizon
    assert df.sort_values("rank").iloc[0].sim_s == pytest.approx(0.12)
    assert (df[df["round"] == 2].iloc[0].kind == "elite") and df.iloc[0].kind == "start"
    assert man["new_compilations_after_round_1"] in (0, None)
    # one compiled chunk function for every rung, bracket and the confirmation (continued states keep their types)
    assert man["compiled_variants_per_round"][-1] in (1, None)
    assert man["compiled_variants_after_confirmation"] in (1, None)
    from wbc_jax.campaign.build import has_accelerator

    if not has_accelerator():
        assert man["runs_per_call"] == 1
    # the continued survivors' metrics equal an uninterrupted rollout (the confirmation) on the same seeds
    best = pd.read_csv(out / "best_runs.csv")
    best = best[best.candidate == "best"]
    conf = pd.read_csv(out / "confirm_runs.csv")
    assert len(set(conf.candidate)) == 3 and {"default", "rank 1"} <= set(conf.candidate)
    assert (conf.groupby("candidate").size() == 8).all()
    got = conf[conf.candidate == "rank 1"].merge(best, on=["m", "mu", "d", "rep"], suffixes=("", "_tune"))
    assert len(got) == len(CELLS) and (got.seed == got.seed_tune).all()
    np.testing.assert_allclose(got[["R", "S", "T_mm"]].to_numpy(float), got[["R_tune", "S_tune", "T_mm_tune"]]
                               .to_numpy(float), rtol=METRIC_RTOL)
    report = (out / "report.md").read_text()
    assert "Wilcoxon signed-rank" in report and "McNemar" in report and "| J |" in report
    fails = [f"{who} {(~g.success).sum()} of {len(g)}" if (~g.success).any() else f"{who} none"
             for who, g in conf.groupby("candidate", sort=False)]
    assert ("failed runs: " + ", ".join(fails)).split(" (")[0] in r.stdout  # the counts, as confirm_runs.csv's
    assert len(man["comparison"]) == 5 and man["confirmation"]["runs"] == 8


def test_tune_refuses_a_campaign_of_another_controller(tmp_path):
    """The search space is the transport controller's gains: a centroidal campaign spec is a one-line SpecError."""
    p = _write(tmp_path, TINY.replace(str(BASELINE_SPEC), str(SWEEPS / "trot_quick.toml")))
    with pytest.raises(SpecError) as e:
        load_tune_spec(p)
    msg = str(e.value)
    assert str(p) in msg and "campaign.controller 'centroidal'" in msg and "\n" not in msg
