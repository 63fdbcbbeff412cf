"""Issue 19: a careless or hostile user never loses files or a finished campaign, and every bad input is one line.

``BAD_INPUTS`` is the table of the bad inputs tried (every case of the issue) with the one-line message each must
give: exit 2, one stderr line ``wbc-jax CMD: error: ...`` containing the message, no traceback, and every file
that was there before still there, unchanged. None of them reaches a JAX compile (they fail before any work).
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from wbc_jax import cli
from wbc_jax.campaign.spec import SWEEPS

REPO = Path(__file__).resolve().parents[1]
TINY = SWEEPS.parent / "reports" / "baseline" / "spec.toml"  # the tiny campaign of tests/test_campaign.py
HUGE_SPEC = ("[campaign]\nreps = 1000\n[factors]\nm = [{}]\nmu = [{}]\nd = [0.06, 0.1]\n".format(
    ", ".join(f"{0.1 + 0.01 * i:.2f}" for i in range(20)), ", ".join(f"{0.1 + 0.01 * i:.2f}" for i in range(25))))


def campaign_table(reps: int = 1, seed: int = 0) -> pd.DataFrame:
    """A table with the columns of a campaign's results.csv (wbc_jax.campaign.results.results_table), all runs
    successful, 2 x 2 x 2 cells."""
    rng = np.random.default_rng(seed)
    df = pd.DataFrame([dict(m=m, mu=mu, d=d, rep=r) for m, mu, d in itertools.product([0.2, 0.4], [0.4, 1.0],
                                                                                      [0.06, 0.1])
                       for r in range(reps)])
    n = len(df)
    df.insert(0, "run", np.arange(n))
    df["seed"], df["success"] = rng.integers(0, 2**32, n), True
    for k in ("R", "T", "S", "max_slip_mm"):
        df[k] = rng.random(n)
    for k in ("fell", "trunk_low", "body_contact", "dropped", "slid", "hit_wall", "qp_flagged", "nonfinite"):
        df[k] = False
    df["boundary_fraction"], df["final_err_mm"] = 0.0, rng.random(n)
    df["fail_reason"], df["first_contact_s"], df["first_contact"] = "", np.nan, ""
    for k in ("obj_dx_mm", "obj_dy_mm", "obj_yaw_deg", "push_N"):
        df[k] = rng.random(n)
    return df


def _setup(t: Path) -> dict:
    """The files the bad inputs point at, inside ``t`` (the test's current folder)."""
    (t / "spec.toml").write_bytes(TINY.read_bytes())
    (t / "huge.toml").write_text(HUGE_SPEC)
    (t / "backend.toml").write_text(TINY.read_text().replace("[campaign]", '[campaign]\nbackend = "bullet"', 1))
    (t / "sensing.toml").write_text(TINY.read_text().replace("[campaign]", '[campaign]\nsensing = "late"', 1))
    (t / "delayed.toml").write_text(TINY.read_text().replace("[campaign]", '[campaign]\nbackend = "jax"\n'
                                                             'sensing = "delayed"', 1))
    (t / "factor.toml").write_text(TINY.read_text().replace("[factors]", "[factors]\nwind = [1.0, 2.0]", 1))
    (t / "variant.toml").write_text(TINY.read_text().replace("[factors]", '[factors]\nvariant = ["full", "no_arm"]', 1))
    full = t / "full"
    full.mkdir()
    (full / "notes.txt").write_text("my notes")
    ro = t / "readonly"
    ro.mkdir()
    (ro / "keep.txt").write_text("keep")
    ro.chmod(0o555)
    (t / "plain.txt").write_text("a file")
    camp = t / "camp"  # an earlier campaign's folder
    camp.mkdir()
    (camp / "manifest.json").write_text(json.dumps({"command": "wbc-jax campaign"}))
    campaign_table().to_csv(camp / "results.csv", index=False)
    (camp / "spec.toml").write_bytes(TINY.read_bytes())
    campaign_table().assign(push_N=np.arange(8.0)).to_csv(t / "results.csv", index=False)
    (t / "base").mkdir()
    (t / "base" / "spec.toml").write_bytes(TINY.read_bytes())
    (t / "base" / "baseline.json").write_text("{not json")
    return {"T": str(t), "LONG": str(t / ("x" * 250))}


# (name, argv, expected part of the one-line message). {T}: the test folder (also the current folder).
BAD_INPUTS = [
    # physics backend: the spec key and the flag name the expected values
    ("campaign_spec_backend", ["campaign", "--spec", "backend.toml", "--out", "new_b"],
     'campaign.backend: = \'bullet\': expected one of auto, jax, warp'),
    # factors beyond the paper (wbc_jax.campaign.factors): an unknown name, a bad level
    ("campaign_spec_unknown_factor", ["campaign", "--spec", "factor.toml", "--out", "new_f"],
     "factor.toml: factors.wind: unknown factor; expected one of m, mu, d, ground_mu, speed, push_N"),
    ("campaign_spec_bad_variant", ["campaign", "--spec", "variant.toml", "--out", "new_v"],
     "variant.toml: factors.variant: level 'no_arm': expected one of full, no_tray_cone, no_observer, no_posture"),
    ("bench_backend", ["bench", "rollout", "--backend", "bullet"], "--backend 'bullet'"),
    ("bench_sensing", ["bench", "rollout", "--backend", "jax:delayed"], "sensing = 'delayed' needs the Warp backend"),
    ("bench_rounds", ["bench", "rollout", "--rounds", "0"], "--rounds 0: expected an integer >= 1"),
    ("campaign_spec_sensing", ["campaign", "--spec", "sensing.toml", "--out", "new_s"],
     "campaign.sensing: = 'late': expected one of auto, exact, delayed"),
    ("campaign_spec_delayed_jax", ["campaign", "--spec", "delayed.toml", "--out", "new_d"],
     "campaign.sensing = 'delayed': needs campaign.backend 'warp' (here 'jax')"),
    # 1. --out never deletes what the command did not create
    ("campaign_out_nonempty", ["campaign", "--spec", "spec.toml", "--out", "full"], "folder is not empty"),
    ("campaign_out_nonempty_force", ["campaign", "--spec", "spec.toml", "--out", "full", "--force"],
     "holds no earlier wbc-jax campaign run"),
    ("campaign_out_cwd", ["campaign", "--spec", "spec.toml", "--out", "."], "is the current folder"),
    ("campaign_out_parent_of_cwd", ["campaign", "--spec", "spec.toml", "--out", ".."], "is the current folder"),
    ("campaign_out_empty_string", ["campaign", "--spec", "spec.toml", "--out", ""], "empty path"),
    ("campaign_out_plain_file", ["campaign", "--spec", "spec.toml", "--out", "plain.txt"], "is not a folder"),
    ("campaign_out_readonly", ["campaign", "--spec", "spec.toml", "--out", "readonly"], "folder is not empty"),
    ("campaign_out_earlier_run", ["campaign", "--spec", "spec.toml", "--out", "camp"], "pass --force"),
    ("campaign_out_holds_spec", ["campaign", "--spec", "camp/spec.toml", "--out", "camp", "--force"],
     "holds the input camp/spec.toml, which would be deleted"),
    ("report_out_holds_input", ["report", "camp/results.csv", "--out", "camp", "--force"],
     "holds the input camp/results.csv"),
    ("report_out_nonempty", ["report", "camp/results.csv", "--out", "full"], "folder is not empty"),
    ("report_out_cwd", ["report", "camp/results.csv", "--out", "."], "is the current folder"),
    ("report_out_empty_string", ["report", "camp/results.csv", "--out", ""], "empty path"),
    ("report_out_plain_file", ["report", "camp/results.csv", "--out", "plain.txt"], "is not a folder"),
    ("report_out_campaign_folder", ["report", "results.csv", "--out", "camp", "--force"],
     "holds no earlier wbc-jax report run"),
    ("demo_out_nonempty", ["demo", "--out", "full"], "folder is not empty"),
    ("trot_out_nonempty", ["trot", "--out", "full"], "folder is not empty"),
    ("tune_out_nonempty", ["tune", "--out", "full"], "folder is not empty"),
    # 7. output folder problems before setup
    ("campaign_out_name_too_long", ["campaign", "--spec", "spec.toml", "--out", "{LONG}"],
     "folder name is 250 bytes, at most 239"),
    ("campaign_out_parent_is_file", ["campaign", "--spec", "spec.toml", "--out", "plain.txt/sub"],
     "plain.txt is not a folder"),
    ("campaign_out_unwritable_parent", ["campaign", "--spec", "spec.toml", "--out", "/proc/wbc-jax-out/x"],
     "cannot create folders in /proc"),
    ("report_out_name_too_long", ["report", "camp/results.csv", "--out", "{LONG}"], "folder name is 250 bytes"),
    # 6. report: a continuous column as a factor
    ("report_continuous_factor", ["report", "results.csv", "--out", "rep", "--factors", "m,push_N"],
     "factor 'push_N' has 8 distinct values in 8 rows: a continuous column"),
    # 8. upper bounds
    ("campaign_million_runs", ["campaign", "--spec", "huge.toml", "--out", "big"], "1,000,000 runs need about"),
    ("campaign_spec_dev_zero", ["campaign", "--spec", "/dev/zero", "--out", "o"], "spec file larger than"),
    ("campaign_gains_dev_zero", ["campaign", "--spec", "spec.toml", "--gains", "/dev/zero", "--out", "o"],
     "gains file larger than"),
    ("report_results_dev_zero", ["report", "/dev/zero", "--out", "o"], "results file larger than"),
    ("demo_seconds_inf", ["demo", "--seconds", "inf", "--out", "o"], "--seconds = inf: expected 0 < value <= 600"),
    ("demo_seconds_nan", ["demo", "--seconds", "nan", "--out", "o"], "--seconds = nan"),
    ("demo_distance_huge", ["demo", "--distance", "1e9", "--out", "o"], "--distance = 1000000000.0: expected 0.05"),
    ("demo_iters_huge", ["demo", "--iters", "1000000", "--out", "o"], "--iters = 1000000"),
    ("trot_seconds_inf", ["trot", "--seconds", "inf", "--out", "o"], "--seconds = inf: expected 0 < value <= 600"),
    ("trot_step_time_tiny", ["trot", "--step-time", "1e-9", "--out", "o"], "--step-time = 1e-09"),
    # 9. regress checks its baseline before rerunning anything
    ("regress_malformed_baseline", ["regress", "--baseline", "base"], "not a valid baseline file (not JSON"),
]


@pytest.fixture(scope="module")
def bad_runs(tmp_path_factory):
    """Every BAD_INPUTS row through the real CLI (in process, from the test folder): (rc, stderr, stdout)."""
    import contextlib
    import io

    t = tmp_path_factory.mktemp("bad inputs ü")  # a space and non-ASCII in the path
    subst = _setup(t)
    before = _snapshot(t)
    cwd = os.getcwd()
    os.chdir(t)
    runs = {}
    try:
        for name, argv, _ in BAD_INPUTS:
            err, out = io.StringIO(), io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
                rc = cli.main([a.format(**subst) for a in argv])
            runs[name] = (rc, err.getvalue(), out.getvalue())
    finally:
        os.chdir(cwd)
        (t / "readonly").chmod(0o755)
    return runs, before, _snapshot(t)


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in folder.rglob("*")}


