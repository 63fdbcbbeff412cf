"""A finished campaign is never lost (second part of tests/test_reliability.py): output folders owned by one command
at a time, ``--force`` replacing only what a run wrote, links written through, files 0644, interrupts that exit 130 /
143 with one line, a failing report that keeps the results, regress grouping by every factor, the campaign's
warnings. None of them compiles anything.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from test_reliability import REPO, TINY, campaign_table, hold_lock, planned_only

from wbc_jax import cli
from wbc_jax.errors import OutputError, WbcJaxError

CMD = "wbc-jax campaign"


# ---------------------------------------------------------------- outputs: --force, own folders


def test_own_folder_recognised_by_manifest_and_replaced_only_with_force(tmp_path):
    from wbc_jax.errors import OutputError
    from wbc_jax.io_utils import atomic_dir, check_out_dir

    out = tmp_path / "demo"
    check_out_dir(out, "wbc-jax demo")
    with atomic_dir(out, command="wbc-jax demo") as tmp:  # demo and trot write no manifest of their own
        (tmp / "summary.json").write_text("{}")
    assert json.loads((out / "manifest.json").read_text()) == {"command": "wbc-jax demo",
                                                                "files": ["manifest.json", "summary.json"]}
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


def test_campaign_report_in_a_worker_leaves_the_statistics_unloaded(tmp_path):
    """With a report worker, the campaign's process does not import the report's statistics (the worker writes it):
    ``wbc_jax.analysis.report`` stays out of its modules."""
    code = (
        "import json, sys\n"
        "from pathlib import Path\n"
        "from wbc_jax.campaign.results import campaign_report\n"
        "class Worker:\n"
        "    def run_report(self, *a, **k): return {}\n"
        "    def close(self): pass\n"
        f"campaign_report(Path({str(tmp_path)!r}), {{'warnings': []}}, [], Worker())\n"
        "print(json.dumps('wbc_jax.analysis.report' in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) is False, out.stdout + out.stderr


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


# ---------------------------------------------------------------- regress, bench, git


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


def test_force_replaces_only_what_the_earlier_run_wrote(tmp_path):
    """An earlier run's folder with the user's notes and subfolder in it: --force replaces that run's files (its
    report included) and leaves the user's; the new manifest lists only what the new run wrote."""
    from wbc_jax.io_utils import atomic_dir, check_out_dir

    out = tmp_path / "camp"
    with atomic_dir(out, command=CMD) as tmp:
        (tmp / "results.csv").write_text("old")
        (tmp / "report").mkdir()
        (tmp / "report" / "report.md").write_text("old")
    (out / "notes.txt").write_text("mine")
    (out / "analysis").mkdir()
    (out / "analysis" / "fit.py").write_text("mine")
    assert check_out_dir(out, CMD, force=True, writes=("results.csv", "report")) == out
    with atomic_dir(out) as tmp:
        (tmp / "manifest.json").write_text(json.dumps({"command": CMD}))
        (tmp / "results.csv").write_text("new")
    assert (out / "results.csv").read_text() == "new" and not (out / "report").exists()
    assert (out / "notes.txt").read_text() == "mine" and (out / "analysis" / "fit.py").read_text() == "mine"
    assert json.loads((out / "manifest.json").read_text())["files"] == ["manifest.json", "results.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camp"]  # no temporary or old siblings left
    (out / "report").mkdir()  # the user's own report folder, which the earlier run did not write
    with pytest.raises(OutputError, match="holds report, which the earlier wbc-jax campaign run did not write"):
        check_out_dir(out, CMD, force=True, writes=("results.csv", "report"))


def test_symlinked_out_is_written_through(tmp_path):
    """``--out`` a link to a folder (missing at first): the output lands in the target, the link stays a link, a
    second run with --force too; nothing is renamed aside."""
    from wbc_jax.io_utils import atomic_dir, check_out_dir

    link, real = tmp_path / "link", tmp_path / "data" / "real"
    real.parent.mkdir()
    link.symlink_to(real)
    for force in (False, True):
        assert check_out_dir(link, CMD, force=force) == real
        with atomic_dir(link, command=CMD) as tmp:
            (tmp / "results.csv").write_text(str(force))
        assert link.is_symlink() and (link / "results.csv").read_text() == str(force)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "link"] and os.listdir(real.parent) == ["real"]


