"""A campaign's checkpoint: the batched rollout state after the last finished chunk, next to the output folder.

``.<DIR name>.campaign-ckpt/`` holds ``meta.json`` (chunks done, wall time so far, the run's identity
(``wbc_jax.campaign.manifest.run_identity``: spec, gains, backend, numerics versions, run count)) and the state it
names with each file's SHA-256: either ``state_K.npz`` (every leaf of the batched RunState after chunk K, all runs)
or, for a Warp campaign over several processes (``wbc_jax.campaign.blocks``), ``block_K_I.npz`` per process I (the
runs it was dealt, ``rows`` [start, stop, step] of the batch). :func:`save_state` writes the state first and then
the meta that names it, so an interruption at any point leaves a consistent pair; :class:`Writer` runs writes in a
background thread, one at a time. :func:`read_meta` checks the meta against this run's identity before anything is
built or compiled, and :func:`load_state` the state against the fresh state's structure. Damage or a mismatch is a
one-line ``CheckpointError`` that says how to restart; a checkpoint is never trusted silently.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import threading
import zipfile
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from wbc_jax.errors import CheckpointError, OutputError
from wbc_jax.io_utils import file_mode, write_json_atomic
from wbc_jax.rollout import runs
from wbc_jax.runtime.transfer import to_device

RESTART = "delete {ck}, or run with --force instead of --resume to start over"


def ckpt_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.campaign-ckpt"


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class Cancelled(Exception):
    """A write stopped by :meth:`Writer.cancel` before it ended (its file removed, the meta not written)."""


def write_npz(f, leaves, block: int = 1 << 20, cancelled: Callable[[], bool] | None = None) -> None:
    """``leaves`` (numpy arrays) to the open binary file ``f`` as ``np.savez`` writes them (uncompressed,
    ``arr_0.npy`` ...; read by ``np.load``), each array's bytes handed to the zip in ``block``-byte views: the zip's
    CRC and the file writes release the interpreter lock, where ``np.savez`` holds it while it copies each 16 MiB
    piece, which stalls the simulating thread (Warp's launch callback) of a campaign writing in the background.
    Raises :class:`Cancelled` between two blocks once ``cancelled()`` is true."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for i, x in enumerate(leaves):
            x = np.asarray(x, order="C")  # (np.ascontiguousarray makes a 0-d array 1-d)
            with zf.open(f"arr_{i}.npy", "w", force_zip64=True) as fp:
                np.lib.format.write_array_header_1_0(fp, np.lib.format.header_data_from_array_1_0(x))
                data = memoryview(x.reshape(-1).view(np.uint8))
                for start in range(0, len(data), block):
                    if cancelled is not None and cancelled():
                        raise Cancelled("checkpoint write cancelled")
                    fp.write(data[start:start + block])


def _write_leaves(ck: Path, name: str, leaves, cancelled: Callable[[], bool] | None = None) -> str:
    """``leaves`` (host arrays) to ``ck/name`` atomically (a temporary file renamed, removed when the write fails
    or is cancelled: :func:`write_npz`); returns its SHA-256."""
    ck.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".state.", suffix=".npz", dir=ck)
    try:
        with os.fdopen(fd, "wb") as f:
            write_npz(f, leaves, cancelled=cancelled)
        if cancelled is not None and cancelled():  # before the file is read again for its hash
            raise Cancelled("checkpoint write cancelled")
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    os.chmod(tmp, file_mode())
    digest = sha256_file(Path(tmp))
    os.replace(tmp, ck / name)
    return digest


def save_state(ck: Path, state, meta: dict, cancelled: Callable[[], bool] | None = None) -> None:
    """State of chunk k to ``state_k.npz`` first, then ``meta.json`` (naming that file and its SHA-256)
    atomically, then the older state files go: an interruption at any point (or :class:`Cancelled`, once
    ``cancelled()`` is true) leaves a consistent (meta, state) pair."""
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(state))]
    name = f"state_{meta['chunks_done']}.npz"
    digest = _write_leaves(ck, name, leaves, cancelled)
    write_json_atomic(ck / "meta.json", dict(meta, state_file=name, state_sha256=digest))
    for old in ck.glob("state_*.npz"):
        if old.name != name:
            old.unlink(missing_ok=True)


