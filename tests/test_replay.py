"""``wbc-jax replay``: a run of the tiny campaign re-simulated bit for bit with the campaign's compiled program, the
files it writes, the one-line errors of a spec or results table that does not match the campaign's manifest, and
the report's failed-runs table with each run's replay command."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from wbc_jax.analysis import report
from wbc_jax.cli.parser import Parser
from wbc_jax.errors import InputError, SpecError
from wbc_jax.studies import replay
from wbc_jax.studies.replay_check import REPLAY_RTOL, compare, relative_difference
from wbc_jax.studies.replay_inputs import read_campaign, read_results
from wbc_jax.studies.replay_sim import Program, adopt_xla, campaign_program, fill_slots, part_rows, recorded_chunks
from wbc_jax.studies.replay_write import default_window

RUN = 5  # the replayed run of the tiny campaign (8 runs)


def _args(*argv):
    """The ``replay`` subcommand's arguments as the CLI parses them."""
    parser = Parser(prog="wbc-jax")
    replay.add_parser(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(["replay", *map(str, argv)])


def _chunk_programs() -> dict:
    """The campaign's cached chunk functions and how many programs each has compiled."""
    from wbc_jax.campaign import build

    return {key: fn._cache_size() for key, fn in build._FNS.items()}


def test_fill_slots_keeps_each_run_in_its_own_slot():
    assert fill_slots([5], 8).tolist() == [5] * 8
    assert fill_slots([6, 1], 8).tolist() == [1, 1, 1, 6, 1, 6, 6, 6]
    assert fill_slots([2], 4, whole_batch=True).tolist() == [0, 1, 2, 3]


def test_part_rows_keep_each_run_in_its_slot_of_its_part():
    """A campaign of 7 runs over 2 devices (4 per device, the last padded with run 6): run 5 sits in slot 1 of part
    1, run 2 in slot 2 of part 0; each part is replayed as a batch of the part's size."""
    mesh = Program("mesh", 2, 4)
    assert [r.tolist() for r in part_rows([5, 2], 7, mesh)] == [[2, 2, 2, 2], [5, 5, 5, 5]]
    assert [r.tolist() for r in part_rows([4, 6], 7, mesh)] == [[4, 6, 6, 6]]
    assert [r.tolist() for r in part_rows([5], 7, mesh, whole_batch=True)] == [[4, 5, 6, 6]]
    assert [r.tolist() for r in part_rows([3], 8, Program("one", 1, 8))] == [fill_slots([3], 8).tolist()]


def test_part_rows_of_dealt_blocks():
    """Warp's blocks: 7 runs dealt to 2 processes (process 0: runs 0, 2, 4, 6; process 1: 1, 3, 5 and run 6
    again as padding), as ``Spread.block`` deals them; run 5 sits in slot 2 of part 1, run 2 in slot 1 of part 0."""
    from wbc_jax.rollout.spread import Spread

    blocks = Program("blocks", 2, 4, dealt=True)
    assert [Spread("blocks", process=i, processes=2).block(7).tolist() for i in range(2)] == [[0, 2, 4, 6],
                                                                                               [1, 3, 5, 6]]
    assert [r.tolist() for r in part_rows([5], 7, blocks, whole_batch=True)] == [[1, 3, 5, 6]]
    assert [r.tolist() for r in part_rows([5, 2], 7, blocks)] == [[2, 2, 2, 2], [5, 5, 5, 5]]
    assert [r.tolist() for r in part_rows([1, 5], 7, blocks)] == [[1, 5, 5, 5]]


def test_campaign_program_from_the_manifest_or_its_layout():
    record = dict(spread="mesh", devices=2, parts=2, per_device_runs=4, padded_runs=8)
    assert campaign_program({"program": record}, 7) == Program("mesh", 2, 4)
    older = {"layout": {"spread": "mesh", "processes": 1, "devices": [{}, {}, {}]}}
    assert campaign_program(older, 7) == Program("mesh", 3, 3)
    assert campaign_program({"layout": {"spread": "blocks", "processes": 2}}, 7) == Program("blocks", 2, 4)
    dealt = dict(spread="blocks", devices=1, parts=2, per_device_runs=4, padded_runs=8, dealt=True)
    assert campaign_program({"program": dealt}, 7) == Program("blocks", 2, 4, dealt=True)
    assert campaign_program({}, 7) == Program("one", 1, 7)


def test_replay_steps_the_campaigns_recorded_chunks():
    """The chunks a replay steps are the manifest's (its program record, else an older manifest's chunk_s and
    n_chunks), whatever this version's chunk plan makes of the spec; a manifest without them keeps the plan."""
    from types import SimpleNamespace

    from wbc_jax.campaign.build import Built

    built = Built(SimpleNamespace(log_every=20, dt_control=0.001), None, None, 27.65, 94, 15)  # 15 x 1.88 s
    recorded = lambda man: SimpleNamespace(manifest=man)  # noqa: E731
    program = recorded_chunks(recorded(dict(program=dict(logs_per_chunk=100, n_chunks=15), chunk_s=2.0)), built)
    legacy = recorded_chunks(recorded(dict(chunk_s=2.0, n_chunks=15)), built)  # before the program record
    assert (program.logs_per_chunk, program.n_chunks) == (legacy.logs_per_chunk, legacy.n_chunks) == (100, 15)
    assert recorded_chunks(recorded({}), built) is built


def test_deterministic_gpu_ops_by_default_where_cuda_can_start(monkeypatch):
    from wbc_jax.runtime import jaxcfg

    flag = jaxcfg.DETERMINISTIC_FLAG
    assert jaxcfg.xla_flag_value(f"--a=1 {flag}=true {flag}=false", flag) is False
    assert jaxcfg.with_xla_flag(f"{flag}=false --a=1", flag, True) == f"--a=1 {flag}=true"
    monkeypatch.setattr(jaxcfg, "backends_started", lambda: False)
    monkeypatch.setattr(jaxcfg, "_cuda_plugin_installed", lambda: True)
    for env, flags, expect in ((None, "--a=1", f"--a=1 {flag}=true"), ("off", "--a=1", "--a=1"),
                               (None, f"{flag}=false", f"{flag}=false")):
        monkeypatch.setattr(jaxcfg, "_configured", False)
        monkeypatch.setenv("XLA_FLAGS", flags)
        if env is None:
            monkeypatch.delenv("WBC_JAX_DETERMINISTIC", raising=False)
        else:
            monkeypatch.setenv("WBC_JAX_DETERMINISTIC", env)
        jaxcfg.configure()
        assert jaxcfg.xla_record()["flags"] == expect


def test_xla_settings_taken_from_the_campaign_or_named(monkeypatch):
    """The campaign's deterministic setting is taken before JAX starts and named after; other XLA flags and a GPU
    campaign without deterministic ops are named."""
    from wbc_jax.runtime import jaxcfg

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_foo=1")
    monkeypatch.setattr(jaxcfg, "backends_started", lambda: False)
    gpu = {"device": {"backend": "gpu"}}
    same = {"program": {"xla": {"flags": "--xla_cpu_foo=1", "deterministic_ops": False}}}
    assert adopt_xla(same) == []
    assert adopt_xla({"program": {"xla": {"flags": "--xla_cpu_foo=1", "deterministic_ops": True}}}) == []
    assert jaxcfg.deterministic_ops()  # taken: JAX had not started
    monkeypatch.setattr(jaxcfg, "backends_started", lambda: True)
    notes = adopt_xla(dict(gpu, program={"xla": {"flags": "", "deterministic_ops": False}}))
    assert len(notes) == 3 and "scatter adds" in notes[0] and "deterministic GPU ops off, this process started " \
        "JAX with them on" in notes[1] and "XLA_FLAGS differ" in notes[2]
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_foo=1")
    assert "scatter adds" in adopt_xla(dict(same, **gpu))[0]
    assert "records no XLA settings" in adopt_xla(gpu)[0] and adopt_xla({}) == []
    assert replay.verdict([], []) == "0 of 0 runs reproduce the campaign's results"
    differ = compare(3, pd.Series(dict(R=0.5, T=0.1, S=1.0, success=True, fail_reason="")),
                     dict(R=0.5, T=0.1, S=1.0, success=False, fail_reason="fell"))
    assert replay.verdict([differ], []).startswith("REPLAY MISMATCH: 1 of 1 runs differ") and "unexplained" in \
        replay.verdict([differ], [])
    assert replay.verdict([differ], ["another device"]).endswith("did not run exactly as the campaign did (another "
                                                                  "device)")


def test_arguments_are_one_line_errors():
    assert replay.parse_runs("3, 17") == [3, 17]
    assert replay.parse_window("14,15.5") == (14.0, 15.5) and replay.parse_window(None) is None
    for bad in ("3;4", "", "-1"):
        with pytest.raises(InputError, match="--runs"):
            replay.parse_runs(bad)
    for bad in ("15,14", "1", "a,b", "-1,2", "0,inf"):
        with pytest.raises(InputError, match="--window"):
            replay.parse_window(bad)
    args = _args("camp", "--failed")
    assert args.failed and args.run is None and args.out is None and not args.force


def test_compare_by_hand():
    row = pd.Series(dict(R=0.5, T=0.002, S=float("nan"), success=False, fail_reason="fell", failure_s=1.25))
    same = dict(R=0.5, T=0.002, S=float("nan"), success=False, fail_reason="fell", failure_s=1.25)
    check = compare(3, row, same)
    assert check.equal and check.bit_for_bit and check.max_rel == 0.0
    close = dict(same, R=0.5 * (1 + REPLAY_RTOL / 2))
    check = compare(3, row, close)
    assert check.equal and not check.bit_for_bit and math.isclose(check.max_rel, REPLAY_RTOL / 2, rel_tol=1e-6)
    check = compare(3, row, dict(same, T=0.003, success=True, fail_reason="", failure_s=float("nan")))
    assert not check.equal and len(check.differences) == 4
    assert relative_difference(1.0, float("nan")) == math.inf and relative_difference(0.0, 0.0) == 0.0
    assert default_window(np.arange(0.0, 30.0, 0.04), 14.475) == pytest.approx((9.475, 15.475))
    assert default_window(np.array([0.02, 0.04]), float("nan")) == (0.0, 0.04)


def test_replay_is_bit_for_bit_with_the_campaigns_program(full_run, tmp_path, capsys):
    """Run RUN of the tiny campaign replayed in this process: the campaign's compiled chunk program is reused (no
    new program), R, T, S equal its results.csv row bit for bit, success and fail_reason too; files written."""
    camp, _ = full_run
    before = _chunk_programs()
    out = tmp_path / "replay"
    assert replay.main(_args(camp, "--run", RUN, "--out", out, "--no-progress")) == 0
    assert _chunk_programs() == before
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith(f"run {RUN} ")]
    assert len(line) == 1 and "as in the campaign; R, T, S equal bit for bit" in line[0]
    row = read_results(camp / "results.csv").iloc[RUN]
    folder = out / f"run_{RUN}"
    man = json.loads((folder / "manifest.json").read_text())
    assert man["command"] == "wbc-jax replay" and man["run"] == RUN and man["check"]["bit_for_bit"]
    assert man["batch"]["same_layout"] and man["batch"]["batches"] == [8] and man["notes"] == []
    assert man["campaign_program"] == dict(spread="one", devices=1, parts=1, per_device_runs=8, padded_runs=8,
                                           dealt=False, logs_per_chunk=2, n_chunks=3, platform="cpu", xla=man["xla"])
    for k in ("R", "T", "S"):
        assert man["check"]["replay"][k] == row[k]
    assert man["check"]["replay"]["success"] == bool(row["success"])
    assert man["check"]["replay"]["fail_reason"] == row["fail_reason"]
    trajectory = np.load(folder / "trajectory.npz")
    n = len(trajectory["time"])
    assert n == 6 and trajectory["qpos"].shape[0] == n and trajectory["tau"].shape == (n, 18)
    np.testing.assert_allclose(trajectory["t"], trajectory["time"], atol=1e-6)  # the run's own clock (not failed)
    assert (folder / "plots.png").stat().st_size > 10_000
    videos = [p.name for p in folder.iterdir() if p.name.startswith("video.")]
    assert videos or man["video_note"].startswith("no video: offscreen rendering unavailable")
    assert sorted(man["files"]) == sorted(["manifest.json", "plots.png", "trajectory.npz", *videos])


