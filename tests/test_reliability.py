"""A careless or hostile user never loses files or a finished campaign, and every bad input is one line.

``BAD_INPUTS`` is the table of the bad inputs tried with the one-line message each must give: exit 2, one stderr
line ``wbc-jax CMD: error: ...`` containing the message, no traceback, no numpy repr, and every file that was there
before still there, unchanged. None of them reaches a JAX compile (they fail before any work; the two chunk-plan
rows reach a stand-in for the build, which compiles the batch's initial states). tests/test_safety.py: locks,
folder policy, interrupts, report failures.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
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
    _setup_round_two(t)
    return {"T": str(t), "LONG": str(t / ("x" * 250))}


def _baseline(t: Path, name: str, cells=None, mode=None) -> None:
    """A baseline folder ``t/name`` (the tiny spec; its committed baseline.json with ``cells`` instead, and
    ``mode``)."""
    b = t / name
    b.mkdir()
    (b / "spec.toml").write_bytes(TINY.read_bytes())
    base = json.loads((TINY.parent / "baseline.json").read_text())
    (b / "baseline.json").write_text(json.dumps(base if cells is None else dict(base, cells=cells)))
    if mode is not None:
        (b / "baseline.json").chmod(mode)


def _setup_round_two(t: Path) -> None:
    """Files of the second round's rows: own and legacy campaign folders, a checkpoint of finished chunks,
    baselines, gains and specs that make the QP infeasible, a tuning spec copied out of sweeps/, a link."""
    ck = t / ".ckdir.campaign-ckpt"  # 2 of 3 chunks finished beside --out ckdir
    ck.mkdir()
    (ck / "state_2.npz").write_bytes(b"state")
    (ck / "meta.json").write_text(json.dumps(dict(chunks_done=2, n_chunks=3, identity={}, state_file="state_2.npz")))
    legacy = t / "legacy"  # an earlier campaign whose manifest lists no files
    legacy.mkdir()
    (legacy / "manifest.json").write_text(json.dumps({"command": "wbc-jax campaign"}))
    own = t / "own"  # an earlier campaign (results only) and the user's own report folder inside it
    (own / "report").mkdir(parents=True)
    (own / "manifest.json").write_text(json.dumps({"command": "wbc-jax campaign",
                                                   "files": ["manifest.json", "results.csv"]}))
    (own / "results.csv").write_text("run\n0\n")
    (own / "report" / "mine.md").write_text("my report")
    _fake_ckpt(t, out="resumed")  # made with the jax backend
    cells = json.loads((TINY.parent / "baseline.json").read_text())["cells"]
    _baseline(t, "base_empty", cells=[])
    _baseline(t, "base_part", cells=cells[:-1])
    _baseline(t, "base_ro", mode=0o444)
    (t / "fmin.toml").write_text("[gains]\nf_min = 500.0\nf_max = 1.0\n")
    (t / "rlam.toml").write_text("[gains]\nr_lam = 0.0\n")
    factor = lambda line: TINY.read_text().replace("[factors]", f"[factors]\n{line}", 1)  # noqa: E731
    (t / "gain_zero.toml").write_text(factor('"gain.r_vdot" = [0.0, 1.0]'))
    (t / "gain_fmax.toml").write_text(factor('"gain.f_max" = [0.001, 1.0]'))
    (t / "chunks.toml").write_text(TINY.read_text().replace("max_seconds = 0.12", "max_seconds = 0.13"))
    (t / "short.toml").write_text(TINY.read_text().replace("max_seconds = 0.12", "max_seconds = 0.0001"))
    (t / "tune.toml").write_bytes((SWEEPS / "gain_tuning_cpu.toml").read_bytes())
    (t / "link_file").symlink_to(t / "plain.txt")


# (name, argv, expected part of the one-line message). {T}: the test folder (also the current folder).
BAD_INPUTS = [
    # physics backend: the spec key and the flag name the expected values
    ("campaign_spec_backend", ["campaign", "--spec", "backend.toml", "--out", "new_b"],
     'campaign.backend: = \'bullet\': expected one of auto, jax, warp'),
    # factors beyond the paper (wbc_jax.campaign.factors): an unknown name, a bad level
    ("campaign_spec_unknown_factor", ["campaign", "--spec", "factor.toml", "--out", "new_f"],
     "factor.toml: factors.wind: unknown factor; expected one of m, mu, d, ground_mu, speed, obj_accel, push_N"),
    ("campaign_spec_bad_variant", ["campaign", "--spec", "variant.toml", "--out", "new_v"],
     "variant.toml: factors.variant: level 'no_arm': expected one of full, no_tray_cone, no_observer, no_posture"),
    ("bench_backend", ["bench", "rollout", "--backend", "bullet"], "--backend 'bullet'"),
    ("bench_sensing", ["bench", "rollout", "--backend", "jax:delayed"], "sensing = 'delayed' needs the Warp backend"),
    ("bench_rounds", ["bench", "rollout", "--rounds", "0"], "--rounds 0: expected an integer >= 1"),
    ("bench_cold_warm_alone", ["bench", "rollout", "--cold-warm"], "--cold-warm: expected with rollout --campaign"),
    ("bench_cold_warm_processes", ["bench", "rollout", "--campaign", "spec.toml", "--cold-warm", "--num-processes",
                                   "2", "--process-id", "0", "--coordinator", "localhost:1"],
     "--cold-warm: expected in a one-process bench"),
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
    # second round: an output folder is one command's at a time (held by another process: see bad_runs)
    ("campaign_out_locked", ["campaign", "--spec", "spec.toml", "--out", "locked"],
     "--out locked: in use by wbc-jax campaign (pid"),
    ("demo_out_locked", ["demo", "--out", "locked"], "in use by wbc-jax campaign (pid"),
    ("report_out_locked", ["report", "results.csv", "--out", "locked"], "in use by wbc-jax campaign (pid"),
    # finished chunks are never discarded implicitly; --force replaces only what the tool wrote; links
    ("campaign_finished_chunks", ["campaign", "--spec", "spec.toml", "--out", "ckdir"],
     "2 of 3 chunks finished in"),
    ("campaign_finished_chunks_says_how", ["campaign", "--spec", "spec.toml", "--out", "ckdir"],
     "continue with --resume, or --force to start over"),
    ("campaign_force_legacy_folder", ["campaign", "--spec", "spec.toml", "--out", "legacy", "--force"],
     "does not list the files it wrote"),
    ("campaign_force_keeps_users_report", ["campaign", "--spec", "spec.toml", "--out", "own", "--force"],
     "holds report, which the earlier wbc-jax campaign run did not write"),
    ("campaign_out_link_to_file", ["campaign", "--spec", "spec.toml", "--out", "link_file"], "is a link to"),
    ("bench_json_exists", ["bench", "qp", "--json", "plain.txt"], "--json plain.txt: exists; pass --force"),
    ("bench_json_no_folder", ["bench", "qp", "--json", "nowhere/b.json"], "does not exist"),
    ("bench_json_is_folder", ["bench", "qp", "--json", "full"], "--json full: is a folder"),
    # regress cannot pass having compared nothing
    ("regress_no_cells", ["regress", "--baseline", "base_empty"], "no cells: it would compare nothing"),
    ("regress_cells_miss_design", ["regress", "--baseline", "base_part"],
     "its cells do not cover the 8 cells of"),
    ("regress_update_read_only", ["regress", "--baseline", "base_ro", "--update"],
     "baseline.json: read-only (mode 0444)"),
    # gains that make the QP infeasible or singular
    ("campaign_gains_fmin_above_fmax", ["campaign", "--spec", "spec.toml", "--gains", "fmin.toml", "--out", "o"],
     "gains.f_min: f_min 500 N > f_max 1 N: no contact force would satisfy the QP's bounds"),
    ("campaign_gains_zero_regularization", ["campaign", "--spec", "spec.toml", "--gains", "rlam.toml", "--out", "o"],
     "gains.r_lam: = 0: a regularization weight must be > 0"),
    ("campaign_factor_zero_regularization", ["campaign", "--spec", "gain_zero.toml", "--out", "o"],
     "factors.gain.r_vdot: level 0: a regularization weight's multiplier must be > 0"),
    ("campaign_factor_fmax_below_fmin", ["campaign", "--spec", "gain_fmax.toml", "--out", "o"],
     "factors.gain.f_max: f_min 2 N > f_max 0.4 N"),
    # a max_seconds that no chunks can meet exactly; one too short for metrics
    ("campaign_chunks_overrun_cap", ["campaign", "--spec", "chunks.toml", "--out", "o"],
     "max_seconds = 0.13 is not a whole number of logged intervals (0.02 s = 20 control steps), so 0.16 s would be "
     "simulated; use a multiple of 0.02 s, e.g. 0.12"),
    ("campaign_cap_too_short", ["campaign", "--spec", "short.toml", "--out", "o"],
     "max_seconds = 0.0001: shorter than one logged interval (0.02 s"),
    # unclear messages made clear
    ("campaign_resume_other_backend", ["campaign", "--spec", "spec.toml", "--out", "resumed", "--resume",
                                       "--backend", "warp"],
     "made with the 'jax' physics backend, this run would use 'warp' (--backend warp); resume with --backend jax"),
    ("tune_relative_campaign_spec", ["tune", "--spec", "tune.toml", "--out", "tn"],
     "campaign spec 'quick.toml': no file"),
    ("campaign_unknown_flag", ["campaign", "--reps", "3"], "unrecognized arguments: --reps 3"),
    ("report_alpha_not_a_number", ["report", "results.csv", "--out", "o", "--alpha", "x"],
     "argument --alpha: invalid float value: 'x'"),
]


@pytest.fixture(scope="module")
def bad_runs(tmp_path_factory):
    """Every BAD_INPUTS row through the real CLI (in process, from the test folder): (rc, stderr, stdout)."""
    import contextlib
    import io

    from wbc_jax.campaign import runner

    t = tmp_path_factory.mktemp("bad inputs ü")  # a space and non-ASCII in the path
    subst = _setup(t)
    holder = hold_lock(t / "locked")  # another process runs a campaign into t/locked
    before = _snapshot(t)
    cwd = os.getcwd()
    os.chdir(t)
    runs = {}
    keep_build, runner.build = runner.build, planned_only
    try:
        for name, argv, _ in BAD_INPUTS:
            err, out = io.StringIO(), io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
                rc = cli.main([a.format(**subst) for a in argv])
            runs[name] = (rc, err.getvalue(), out.getvalue())
    finally:
        runner.build = keep_build
        os.chdir(cwd)
        holder.kill()
        holder.wait()
        (t / "readonly").chmod(0o755)
    return runs, before, _snapshot(t)


def planned_only(spec, gains=None):
    """A stand-in for ``campaign.build``: the chunk plan of ``spec`` on the flat scene (1 ms control steps) with a
    planned duration of 5 s, without building the batch; the rows that reach it stop at its checks."""
    from types import SimpleNamespace

    from wbc_jax.campaign.build import Built, chunk_plan

    return Built(SimpleNamespace(dt_control=0.001), None, None, 5.0, *chunk_plan(spec.campaign, 0.001, 5.0))


def hold_lock(out: Path, command: str = "wbc-jax campaign") -> subprocess.Popen:
    """Another process that claims ``out`` (wbc_jax.io_utils.claim_out_dir) and holds it until killed."""
    code = (f"from wbc_jax.io_utils import claim_out_dir; claim_out_dir({str(out)!r}, {command!r}); "
            "print('held', flush=True); import time; time.sleep(600)")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=REPO)
    assert p.stdout.readline().strip() == "held"
    return p


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in folder.rglob("*")}


@pytest.mark.parametrize("name, argv, msg", BAD_INPUTS, ids=[r[0] for r in BAD_INPUTS])
def test_bad_input_is_one_line_exit_2(bad_runs, name, argv, msg):
    runs, _, _ = bad_runs
    rc, err, _ = runs[name]
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"wbc-jax {argv[0]}: error: ") and msg in lines[0], err
    assert "np." not in lines[0] and "Traceback" not in err


def test_bad_inputs_leave_every_file(bad_runs):
    """No bad input deleted, changed or added a file (the spec, notes.txt, the read-only folder, the other
    process's lock, the checkpoint of finished chunks, the user's report inside a campaign folder, ...)."""
    _, before, after = bad_runs
    assert after == before


# ---------------------------------------------------------------- checkpoint identity and damage


def _fake_ckpt(tmp_path, gains=None, out="out", **meta_over):
    """A checkpoint next to ``tmp_path/out`` with the identity of the tiny spec (and ``gains``)."""
    import hashlib

    from wbc_jax.campaign.checkpoint import ckpt_dir as _ckpt_dir
    from wbc_jax.campaign.manifest import run_identity
    from wbc_jax.campaign.spec import load_spec

    ck = _ckpt_dir(tmp_path / out)
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


def test_resume_refuses_a_checkpoint_of_other_chunks(tmp_path):
    """A checkpoint whose meta.json records chunks of another length (a chunk plan of another version) is refused
    with the restart line; one of the same length, or one written before meta.json recorded it, is read."""
    from wbc_jax.campaign.checkpoint import CheckpointError, read_meta
    from wbc_jax.campaign.manifest import run_identity
    from wbc_jax.campaign.spec import load_spec

    identity = run_identity(load_spec(TINY))
    for out, logs in (("a", 2), ("b", None)):
        ck = _fake_ckpt(tmp_path, out=out, **({} if logs is None else dict(logs_per_chunk=logs)))
        assert read_meta(ck, identity, 3, logs_per_chunk=2)["chunks_done"] == 1
    ck = _fake_ckpt(tmp_path, out="c", logs_per_chunk=3)
    with pytest.raises(CheckpointError, match=r"chunks of 3 logged intervals, this run's have 2 .*--resume to start"):
        read_meta(ck, identity, 3, logs_per_chunk=2)


def test_run_identity_names_what_determines_the_result():
    from wbc_jax.campaign.manifest import run_identity
    from wbc_jax.campaign.spec import load_spec
    from wbc_jax.control.transport import default_gains

    spec = load_spec(TINY)
    a = run_identity(spec)
    assert set(a) == {"spec_hash", "gains_hash", "backend", "platform", "versions", "n_runs", "deterministic_ops"}
    assert a["backend"] == "jax" and a["n_runs"] == 8 and a["versions"]["jax"] and a["versions"]["mujoco"]
    assert run_identity(spec, default_gains()) == a  # the defaults, given or not
    assert run_identity(spec, default_gains()._replace(kp_obj=default_gains().kp_obj * 2))["gains_hash"] != \
        a["gains_hash"]
