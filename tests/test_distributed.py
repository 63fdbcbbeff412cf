"""Campaigns and gain searches over several processes (``wbc_jax.rollout.distributed``): settings from flags, JAX_* and
SLURM variables, one-line errors for bad ones, and a real 2-process run on this machine (localhost coordinator, one
CPU device per process, gloo collectives) of `wbc-jax campaign` and then `wbc-jax tune` whose outputs equal, bit for
bit, the single-process run's over two CPU devices (the same per-device program), with only process 0 writing.

A one-device reference rounds differently (it compiles the rollout for all runs at once; the low-friction cells
amplify that), hence the two-device one. That reference keeps at most 2 runs per device: with more, on a 2-core
machine, both threads of XLA's CPU intra-op pool can each wait in a batched LAPACK triangular solve whose slices
are queued on that same pool (a deadlock without any collective). One device per process, as on a cluster, does
not meet it."""

import io
import json
import os
import socket
import subprocess
import sys
import textwrap
import time
from typing import NamedTuple

import numpy as np
import pandas as pd
import pytest
from jax._src import cache_key

from wbc_jax import cli
from wbc_jax.errors import InputError
from wbc_jax.rollout.distributed import DEFAULT_PORT, Layout, first_host, resolve, shared_gpu

TIMEOUT_S = 900  # three processes compile at once on 2 cores


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
    (dict(num_processes=2, process_id=2, coordinator="h:1"), {},
     "--process-id = 2: expected an integer, 0 <= value <= 1"),
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


def test_a_gpu_shared_by_two_processes_is_named():
    """Two processes of one host on one GPU (NCCL would fail at the first collective with "Duplicate GPU detected"):
    the first such GPU (its PCI bus id) and its processes named in one line; the same bus id on two hosts, or
    different bus ids, are no conflict; processes without GPUs (CPU runs) none."""
    a, b = "0000:60:00.0", "0000:61:00.0"
    assert shared_gpu({0: ("h1", [a]), 1: ("h1", [b]), 2: ("h2", [a]), 3: ("h2", [b])}) is None
    assert shared_gpu({0: ("h1", []), 1: ("h1", [])}) is None
    msg = shared_gpu({0: ("h1", [a, b]), 1: ("h2", [a]), 2: ("h1", ["0000:62:00.0", b])})
    assert msg.startswith(f"processes 0 and 2 both use the GPU at PCI bus {b} of host h1: give each process its own")
    assert "--local-device-ids" in msg and "\n" not in msg
    assert shared_gpu({1: ("h1", [a]), 0: ("h1", [a])}).startswith("processes 0 and 1 ")


def test_own_gpus_checked_through_the_store(monkeypatch):
    """check_own_gpus: this process's GPUs' bus ids (from the CUDA driver, here a stand-in for devices 0 and 1)
    published, every process's read back; process 1 of one host on the same bus id is an InputError, on another
    none, and the check runs once per process; a GPU whose bus id the driver does not give is left out."""
    import jax

    from wbc_jax.rollout import distributed

    class Dev(NamedTuple):
        platform: str
        local_hardware_id: int

    store = {"wbc-jax/gpus/1": json.dumps([socket.gethostname(), ["0000:61:00.0"]])}
    monkeypatch.setattr(distributed, "share", store.__setitem__)
    monkeypatch.setattr(distributed, "shared", lambda key, timeout_s: store[key])
    monkeypatch.setattr(distributed, "_ACTIVE", Layout("h:1", 2, 0, (1,), "flags"))
    monkeypatch.setattr(distributed, "_bus_id", {0: "0000:60:00.0", 1: "0000:61:00.0"}.get)
    monkeypatch.setattr(jax, "local_devices", lambda: [Dev("gpu", 1)])
    monkeypatch.setattr(distributed, "_GPUS_CHECKED", False)
    with pytest.raises(InputError, match="processes 0 and 1 both use the GPU at PCI bus 0000:61:00.0 of host"):
        distributed.check_own_gpus()
    assert json.loads(store["wbc-jax/gpus/0"])[1] == ["0000:61:00.0"]
    distributed.check_own_gpus()  # once per process: no second exchange
    monkeypatch.setattr(distributed, "_GPUS_CHECKED", False)
    monkeypatch.setattr(jax, "local_devices", lambda: [Dev("gpu", 0), Dev("gpu", 7), Dev("cpu", 1)])
    store.pop("wbc-jax/gpus/0")
    distributed.check_own_gpus()
    assert json.loads(store["wbc-jax/gpus/0"])[1] == ["0000:60:00.0"]


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


