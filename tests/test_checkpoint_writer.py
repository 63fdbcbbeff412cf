"""The campaign's checkpoint written in a background thread and its per-chunk gather split in two.

The state file (:func:`wbc_jax.campaign.checkpoint.write_npz`) reads back like ``np.savez``'s.

:class:`wbc_jax.campaign.checkpoint.Writer`: one write at a time, a failed write's exception raised in the caller's
thread at the next join (never lost). The campaign's chunk loop (``runner._run_chunks``) on a stand-in chunk
program (a counter, no physics, nothing to compile): after every chunk the checkpoint holds that chunk's state,
``status.saved`` moves only once the write ended, a stop after a chunk leaves its checkpoint complete, and a write
that fails stops the run with its error. ``Spread.gather_start`` / ``Gathering.finish`` in two real processes
(localhost coordinator, one CPU device each, gloo): the "blocks" and "mesh" layouts give every run once, in order,
the padding dropped, leaves without a run axis this process's own, equal to the all-gather through the host.
"""

import json
import subprocess
import sys
import textwrap
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from wbc_jax.campaign import checkpoint, interrupts, runner
from wbc_jax.campaign.job import Status
from wbc_jax.campaign.resume import Start
from wbc_jax.errors import OutputError
from wbc_jax.rollout.spread import Spread

SLOW_WRITE_S = 0.3  # a stand-in write's extra time: long enough that an unjoined write would still be running
TIMEOUT_S = 300  # two processes import JAX and compile three small programs on 2 shared cores


# ---------------------------------------------------------------- the writer alone


def _slow_save(monkeypatch, fail_at: int | None = None):
    """``checkpoint.save_state`` made slow (``SLOW_WRITE_S``), failing with OSError for chunk ``fail_at``."""
    real = checkpoint.save_state

    def save(ck, state, meta, cancelled=None):
        time.sleep(SLOW_WRITE_S)
        if meta["chunks_done"] == fail_at:
            raise OSError(28, "No space left on device")
        real(ck, state, meta, cancelled)

    monkeypatch.setattr(checkpoint, "save_state", save)


def test_writer_runs_one_write_at_a_time_and_raises_its_error_once(tmp_path, monkeypatch):
    _slow_save(monkeypatch, fail_at=2)
    writer, ck, saved = checkpoint.Writer(), tmp_path / "ck", []
    t0 = time.perf_counter()
    writer.save(ck, {"a": np.zeros(3)}, dict(chunks_done=1), on_saved=lambda: saved.append(1))
    assert time.perf_counter() - t0 < SLOW_WRITE_S and saved == []  # the caller goes on while it writes
    assert any(t.name == "wbc-jax-checkpoint" for t in threading.enumerate())
    writer.save(ck, {"a": np.ones(3)}, dict(chunks_done=2), on_saved=lambda: saved.append(2))  # waits for write 1
    assert saved == [1] and json.loads((ck / "meta.json").read_text())["chunks_done"] == 1
    with pytest.raises(OSError, match="No space left"):  # write 2 failed in its thread: raised here
        writer.join()
    writer.join()  # once
    assert saved == [1] and [p.name for p in ck.glob("state_*.npz")] == ["state_1.npz"]  # chunk 1's kept whole
    writer.save(ck, {"a": np.ones(3)}, dict(chunks_done=3))
    writer.join()
    assert json.loads((ck / "meta.json").read_text())["chunks_done"] == 3


def test_join_keeping_names_both_failed_writes(tmp_path, monkeypatch):
    """Writer.join_keeping (a campaign's results could not be written): the write in progress completes and keeps
    its state, nothing raised; where it failed too, one OutputError names the folder and both errors."""
    _slow_save(monkeypatch, fail_at=2)
    writer, ck, out = checkpoint.Writer(), tmp_path / "ck", tmp_path / "out"
    results_error = PermissionError(13, "Permission denied")
    writer.save(ck, {"a": np.zeros(3)}, dict(chunks_done=1))
    writer.join_keeping(results_error, out)
    assert json.loads((ck / "meta.json").read_text())["chunks_done"] == 1
    writer.save(ck, {"a": np.ones(3)}, dict(chunks_done=2))
    with pytest.raises(OutputError, match=r"out: results not written \(.*Permission denied\); the last checkpoint's "
                       r"write failed too \(.*No space left on device\): the finished simulation is lost") as e:
        writer.join_keeping(results_error, out)
    assert e.value.__cause__ is results_error