@pytest.mark.parametrize("name, argv, msg", BAD_INPUTS, ids=[r[0] for r in BAD_INPUTS])
def test_bad_input_is_one_line_exit_2(bad_runs, name, argv, msg):
    runs, _, _ = bad_runs
    rc, err, _ = runs[name]
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"wbc-jax {argv[0]}: error: ") and msg in lines[0], err


def test_bad_inputs_leave_every_file(bad_runs):
    """No bad input deleted, changed or added a file (the spec, notes.txt, the read-only folder, ...)."""
    _, before, after = bad_runs
    assert after == before


# ---------------------------------------------------------------- outputs: --force, own folders


def test_own_folder_recognised_by_manifest_and_replaced_only_with_force(tmp_path):
    from wbc_jax.errors import OutputError
    from wbc_jax.io_utils import atomic_dir, check_out_dir

    out = tmp_path / "demo"
    check_out_dir(out, "wbc-jax demo")
    with atomic_dir(out, command="wbc-jax demo") as tmp:  # demo and trot write no manifest of their own
        (tmp / "summary.json").write_text("{}")
    assert json.loads((out / "manifest.json").read_text()) == {"command": "wbc-jax demo"}
    with pytest.raises(OutputError, match="pass --force"):
        check_out_dir(out, "wbc-jax demo")
    with pytest.raises(OutputError, match="holds no earlier wbc-jax trot run"):
        check_out_dir(out, "wbc-jax trot", force=True)
    assert check_out_dir(out, "wbc-jax demo", force=True) == out
    (tmp_path / "empty").mkdir()
    assert check_out_dir(tmp_path / "empty", "wbc-jax demo") == tmp_path / "empty"