def test_lock_names_its_owner_and_a_stale_lock_is_taken_over(tmp_path, capsys):
    """A folder claimed by a running process is refused naming that process; once it is killed (its lock file
    left behind) the lock is taken over with a note, and released with the file."""
    from wbc_jax.io_utils import claim_out_dir, lock_path, release_out_dir

    out = tmp_path / "sub" / "out"
    holder = hold_lock(out, "wbc-jax demo")
    try:
        with pytest.raises(OutputError, match=f"in use by wbc-jax demo \\(pid {holder.pid} on {platform.node()}"):
            claim_out_dir(out, CMD)
    finally:
        holder.kill()
        holder.wait()
    assert lock_path(out).exists()  # killed: the file stays, the kernel released the flock
    assert claim_out_dir(out, CMD) == out
    note = capsys.readouterr().out
    assert f"took over the lock of wbc-jax demo (pid {holder.pid}" in note and "ended without releasing it" in note
    assert json.loads(lock_path(out).read_text())["pid"] == os.getpid()
    release_out_dir(out)
    assert not lock_path(out).exists()


def test_output_files_are_0644(tmp_path):
    """Under the usual umask 022: manifest.json, the other files and the checkpoint 0644, folders 0755."""
    from wbc_jax.campaign import checkpoint
    from wbc_jax.io_utils import atomic_dir, write_json_atomic

    old = os.umask(0o022)
    try:
        with atomic_dir(tmp_path / "out", command=CMD) as tmp:
            write_json_atomic(tmp / "summary.json", {})
        ck = tmp_path / "ck"
        checkpoint.save_state(ck, {"a": np.zeros(3)}, dict(chunks_done=1))
    finally:
        os.umask(old)
    mode = lambda p: p.stat().st_mode & 0o777  # noqa: E731
    assert mode(tmp_path / "out") == 0o755
    assert {p.name: mode(p) for p in (tmp_path / "out").iterdir()} == {"manifest.json": 0o644, "summary.json": 0o644}
    assert {p.name: mode(p) for p in ck.iterdir()} == {"state_1.npz": 0o644, "meta.json": 0o644}


def test_progress_bar_never_shows_negative_time():
    """The bar counts whole chunks (simulated seconds shown): a surplus update or a resumed start cannot push it
    past its total, so the time left is never negative."""
    from tqdm import tqdm

    from wbc_jax.campaign.progress import ProgressBar

    for done in (0, 3):
        bar = ProgressBar(3, done, 0.04, 8, 0.001)
        for _ in range(5):
            bar.chunk_done(0.01)
        text = tqdm.format_meter(**bar._bar.format_dict)
        bar.close()
        assert bar._bar.n == 3 and "<-" not in text and "0.12/0.12 sim-s" in text, text


# ---------------------------------------------------------------- interrupts


@pytest.mark.parametrize("signum, code, word", [(signal.SIGINT, 130, "interrupted (SIGINT)"),
                                                 (signal.SIGTERM, 143, "terminated (SIGTERM)")])
def test_signal_during_setup_exits_with_one_line(tmp_path, monkeypatch, capsys, signum, code, word):
    """SIGINT or SIGTERM while the campaign sets up: exit 130 / 143, one line naming what exists (nothing), the
    output folder's lock released."""
    from wbc_jax.campaign import preflight
    from wbc_jax.io_utils import lock_path

    def signalled(*a, **k):
        os.kill(os.getpid(), signum)
        time.sleep(5)  # the handler interrupts this
        pytest.fail("the signal did not stop the setup")

    monkeypatch.setattr(preflight, "notes", signalled)
    assert cli.main(["campaign", "--spec", str(TINY), "--out", str(tmp_path / "out"), "--no-report"]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"wbc-jax campaign: {word} during setup; nothing written"], err
    assert not lock_path(tmp_path / "out").exists() and list(tmp_path.iterdir()) == []