ALL_IN_ONE = textwrap.dedent("""
    import os, sys
    if any(a.startswith("--coordinator") for a in sys.argv):  # SHARE_COMPILED: process 1 loads process 0's
        import jax
        from jax._src import cache_key
        cache_key._hash_accelerator_config = cache_key._hash_devices
        jax.config.update("jax_share_binary_between_hosts", True)
    from wbc_jax import cli
    args = sys.argv[1:]
    cut = args.index("--then")
    camp, tune = args[:cut], args[cut + 1:]
    mp = [a for a in camp if a.startswith(("--coordinator", "--num-processes", "--process-id"))]
    if cli.main(camp):  # out: the plain campaign
        sys.exit(1)
    from wbc_jax.campaign import runner
    spec = camp[camp.index("--spec") + 1]
    def _cut(done, n_chunks):
        raise KeyboardInterrupt
    runner.after_chunk, keep = _cut, runner.after_chunk
    try:  # cut: the same campaign interrupted after its first chunk ...
        runner.run_campaign(spec, "cut", report=False, progress=False)
        sys.exit("not interrupted")
    except KeyboardInterrupt as stop:
        print(stop, file=sys.stderr, flush=True)
        runner.after_chunk = keep
    kept = sorted(os.listdir("."))
    want = [] if "--process-id=1" in mp else [".cut.campaign-ckpt", "out"]  # process 1 writes nothing
    if kept != want:
        sys.exit(f"after the interrupt: {kept}, expected {want}")
    # ... resumed (the compiled chunk function reused), then the tune
    code = cli.main(["campaign", "--spec", spec, "--out", "cut", "--no-report", "--resume", *mp]) or cli.main(tune)
    if code or not mp:
        sys.exit(code)
    # Warp (the reference is computed in the test: _warp_blocks), into process 0's folder from both processes (a
    # shared filesystem: the checkpoint's blocks are every process's); then interrupted after its first chunk in
    # both processes and resumed
    shared = os.environ["SHARED_OUT"]
    warp = ["campaign", "--spec", spec, "--backend", "warp", "--no-report", *mp]
    if cli.main(warp + ["--out", os.path.join(shared, "warp")]):
        sys.exit(1)
    runner.after_chunk = _cut
    try:
        runner.run_campaign(spec, os.path.join(shared, "warpcut"), report=False, progress=False, backend="warp")
        sys.exit("not interrupted")
    except KeyboardInterrupt as stop:
        print(stop, file=sys.stderr, flush=True)
        runner.after_chunk = keep
    sys.exit(cli.main(warp + ["--out", os.path.join(shared, "warpcut"), "--resume"]))
""")  # one launch for all three: every fresh process compiles the rollout again
# SHARE_COMPILED: the two processes' programs over both processes (the campaign's and the tune's chunk programs,
# the gathers) are the same program; with jax_share_binary_between_hosts process 0 compiles each and hands the
# executable to process 1 through the coordinator instead of both compiling it on the same 2 cores. JAX names an
# executable there by its persistent-cache key, which on the CPU holds a topology fingerprint that differs between
# the processes (measured: their keys differ in that entry only), so process 1 would wait for a key process 0 never
# sets; the script keys the devices by their kind instead (JAX's own fallback where a backend has no topology).
# Each process still runs its own copy; the results are compared bit for bit below as before.