# ---------------------------------------------------------------- a finished campaign is never lost


def test_report_failure_keeps_results_and_report_can_be_rerun(tmp_path, monkeypatch, capsys):
    """The statistics failing after the simulation: results.csv and manifest.json stay, report_error.txt says why,
    the error is one line, and ``wbc-jax report`` on the kept results.csv works."""
    from wbc_jax.analysis import report
    from wbc_jax.campaign import results as campaign
    from wbc_jax.errors import ReportError

    out = tmp_path / "camp"
    out.mkdir()
    campaign_table().to_csv(out / "results.csv", index=False)
    manifest = {"command": "wbc-jax campaign", "warnings": []}
    (out / "manifest.json").write_text(json.dumps(manifest))

    def boom(*a, **k):
        raise ValueError("r_matrix performs f_test\nfor using dimensions")

    monkeypatch.setattr(report, "run_report", boom)
    with pytest.raises(ReportError) as e:
        campaign.campaign_report(out, manifest, [])
    msg = str(e.value)
    assert "\n" not in msg and "results.csv and manifest.json are written" in msg and "wbc-jax report" in msg
    assert "ValueError: r_matrix" in (out / "report_error.txt").read_text()
    assert json.loads((out / "manifest.json").read_text())["warnings"][0].startswith("no report: ValueError")
    monkeypatch.undo()
    assert cli.main(["report", str(out / "results.csv"), "--out", str(out / "report")]) == 0
    assert (out / "report" / "report.md").exists() and (out / "results.csv").exists()


