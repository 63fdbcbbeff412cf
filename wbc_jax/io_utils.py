"""Output helpers: nothing half-written is ever left behind, and nothing a command did not create is replaced.

:func:`check_out_dir` is called by every command before any work: it accepts a new or empty folder, or (with
``force``) a folder holding an earlier run of the same command, recognised by its ``manifest.json`` naming the
command and listing the files that run wrote (``files``); anything else (a file, a non-empty foreign folder, the
current folder, a folder holding an input, an unwritable parent, a name too long for the temporary siblings) is an
:class:`~wbc_jax.errors.OutputError`. :func:`atomic_dir` then builds the output next to it and moves it into place:
a new folder by one rename; into an earlier run's folder by replacing only the files that run listed, so anything
else a user put there stays. A symbolic link as the output folder is written through (its target is the folder).

:func:`claim_out_dir` makes a command the only one writing a folder: a lock file ``.NAME.lock`` beside it, held
with ``flock`` (released by the kernel when the process ends) and naming the owner (pid, host, command, start).
"""

from __future__ import annotations

import atexit
import fcntl
import json
import os
import platform
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

from wbc_jax.errors import InputError, OutputError

# longest suffix a command adds to the output folder's name for its siblings: ".NAME.campaign-ckpt" (15),
# ".NAME.tmp-XXXXXXXX" and ".NAME.old-XXXXXXXX" (14) of atomic_dir, ".NAME.lock" (6)
SIBLING_EXTRA = 16
READ_LIMIT = 1 << 20  # default cap on an input file's size [bytes] (spec, gains, baseline: a few kB)
MANIFEST = "manifest.json"
_HELD: dict[Path, tuple[Path, int, list[Path], int]] = {}  # out -> (lock file, fd, parents made, claims)


def _read_manifest(folder: Path) -> dict:
    """``folder/manifest.json`` as a dict ({} when absent, unreadable or not an object)."""
    try:
        m = json.loads(read_capped(folder / MANIFEST, what="manifest"))
    except (OSError, ValueError, InputError):
        return {}
    return m if isinstance(m, dict) else {}


def _nearest_existing(p: Path) -> Path:
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def output_path(out) -> Path:
    """The absolute output folder of ``--out`` (a symbolic link: its target, so that it is written through)."""
    if out is None or not str(out).strip():
        raise OutputError(f"--out {str(out)!r}: empty path; name a new or empty folder")
    p = Path(os.path.abspath(os.fspath(out)))
    if p.is_symlink():
        target = p.resolve()
        if not target.is_dir() and target.exists():
            raise OutputError(f"--out {out}: is a link to {target}, which is not a folder; name a new or empty folder")
        return target
    return p


def _check_path(out, p: Path, inputs=()) -> None:
    """Where ``p`` (the output folder of ``--out out``) may not be: the current folder or one enclosing it, a
    folder holding an input, a name too long, a parent that is a file or cannot take new folders."""
    real = p.resolve()
    cwd = Path.cwd().resolve()
    if real == cwd or real in cwd.parents:
        raise OutputError(f"--out {out}: is the current folder or one enclosing it; name a new or empty folder")
    for f in inputs:
        if f is None:
            continue
        fr = Path(f).resolve()
        if fr == real or real in fr.parents:
            raise OutputError(f"--out {out}: holds the input {f}, which would be deleted; name another folder")
    limit = _name_max(_nearest_existing(p))
    if len(p.name.encode()) + SIBLING_EXTRA > limit:
        raise OutputError(f"--out {out}: folder name is {len(p.name.encode())} bytes, at most "
                          f"{limit - SIBLING_EXTRA} (its temporary and checkpoint siblings add {SIBLING_EXTRA})")
    _probe_writable(_nearest_existing(p.parent), out)


def check_out_dir(out, command: str, *, force: bool = False, inputs=(), writes=()) -> Path:
    """Check an output folder before any work; return its absolute path (a link's target).

    Args:
        out: the output folder (``--out``).
        command: the command writing it, e.g. ``"wbc-jax campaign"`` (its ``manifest.json`` names it).
        force: allow replacing the files of an earlier run of ``command`` (those its manifest lists).
        inputs: input files of the command; a folder holding one of them is refused (even with ``force``).
        writes: names the command writes into the folder; one the earlier run did not write is refused.

    Raises:
        OutputError: one line saying what is wrong with ``out`` and what to do.
    """
    p = output_path(out)
    _check_path(out, p, inputs)
    if p.exists() or p.is_symlink():
        if not p.is_dir():
            raise OutputError(f"--out {out}: exists and is not a folder; name a new or empty folder")
        entries = sorted(e.name for e in p.iterdir())
        if entries:
            _check_earlier_run(out, p, entries, command, force, writes)
        if not os.access(p, os.W_OK):
            raise OutputError(f"--out {out}: folder is not writable")
    return p


