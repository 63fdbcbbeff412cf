"""A campaign's checkpoint: the batched rollout state after the last finished chunk, next to the output folder.

``.<DIR name>.campaign-ckpt/`` holds ``state_K.npz`` (every leaf of the batched RunState after chunk K) and
``meta.json`` (chunks done, wall time so far, the run's identity (``wbc_jax.campaign.manifest.run_identity``: spec,
gains, backend, numerics versions, run count) and the state file's SHA-256). :func:`save_state` writes the state
first and then the meta that names it, so an interruption at any point leaves a consistent pair; :class:`Writer`
runs those writes in a background thread, one at a time. :func:`read_meta` checks the meta against this run's
identity before anything is built or compiled, and :func:`load_state` the state against the fresh state's
structure. Damage or a mismatch is a one-line ``CheckpointError`` that says how to restart; a checkpoint is never
trusted silently.
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
import jax.numpy as jnp
import numpy as np

from wbc_jax.errors import CheckpointError
from wbc_jax.io_utils import file_mode, write_json_atomic

RESTART = "delete {ck}, or run with --force instead of --resume to start over"


def ckpt_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.campaign-ckpt"


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_npz(f, leaves, block: int = 1 << 20) -> None:
    """``leaves`` (numpy arrays) to the open binary file ``f`` as ``np.savez`` writes them (uncompressed,
    ``arr_0.npy`` ...; read by ``np.load``), each array's bytes handed to the zip in ``block``-byte views: the zip's
    CRC and the file writes release the interpreter lock, where ``np.savez`` holds it while it copies each 16 MiB
    piece, which stalls the simulating thread (Warp's launch callback) of a campaign writing in the background."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for i, x in enumerate(leaves):
            x = np.asarray(x, order="C")  # (np.ascontiguousarray makes a 0-d array 1-d)
            with zf.open(f"arr_{i}.npy", "w", force_zip64=True) as fp:
                np.lib.format.write_array_header_1_0(fp, np.lib.format.header_data_from_array_1_0(x))
                data = memoryview(x.reshape(-1).view(np.uint8))
                for start in range(0, len(data), block):
                    fp.write(data[start:start + block])


def save_state(ck: Path, state, meta: dict) -> None:
    """State of chunk k to ``state_k.npz`` first, then ``meta.json`` (naming that file and its SHA-256)
    atomically, then the older state files go: an interruption at any point leaves a consistent (meta, state)
    pair."""
    ck.mkdir(parents=True, exist_ok=True)
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(state))]
    name = f"state_{meta['chunks_done']}.npz"
    fd, tmp = tempfile.mkstemp(prefix=".state.", suffix=".npz", dir=ck)
    with os.fdopen(fd, "wb") as f:
        write_npz(f, leaves)
    os.chmod(tmp, file_mode())
    digest = sha256_file(Path(tmp))
    os.replace(tmp, ck / name)
    write_json_atomic(ck / "meta.json", dict(meta, state_file=name, state_sha256=digest))
    for old in ck.glob("state_*.npz"):
        if old.name != name:
            old.unlink(missing_ok=True)


class Writer:
    """:func:`save_state` in a background thread, one write at a time, so that the caller's next chunk runs meanwhile.

    :meth:`save` first waits for the previous write; :meth:`join` waits for the write in progress and raises, in the
    caller's thread, the exception the write raised (once). The thread is not a daemon: an exiting interpreter
    waits for the write in progress.
    """

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def save(self, ck: Path, state, meta: dict, on_saved: Callable[[], None] | None = None) -> None:
        """Start writing ``state`` (host arrays the caller leaves unchanged) and ``meta`` to ``ck`` once the previous
        write ended (:meth:`join`: its error is raised here); ``on_saved`` runs in the writer thread after both files
        are written."""
        self.join()

        def write():
            try:
                save_state(ck, state, meta)
                if on_saved is not None:
                    on_saved()
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


def read_meta(ck: Path, identity: dict, n_chunks: int) -> dict | None:
    """The checked ``meta.json`` of checkpoint ``ck`` (None when there is no checkpoint).

    Raises:
        CheckpointError: meta.json missing beside state files, unreadable, incomplete or with values out of
            range; an identity entry that differs from ``identity``; the state file missing or not matching its
            SHA-256. The message says how to restart.
    """
    restart = RESTART.format(ck=ck)
    if not ck.exists():
        return None
    meta_p = ck / "meta.json"
    if not meta_p.exists():
        if any(ck.iterdir()):
            raise CheckpointError(f"{ck}: damaged checkpoint (meta.json missing); {restart}")
        return None
    try:
        meta = json.loads(meta_p.read_text())
        done, name, digest = int(meta["chunks_done"]), str(meta["state_file"]), str(meta["state_sha256"])
        float(meta["wall_s"]), list(meta["marks"]), dict(meta["identity"])  # noqa: B018
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{ck}: damaged checkpoint (meta.json unreadable or incomplete: "
                              f"{type(e).__name__} {e}); {restart}") from None
    differ = sorted(k for k in set(identity) | set(meta["identity"]) if meta["identity"].get(k) != identity.get(k))
    if differ:
        raise CheckpointError(f"{ck}: checkpoint belongs to another run ({', '.join(differ)} differ"
                              f"{': started with other --gains' if 'gains_hash' in differ else ''}); {restart}")
    if not (1 <= done <= n_chunks) or meta.get("n_chunks") != n_chunks or name != f"state_{done}.npz":
        raise CheckpointError(f"{ck}: damaged checkpoint (chunks_done {meta.get('chunks_done')!r} of "
                              f"{meta.get('n_chunks')!r}, state file {name!r}; this run has {n_chunks}); {restart}")
    state_p = ck / name
    if not state_p.is_file() or sha256_file(state_p) != digest:
        raise CheckpointError(f"{ck}: damaged checkpoint ({name} missing or its SHA-256 differs); {restart}")
    return meta


def load_state(ck: Path, state_like, identity: dict, n_chunks: int):
    meta = read_meta(ck, identity, n_chunks)
    if meta is None:
        return None, None
    try:
        with np.load(ck / meta["state_file"]) as z:
            leaves = [z[f"arr_{i}"] for i in range(len(z.files))]
    except (OSError, ValueError, KeyError) as e:
        raise CheckpointError(f"{ck}: damaged checkpoint ({meta['state_file']}: {e}); "
                              f"{RESTART.format(ck=ck)}") from None
    treedef = jax.tree_util.tree_structure(state_like)
    like = jax.tree_util.tree_leaves(state_like)
    if treedef.num_leaves != len(leaves) or any(x.shape != a.shape for x, a in zip(leaves, like)):
        raise CheckpointError(f"{ck}: checkpoint does not match this version's rollout state; "
                              f"{RESTART.format(ck=ck)}")
    # placed like the fresh state (committed to its device where that is): an uncommitted leaf changes the lowered
    # program's input shardings, so the chunk function would compile a second time and miss the compilation cache
    out = [jax.device_put(x, a.sharding) if getattr(a, "committed", False) else jnp.asarray(x)
           for x, a in zip(leaves, like)]
    return jax.tree_util.tree_unflatten(treedef, out), meta


def peek(ck: Path) -> dict | None:
    """A checkpoint's ``meta.json`` unchecked (chunks done, chunk count, identity, sessions): None when ``ck`` holds
    no file at all, {} when meta.json is missing or unreadable beside other files."""
    if not ck.is_dir() or not any(ck.iterdir()):
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