@pytest.mark.parametrize("case, warning", [
    ("all_success", None),
    ("nan_metric_1rep", "main effects only"),
    ("empty_cell_1rep", "1 cells have runs but no successful run"),
    ("huge_values", "values up to 1e+250 overflow"),
    ("all_fail", "no successful runs"),
    ("empty_metric_cell", "1 successful run(s) have no R value"),
])
def test_report_works_on_any_campaign_table(tmp_path, case, warning):
    """A campaign's results.csv (1 rep, all success, all fail, NaN and empty cells, huge values) gets a report,
    with default metrics R, T, S and the problem among its warnings."""
    from wbc_jax.analysis.report import run_report

    df = campaign_table()
    if case == "nan_metric_1rep":
        df.loc[2, "R"] = np.nan
    elif case == "empty_cell_1rep":  # 1 rep, one run failed: a cell with no successful run
        df.loc[2, ["success", "fail_reason"]] = [False, "fell"]
    elif case == "huge_values":
        df.loc[3, "R"] = 1e250
    elif case == "all_fail":
        df["success"], df["fail_reason"] = False, "fell"
    csv = tmp_path / "results.csv"
    df.to_csv(csv, index=False)
    if case == "empty_metric_cell":  # an empty cell in the CSV text itself
        lines = csv.read_text().splitlines()
        head = lines[0].split(",")
        row = lines[3].split(",")
        row[head.index("R")] = ""
        lines[3] = ",".join(row)
        csv.write_text("\n".join(lines) + "\n")
    summary = run_report(str(csv), str(tmp_path / "rep"), figures=False)
    md = (tmp_path / "rep" / "report.md").read_text()
    if case == "all_fail":
        assert summary["metrics"] == {} and "## Design" in md
    else:
        assert set(summary["metrics"]) <= {"R", "T", "S"} and "T" in summary["metrics"]
    if warning is None:
        assert list(summary["metrics"]) == ["R", "T", "S"]
    else:
        assert warning in md


