"""Output helpers: nothing half-written is ever left behind, and nothing a command did not create is replaced.

:func:`check_out_dir` is called by every command before any work: it accepts a new or empty folder, or (with
``force``) a folder holding an earlier run of the same command, recognised by its ``manifest.json`` naming the
command; anything else (a file, a non-empty foreign folder, the current folder, a folder holding an input, an
unwritable parent, a name too long for the temporary siblings) is an :class:`~wbc_jax.errors.OutputError`.
:func:`atomic_dir` then builds the output next to it and renames it into place.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import uuid
from contextlib import contextmanager
from pathlib import Path

from wbc_jax.errors import InputError, OutputError

# longest suffix a command adds to the output folder's name for its siblings: ".NAME.campaign-ckpt" (15),
# ".NAME.tmp-XXXXXXXX" and ".NAME.old-XXXXXXXX" (14) of atomic_dir
SIBLING_EXTRA = 16
READ_LIMIT = 1 << 20  # default cap on an input file's size [bytes] (spec, gains, baseline: a few kB)


def _manifest_command(folder: Path) -> str | None:
    """The ``command`` named by ``folder/manifest.json`` (None when absent or unreadable)."""
    try:
        m = json.loads(read_capped(folder / "manifest.json", what="manifest"))
    except (OSError, ValueError, InputError):
        return None
    return m.get("command") if isinstance(m, dict) else None


def _nearest_existing(p: Path) -> Path:
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_out_dir(out, command: str, *, force: bool = False, inputs=()) -> Path:
    """Check an output folder before any work; return its absolute path.

    Args:
        out: the output folder (``--out``).
        command: the command writing it, e.g. ``"wbc-jax campaign"`` (its ``manifest.json`` names it).
        force: allow replacing a folder that holds an earlier run of ``command``.
        inputs: input files of the command; a folder holding one of them is refused (even with ``force``).

    Raises:
        OutputError: one line saying what is wrong with ``out`` and what to do.
    """
    if out is None or not str(out).strip():
        raise OutputError(f"--out {str(out)!r}: empty path; name a new or empty folder")
    p = Path(os.path.abspath(os.fspath(out)))
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
    if p.exists() or p.is_symlink():
        if not p.is_dir():
            raise OutputError(f"--out {out}: exists and is not a folder; name a new or empty folder")
        entries = sorted(e.name for e in p.iterdir())
        if entries:
            own = _manifest_command(p) == command
            if not own:
                raise OutputError(f"--out {out}: folder is not empty ({len(entries)} entries, e.g. {entries[0]!r}) "
                                  f"and holds no earlier {command} run; name a new or empty folder")
            if not force:
                raise OutputError(f"--out {out}: holds an earlier {command} run; pass --force to replace it, "
                                  "or name a new folder")
        if not os.access(p, os.W_OK):
            raise OutputError(f"--out {out}: folder is not writable")
    _probe_writable(_nearest_existing(p.parent), out)
    return p


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


@contextmanager
def atomic_dir(out: str | os.PathLike, command: str | None = None):
    """Yield a temporary folder next to ``out``; on success it replaces ``out``, on error it vanishes.

    Call :func:`check_out_dir` first: this replaces whatever is at ``out``. ``command``: also write
    ``manifest.json`` naming it when the caller wrote none (so a later run recognises the folder).
    """
    out = Path(out).absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        yield tmp
        if command is not None and not (tmp / "manifest.json").exists():
            (tmp / "manifest.json").write_text(json.dumps({"command": command}) + "\n")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it 0700
        if out.exists():
            old = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
            os.rename(out, old)
            try:
                os.rename(tmp, out)
            except OSError:
                os.rename(old, out)  # put the previous output back
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_json_atomic(path: str | os.PathLike, obj) -> None:
    """Write JSON to ``path`` through a temporary file and an atomic rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump(obj, f, indent=2, default=float)
    os.replace(tmp, path)