@pytest.mark.slow
@pytest.mark.llvm_default  # the bit-for-bit match across batch sizes holds for LLVM's optimized code, not for -O0's
def test_replay_part_by_part_where_the_layout_differs(full_run, tmp_path, capsys):
    """The tiny campaign's manifest made to say it ran over 2 devices of 4 runs (this process has one device): runs 1
    and RUN (one in each part) are replayed in two batches of 4 runs on one device, each in its slot of its part; the
    note names the layout. On the CPU a batch's size does not change a run's arithmetic: bit for bit."""
    camp, _ = full_run
    man = json.loads((camp / "manifest.json").read_text())
    copy = tmp_path / "camp"
    copy.mkdir()
    (copy / "results.csv").write_text((camp / "results.csv").read_text())
    program = dict(man["program"], spread="mesh", devices=2, parts=2, per_device_runs=4, padded_runs=8)
    (copy / "manifest.json").write_text(json.dumps(dict(man, program=program)))
    code = replay.main(_args(copy, "--runs", f"1,{RUN}", "--out", tmp_path / "out", "--no-video", "--no-progress"))
    out = capsys.readouterr().out
    assert code == 0 and "2 batch(es) of 4 runs, the campaign's per-device batch, on one device" in out
    for run in (1, RUN):
        record = json.loads((tmp_path / "out" / f"run_{run}" / "manifest.json").read_text())
        assert record["batch"]["batches"] == [4, 4] and not record["batch"]["same_layout"]
        assert "2 part(s) of 4 runs (mesh), this machine would run 1 (one)" in record["notes"][0]
        assert record["check"]["bit_for_bit"], record["check"]