def test_a_cancelled_write_leaves_the_checkpoint_before_it(tmp_path):
    """``save_state`` cancelled: :class:`checkpoint.Cancelled`, no state file of its chunk nor a temporary one, the
    meta still naming the chunk before; :meth:`Writer.cancel` stops a write in progress and returns at once."""
    ck = tmp_path / "ck"
    checkpoint.save_state(ck, {"a": np.zeros(3)}, dict(chunks_done=1))
    with pytest.raises(checkpoint.Cancelled):
        checkpoint.save_state(ck, {"a": np.ones(3)}, dict(chunks_done=2), cancelled=lambda: True)
    with pytest.raises(checkpoint.Cancelled):  # nothing to write block by block: cancelled before the hash
        checkpoint.save_state(ck, {"a": np.zeros(0)}, dict(chunks_done=2), cancelled=lambda: True)
    assert sorted(p.name for p in ck.iterdir()) == ["meta.json", "state_1.npz"]
    assert json.loads((ck / "meta.json").read_text())["chunks_done"] == 1

    writer, blocks_written = checkpoint.Writer(), []
    real = checkpoint.write_npz

    def slow(f, leaves, block=1 << 20, cancelled=None):  # a write of many 1-element blocks, 10 ms each
        def late():
            blocks_written.append(1)
            time.sleep(0.01)
            return cancelled()
        real(f, leaves, block=1, cancelled=late)

    checkpoint.write_npz, t0 = slow, time.perf_counter()
    try:
        writer.save(ck, {"a": np.ones(10_000)}, dict(chunks_done=2))  # ~80,000 blocks: minutes uncancelled
        time.sleep(0.2)
        writer.cancel()
    finally:
        checkpoint.write_npz = real
    assert time.perf_counter() - t0 < 5 and len(blocks_written) > 5
    assert sorted(p.name for p in ck.iterdir()) == ["meta.json", "state_1.npz"]
    writer.save(ck, {"a": np.ones(3)}, dict(chunks_done=3))  # the writer writes again after a cancel
    writer.join()
    assert json.loads((ck / "meta.json").read_text())["chunks_done"] == 3


def test_write_npz_reads_back_like_np_savez(tmp_path):
    """The checkpoint's state file: what ``np.load`` reads from it equals what it reads from ``np.savez``'s, for
    leaves of every kind a state holds (0-d, empty, bool, int, Fortran-ordered, NaN) and arrays over many blocks."""
    rng = np.random.default_rng(0)
    leaves = [rng.normal(size=(5, 3)).astype(np.float32), np.arange(7), np.zeros((4, 0)), np.array(3.5),
              np.array([True, False]), np.asfortranarray(rng.normal(size=(3, 4))), rng.normal(size=30_001),
              np.array([np.nan, 1.0])]
    with open(tmp_path / "ours.npz", "wb") as f:
        checkpoint.write_npz(f, leaves, block=1000)
    np.savez(tmp_path / "numpy.npz", *leaves)
    with np.load(tmp_path / "ours.npz") as ours, np.load(tmp_path / "numpy.npz") as ref:
        assert ours.files == ref.files
        for k in ref.files:
            a, b = ours[k], ref[k]
            assert (a.dtype, a.shape) == (b.dtype, b.shape) and np.array_equal(a, b, equal_nan=True), k


# ---------------------------------------------------------------- the chunk loop on a stand-in program

N_RUNS, N_CHUNKS = 3, 3