def save_block(ck: Path, leaves: list, chunk: int, process: int, rows: range) -> dict:
    """Process ``process``'s runs ``rows`` (a range of run indices, in block order) after chunk ``chunk`` (host
    arrays ``leaves``, the state's leaves in order, the run axis first where there is one) to
    ``block_<chunk>_<process>.npz``; returns its entry of ``meta.json``'s ``state_blocks`` (file, SHA-256, rows as
    [start, stop, step])."""
    name = f"block_{chunk}_{process}.npz"
    return dict(file=name, sha256=_write_leaves(ck, name, [np.asarray(x) for x in leaves]),
                rows=[rows.start, rows.stop, rows.step])


def save_block_meta(ck: Path, meta: dict, blocks: list[dict]) -> None:
    """``meta.json`` naming the blocks of chunk ``meta["chunks_done"]`` (:func:`save_block`'s entries, in process
    order), written once every block is; then a whole state file of an earlier chunk goes."""
    write_json_atomic(ck / "meta.json", dict(meta, state_blocks=blocks))
    for old in ck.glob("state_*.npz"):
        old.unlink(missing_ok=True)


def prune_blocks(ck: Path, before: int) -> None:
    """Delete the block files of chunks before ``before`` (whichever process wrote them)."""
    for old in ck.glob("block_*_*.npz"):
        try:
            chunk = int(old.name.split("_")[1])
        except ValueError:
            continue
        if chunk < before:
            old.unlink(missing_ok=True)