def test_report_cli_on_all_success_campaign_table_with_figures(tmp_path, capsys):
    csv = tmp_path / "results.csv"
    campaign_table(reps=2).to_csv(csv, index=False)
    assert cli.main(["report", str(csv), "--out", str(tmp_path / "rep")]) == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "rep" / "anova.json").read_text())["manifest"]["metrics"] == ["R", "T", "S"]


# ---------------------------------------------------------------- checkpoint identity and damage


def _fake_ckpt(tmp_path, gains=None, **meta_over):
    """A checkpoint next to ``tmp_path/out`` with the identity of the tiny spec (and ``gains``)."""
    import hashlib

    from wbc_jax.campaign.checkpoint import ckpt_dir as _ckpt_dir
    from wbc_jax.campaign.manifest import run_identity
    from wbc_jax.campaign.spec import load_spec

    ck = _ckpt_dir(tmp_path / "out")
    ck.mkdir()
    (ck / "state_1.npz").write_bytes(b"state bytes")
    meta = dict(identity=run_identity(load_spec(TINY), gains), chunks_done=1, n_chunks=3, wall_s=1.0, marks=[],
                p_goal=None, state_file="state_1.npz",
                state_sha256=hashlib.sha256(b"state bytes").hexdigest())
    meta.update(meta_over)
    (ck / "meta.json").write_text(json.dumps(meta))
    return ck