def test_spec_that_differs_is_one_line_and_nothing_written(full_run, tmp_path):
    camp, man = full_run
    spec = tmp_path / "spec.toml"
    text = open(man["spec_path"]).read()
    spec.write_text(text.replace("seed = 3", "seed = 4"))
    with pytest.raises(SpecError, match="differs from the spec campaign") as e:
        replay.main(_args(camp, "--run", RUN, "--spec", spec, "--out", tmp_path / "out"))
    assert "\n" not in str(e.value) and not (tmp_path / "out").exists()


def test_results_that_differ_are_one_line_and_nothing_written(full_run, tmp_path):
    camp, _ = full_run
    copy = tmp_path / "camp"
    copy.mkdir()
    (copy / "manifest.json").write_text((camp / "manifest.json").read_text())
    df = read_results(camp / "results.csv")
    df.loc[2, "R"] *= 1.01
    df.to_csv(copy / "results.csv", index=False)
    with pytest.raises(InputError, match="results.csv does not match .*manifest.json: mean R") as e:
        replay.main(_args(copy, "--run", RUN))
    assert "\n" not in str(e.value) and sorted(p.name for p in copy.iterdir()) == ["manifest.json", "results.csv"]
    df.loc[2, "R"] /= 1.01
    df.loc[3, "seed"] += 1
    df.to_csv(copy / "results.csv", index=False)
    with pytest.raises(InputError, match="run 3 has seed"):
        replay.main(_args(copy, "--runs", "1,3"))