def _check_earlier_run(out, p: Path, entries: list[str], command: str, force: bool, writes) -> None:
    """A non-empty output folder: an earlier run of ``command`` whose files ``force`` may replace, nothing else."""
    manifest = _read_manifest(p)
    if manifest.get("command") != command:
        raise OutputError(f"--out {out}: folder is not empty ({len(entries)} entries, e.g. {entries[0]!r}) "
                          f"and holds no earlier {command} run; name a new or empty folder")
    if not force:
        raise OutputError(f"--out {out}: holds an earlier {command} run; pass --force to replace it, "
                          "or name a new folder")
    listed = manifest.get("files")
    if not isinstance(listed, list):
        raise OutputError(f"--out {out}: holds an earlier {command} run whose manifest.json does not list the files "
                          "it wrote (an older version); delete them yourself or name a new folder")
    foreign = sorted((set(entries) - set(listed) - {MANIFEST}) & set(writes))
    if foreign:
        raise OutputError(f"--out {out}: holds {foreign[0]}, which the earlier {command} run did not write and "
                          "this one would replace; move it or name another folder")


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _probe_writable(parent: Path, out) -> None:
    """Create and remove a temporary folder in ``parent`` (the nearest existing ancestor of the output)."""
    if not parent.is_dir():
        raise OutputError(f"--out {out}: {parent} is not a folder")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".wbc-jax-probe-", dir=parent))
    except OSError as e:
        raise OutputError(f"--out {out}: cannot create folders in {parent} ({e.strerror or e})") from None


def read_capped(path, limit: int = READ_LIMIT, what: str = "input") -> bytes:
    """Read at most ``limit`` bytes of ``path``; a longer file (or a device such as /dev/zero) is an InputError.

    Raises:
        InputError: the file is larger than ``limit`` [bytes].
        OSError: the file cannot be read (callers word it).
    """
    with open(path, "rb") as f:
        data = f.read(limit + 1)
    if len(data) > limit:
        raise InputError(f"{path}: {what} file larger than {limit:,} bytes; is it the right file?")
    return data


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def file_mode() -> int:
    """The mode a new file gets under this process's umask (0644 under the usual 022)."""
    return 0o666 & ~_umask()


def _record_files(tmp: Path, command: str | None, kept: list[str]) -> None:
    """``tmp/manifest.json``: ``command`` (when the caller wrote none) and ``files``, the entries written (and
    those the caller listed already, e.g. a report written later); ``kept``: entries left from before."""
    manifest = _read_manifest(tmp)
    if command is not None and not (tmp / MANIFEST).exists():
        manifest = {"command": command}
    if not manifest:
        return
    written = {e.name for e in tmp.iterdir()} | {MANIFEST}
    listed = manifest.get("files") if isinstance(manifest.get("files"), list) else []
    manifest["files"] = sorted((written | set(listed)) - set(kept))
    write_json_atomic(tmp / MANIFEST, manifest)


@contextmanager
def atomic_dir(out: str | os.PathLike, command: str | None = None):
    """Yield a temporary folder next to ``out``; on success its content replaces ``out``'s, on error it vanishes.

    Call :func:`check_out_dir` first. A new or empty ``out`` is replaced by one rename; an earlier run's folder
    keeps every entry its ``manifest.json`` does not list (the user's), the listed ones are replaced.
    ``command``: also write ``manifest.json`` naming it when the caller wrote none (so a later run recognises the
    folder). The manifest gets ``files``: the entries this run wrote.
    """
    out = output_path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        yield tmp
        old = sorted(e.name for e in out.iterdir()) if out.is_dir() else []
        listed = (_read_manifest(out).get("files") or []) if old else []
        _record_files(tmp, command, [e for e in old if e not in listed and e != MANIFEST])
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it 0700
        if not old:
            os.rename(tmp, out)  # rename() replaces an empty folder
        else:
            _replace_listed(tmp, out, old, listed)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _replace_listed(tmp: Path, out: Path, old: list[str], listed: list) -> None:
    """Move ``tmp``'s entries into ``out`` in place of the earlier run's ``listed`` ones (manifest.json last);
    the entries of ``out`` not listed stay. A failure puts the earlier entries back."""
    new = sorted(e.name for e in tmp.iterdir())
    clash = sorted(set(new) & (set(old) - set(listed) - {MANIFEST}))
    if clash:
        raise OutputError(f"{out}: holds {clash[0]}, which the earlier run did not write; not replaced")
    trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    moved_old, moved_new = [], []
    order = [e for e in new if e != MANIFEST] + [MANIFEST]
    try:
        for name in [e for e in old if e in listed and e != MANIFEST] + [MANIFEST]:
            if (out / name).exists() or (out / name).is_symlink():
                os.rename(out / name, trash / name)
                moved_old.append(name)
        for name in order:
            if (tmp / name).exists():
                os.rename(tmp / name, out / name)
                moved_new.append(name)
    except OSError:
        for name in moved_new:
            os.rename(out / name, tmp / name)
        for name in moved_old:
            os.rename(trash / name, out / name)
        raise
    shutil.rmtree(trash, ignore_errors=True)


