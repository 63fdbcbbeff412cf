"""A Warp campaign's checkpoint over several processes, each process writing its own block of runs
(``wbc_jax.campaign.blocks``, ``wbc_jax.campaign.checkpoint``'s block files).

The block files alone: written, named in meta.json, checked (SHA-256, names, rows) and joined back into the whole
state, the leaves without a run axis block 0's; blocks never committed are no checkpoint. Then the campaign's chunk
loop (``runner._run_chunks``) on a stand-in chunk program (a counter, no physics) in two real processes (localhost
coordinator, one CPU device each, gloo), one shared checkpoint folder: after every chunk meta.json names a complete
earlier chunk whose blocks join into that chunk's state; the last chunk is saved whole and the blocks go; both
processes stopped after chunk 2 leave chunk 2 committed, and a resume from it gives the uninterrupted end state.
"""

import json
import textwrap

import numpy as np
import pytest
from test_checkpoint_writer import run_two

from wbc_jax.campaign import checkpoint
from wbc_jax.errors import CheckpointError

IDENTITY = {"spec": "x"}


def _state(n: int, add: float = 0.0) -> dict:
    return {"q": np.arange(n * 3, dtype=np.float32).reshape(n, 3) + add, "k": np.full(n, add, np.int32),
            "shared": np.array([5.0, 6.0], np.float32)}


AXES = {"q": 0, "k": 0, "shared": None}


def _meta(done: int, n_chunks: int = 4) -> dict:
    return dict(identity=IDENTITY, chunks_done=done, n_chunks=n_chunks, marks=[], p_goal=None, wall_s=1.0,
                sessions=[])


def _write_blocks(ck, state, done: int, rows: list[range]) -> list[dict]:
    import jax

    entries = []
    for i, r in enumerate(rows):
        block = {k: (v if AXES[k] is None else v[np.asarray(r, dtype=int)]) for k, v in state.items()}
        entries.append(checkpoint.save_block(ck, jax.tree_util.tree_leaves(block), done, i, r))
    checkpoint.save_block_meta(ck, _meta(done), entries)
    return entries


def test_blocks_join_back_into_the_whole_state(tmp_path):
    ck = tmp_path / "ck"
    whole = _state(5, add=2.0)
    checkpoint.save_state(ck, _state(5), _meta(1))  # a whole state file (a resumed run's), then blocks
    _write_blocks(ck, whole, 2, [range(0, 5, 2), range(1, 5, 2)])  # dealt out in turn, as Spread deals runs
    assert sorted(p.name for p in ck.iterdir()) == ["block_2_0.npz", "block_2_1.npz", "meta.json"]
    got, meta = checkpoint.load_state(ck, _state(5), IDENTITY, 4, AXES)
    assert meta["chunks_done"] == 2 and [b["rows"] for b in meta["state_blocks"]] == [[0, 5, 2], [1, 5, 2]]
    for k in whole:
        np.testing.assert_array_equal(np.asarray(got[k]), whole[k])
        assert np.asarray(got[k]).dtype == whole[k].dtype


def test_an_empty_block_of_padding_joins(tmp_path):
    """More processes than runs: the last block holds no run."""
    ck = tmp_path / "ck"
    whole = _state(2, add=1.0)
    _write_blocks(ck, whole, 1, [range(0, 2, 3), range(1, 2, 3), range(2, 2, 3)])
    got, _ = checkpoint.load_state(ck, _state(2), IDENTITY, 4, AXES)
    np.testing.assert_array_equal(np.asarray(got["q"]), whole["q"])


@pytest.mark.parametrize("damage, expect", [
    ("sha", "block_2_1.npz missing or its SHA-256 differs"),
    ("missing", "block_2_1.npz missing or its SHA-256 differs"),
    ("gap", "state blocks' rows"),
    ("name", "state block 0"),
    ("runs", "does not match this version's rollout state"),
])
def test_damaged_blocks_are_one_line_errors(tmp_path, damage, expect):
    ck = tmp_path / "ck"
    entries = _write_blocks(ck, _state(5, add=2.0), 2, [range(0, 3), range(3, 5)])
    if damage == "sha":
        entries[1]["sha256"] = "0" * 64
    elif damage == "missing":
        (ck / "block_2_1.npz").unlink()
    elif damage == "gap":
        entries[1]["rows"] = [4, 5, 1]
    elif damage == "name":
        entries[0]["file"] = "block_1_0.npz"
    checkpoint.save_block_meta(ck, _meta(2), entries)
    like = _state(6) if damage == "runs" else _state(5)
    with pytest.raises(CheckpointError) as e:
        checkpoint.load_state(ck, like, IDENTITY, 4, AXES)
    assert expect in str(e.value) and "\n" not in str(e.value) and "--force" in str(e.value)


def test_uncommitted_blocks_are_no_checkpoint_and_old_blocks_are_pruned(tmp_path):
    import jax

    ck = tmp_path / "ck"
    for done in (1, 2, 3):
        checkpoint.save_block(ck, jax.tree_util.tree_leaves(_state(2)), done, 0, range(2))
    assert checkpoint.peek(ck) is None and checkpoint.read_meta(ck, IDENTITY, 4) is None  # no meta.json yet
    checkpoint.prune_blocks(ck, 2)
    assert sorted(p.name for p in ck.iterdir()) == ["block_2_0.npz", "block_3_0.npz"]
    (ck / "meta.json").write_text("{")
    assert checkpoint.peek(ck) == {}


# ---------------------------------------------------------------- the chunk loop in two processes