def _job(tmp_path, monkeypatch):
    """A Job-like record of N_RUNS runs whose "chunk" adds 1 to every state leaf (runner.chunk_fn replaced)."""
    import jax.numpy as jnp

    def chunk(model, state, plan, om, gains, push, mu_ground):
        logs = SimpleNamespace(p_goal=state["q"][:, None, :2] * 10.0)
        return {k: v + 1 for k, v in state.items()}, logs

    monkeypatch.setattr(runner, "chunk_fn", lambda *a, **k: chunk)
    sim = SimpleNamespace(controller=SimpleNamespace(final_input=lambda logs: logs.p_goal[:, -1], extra_columns=()),
                          dt_physics=0.01)
    built = SimpleNamespace(sim=sim, n_chunks=N_CHUNKS, logs_per_chunk=1, design=SimpleNamespace(n=N_RUNS))
    state = {"q": jnp.arange(N_RUNS * 3, dtype=jnp.float32).reshape(N_RUNS, 3), "k": jnp.zeros(N_RUNS, jnp.int32)}
    batch = SimpleNamespace(model=None, plan=None, om=None, gains=None, push=None, mu_ground=None, in_axes=None,
                            state=state, state_axes={"q": 0, "k": 0})
    status = Status(str(tmp_path / "out"), ckpt=tmp_path / "ck", stage="chunks", n_chunks=N_CHUNKS)
    return SimpleNamespace(batch=batch, spread=Spread("one"), built=built, writer=True, ckpt=status.ckpt,
                           identity={"spec": "x"}, status=status)


def _start(job) -> Start:
    return Start(job.batch.state, 0, 0.0, [], None, [{"git_commit": None, "chunks_before": 0}])


def _run(job, saver):
    with interrupts.Guard("test") as guard:
        return runner._run_chunks(job, _start(job), False, False, guard, saver)


def _saved_state(ck):
    meta = json.loads((ck / "meta.json").read_text())
    with np.load(ck / meta["state_file"]) as z:
        return meta, [z[f"arr_{i}"] for i in range(len(z.files))]


def test_every_chunk_checkpointed_in_the_background(tmp_path, monkeypatch):
    """Each chunk's checkpoint holds that chunk's state (as the synchronous write wrote it), written while the
    loop goes on; ``status.saved`` advances when the write ended; the last one is complete once joined."""
    job = _job(tmp_path, monkeypatch)
    _slow_save(monkeypatch)
    seen = []

    def after(done, n_chunks):  # chunk `done`'s write is in progress, chunk done - 1's finished
        seen.append((done, job.status.saved))

    monkeypatch.setattr(runner, "after_chunk", after)
    saver = checkpoint.Writer()
    rollout, _ = _run(job, saver)
    assert seen == [(1, 0), (2, 1)]
    saver.join()
    assert job.status.saved == N_CHUNKS
    meta, leaves = _saved_state(job.ckpt)
    assert meta["chunks_done"] == N_CHUNKS and meta["n_chunks"] == N_CHUNKS and len(meta["marks"]) == N_CHUNKS
    q0 = np.arange(N_RUNS * 3, dtype=np.float32).reshape(N_RUNS, 3)
    np.testing.assert_array_equal(leaves[1], q0 + N_CHUNKS)  # leaves in tree order: k, q
    np.testing.assert_array_equal(leaves[0], np.full(N_RUNS, N_CHUNKS, np.int32))
    np.testing.assert_array_equal(meta["p_goal"], (q0 + N_CHUNKS - 1)[:, :2] * 10.0)
    np.testing.assert_array_equal(rollout.p_goal, meta["p_goal"])
    np.testing.assert_array_equal(np.asarray(rollout.state["q"]), q0 + N_CHUNKS)