def test_spec_recorded_in_the_manifest_stands_in_for_a_missing_file(full_run, tmp_path, capsys):
    camp, _ = full_run
    man = json.loads((camp / "manifest.json").read_text())
    copy = tmp_path / "camp"
    copy.mkdir()
    (copy / "results.csv").write_text((camp / "results.csv").read_text())
    (copy / "manifest.json").write_text(json.dumps(dict(man, spec_path=str(tmp_path / "moved.toml"))))
    recorded = read_campaign(copy)
    assert recorded.spec.factors == man["spec"]["factors"] and recorded.spec.perturbations == man["spec"][
        "perturbations"] and recorded.spec.campaign == dict(man["spec"]["campaign"], backend=man["physics_backend"])
    assert "manifest.json records is used" in capsys.readouterr().out
    spec = json.loads((copy / "manifest.json").read_text())["spec"]
    spec["campaign"]["seed"] += 1
    (copy / "manifest.json").write_text(json.dumps(dict(man, spec_path=str(tmp_path / "moved.toml"), spec=spec)))
    with pytest.raises(SpecError, match="does not hash to its spec_hash"):
        read_campaign(copy)


def test_cli_error_is_one_line_exit_2(full_run, tmp_path, capsys):
    from wbc_jax import cli

    if "replay" not in cli.COMMANDS:
        pytest.skip("wbc-jax replay is not registered in wbc_jax.cli")
    camp, _ = full_run
    assert cli.main(["replay", str(camp), "--run", "99", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("wbc-jax replay: error: run 99: the campaign") and "\n" not in err


def test_report_lists_failed_runs_with_their_replay_commands(tmp_path):
    folder = tmp_path / "my camp"
    folder.mkdir()
    grid = pd.MultiIndex.from_product([[0.2, 0.4], [0.4, 1.0], range(3)], names=["m", "mu", "rep"])
    df = grid.to_frame(index=False)
    df.insert(0, "run", np.arange(len(df)))
    rng = np.random.default_rng(0)
    df = df.assign(d=0.06, seed=df["run"], success=True, fail_reason="", failure_s=np.nan, first_contact="",
                   first_contact_s=np.nan, R=0.3 + 0.01 * rng.standard_normal(len(df)),
                   T=0.01 + 0.001 * rng.standard_normal(len(df)), S=1.0 + 0.1 * rng.standard_normal(len(df)))
    df.loc[[4, 9], ["success", "fail_reason", "failure_s"]] = [[False, "fell", 1.25], [False, "dropped", 0.5]]
    df.loc[4, ["first_contact", "first_contact_s"]] = ["FR_shank (body FR_calf) / floor", 1.2]
    df.to_csv(folder / "results.csv", index=False)
    spec = {"campaign": {"name": "tiny"}, "factors": {"m": [], "mu": []}, "analysis": {"order": 2}}
    (folder / "manifest.json").write_text(json.dumps({"command": "wbc-jax campaign", "spec_path": "t.toml",
                                                      "spec": spec}))
    report.run_report(str(folder / "results.csv"), str(tmp_path / "rep"), figures=False)
    md = (tmp_path / "rep" / "report.md").read_text()
    section = md.split("## Failed runs\n")[1].split("\n## ")[0]
    assert f"`wbc-jax replay '{folder}' --failed` replays them all" in section
    rows = [r for r in section.splitlines() if r.startswith("| 4 ") or r.startswith("| 9 ")]
    assert rows[0] == (f"| 4 | 0.2 | 1 | 1 | fell | 1.250 | FR_shank (body FR_calf) / floor at 1.200 s | "
                       f"`wbc-jax replay '{folder}' --run 4` |")
    assert rows[1].startswith("| 9 | 0.4 | 1 | 0 | dropped | 0.500 |  | ")