LOOP = textwrap.dedent("""
    import json, sys
    from types import SimpleNamespace
    import numpy as np
    from wbc_jax.rollout import distributed
    port, pid, ck, cut = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
    distributed.initialize(distributed.Layout(f"localhost:{port}", 2, pid, None, "flags"))
    import jax, jax.numpy as jnp
    from pathlib import Path
    from wbc_jax.campaign import checkpoint, interrupts, runner
    from wbc_jax.campaign.blocks import Blocks
    from wbc_jax.campaign.job import Status
    from wbc_jax.campaign.resume import Start
    from wbc_jax.rollout.spread import Spread

    N, CHUNKS, ck = 3, 4, Path(ck)
    def chunk(model, state, plan, om, gains, push, mu_ground):
        return {k: v + 1 for k, v in state.items()}, SimpleNamespace(p_goal=state["q"][:, None, :2] * 10.0)
    runner.chunk_fn = lambda *a, **k: chunk
    sp = Spread("blocks", process=pid, processes=2)
    axes = {"q": 0, "k": 0}
    state0 = {"q": np.arange(N * 3, dtype=np.float32).reshape(N, 3), "k": np.zeros(N, np.int32)}
    sim = SimpleNamespace(controller=SimpleNamespace(final_input=lambda logs: logs.p_goal[:, -1], extra_columns=()),
                          dt_physics=0.01)
    built = SimpleNamespace(sim=sim, n_chunks=CHUNKS, logs_per_chunk=1, design=SimpleNamespace(n=N))
    batch = SimpleNamespace(model=None, plan=None, om=None, gains=None, push=None, mu_ground=None, in_axes=None,
                            state=sp.place_state(state0, N, axes), state_axes=axes)
    status = Status("out", ckpt=ck if pid == 0 else None, stage="chunks", n_chunks=CHUNKS, writer=pid == 0)
    job = SimpleNamespace(batch=batch, spread=sp, built=built, writer=pid == 0, ckpt=status.ckpt,
                          identity={"spec": "x"}, status=status)
    start = Start(batch.state, 0, 0.0, [], None, [])
    if cut < 0:  # resume: process 0 loads chunk 2's blocks, both start from them
        st, meta = checkpoint.load_state(ck, state0, {"spec": "x"}, CHUNKS, axes)
        host = jax.device_get(st)
        start = Start(sp.place_state(host, N, axes), meta["chunks_done"], meta["wall_s"], meta["marks"], None, [])
    seen = []
    def after(done, n_chunks):
        if pid == 0 and done >= 2:  # meta.json names chunk done - 1 (committed at this chunk's end)
            m = checkpoint.read_meta(ck, {"spec": "x"}, CHUNKS)
            seen.append(m["chunks_done"])
        if done == cut:
            raise KeyboardInterrupt
    runner.after_chunk = after
    saver = checkpoint.Writer()
    blocks = Blocks(ck, sp, N, pid == 0, on_meta=lambda k: setattr(status, "saved", k))
    try:
        with interrupts.Guard("test") as guard:
            rollout, _ = runner._run_chunks(job, start, False, False, guard, saver, blocks)
    except KeyboardInterrupt:
        print(json.dumps(dict(stopped=True, saved=status.saved, seen=seen)))
        sys.exit(0)
    saver.join()
    blocks.finish()
    out = dict(stopped=False, seen=seen, saved=status.saved)
    if pid == 0:
        out["q"] = np.asarray(rollout.state["q"]).tolist()
    print(json.dumps(out))
""")


def _two(ck, cut: int) -> list[dict]:
    logs = run_two(LOOP, [[str(ck), str(cut)]] * 2)
    return [json.loads(x.strip().splitlines()[-1]) for x in logs]


def test_blocked_checkpoint_in_two_processes(tmp_path):
    q0 = np.arange(9, dtype=np.float32).reshape(3, 3)
    ck = tmp_path / ".out.campaign-ckpt"
    full = _two(ck, 0)  # uninterrupted: meta.json one chunk behind, then the last chunk whole
    assert full[0]["seen"] == [1, 2] and full[0]["saved"] == 4
    np.testing.assert_array_equal(full[0]["q"], q0 + 4)
    assert sorted(p.name for p in ck.iterdir()) == ["meta.json", "state_4.npz"]
    meta = json.loads((ck / "meta.json").read_text())
    assert meta["chunks_done"] == 4 and "state_blocks" not in meta
    np.testing.assert_array_equal(meta["p_goal"], (q0 + 3)[:, :2] * 10.0)

    ck2 = tmp_path / ".cut.campaign-ckpt"
    stopped = _two(ck2, 2)  # both stop after chunk 2: its blocks committed on the way out
    assert [s["stopped"] for s in stopped] == [True, True] and stopped[0]["saved"] == 2
    got, meta = checkpoint.load_state(ck2, {"q": q0, "k": np.zeros(3, np.int32)}, {"spec": "x"}, 4,
                                      {"q": 0, "k": 0})
    assert meta["chunks_done"] == 2 and [b["rows"] for b in meta["state_blocks"]] == [[0, 3, 2], [1, 3, 2]]
    np.testing.assert_array_equal(np.asarray(got["q"]), q0 + 2)
    np.testing.assert_array_equal(np.asarray(got["k"]), np.full(3, 2))
    resumed = _two(ck2, -1)
    np.testing.assert_array_equal(resumed[0]["q"], q0 + 4)
    assert sorted(p.name for p in ck2.iterdir()) == ["meta.json", "state_4.npz"]
