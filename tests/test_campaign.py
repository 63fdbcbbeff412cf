"""`wbc-jax campaign`: spec validation, design table, one tiny batched campaign, interrupt + resume."""

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_reliability import campaign_table

from wbc_jax import cli
from wbc_jax.campaign.spec import SWEEPS, design, load_spec, parse_spec
from wbc_jax.errors import OutputError, SpecError, WbcJaxError

BASELINE = SWEEPS.parent / "reports" / "baseline"  # its spec.toml is the tiny campaign of these tests (conftest.py)
NUMERIC = ["m", "mu", "d", "rep", "seed", "R", "T", "S", "max_slip_mm", "boundary_fraction", "final_err_mm"]


# ---------------------------------------------------------------- specs


def test_shipped_specs_load():
    paper = load_spec(SWEEPS / "paper_campaign.toml")
    quick = load_spec(SWEEPS / "quick.toml")
    assert design(paper).n == 270 and paper.reps == 10 and paper.campaign["scene"] == "transport"
    assert paper.factors == dict(m=[0.2, 0.3, 0.4], mu=[0.4, 0.7, 1.0], d=[0.06, 0.08, 0.10])
    assert quick.factors == paper.factors and design(quick).n < 270
    assert not paper.zero_noise and not quick.zero_noise


@pytest.mark.parametrize("text, key, expect", [
    ("[campaign]\nrepz = 3\n[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n", "campaign.repz", "unknown key"),
    ("[campaign]\nreps = 'ten'\n[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n", "campaign.reps", "integer"),
    ("[campaign]\nreps = 2.5\n[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n", "campaign.reps", "integer"),
    ("[campaign]\nreps = 0\n[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n", "campaign.reps",
     "1 <= value <= 1000"),
    ("[factors]\nm=[0.2,0.3]\nmu=[0.4,7.0]\nd=[0.06,0.1]\n", "factors.mu", "0.0 < value <= 5.0"),
    ("[factors]\nm=[0.2]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n", "factors.m", "at least 2 levels"),
    ("[factors]\n", "factors", "0 factors: expected 1 to 5"),  # a factor left out takes its campaign value
    ("[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\nk=[1,2]\n", "factors.k", "unknown factor"),
    ("[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n[perturbations]\nobject_xy_mm = -1\n",
     "perturbations.object_xy_mm", "0.0 <= value <= 20.0"),
    ("[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n[perturbations]\npush_window = [0.8, 0.2]\n",
     "perturbations.push_window", "0 <= a <= b < 1"),
    ("[campaign]\nscene = 'moon'\n[factors]\nm=[0.2,0.3]\nmu=[0.4,1.0]\nd=[0.06,0.1]\n", "campaign.scene", "flat"),
    ("[gains]\nkp = 1\n", "gains", "unknown table"),
])
def test_bad_spec_names_file_key_and_range(tmp_path, text, key, expect):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(SpecError) as e:
        load_spec(p)
    msg = str(e.value)
    assert str(p) in msg and key in msg and expect in msg and "\n" not in msg