@pytest.mark.parametrize("damage, msg", [
    ("gains", "gains_hash differ: started with other --gains"),
    ("versions", "versions differ"),
    ("spec", "spec_hash differ"),
    ("truncated_state", "SHA-256 differs"),
    ("missing_state", "state_1.npz missing"),
    ("missing_meta", "meta.json missing"),
    ("garbage_meta", "meta.json unreadable"),
    ("old_meta", "meta.json unreadable or incomplete"),
    ("all_chunks_claimed", "damaged checkpoint (chunks_done 3 of 3, state file 'state_1.npz'"),
])
def test_resume_refuses_a_foreign_or_damaged_checkpoint(tmp_path, monkeypatch, capsys, damage, msg):
    """``--resume`` with a checkpoint of other gains, versions or spec, or a damaged one: one line naming what and
    how to restart, before anything is built (build is not reached)."""
    from wbc_jax.campaign import runner as campaign
    from wbc_jax.control.transport import default_gains

    ck = _fake_ckpt(tmp_path, gains=default_gains()._replace(kp_obj=default_gains().kp_obj * 0.5)
                    if damage == "gains" else None)
    meta = json.loads((ck / "meta.json").read_text())
    if damage == "versions":
        meta["identity"]["versions"]["jax"] = "0.0.1"
    elif damage == "spec":
        meta["identity"]["spec_hash"] = "0" * 64
    elif damage == "truncated_state":
        (ck / "state_1.npz").write_bytes(b"state")
    elif damage == "missing_state":
        (ck / "state_1.npz").unlink()
    elif damage == "missing_meta":
        (ck / "meta.json").unlink()
    elif damage == "garbage_meta":
        (ck / "meta.json").write_text('{"chunks_done": ')
    elif damage == "old_meta":  # a checkpoint of the version before identities: spec hash and run count only
        meta = dict(spec_hash=meta["identity"]["spec_hash"], n_runs=8, chunks_done=1, n_chunks=3, wall_s=1.0,
                    marks=[], state_file="state_1.npz")
    elif damage == "all_chunks_claimed":
        meta["chunks_done"] = 3
    if damage not in ("missing_meta", "garbage_meta"):
        (ck / "meta.json").write_text(json.dumps(meta))
    monkeypatch.setattr(campaign, "build", lambda *a, **k: pytest.fail("built despite a bad checkpoint"))
    assert cli.main(["campaign", "--spec", str(TINY), "--out", str(tmp_path / "out"), "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and msg in err[0] and "--resume to start over" in err[0], err
    assert ck.exists()  # kept: the user decides


def test_run_identity_names_what_determines_the_result():
    from wbc_jax.campaign.manifest import run_identity
    from wbc_jax.campaign.spec import load_spec
    from wbc_jax.control.transport import default_gains

    spec = load_spec(TINY)
    a = run_identity(spec)
    assert set(a) == {"spec_hash", "gains_hash", "backend", "platform", "versions", "n_runs"}
    assert a["backend"] == "jax" and a["n_runs"] == 8 and a["versions"]["jax"] and a["versions"]["mujoco"]
    assert run_identity(spec, default_gains()) == a  # the defaults, given or not
    assert run_identity(spec, default_gains()._replace(kp_obj=default_gains().kp_obj * 2))["gains_hash"] != \
        a["gains_hash"]


# ---------------------------------------------------------------- regress, bench, git


def test_regress_spec_mismatch_found_before_rerun(tmp_path, monkeypatch, capsys):
    from wbc_jax.campaign import regress

    b = tmp_path / "base"
    b.mkdir()
    shutil.copy(TINY.parent / "baseline.json", b / "baseline.json")
    (b / "spec.toml").write_text(TINY.read_text().replace("seed = 3", "seed = 4"))
    monkeypatch.setattr(regress, "run_campaign", lambda *a, **k: pytest.fail("reran before checking the baseline"))
    assert cli.main(["regress", "--baseline", str(b)]) == 2
    assert "spec changed since the baseline was stored" in capsys.readouterr().err
    base = json.loads((TINY.parent / "baseline.json").read_text())
    for bad, msg in ((dict(base, cells="x"), "expected keys tolerance, cells"),
                     (dict(base, tolerance={}), "tolerance.R"),
                     (dict(base, cells=[{"m": 0.2}]), "cells[0]")):
        (b / "baseline.json").write_text(json.dumps(bad))
        assert cli.main(["regress", "--baseline", str(b)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err


def test_bench_defaults_are_cpu_sized(monkeypatch):
    import jax

    from wbc_jax.bench import rollout

    assert jax.default_backend() == "cpu"
    got = {}
    monkeypatch.setattr(rollout, "run_bench", lambda **k: got.update(k))
    monkeypatch.setattr(rollout, "run_profile", lambda **k: got.update(profile=k["batch"]))
    assert cli.main(["bench", "rollout"]) == 0 and cli.main(["bench", "profile"]) == 0
    assert max(got["batches"]) <= 16 and got["profile"] <= 16


def test_git_commit_is_this_projects_or_none(tmp_path):
    from wbc_jax.campaign.manifest import git_commit as _git_commit

    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    if not head:
        pytest.skip("the tests do not run from a git checkout")
    assert _git_commit().split("-")[0] == head
    other = tmp_path / "other"  # a copy of the package inside another repository
    (other / "vendor" / "wbc_jax").mkdir(parents=True)
    shutil.copy(REPO / "wbc_jax" / "__init__.py", other / "vendor" / "wbc_jax" / "__init__.py")
    subprocess.run(["git", "init", "-q", str(other)], check=True)
    subprocess.run(["git", "-C", str(other), "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q",
                    "--allow-empty", "-m", "x"], check=True)
    assert _git_commit(other / "vendor" / "wbc_jax") is None
    (other / "wbc_jax").mkdir()  # at the root, but not tracked there
    assert _git_commit(other / "wbc_jax") is None
    assert _git_commit(tmp_path / "nowhere") is None