def _run_all(cmds, envs, cwds) -> tuple[list[int], list[str]]:
    """Run the commands at once, each with its env and working folder: (return codes, outputs); the caller
    checks the codes."""
    procs = [subprocess.Popen(c, cwd=d, env=e, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for c, e, d in zip(cmds, envs, cwds)]
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
    print(f"{len(cmds)} processes: {time.perf_counter() - t0:.1f} s wall")
    return [p.returncode for p in procs], logs


TUNE = """
[tune]
name = "two-process"
campaign = "{campaign}"
method = "halving"
candidates = 4
rounds = 1
seed = 5
cells = [[0.2, 0.4, 0.08]]
batch = 4
[start]
kp = 0.5
[leaves]
kp_com = [0.1, 4.0]
kp_obj = [0.1, 4.0]
[halving]
eta = 3
rungs = 2
"""  # one cell: 4 candidates (rung 1), 2 survivors continued from their states (rung 2), then default and best
#      confirmed; every call 4 runs (padded), 2 per device as in the campaign


@pytest.mark.slow  # three fresh processes compile on 2 cores; tests/test_sharding.py checks the run axis over two
#                   devices and tests/test_backends.py the Warp blocks, in one process each
def test_two_processes_equal_one(tiny_spec, tmp_path, monkeypatch):
    """2 processes x 1 CPU device, the run axis over both, against one process over 2 CPU devices (the same
    per-device program, 2 runs each), the three launched once (ALL_IN_ONE): `wbc-jax campaign`'s results.csv equal
    bit for bit, every run once; process 0 writes DIR and the manifest's layout, process 1 (its own --out and
    working folder) writes nothing. Then the same campaign interrupted after its first chunk (process 0 keeps the
    checkpoint, process 1 writes nothing: checked in the processes) and resumed with --resume: the same results.csv
    again. Then `wbc-jax tune` (successive halving: survivors continue from their gathered states) writes the same
    leaderboard, per-run tables and best gains as the reference, from process 0 only. Then the campaign on Warp
    physics (a block of runs per process, ``wbc_jax.rollout.spread``; both processes given process 0's folder, as on
    a shared filesystem) against its two blocks stepped in this process one after the other, bit for bit; and the
    Warp campaign interrupted after its first chunk in both processes (each keeps its checkpoint block,
    ``wbc_jax.campaign.blocks``) and resumed: the same results.csv. The spec is the CI baseline's
    with d fixed (4 runs): with 3 or more runs per device the one-process reference deadlocks on 2 cores (module
    docstring)."""
    spec = tmp_path / "four.toml"
    spec.write_text("\n".join(x for x in tiny_spec.read_text().splitlines() if not x.startswith("d = ")))
    tune = tmp_path / "tune.toml"
    tune.write_text(TUNE.format(campaign=spec))
    flags = os.environ.get("XLA_FLAGS", "")  # the tests' compile settings (conftest.py): the reference's here
    one = dict(os.environ, XLA_FLAGS=f"{flags} --xla_force_host_platform_device_count=1", JAX_PLATFORMS="cpu")
    two = dict(one, XLA_FLAGS=f"{flags} --xla_force_host_platform_device_count=2")
    dirs = [tmp_path / n for n in ("p0", "p1", "ref")]
    for d in dirs:
        d.mkdir()
    port = _free_port()
    mp = [[f"--coordinator=localhost:{port}", "--num-processes=2", f"--process-id={i}"] for i in range(2)]
    camp = [sys.executable, "-c", ALL_IN_ONE, "campaign", "--spec", str(spec), "--out", "out", "--no-report"]
    tn = ["--then", "tune", "--spec", str(tune), "--out", "tune", "--no-progress"]
    # the Warp reference first, keyed as the processes key their programs (SHARE_COMPILED): its compiled programs are
    # then persistent-cache hits for both processes' Warp campaign instead of two more compiles
    monkeypatch.setattr(cache_key, "_hash_accelerator_config", cache_key._hash_devices)
    warp_ref = _warp_blocks(spec, 2)
    shared = dict(one, SHARED_OUT=str(dirs[0]))
    codes, logs = _run_all([camp + mp[0] + tn + mp[0], camp + mp[1] + tn + mp[1], camp + tn], [shared, shared, two],
                           dirs)
    assert codes == [0, 0, 0], "\n---\n".join(x[-3000:] for x in logs)
    assert logs[1].count("process 1: done; process 0 writes") == 5  # campaign, resumed, tune, Warp, Warp resumed
    assert logs[0].count("interrupted (SIGINT) after 1 of") == 2 and logs[0].count("resuming from") == 2
    assert list(dirs[1].iterdir()) == []  # process 1: no --out, no checkpoint, no stray file

    # the campaign: process 0's results.csv equals the one-process reference's, bit for bit
    out = dirs[0] / "out"
    assert sorted(x.name for x in dirs[0].iterdir()) == ["cut", "out", "tune", "warp", "warpcut"]  # no checkpoint
    got = pd.read_csv(out / "results.csv")
    ref = pd.read_csv(dirs[2] / "out" / "results.csv")
    assert got["run"].tolist() == list(range(4))  # every run once
    assert np.ptp(got["R"]) > 0.1 and got["success"].all()  # real, different runs
    pd.testing.assert_frame_equal(got, ref, check_exact=True)

    man = json.loads((out / "manifest.json").read_text())
    lay = man["layout"]
    assert lay["processes"] == 2 and lay["process_index"] == 0 and lay["source"] == "flags"
    assert [d["process"] for d in lay["devices"]] == [0, 1] and man["device"]["count"] == 2
    ref_lay = json.loads((dirs[2] / "out" / "manifest.json").read_text())["layout"]
    assert ref_lay["processes"] == 1 and ref_lay["coordinator"] is None and len(ref_lay["devices"]) == 2

    # interrupted after one chunk and resumed on the same 2-process layout: the same results.csv
    assert json.loads((dirs[0] / "cut" / "manifest.json").read_text())["resumed"]
    pd.testing.assert_frame_equal(pd.read_csv(dirs[0] / "cut" / "results.csv"), got, check_exact=True)

    # the tune: process 0's outputs equal the one-process reference's, bit for bit
    for name in ("leaderboard.csv", "best_runs.csv", "confirm_runs.csv", "best_gains.toml"):
        assert (dirs[0] / "tune" / name).read_bytes() == (dirs[2] / "tune" / name).read_bytes(), name
    board = pd.read_csv(dirs[0] / "tune" / "leaderboard.csv")
    assert len(board) == 4 and set(np.round(board.sim_s, 6)) == {0.04, 0.12} and board["T_mm"].nunique() > 1
    tman = json.loads((dirs[0] / "tune" / "manifest.json").read_text())
    assert tman["layout"]["processes"] == 2 and tman["physics_backend"] == "jax"
    assert tman["new_compilations_after_round_1"] in (0, None)

    # Warp physics: a block of runs per process (wbc_jax.rollout.spread), equal bit for bit to the same two blocks
    # stepped here one after the other with the single-device program
    warp = pd.read_csv(dirs[0] / "warp" / "results.csv")
    assert warp["run"].tolist() == list(range(4)) and warp["success"].all()
    ref = pd.read_csv(io.StringIO(warp_ref.to_csv(index=False)))  # as the campaign writes it
    pd.testing.assert_frame_equal(warp, ref, check_exact=True)
    wman = json.loads((dirs[0] / "warp" / "manifest.json").read_text())
    assert wman["physics_backend"] == "warp" and wman["layout"]["processes"] == 2
    assert wman["layout"]["spread"] == "blocks" and lay["spread"] == "mesh" and ref_lay["spread"] == "mesh"
    # interrupted after its first chunk (both processes keep their blocks of it) and resumed: the same results.csv
    assert json.loads((dirs[0] / "warpcut" / "manifest.json").read_text())["resumed"]
    pd.testing.assert_frame_equal(pd.read_csv(dirs[0] / "warpcut" / "results.csv"), warp, check_exact=True)


def _warp_blocks(spec_path, n_blocks: int) -> pd.DataFrame:
    """results.csv of ``spec_path`` on Warp physics computed as ``n_blocks`` processes compute it, in this one
    process: each block (``Spread.place``: the runs dealt out in turn) stepped alone by the campaign's single-device
    chunk function, the runs then put back in order."""
    import jax

    from wbc_jax.campaign import runner as C
    from wbc_jax.campaign.spec import load_spec
    from wbc_jax.rollout import final_results, runs
    from wbc_jax.rollout.spread import Spread

    spec = C.with_backend(load_spec(spec_path), "warp")
    sim, design, b, _, logs_per_chunk, n_chunks = C.build(spec)
    fn = C.chunk_fn(sim, b.in_axes, logs_per_chunk, None, b.state_axes)
    states, goals = [], []
    for i in range(n_blocks):
        sub = Spread("blocks", process=i, processes=n_blocks).place(b, own_contacts=True)
        st = sub.state
        for _ in range(n_chunks):
            st, logs = fn(sub.model, st, sub.plan, sub.om, sub.gains, sub.push, sub.mu_ground)
        states.append(jax.device_get(st))
        goals.append(np.asarray(logs.p_obj_ref[:, -1]))
    order = Spread("blocks", processes=n_blocks).run_order(design.n)  # each run's row of the joined blocks
    state = runs.take(runs.concat(states, sub.state_axes), order, sub.state_axes)
    return C.results_table(spec, design, final_results(sim, state, np.concatenate(goals)[order], design.mu))