def test_bad_spec_cli_is_one_line_exit_2_nothing_written(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[campaign]\nreps = [\n")  # not TOML
    out = tmp_path / "out"
    assert cli.main(["campaign", "--spec", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("wbc-jax campaign: error:") and str(p) in err[0]
    assert cli.main(["campaign", "--spec", str(tmp_path / "missing.toml"), "--out", str(out)]) == 2
    assert not out.exists() and list(tmp_path.iterdir()) == [p]


def test_design_seeds_and_perturbations(tiny_spec):
    s = load_spec(tiny_spec)
    a, b = design(s), design(s)
    da, db = a.asdict(), b.asdict()
    for k, v in da.items():
        pairs = [(v[n], db[k][n]) for n in v] if isinstance(v, dict) else [(v, db[k])]  # levels: name -> (B,)
        for x, y in pairs:
            np.testing.assert_array_equal(x, y)  # deterministic
    assert a.n == 8 and len(set(a.seed.tolist())) == 8
    assert np.all(np.abs(a.obj_dx) <= 2e-3) and np.all(np.abs(a.obj_yaw) <= np.deg2rad(2.0))
    assert np.all(np.linalg.norm(a.push_force, axis=1) <= 20.0) and np.all((a.push_frac >= 0) & (a.push_frac <= 0.04))
    assert np.std(a.obj_dx) > 0  # repetitions differ
    z = parse_spec(dict(factors=s.factors, campaign=dict(reps=2)), "zero.toml")
    dz = design(z)
    assert z.zero_noise and np.all(dz.obj_dx == 0) and np.all(dz.push_force == 0) and np.all(dz.v0 == 0)


# ---------------------------------------------------------------- one tiny campaign


def test_campaign_writes_results_report_manifest(full_run):
    out, man = full_run
    df = pd.read_csv(out / "results.csv")
    assert len(df) == 8
    for col in ["m", "mu", "d", "rep", "seed", "success", "R", "T", "S", "max_slip_mm", "fell", "dropped", "slid",
                "hit_wall", "qp_flagged"]:
        assert col in df.columns
    assert df.success.all(), df
    th2 = np.arctan(df.mu) ** 2
    assert np.all(df.R > 0) and np.all(df.R <= th2 + 1e-6)  # 1/H <= atan(mu)^2 (metrics docstring)
    assert np.all(df["T"] >= 0) and np.all(df["T"] < 0.01) and np.all(df.S > 0)
    assert (out / "report" / "report.md").exists() and (out / "report" / "anova.json").exists()
    m = json.loads((out / "manifest.json").read_text())
    for k in ("versions", "device", "spec_hash", "seeds", "wall_s_total", "compile_s_estimate", "env_steps_per_s"):
        assert k in m
    assert m["seeds"] == df.seed.tolist() and m["versions"]["jax"] and m["n_runs"] == 8
    assert m["n_chunks"] == 3 and abs(m["simulated_s"] - 0.12) < 1e-9 and m["env_steps_per_s"] > 0
    assert not list(out.parent.glob(".full.campaign-ckpt"))  # checkpoint removed after success
    assert m["files"] == ["manifest.json", "report", "results.csv"] and m["qp_flagged_runs"] == 0
    assert len(m["sessions"]) == 1 and not m["resumed"] and not (out.parent / ".full.lock").exists()


def _cut(done, n_chunks):
    """``runner.after_chunk`` that interrupts the campaign after its first chunk."""
    raise KeyboardInterrupt


def test_interrupt_and_resume_equal_uninterrupted(full_run, tiny_spec, tmp_path, monkeypatch):
    from wbc_jax.campaign import runner
    from wbc_jax.campaign.runner import run_campaign

    ref = pd.read_csv(full_run[0] / "results.csv")
    out = tmp_path / "resumed"
    monkeypatch.setattr(runner, "after_chunk", _cut)
    with pytest.raises(KeyboardInterrupt) as stop:
        run_campaign(str(tiny_spec), str(out), report=False, progress=False)
    monkeypatch.undo()
    ck = tmp_path / ".resumed.campaign-ckpt"
    assert str(stop.value) == (f"interrupted (SIGINT) after 1 of 3 chunks; finished chunks kept in {ck}; continue "
                               "with --resume") and stop.value.exit_code == 130
    assert not out.exists() and not (tmp_path / ".resumed.lock").exists()  # nothing partial in DIR, lock released
    meta = json.loads((ck / "meta.json").read_text())
    assert meta["chunks_done"] == 1 and [f.name for f in ck.glob("state_*.npz")] == [meta["state_file"]]
    with pytest.raises(OutputError, match="1 of 3 chunks finished in .*; continue with --resume, or --force"):
        run_campaign(str(tiny_spec), str(out), report=False, progress=False)  # never discarded implicitly
    meta["sessions"][0]["git_commit"] = "0" * 40  # the first session ran under another commit
    (ck / "meta.json").write_text(json.dumps(meta))
    man = run_campaign(str(tiny_spec), str(out), resume=True, report=False, progress=False)
    got = pd.read_csv(out / "results.csv")
    assert man["resumed"] and [s["chunks_before"] for s in man["sessions"]] == [0, 1]
    assert man["git_commits"][0] == "0" * 40 and len(man["git_commits"]) == (2 if man["git_commit"] else 1)
    pd.testing.assert_frame_equal(got, ref, check_exact=True)
    assert not ck.exists()


def test_interrupt_during_the_report_keeps_the_results(full_run, tiny_spec, tmp_path, monkeypatch, capsys):
    """SIGINT while the report is written (the compiled chunks of full_run reused): exit 130 with one line saying
    that results.csv and manifest.json are written and how to write the report."""
    import os
    import signal
    import time

    from wbc_jax.campaign import runner

    def signalled(out, manifest, warnings, reporter=None):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # the handler interrupts this
            pytest.fail("the signal did not stop the report")
        finally:
            if reporter is not None:
                reporter.close()

    out = tmp_path / "cut"
    monkeypatch.setattr(runner, "campaign_report", signalled)
    assert cli.main(["campaign", "--spec", str(tiny_spec), "--out", str(out)]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"wbc-jax campaign: interrupted (SIGINT) during the report; {out}/results.csv and "
                       f"manifest.json are written; write the report with wbc-jax report {out}/results.csv --out "
                       f"{out}/report"), err
    pd.testing.assert_frame_equal(pd.read_csv(out / "results.csv"), pd.read_csv(full_run[0] / "results.csv"))
    assert json.loads((out / "manifest.json").read_text())["n_runs"] == 8


def test_nan_run_does_not_poison_the_batch(full_run, tiny_spec):
    """A run whose state goes NaN is frozen and marked failed; every other run's metrics equal the clean batch's."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.campaign import runner as C
    from wbc_jax.metrics import paper as metrics

    sim, dz, b, _, logs_per_chunk, n_chunks = C.build(load_spec(tiny_spec))
    bad = 3
    d = b.state.d
    state = b.state._replace(d=d.replace(qvel=d.qvel.at[bad].set(jnp.nan)))
    fn = C.chunk_fn(sim, b.in_axes, logs_per_chunk)  # the compiled function of the clean run (same shapes)
    for _ in range(n_chunks):
        state, logs = fn(b.model, state, b.plan, b.om, b.gains, b.push, b.mu_ground)
    acc = jax.device_get(state.acc)
    p_obj = np.asarray(state.d.xpos[:, sim.robot.ids.obj_body])
    final_err = np.linalg.norm(p_obj - np.asarray(logs.p_obj_ref[:, -1]), axis=1)
    res = metrics.finalize(acc, sim.dt_control, dz.mu, course=False, final_err=final_err, substeps=sim.n_substeps)
    ref = pd.read_csv(full_run[0] / "results.csv")
    assert res["nonfinite"][bad] and not res["success"][bad]
    ok = np.arange(dz.n) != bad
    assert np.all(res["success"][ok]) and not np.any(res["nonfinite"][ok])
    for k, atol in (("R", 0), ("T", 0), ("S", 0), ("max_slip_mm", 5e-7)):  # the table rounds slip to 1 nm
        np.testing.assert_allclose(np.asarray(res[k])[ok], ref[k].to_numpy()[ok], rtol=1e-9, atol=atol, err_msg=k)


def test_sensor_noise_is_seeded_and_velocity_only(tiny_spec):
    """The controller's view: positions exact, velocities noisy with the spec's std, reproducible per (seed, step)."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.campaign import runner as C
    from wbc_jax.physics.backend import sense_with_view
    from wbc_jax.rollout import seen_qvel

    spec = load_spec(tiny_spec)
    sim, dz, b, *_ = C.build(spec)
    assert sim.sensor_noise and np.all(dz.qvel_noise_std == spec.perturbations["qvel_noise_std"])
    m0 = jax.tree_util.tree_map(lambda a, x: x if a is None else x[0], b.in_axes, b.model, is_leaf=lambda v: v is None)
    d0 = jax.tree_util.tree_map(lambda x: x[0], b.state.d)
    p0 = jax.tree_util.tree_map(lambda x: x[0], b.push)
    view = jax.jit(lambda d, p, k: sense_with_view(m0, d, seen_qvel(sim, d, p, k))[1])
    a, a2, c = view(d0, p0, 5), view(d0, p0, 5), view(d0, p0, 6)
    np.testing.assert_array_equal(a.qvel, a2.qvel)  # same seed and step: same draw
    assert not np.allclose(a.qvel, c.qvel)  # next step: a new draw
    np.testing.assert_array_equal(a.xpos, d0.xpos)  # kinematics untouched
    noise = np.asarray(a.qvel - d0.qvel)
    assert 0.3 * 0.02 < noise.std() < 3 * 0.02  # 30 draws of std 0.02
    assert not np.allclose(a.qfrc_bias, d0.qfrc_bias)  # velocity terms recomputed from the noisy view
    p1 = jax.tree_util.tree_map(lambda x: x[1], b.push)
    assert not np.allclose(view(d0, p1, 5).qvel, a.qvel)  # another run's seed: another draw
    assert jnp.all(b.push.qvel_noise_std == 0.02)


# ---------------------------------------------------------------- CI regression


def test_regress_passes_on_baseline_and_fails_on_gain_change(full_run, tmp_path, capsys):
    """The committed baseline passes; a deliberate controller-gain change (object position gain 250 -> 50)
    fails with a table of what moved; restoring the gain passes again (the first call)."""
    from wbc_jax.campaign.regress import run_regress
    from wbc_jax.control.transport import default_gains

    code, moved = run_regress(str(BASELINE))
    assert code == 0 and moved == [], capsys.readouterr().out
    bad = default_gains()._replace(kp_obj=default_gains().kp_obj * 0.2)
    code, moved = run_regress(str(BASELINE), gains=bad)
    out = capsys.readouterr().out
    assert code == 1 and moved and "REGRESSION" in out and any(r["metric"] == "T" for r in moved)


def test_regress_update_and_cli(tmp_path, full_run, capsys):
    from wbc_jax.campaign.regress import cell_means, compare

    b = tmp_path / "base"
    b.mkdir()
    shutil.copy(BASELINE / "spec.toml", b / "spec.toml")
    assert cli.main(["regress", "--baseline", str(b)]) == 2  # no baseline.json yet: one-line error
    assert "--update" in capsys.readouterr().err
    # compare() on the tiny campaign's own results: identical -> nothing moved; a shifted mean -> moved
    cells = cell_means(pd.read_csv(full_run[0] / "results.csv"))
    base = json.loads((BASELINE / "baseline.json").read_text())
    assert compare(dict(base, cells=cells), cells) == []
    shifted = [dict(c, R=c["R"] * 1.5) for c in cells]
    assert len(compare(dict(base, cells=cells), shifted)) == len(cells)


def test_regress_compare_two_campaigns(full_run, tmp_path, capsys):
    """``regress --compare BEFORE AFTER``: the tiny campaign against itself passes; against a copy with every R
    x 1.5 (outside the transport's band) or one run failed it fails with the table of what moved; against a copy
    with every run twice (other repetitions) success rates compare and it passes; a folder that is not a
    campaign's, or ``--update`` beside it, is a one-line error."""
    a = full_run[0]
    df = pd.read_csv(a / "results.csv")
    n_cells = len(df.groupby(["m", "mu", "d"]))

    def copy(name, table):
        d = tmp_path / name
        d.mkdir()
        shutil.copy(a / "manifest.json", d / "manifest.json")
        table.to_csv(d / "results.csv", index=False)
        return str(d)

    assert cli.main(["regress", "--compare", str(a), str(a)]) == 0
    assert f"all {n_cells} cells" in capsys.readouterr().out
    assert df.success.all()
    failed = df.assign(success=[False] + [True] * (len(df) - 1))
    for name, table, metric, rows in (("r", df.assign(R=df.R * 1.5), "R", n_cells), ("fail", failed, "n_success", 1)):
        assert cli.main(["regress", "--compare", str(a), copy(name, table)]) == 1
        out = capsys.readouterr().out
        assert "REGRESSION" in out and sum(line.split()[3:4] == [metric] for line in out.splitlines()) == rows, out
    assert cli.main(["regress", "--compare", str(a), copy("twice", pd.concat([df, df]))]) == 0
    capsys.readouterr()
    (tmp_path / "empty").mkdir()
    for args in (["--compare", str(a), str(tmp_path / "empty")], ["--compare", str(a), str(a), "--update"]):
        assert cli.main(["regress", *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and ("manifest.json" in err[0] or "--update" in err[0]), err


def test_regress_spec_mismatch_found_before_rerun(tmp_path, monkeypatch, capsys):
    from wbc_jax.campaign import regress

    b = tmp_path / "base"
    b.mkdir()
    shutil.copy(BASELINE / "baseline.json", b / "baseline.json")
    (b / "spec.toml").write_text((BASELINE / "spec.toml").read_text().replace("seed = 3", "seed = 4"))
    monkeypatch.setattr(regress, "run_campaign", lambda *a, **k: pytest.fail("reran before checking the baseline"))
    assert cli.main(["regress", "--baseline", str(b)]) == 2
    assert "spec changed since the baseline was stored" in capsys.readouterr().err
    base = json.loads((BASELINE / "baseline.json").read_text())
    for bad, msg in ((dict(base, cells="x"), "expected keys tolerance, cells"),
                     (dict(base, tolerance={}), "tolerance.R"),
                     (dict(base, cells=[{"m": 0.2}]), "cells[0]")):
        (b / "baseline.json").write_text(json.dumps(bad))
        assert cli.main(["regress", "--baseline", str(b)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err


def test_regress_groups_cells_by_every_factor():
    """A spec varying push_N besides m, mu, d: each (m, mu, d, push_N) combination is its own cell, not merged
    into (m, mu, d) cells of a pushed and an unpushed run; the baseline must cover exactly the design's cells."""
    from wbc_jax.campaign.regress import cell_means, check_coverage
    from wbc_jax.campaign.spec import parse_spec

    df = campaign_table(reps=2)
    df["push_N"] = np.tile([0.0, 30.0], 8)
    factors = ["m", "mu", "d", "push_N"]
    cells = cell_means(df, factors)
    assert len(cells) == 16 and {c["runs"] for c in cells} == {1} and len(cell_means(df)) == 8
    spec = parse_spec(dict(factors=dict(m=[0.2, 0.4], mu=[0.4, 1.0], d=[0.06, 0.1], push_N=[0.0, 30.0])), "s.toml")
    check_coverage(dict(cells=cells), spec, Path("b.json"))
    with pytest.raises(WbcJaxError, match="15 covered; missing m=0.4 mu=1 d=0.1 push_N=30"):
        check_coverage(dict(cells=cells[:-1]), spec, Path("b.json"))


def test_default_spec_follows_the_device():
    from wbc_jax.campaign.spec import default_spec_path

    assert default_spec_path(accelerator=False).name == "quick.toml"
    assert default_spec_path(accelerator=True).name == "paper_campaign.toml"


def test_chunk_function_state_types_are_stable(tiny_spec):
    """The chunk function returns the state with the avals it takes (shape, dtype and weak type of every leaf), so
    chunk 2 reuses chunk 1's compilation (a weak-typed initial leaf once made every campaign compile twice)."""
    import jax

    from wbc_jax.campaign import runner as C

    sim, _, b, _, logs_per_chunk, _ = C.build(load_spec(tiny_spec))
    fn = C.chunk_fn(sim, b.in_axes, logs_per_chunk)
    out, _ = jax.eval_shape(fn, b.model, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground)
    ins = jax.tree_util.tree_leaves_with_path(b.state)
    for (path, a), o in zip(ins, jax.tree_util.tree_leaves(out), strict=True):
        a = jax.typeof(a)
        assert (a.shape, a.dtype, a.weak_type) == (o.shape, o.dtype, o.weak_type), jax.tree_util.keystr(path)


def test_regress_noise_band_from_rounding_probes():
    """``regress --update``'s noise floor: means over the run and its rounding probes, noise = the largest deviation
    from that mean; compare() widens only that cell's and metric's band, by NOISE_FACTOR x noise (hand numbers)."""
    from wbc_jax.campaign.regress import NOISE_FACTOR, _with_noise, compare

    def cell(R, S, ok=1):
        return dict(m=0.2, mu=0.4, d=0.06, runs=1, n_success=ok, R=R, T=1e-3, S=S, max_slip_mm=None if R is None
                    else 0.01)

    cells = _with_noise([cell(0.10, 0.50)], [[cell(0.12, 0.50)], [cell(0.11, 0.50)]])
    c = cells[0]
    assert c["R"] == pytest.approx(0.11) and c["noise"]["R"] == pytest.approx(0.01)
    assert c["S"] == pytest.approx(0.50) and c["noise"]["S"] == pytest.approx(0.0)
    assert c["noise"]["T"] == 0.0 and c["n_success"] == 1
    base = dict(tolerance={k: dict(rel=0.02, abs=1e-3) for k in ("R", "T", "S", "max_slip_mm")}, cells=cells)
    band_R = 0.02 * 0.11 + 1e-3 + NOISE_FACTOR * 0.01
    assert compare(base, [dict(cell(0.11 + 0.99 * band_R, 0.50))]) == []
    moved = compare(base, [dict(cell(0.11 + 1.01 * band_R, 0.50))])
    assert [r["metric"] for r in moved] == ["R"]
    moved = compare(base, [dict(cell(0.11, 0.50 * 1.03))])  # S has no noise: the plain band (2 % + 1e-3)
    assert [r["metric"] for r in moved] == ["S"]
    assert _with_noise([cell(None, None, 0)], [[cell(0.1, 0.5)]])[0]["noise"]["R"] is None


def test_bench_rollout_rejects_a_bad_campaign_spec_before_timing(tmp_path, capsys):
    """``bench rollout --campaign SPEC`` validates the spec first: a bad key is one message naming the file and the
    key, exit 2, and no JSON written."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[campaign]\nreps = 0\n")
    js = tmp_path / "bench.json"
    assert cli.main(["bench", "rollout", "--batches", "1", "--steps", "2", "--campaign", str(bad),
                     "--json", str(js)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "campaign.reps" in err
    assert not js.exists()


def test_bench_round_figures_by_hand():
    """``bench rollout``'s figures of three timed rounds (batch 10, 100 env-steps = 50 control steps per call):
    rates from the median call times, everything but physics the median of the rounds' differences (not the
    difference of the medians: 2 ms here against 4 ms), with its smallest and largest round."""
    from wbc_jax.bench.rollout import round_figures

    f = round_figures([1.00, 1.20, 1.10], [1.50, 1.30, 1.10], batch=10, n_env=100, steps=50)
    assert f["rounds"] == 3
    assert f["physics_steps_per_s"] == pytest.approx(10 * 100 / 1.10)
    assert f["wbc_steps_per_s"] == pytest.approx(10 * 100 / 1.30)
    assert f["ratio"] == pytest.approx(1.10 / 1.30)
    # differences 0.50, 0.10, 0.00 s over 50 control steps: 10, 2, 0 ms
    assert f["non_physics_ms_per_step"] == pytest.approx(2.0)
    assert f["non_physics_ms_per_step_range"] == pytest.approx([0.0, 10.0])
    assert f["wbc_round_s"] == [1.50, 1.30, 1.10]


def test_bench_disturbed_round_is_named():
    """With two rounds (the median is their mean), a call whose slower round took more than ROUND_SPREAD times the
    faster gets one warning line naming the call, its rounds' range and the advice to rerun with more rounds; from
    three rounds (the median leaves one out) none."""
    from wbc_jax.bench.rollout import ROUND_SPREAD, disturbed, spread_warning

    assert spread_warning([1.00, 1.05], [2.00, 2.10], batch=8) is None  # 5 %: the usual spread
    w = spread_warning([1.00, 1.02], [0.51, 0.85], batch=16384)
    assert w.startswith("warning: batch 16384: the physics + WBC call's rounds took 0.510 to 0.850 s (1.67x)"), w
    assert w.endswith("rerun with --rounds 3 or more")
    assert "physics-only" in spread_warning([1.0, 1.0 * ROUND_SPREAD + 0.01], [1.0, 1.0], batch=4)
    assert disturbed("campaign program", [0.5, 0.8]).startswith("the campaign program's rounds took 0.500 to")
    assert disturbed("campaign program", [0.5, 0.8, 0.5]) is None


def test_report_reruns_on_the_campaigns_own_results(full_run, tmp_path, capsys):
    """``wbc-jax report`` on a campaign's own all-success results.csv: metrics R, T, S by default (the empty
    fail_reason column is no metric); the campaign folder itself is refused as --out (it holds the input)."""
    out = full_run[0]
    m = json.loads((out / "manifest.json").read_text())
    assert m["command"] == "wbc-jax campaign" and len(m["gains_hash"]) == 64 and m["default_gains"]
    assert cli.main(["report", str(out / "results.csv"), "--out", str(tmp_path / "rep")]) == 0
    assert list(json.loads((tmp_path / "rep" / "anova.json").read_text())["metrics"]) == ["R", "T", "S"]
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    assert cli.main(["report", str(out / "results.csv"), "--out", str(out), "--force"]) == 2
    assert "holds the input" in capsys.readouterr().err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