class Writer:
    """:func:`save_state` in a background thread, one write at a time, so that the caller's next chunk runs meanwhile.

    :meth:`save` first waits for the previous write; :meth:`join` waits for the write in progress and raises, in the
    caller's thread, the exception the write raised (once); :meth:`cancel` stops a state's write where its caller
    no longer needs it. The thread is not a daemon: an exiting interpreter waits for the write in progress.
    """

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._cancel = threading.Event()

    def save(self, ck: Path, state, meta: dict, on_saved: Callable[[], None] | None = None) -> None:
        """Start writing ``state`` (host arrays the caller leaves unchanged) and ``meta`` to ``ck`` once the previous
        write ended (:meth:`join`: its error is raised here); ``on_saved`` runs in the writer thread after both files
        are written."""
        self.run(lambda: save_state(ck, state, meta, self._cancel.is_set), on_saved and (lambda _: on_saved()))

    def cancel(self) -> None:
        """Stop the state's write in progress (:func:`save_state`: its file removed, the meta naming the state
        before) and wait for it; its error, if any, is dropped. For a caller that has kept what the state holds
        otherwise (a campaign's results)."""
        self._cancel.set()
        try:
            self.join()
        except Exception:  # the write is not needed: a cancelled or failed write is dropped
            pass
        finally:
            self._cancel.clear()

    def run(self, task: Callable[[], object], on_done: Callable[[object], None] | None = None) -> None:
        """Start ``task`` (a write) once the previous one ended (its error is raised here); ``on_done`` gets its
        return value in the writer thread."""
        self.join()

        def write():
            try:
                got = task()
                if on_done is not None:
                    on_done(got)
            except BaseException as e:  # handed to the caller's thread by join
                self._error = e

        self._thread = threading.Thread(target=write, name="wbc-jax-checkpoint")
        self._thread.start()

    def join(self) -> None:
        """Wait for the write in progress (none: return at once); raise the exception it raised, once."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def join_keeping(self, err: BaseException, out) -> None:
        """:meth:`join` where the results could not be written to ``out`` (``err``), so that the write in progress
        keeps the finished simulation. Raises :class:`~wbc_jax.errors.OutputError` naming both failures where that
        write failed too (the simulation is then lost)."""
        try:
            self.join()
        except Exception as e:
            raise OutputError(f"{out}: results not written ({err}); the last checkpoint's write failed too ({e}): "
                              "the finished simulation is lost") from err


def _block_rows(meta: dict) -> list[range]:
    """The run indices of each block ``meta`` names (ValueError unless together they are 0 ... n - 1 once each)."""
    rows = [range(*(int(r) for r in blk["rows"])) for blk in meta["state_blocks"]]
    every = np.sort(np.concatenate([np.asarray(r, dtype=np.int64) for r in rows] + [np.zeros(0, np.int64)]))
    if not rows or not np.array_equal(every, np.arange(len(every))):
        raise ValueError(f"state blocks' rows {[blk['rows'] for blk in meta['state_blocks']]!r}")
    return rows


def _state_files(meta: dict, done: int) -> list[tuple[str, str]]:
    """(file, SHA-256) of every state file ``meta`` names, checked for the names chunk ``done`` gives them and, for
    blocks, rows that cover the runs once each (ValueError, KeyError, TypeError otherwise)."""
    if "state_blocks" not in meta:
        name = str(meta["state_file"])
        if name != f"state_{done}.npz":
            raise ValueError(f"state file {name!r}")
        return [(name, str(meta["state_sha256"]))]
    _block_rows(meta)
    files = []
    for i, blk in enumerate(meta["state_blocks"]):
        if blk["file"] != f"block_{done}_{i}.npz":
            raise ValueError(f"state block {i}: {blk!r}")
        files.append((str(blk["file"]), str(blk["sha256"])))
    return files


def read_meta(ck: Path, identity: dict, n_chunks: int, logs_per_chunk: int | None = None) -> dict | None:
    """The checked ``meta.json`` of checkpoint ``ck`` (None when there is no checkpoint); with ``logs_per_chunk``,
    its chunks must be that long (a checkpoint written before meta.json recorded its chunks' length passes).

    Raises:
        CheckpointError: meta.json missing beside state files, unreadable, incomplete or with values out of
            range; an identity entry that differs from ``identity``; a state file missing or not matching its
            SHA-256; chunks of another length. The message says how to restart.
    """
    restart = RESTART.format(ck=ck)
    if not ck.exists():
        return None
    meta_p = ck / "meta.json"
    if not meta_p.exists():
        if _holds_files(ck):
            raise CheckpointError(f"{ck}: damaged checkpoint (meta.json missing); {restart}")
        return None
    try:
        meta = json.loads(meta_p.read_text())
        done = int(meta["chunks_done"])
        float(meta["wall_s"]), list(meta["marks"]), dict(meta["identity"])  # noqa: B018
        if "state_blocks" not in meta:
            str(meta["state_file"]), str(meta["state_sha256"])  # noqa: B018
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{ck}: damaged checkpoint (meta.json unreadable or incomplete: "
                              f"{type(e).__name__} {e}); {restart}") from None
    differ = sorted(k for k in set(identity) | set(meta["identity"]) if meta["identity"].get(k) != identity.get(k))
    if differ:
        raise CheckpointError(f"{ck}: checkpoint belongs to another run ({', '.join(differ)} differ"
                              f"{': started with other --gains' if 'gains_hash' in differ else ''}); {restart}")
    try:
        files = _state_files(meta, done) if 1 <= done <= n_chunks and meta.get("n_chunks") == n_chunks else None
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        files, why = None, f", {e}"
    else:
        why = ""
    if files is None:
        raise CheckpointError(f"{ck}: damaged checkpoint (chunks_done {meta.get('chunks_done')!r} of "
                              f"{meta.get('n_chunks')!r}{why}; this run has {n_chunks}); {restart}")
    if logs_per_chunk is not None and meta.get("logs_per_chunk", logs_per_chunk) != logs_per_chunk:
        raise CheckpointError(f"{ck}: checkpoint made with chunks of {meta['logs_per_chunk']!r} logged intervals, "
                              f"this run's have {logs_per_chunk} (its chunk plan differs); {restart}")
    for name, digest in files:
        state_p = ck / name
        if not state_p.is_file() or sha256_file(state_p) != digest:
            raise CheckpointError(f"{ck}: damaged checkpoint ({name} missing or its SHA-256 differs); {restart}")
    return meta


def _load_leaves(ck: Path, name: str) -> list[np.ndarray]:
    try:
        with np.load(ck / name) as z:
            return [z[f"arr_{i}"] for i in range(len(z.files))]
    except (OSError, ValueError, KeyError) as e:
        raise CheckpointError(f"{ck}: damaged checkpoint ({name}: {e}); {RESTART.format(ck=ck)}") from None


def _scatter(blocks: list[np.ndarray], rows: list[range]) -> np.ndarray:
    """The blocks' rows put back at their runs' indices (``rows``: each block's run indices)."""
    out = np.empty((sum(len(r) for r in rows), *blocks[0].shape[1:]), blocks[0].dtype)
    for x, r in zip(blocks, rows):
        if x.shape[0] != len(r):
            raise ValueError(f"a state block of {x.shape[0]} runs for {len(r)} rows")
        out[np.asarray(r, dtype=np.int64)] = x
    return out


def load_state(ck: Path, state_like, identity: dict, n_chunks: int, axes=0, logs_per_chunk: int | None = None):
    """The checkpoint's state (placed like ``state_like``, the fresh state of every run, run axes ``axes``: 0 or a
    pytree of 0 / None) and its checked meta; (None, None) without a checkpoint. A blocked state's run leaves are
    its blocks' rows put back in run order; the leaves without a run axis (scratch) are ``state_like``'s.

    Raises:
        CheckpointError: as :func:`read_meta`; a state file unreadable or not of ``state_like``'s structure."""
    meta = read_meta(ck, identity, n_chunks, logs_per_chunk)
    if meta is None:
        return None, None
    like, treedef, like_axes = runs.leaves_and_axes(state_like, axes)
    mismatch = f"{ck}: checkpoint does not match this version's rollout state; {RESTART.format(ck=ck)}"
    if "state_blocks" in meta:
        parts = [_load_leaves(ck, blk["file"]) for blk in meta["state_blocks"]]
        if any(len(p) != len(like) for p in parts):
            raise CheckpointError(mismatch)
        try:
            rows = _block_rows(meta)
            leaves = [None if a is None else _scatter([p[i] for p in parts], rows) for i, a in enumerate(like_axes)]
        except ValueError:
            raise CheckpointError(mismatch) from None
    else:
        leaves = _load_leaves(ck, meta["state_file"])
    # the leaves without a run axis (Warp's shared contact list) are scratch every step rebuilds: the fresh state's
    # (a block's list, as saved by a process of a blocked run, is smaller than the whole batch's)
    if len(leaves) == len(like):
        leaves = [np.asarray(a) if ax is None else x for x, a, ax in zip(leaves, like, like_axes)]
    if treedef.num_leaves != len(leaves) or any(x.shape != a.shape for x, a in zip(leaves, like)):
        raise CheckpointError(mismatch)
    # placed like the fresh state (committed to its device where that is): an uncommitted leaf changes the lowered
    # program's input shardings, so the chunk function would compile a second time and miss the compilation cache
    out = [jax.device_put(x, a.sharding) if getattr(a, "committed", False) else to_device(x)
           for x, a in zip(leaves, like)]
    return jax.tree_util.tree_unflatten(treedef, out), meta


def _holds_files(ck: Path) -> bool:
    """Whether ``ck`` holds a file other than state blocks (blocks without meta.json were never committed: no
    chunk of them can be resumed)."""
    return any(not p.name.startswith("block_") for p in ck.iterdir())


def peek(ck: Path) -> dict | None:
    """A checkpoint's ``meta.json`` unchecked (chunks done, chunk count, identity, sessions): None when ``ck`` holds
    no file at all (or only uncommitted blocks), {} when meta.json is missing or unreadable beside other files."""
    if not ck.is_dir() or not _holds_files(ck):
        return None
    try:
        meta = json.loads((ck / "meta.json").read_text())
    except (OSError, ValueError):
        return {}
    return meta if isinstance(meta, dict) else {}


def n_chunks_hint(ck: Path) -> int:
    """The chunk count a checkpoint's meta.json claims (checked again against the build); 0 when unreadable."""
    try:
        return int((peek(ck) or {})["n_chunks"])
    except (KeyError, TypeError, ValueError):
        return 0
