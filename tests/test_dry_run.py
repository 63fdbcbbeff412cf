"""``wbc-jax campaign --dry-run``: the campaign's own figures and refusals, nothing compiled or written."""

import os
import shutil

import numpy as np
import pytest

from wbc_jax import cli
from wbc_jax.campaign import checkpoint, size
from wbc_jax.campaign.build import LOG_EVERY, build_ahead
from wbc_jax.campaign.dry_run import dry_run
from wbc_jax.campaign.spec import load_spec
from wbc_jax.errors import CheckpointError, LimitError, OutputError
from wbc_jax.io_utils import claim_out_dir, release_out_dir


def _tree(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_figures_are_the_campaigns_own_and_nothing_is_written(full_run, tiny_spec, tmp_path, capsys):
    out = tmp_path / "new" / "camp"
    plan = dry_run(str(tiny_spec), str(out))
    assert _tree(tmp_path) == []  # no folder, no lock, no checkpoint
    built, _ = build_ahead(load_spec(tiny_spec))
    manifest = full_run[1]
    rows = len((full_run[0] / "results.csv").read_text().splitlines()) - 1
    assert plan["runs"] == built.design.n == manifest["n_runs"] == rows
    assert plan["runs"] == plan["cells"] * plan["reps"]
    assert plan["chunks"] == built.n_chunks and plan["out_state"] == "new" and plan["chunks_done"] == 0
    per_chunk = built.logs_per_chunk * LOG_EVERY * built.sim.dt_control
    assert plan["seconds"] == pytest.approx(built.n_chunks * per_chunk)
    substeps = load_spec(tiny_spec).campaign["control_substeps"]  # the steps the chunks take, counted
    assert plan["physics_steps"] == built.n_chunks * built.logs_per_chunk * LOG_EVERY * substeps
    assert plan["env_steps"] == plan["physics_steps"] * plan["runs"]
    assert plan["memory_bytes"] == size.memory_need(load_spec(tiny_spec))[0]
    lines = capsys.readouterr().out.splitlines()
    assert lines[-6].startswith("dry run of campaign") and lines[-1].startswith("the campaign would start")
    assert f"{plan['runs']} runs = {plan['cells']} cells x {plan['reps']} reps" in lines[-5]


def test_an_earlier_campaign_is_refused_as_the_campaign_refuses_it(full_run, tiny_spec, tmp_path):
    out = tmp_path / "earlier"
    shutil.copytree(full_run[0], out)
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    with pytest.raises(OutputError, match="holds an earlier wbc-jax campaign run; pass --force"):
        dry_run(str(tiny_spec), str(out))
    assert dry_run(str(tiny_spec), str(out), force=True)["out_state"] == "replaced"
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before  # --force with --dry-run replaces nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["earlier"]


def test_a_checkpoint_needs_resume_and_is_checked(full_run, tiny_spec, tmp_path, capsys):
    out = tmp_path / "camp"
    ck = checkpoint.ckpt_dir(out.absolute())
    ck.mkdir()
    with pytest.raises(OutputError, match="unreadable checkpoint"):  # a damaged one
        (ck / "meta.json").write_text("{}")
        dry_run(str(tiny_spec), str(out))
    # a checkpoint of 1 finished chunk, as the campaign writes it: its identity and state file are checked
    from wbc_jax.campaign.manifest import run_identity

    spec = load_spec(tiny_spec)
    built, _ = build_ahead(spec)
    meta = dict(identity=run_identity(spec, None, backend="jax"), chunks_done=1, n_chunks=built.n_chunks,
                logs_per_chunk=built.logs_per_chunk, marks=[], p_goal=None, wall_s=1.0, sessions=[])
    checkpoint.save_state(ck, {"x": np.zeros(3)}, meta)  # the campaign's writer (a stand-in state)
    with pytest.raises(OutputError, match="1 of .* chunks finished"):
        dry_run(str(tiny_spec), str(out))
    forced = dry_run(str(tiny_spec), str(out), force=True)  # the campaign would delete them: said, not done
    assert forced["chunks_discarded"] == 1 and "--force deletes the checkpoint of 1 finished" in capsys.readouterr().out
    plan = dry_run(str(tiny_spec), str(out), resume=True)
    assert plan["out_state"] == "resumed" and plan["chunks_done"] == 1
    assert "resumes after 1 of" in capsys.readouterr().out
    assert sorted(p.name for p in ck.iterdir()) == ["meta.json", "state_1.npz"] and not out.exists()
    (ck / "state_1.npz").write_bytes(b"damaged")
    with pytest.raises(CheckpointError, match="damaged"):
        dry_run(str(tiny_spec), str(out), resume=True)


def test_a_folder_in_use_and_a_batch_too_large_are_refused(tiny_spec, tmp_path, monkeypatch):
    out = tmp_path / "busy"
    claim_out_dir(out, "wbc-jax campaign")  # this process holds it, as a running campaign would
    try:
        with pytest.raises(OutputError, match="in use by wbc-jax campaign"):
            dry_run(str(tiny_spec), str(out))
    finally:
        release_out_dir(out)
    monkeypatch.setattr(size, "_available_memory", lambda: 1 << 20)
    with pytest.raises(LimitError, match="--allow-large"):
        dry_run(str(tiny_spec), str(tmp_path / "big"))
    assert dry_run(str(tiny_spec), str(tmp_path / "big"), allow_large=True)["available_bytes"] == 1 << 20
    assert os.listdir(tmp_path) == []


def test_cli_dry_run_exit_codes(tiny_spec, tmp_path, capsys):
    out = tmp_path / "camp"
    assert cli.main(["campaign", "--spec", str(tiny_spec), "--out", str(out), "--dry-run"]) == 0
    assert "nothing is simulated, nothing written in --out" in capsys.readouterr().out and not out.exists()
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert cli.main(["campaign", "--spec", str(tiny_spec), "--out", str(out), "--dry-run", "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "folder is not empty" in err[0] and (out / "notes.txt").read_text() == "mine"


def test_python_dry_run(tiny_spec, tmp_path):
    import wbc_jax

    plan = wbc_jax.run_campaign(tiny_spec, tmp_path / "camp", dry_run=True, report=False, progress=False)
    assert plan["runs"] == load_spec(tiny_spec).reps * plan["cells"] and os.listdir(tmp_path) == []


def test_processes_to_come_are_counted_not_joined(tiny_spec, tmp_path, monkeypatch):
    import jax

    from wbc_jax.campaign import dry_run as dry_run_mod

    parts = dry_run_mod.layout_parts
    assert [parts(1, "warp", 4), parts(2, "jax", 4, 2), parts(3, "jax", 1), parts(1, "jax", 4, 1)] == [4, 8, 3, 4]
    seen = {}
    monkeypatch.setattr(dry_run_mod, "memory_need", lambda spec, parts: (seen.setdefault("parts", parts), None))
    argv = ["campaign", "--spec", str(tiny_spec), "--out", str(tmp_path / "c"), "--dry-run", "--backend", "jax",
            "--num-processes", "3", "--process-id", "0", "--coordinator", "localhost:1"]
    assert cli.main(argv) == 0 and seen.pop("parts") == 3 * jax.local_device_count() and jax.process_count() == 1
    assert cli.main(argv + ["--local-device-ids", "0,1"]) == 0 and seen["parts"] == 6  # two devices per process