def test_a_stop_after_a_chunk_leaves_its_checkpoint_complete(tmp_path, monkeypatch):
    job = _job(tmp_path, monkeypatch)
    _slow_save(monkeypatch)

    def cut(done, n_chunks):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "after_chunk", cut)
    with pytest.raises(KeyboardInterrupt):
        _run(job, checkpoint.Writer())
    assert job.status.saved == 1  # the write ended before the stop went on
    meta, leaves = _saved_state(job.ckpt)
    assert meta["chunks_done"] == 1 and sorted(p.name for p in job.ckpt.iterdir()) == ["meta.json", "state_1.npz"]


def test_a_failed_write_stops_the_run_with_its_error(tmp_path, monkeypatch):
    """Chunk 2's write fails in the writer thread: chunk 3's save raises it; chunk 1's checkpoint stays."""
    job = _job(tmp_path, monkeypatch)
    _slow_save(monkeypatch, fail_at=2)
    with pytest.raises(OSError, match="No space left"):
        _run(job, checkpoint.Writer())
    assert job.status.saved == 1 and _saved_state(job.ckpt)[0]["chunks_done"] == 1


@pytest.mark.parametrize("results_fail", [False, True])
def test_results_written_first_then_the_last_checkpoint_cancelled_or_kept(tmp_path, monkeypatch, results_fail):
    """After the last chunk (``runner._write``, the results' computation stood in): results.csv and manifest.json
    are written while the last chunk's checkpoint is still being written, which is then cancelled and the checkpoint
    deleted; where writing the results fails, the last checkpoint is completed (the finished simulation kept)."""
    import pandas as pd

    from wbc_jax import rollout as rollout_pkg

    job = _job(tmp_path, monkeypatch)
    real = checkpoint.save_state
    last = {}

    def save(ck, state, meta, cancelled=None):  # the last chunk's write: long unless cancelled
        if meta["chunks_done"] == N_CHUNKS:
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < 3.0:
                if cancelled is not None and cancelled():
                    last["cancelled"] = True
                    raise checkpoint.Cancelled("cancelled")
                time.sleep(0.01)
        real(ck, state, meta, cancelled)

    monkeypatch.setattr(checkpoint, "save_state", save)
    saver = checkpoint.Writer()
    rollout, _ = _run(job, saver)
    monkeypatch.setattr(rollout_pkg, "final_results", lambda *a: None)
    monkeypatch.setattr(runner, "results_table",
                        lambda spec, dz, res, extra=(): pd.DataFrame({"success": [True] * N_RUNS}))
    monkeypatch.setattr(runner, "summarize", lambda spec, df: SimpleNamespace(warnings=[], qp_flagged_runs=0))
    monkeypatch.setattr(runner, "campaign_manifest", lambda *a, **k: {"warnings": []})
    monkeypatch.setattr(runner, "sensing_of", lambda spec: "delayed")
    if results_fail:
        def full(path, data):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(runner, "write_json_atomic", full)
    job.built.design.mu, job.out, job.spec, job.gains = np.ones(N_RUNS), tmp_path / "out", None, None
    job.chunk_s, job.seconds = 0.01, 0.03
    clock = {"import": time.perf_counter(), "start": time.perf_counter()}
    t0 = time.perf_counter()
    with interrupts.Guard("test") as guard:
        if results_fail:
            with pytest.raises(OSError, match="No space left"):
                runner._write(job, rollout, clock, False, None, guard, saver)
        else:
            runner._write(job, rollout, clock, False, None, guard, saver)
    if results_fail:  # the last write completed: a resume finds the finished simulation
        assert not (tmp_path / "out" / "results.csv").exists() and "cancelled" not in last
        assert _saved_state(job.ckpt)[0]["chunks_done"] == N_CHUNKS
    else:
        assert time.perf_counter() - t0 < 2.5 and last == {"cancelled": True}
        assert (tmp_path / "out" / "results.csv").exists() and (tmp_path / "out" / "manifest.json").exists()
        assert not job.ckpt.exists()


# ---------------------------------------------------------------- the split gather in two processes