def write_json_atomic(path: str | os.PathLike, obj) -> None:
    """Write JSON to ``path`` through a temporary file and an atomic rename (mode 0644 under the usual umask)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump(obj, f, indent=2, default=float)
    os.chmod(tmp, file_mode())
    os.replace(tmp, path)


def check_file_target(path, flag: str, *, force: bool = False) -> Path:
    """Check an output file (e.g. ``--json``) before any work: its folder exists, it is not a folder, and an
    existing file is replaced only with ``force``. Returns its absolute path.

    Raises:
        OutputError: one line naming ``flag``, the path and what to do.
    """
    p = Path(os.path.abspath(os.fspath(path)))
    if p.is_dir():
        raise OutputError(f"{flag} {path}: is a folder; name a file")
    if not p.parent.is_dir():
        raise OutputError(f"{flag} {path}: folder {p.parent} does not exist")
    if p.exists() and not force:
        raise OutputError(f"{flag} {path}: exists; pass --force to overwrite it, or name a new file")
    if not os.access(p.parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise OutputError(f"{flag} {path}: not writable")
    return p


# ---------------------------------------------------------------- one command per output folder


def lock_path(out: Path) -> Path:
    """The lock file of output folder ``out`` (beside it)."""
    return out.parent / f".{out.name}.lock"


def _owner(fd: int) -> dict:
    """The owner record in an open lock file ({} when empty or unreadable)."""
    try:
        record = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _describe(owner: dict) -> str:
    return (f"{owner.get('command', 'a wbc-jax command')} (pid {owner.get('pid', '?')} on {owner.get('host', '?')}, "
            f"since {owner.get('started', '?')})")


def _in_use(out, fd: int) -> OutputError:
    """The refusal of ``--out out`` whose lock (open as ``fd``) another command holds, naming it."""
    return OutputError(f"--out {out}: in use by {_describe(_owner(fd))}; wait for it to end or name another folder")


def claim_out_dir(out, command: str) -> Path:
    """Make this process the one command writing ``out`` (a second claim by this process is a no-op); return the
    output folder. A lock left by a process that ended without releasing it is taken over, with a note on stdout.

    Raises:
        OutputError: another running command holds the folder (the line names it), or the path is unusable.
    """
    p = output_path(out)
    if p in _HELD:
        path, fd, made, n = _HELD[p]
        _HELD[p] = (path, fd, made, n + 1)
        return p
    _check_path(out, p)
    made = [d for d in [p.parent, *p.parent.parents] if not d.exists()]
    p.parent.mkdir(parents=True, exist_ok=True)
    path = lock_path(p)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            err = _in_use(out, fd)
            os.close(fd)
            _remove_empty(made)
            raise err from None
        try:  # the owner may have removed the file between our open and our lock: lock the current one
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    stale = _owner(fd)
    if stale:
        print(f"note: --out {out}: took over the lock of {_describe(stale)}, which ended without releasing it",
              flush=True)
    record = dict(pid=os.getpid(), host=platform.node(), command=command,
                  started=time.strftime("%Y-%m-%d %H:%M:%S %z"))
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(record).encode(), 0)
    _HELD[p] = (path, fd, made, 1)
    return p


def check_not_in_use(out) -> Path:
    """:func:`claim_out_dir`'s check that no running command holds ``out``, without claiming it (nothing is
    created; the path itself: :func:`check_out_dir`); return the output folder.

    Raises:
        OutputError: another running command holds the folder (the line names it).
    """
    p = output_path(out)
    try:
        fd = os.open(lock_path(p), os.O_RDONLY)
    except FileNotFoundError:  # no lock file: nobody holds the folder
        return p
    except OSError as e:
        raise OutputError(f"--out {out}: cannot read its lock {lock_path(p)} ({e.strerror or e})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        raise _in_use(out, fd) from None
    finally:
        os.close(fd)
    return p


def release_out_dir(out=None) -> None:
    """Release this process's claim on ``out`` (every claim when None); the lock file goes with the last one."""
    keys = list(_HELD) if out is None else [output_path(out)]
    for p in keys:
        if p not in _HELD:
            continue
        path, fd, made, n = _HELD.pop(p)
        if n > 1 and out is not None:
            _HELD[p] = (path, fd, made, n - 1)
            continue
        try:
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                os.unlink(path)
        except OSError:
            pass
        os.close(fd)
        _remove_empty(made)


def _remove_empty(folders: list[Path]) -> None:
    """Remove the parent folders a claim made (innermost first), where they are still empty."""
    for d in folders:
        try:
            d.rmdir()
        except OSError:
            return


atexit.register(release_out_dir)