def test_signal_during_compile_waits_for_it_and_says_so(tmp_path, monkeypatch, capsys):
    """SIGINT while XLA compiles (here: a stand-in build that takes a second after the signal): the compile is not
    cut; a line says the stop waits for it; then exit 130 with one line naming what exists."""
    from wbc_jax.campaign import runner

    finished = []

    def compiling(spec, gains=None):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(10):
            time.sleep(0.1)
        finished.append(True)
        return planned_only(spec, gains)

    monkeypatch.setattr(runner, "build", compiling)
    assert cli.main(["campaign", "--spec", str(TINY), "--out", str(tmp_path / "out"), "--no-report"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert finished and len(err) == 2, err
    assert "SIGINT received; stopping once the compile or chunk in progress ends" in err[0]
    assert err[1] == "wbc-jax campaign: interrupted (SIGINT) during setup; nothing written"


def test_second_signal_during_compile_stops_at_once(tmp_path):
    """A second SIGINT while XLA compiles ends the process at once: exit 130, no crash, a line naming what exists."""
    code = f"""
import os, signal, sys, time
sys.path.insert(0, {str(REPO / "tests")!r})
from test_reliability import planned_only
from wbc_jax import cli
from wbc_jax.campaign import runner
def compiling(spec, gains=None):
    for _ in range(2):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.5)
    time.sleep(30)
runner.build = compiling
sys.exit(cli.main(["campaign", "--spec", {str(TINY)!r}, "--out", {str(tmp_path / "out")!r}]))
"""
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=600)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 130 and lines[-1] == ("wbc-jax campaign: interrupted (SIGINT) during setup; nothing "
                                                 "written (at once)"), r.stderr


# ---------------------------------------------------------------- the campaign's own warnings and messages


def test_qp_flagged_runs_and_failures_are_named_plainly():
    """Runs whose QP was flagged on more than 1 % of their steps are named in a warning (the summary line and the
    manifest count them); a failed run's warning shows its levels as plain numbers."""
    from wbc_jax.campaign.results import summarize
    from wbc_jax.campaign.spec import load_spec

    df = campaign_table()
    df["qp_flag_fraction"] = [0.0, 0.5, 0.0, 0.02, 0.0, 0.0, 0.01, 0.0]
    df.loc[2, ["success", "fail_reason"]] = [False, "fell"]
    s = summarize(load_spec(TINY), df)
    assert s.qp_flagged_runs == 2
    assert any(w.startswith("2 of 8 runs had their QP flagged") and "(worst 50.0%)" in w for w in s.warnings)
    failed = [w for w in s.warnings if "runs failed" in w]
    assert failed and "run 2 (m 0.2, mu 1.0, d 0.06, rep 0): fell" in failed[0], s.warnings
    assert not any("np." in w for w in s.warnings)


def test_spec_with_a_byte_order_mark_loads(tmp_path):
    from wbc_jax.campaign.spec import load_spec

    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf" + TINY.read_bytes())
    assert load_spec(p).hash == load_spec(TINY).hash


def test_huge_spec_with_allow_large_says_what_it_is_doing(tmp_path, monkeypatch, capsys):
    """A million-run spec with --allow-large: a line says the setup comes first, before the design is built, and the
    memory estimate: per run RUN_BYTES and LOG_SAMPLE_BYTES for each of a 2 s chunk's 100 samples (the transport
    scene's 1 ms step x 20 control steps per sample)."""
    from test_reliability import HUGE_SPEC

    from wbc_jax.campaign import build
    from wbc_jax.campaign.size import LOG_SAMPLE_BYTES, RUN_BYTES

    def stop(*a, **k):
        raise WbcJaxError("stopped before the design")

    spec = tmp_path / "huge.toml"
    spec.write_text(HUGE_SPEC)
    monkeypatch.setattr(build, "design", stop)  # the line comes first: nothing of the million runs is built
    assert cli.main(["campaign", "--spec", str(spec), "--out", str(tmp_path / "big"), "--allow-large"]) == 2
    out = capsys.readouterr().out
    assert "setting up 1,000,000 runs (--allow-large): design, plans and initial states first" in out, out
    assert f"; about {1e6 * (RUN_BYTES + 100 * LOG_SAMPLE_BYTES) / 2**30:,.1f} GiB" in out, out


def test_memory_estimate_holds_the_chunk_programs_measured_memory():
    """check_size's estimate per run (RUN_BYTES with one logged sample, LOG_SAMPLE_BYTES per further one) holds what
    XLA's memory analysis of the tiny spec's compiled chunk program gives per run (arguments, outputs, temporaries),
    and INPUT_BYTES its arguments per run. How generous they are for the shipped specs:
    ``examples/campaign_memory.py`` (docs/performance.md)."""
    from wbc_jax.bench.campaign_step import compiled_chunk
    from wbc_jax.campaign.build import build
    from wbc_jax.campaign.size import INPUT_BYTES, LOG_SAMPLE_BYTES, RUN_BYTES
    from wbc_jax.campaign.spec import load_spec

    built = build(load_spec(TINY))
    n, logs = len(built.design.m), built.logs_per_chunk
    ma = compiled_chunk(built.sim, built.batch, logs).memory_analysis()
    measured = (ma.argument_size_in_bytes + ma.output_size_in_bytes + ma.temp_size_in_bytes) / n
    estimate = RUN_BYTES + (logs - 1) * LOG_SAMPLE_BYTES
    assert measured <= estimate, (measured, estimate)
    assert ma.argument_size_in_bytes / n <= INPUT_BYTES, ma.argument_size_in_bytes / n


def test_memory_check_counts_a_devices_share_of_the_runs(tmp_path, monkeypatch):
    """Runs split over accelerators: each device's estimate is its ceil(n / parts) runs and the other runs' inputs
    (the whole batch stays on each process's device), and a refusal names the share; CPU devices share the host's
    memory and count as one."""
    from test_reliability import HUGE_SPEC

    from wbc_jax.campaign import size
    from wbc_jax.campaign.spec import load_spec
    from wbc_jax.errors import LimitError

    path = tmp_path / "huge.toml"
    path.write_text(HUGE_SPEC)
    spec = load_spec(path)
    per_run = size.RUN_BYTES + 100 * size.LOG_SAMPLE_BYTES  # a 2 s chunk: 100 samples of 20 control steps of 1 ms
    four = 250_000 * per_run + 750_000 * size.INPUT_BYTES
    three = 333_334 * per_run + 666_666 * size.INPUT_BYTES
    monkeypatch.setattr(size, "_available_memory", lambda: (four + three) // 2)
    assert size.memory_need(spec, 4)[0] == 1_000_000 * per_run  # the CPU: one memory
    monkeypatch.setattr(size.jax, "default_backend", lambda: "gpu")
    assert size.memory_need(spec, 4)[0] == four
    size.check_size(spec, parts=4)
    with pytest.raises(LimitError, match=r"1,000,000 runs \(333,334 on each of 3 devices\) need about"):
        size.check_size(spec, parts=3)


def test_demo_warns_that_warp_on_a_cpu_is_slow(tmp_path, monkeypatch, capsys):
    from wbc_jax.physics.backend import warp_available
    from wbc_jax.studies import demo

    if not warp_available():
        pytest.skip("warp-lang is not installed")
    monkeypatch.setattr(demo, "run_demo", lambda **k: None)
    assert cli.main(["demo", "--backend", "warp", "--out", str(tmp_path / "d")]) == 0
    assert "warning: --backend warp on a CPU: MuJoCo Warp's kernels run on the CPU here" in capsys.readouterr().out