GATHER = textwrap.dedent("""
    import sys
    import numpy as np
    from wbc_jax.rollout import distributed, runs
    port, pid, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    distributed.initialize(distributed.Layout(f"localhost:{port}", 2, pid, None, "flags"))
    import jax
    from jax.experimental import multihost_utils
    from wbc_jax.rollout.sharding import run_mesh
    from wbc_jax.rollout.spread import Spread

    def host_gather(sp, tree, n, axes):  # every process's block through the hosts, then each run's row
        leaves, treedef, ax = runs.leaves_and_axes(tree, axes)
        host = [np.asarray(x) for x in jax.device_get(leaves)]
        every = iter(multihost_utils.process_allgather([x for x, a in zip(host, ax) if a is not None], tiled=True))
        host = [x if a is None else next(every) for x, a in zip(host, ax)]
        k = -(-n // 2)  # block p holds runs p, p + 2, ...: run r is row (r % 2) * k + r // 2 of the joined blocks
        order = [(r % 2) * k + r // 2 for r in range(n)]
        return runs.take(jax.tree_util.tree_unflatten(treedef, host), np.asarray(order), axes)

    n = 3  # 2 runs per process, the last padded
    rng = np.random.default_rng(0)
    tree = dict(q=rng.normal(size=(n, 4)).astype(np.float32), ok=rng.random(n) > 0.5,
                k=np.arange(n, dtype=np.int32), empty=np.zeros((n, 0), np.float32),
                shared=np.full(5, 7.0 + pid, np.float32))
    axes = dict(q=0, ok=0, k=0, empty=0, shared=None)
    got = {}
    for sp in (Spread("blocks", process=pid, processes=2), Spread("mesh", run_mesh())):
        placed = sp.place_state(tree, n, axes)
        gathering = sp.gather_start(placed, n, axes, fetch=pid == 0)  # process 1: no early copy to the host
        later = jax.tree_util.tree_map(lambda x: x + 1 if x.dtype != bool else x, placed)  # dispatched after
        host = gathering.finish()
        jax.block_until_ready(later)
        ref = host_gather(sp, placed, n, axes) if sp.mode == "blocks" else None
        for key in tree:
            got[f"{sp.mode}.{key}"] = host[key]
            if ref is not None:
                assert host[key].dtype == ref[key].dtype and np.array_equal(host[key], ref[key]), key
        assert all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(host),
                                                        jax.tree_util.tree_leaves(sp.gather(placed, n, axes))))
    np.savez(out, **got)
""")


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def run_two(script: str, args: list[list[str]]) -> list[str]:
    """``python -c script PORT I *args[I]`` as two processes at once (I = 0, 1; a free localhost port; one CPU
    device each); both must exit 0 within ``TIMEOUT_S``. Returns their outputs."""
    import os

    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=1", JAX_PLATFORMS="cpu")
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, "-c", script, str(port), str(i), *args[i]], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for i in range(2)]
    try:
        logs = [p.communicate(timeout=TIMEOUT_S)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert [p.returncode for p in procs] == [0, 0], "\n---\n".join(x[-3000:] for x in logs)
    return logs


def test_split_gather_in_two_processes(tmp_path):
    run_two(GATHER, [[str(tmp_path / f"p{i}.npz")] for i in range(2)])
    rng = np.random.default_rng(0)
    q, ok = rng.normal(size=(3, 4)).astype(np.float32), rng.random(3) > 0.5
    for i in range(2):
        with np.load(tmp_path / f"p{i}.npz") as z:
            for mode in ("blocks", "mesh"):
                np.testing.assert_array_equal(z[f"{mode}.q"], q)
                np.testing.assert_array_equal(z[f"{mode}.ok"], ok)
                np.testing.assert_array_equal(z[f"{mode}.k"], np.arange(3, dtype=np.int32))
                assert z[f"{mode}.empty"].shape == (3, 0) and z[f"{mode}.k"].dtype == np.int32
            np.testing.assert_array_equal(z["blocks.shared"], np.full(5, 7.0 + i, np.float32))  # its own
