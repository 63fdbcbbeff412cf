"""Ctrl-C (SIGINT) and SIGTERM for a running command: a clean stop with one line that says what was left.

Outside a :meth:`Guard.deferred` block a signal raises :class:`Interrupted` at once (Python's usual Ctrl-C,
SIGTERM included). Inside one (XLA compiling or running a chunk: an exception raised in the middle of XLA's compile
can leave the process to crash) the signal is noted, a line on stderr says the stop waits for the work in progress,
and :meth:`Guard.check` raises at the next safe point; a second signal ends the process at once (``os._exit``),
after one line from ``describe``. Exit codes: 130 for SIGINT, 143 for SIGTERM (128 + the signal's number).
Signals are handled in the main thread only; elsewhere a Guard does nothing.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from contextlib import contextmanager
from typing import Callable

SIGNALS = (signal.SIGINT, signal.SIGTERM)
NAMES = {signal.SIGINT: "interrupted (SIGINT)", signal.SIGTERM: "terminated (SIGTERM)"}


class Interrupted(KeyboardInterrupt):
    """A command stopped by SIGINT or SIGTERM; ``where``: what it left (one phrase, may be empty)."""

    def __init__(self, signum: int = signal.SIGINT, where: str = ""):
        super().__init__(signum, where)
        self.signum, self.where = signum, where

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    def __str__(self) -> str:
        return NAMES.get(self.signum, f"stopped by signal {self.signum}") + (f" {self.where}" if self.where else "")


def as_interrupted(e: KeyboardInterrupt, where: str = "") -> Interrupted:
    """``e`` as an :class:`Interrupted` (a plain KeyboardInterrupt is a SIGINT) with ``where`` (kept if set)."""
    return Interrupted(getattr(e, "signum", signal.SIGINT), getattr(e, "where", "") or where)


class Guard:
    """SIGINT and SIGTERM handlers for the life of a ``with`` block.

    Args:
        command: the command's name for the lines it prints, e.g. ``"wbc-jax campaign"``.
        describe: what exists now, one phrase (for a stop during a deferred block); None: nothing to say.
    """

    def __init__(self, command: str, describe: Callable[[], str] | None = None):
        self.command, self.describe = command, describe or (lambda: "")
        self.pending: int | None = None
        self._deferring = 0
        self._seen = 0
        self._saved: dict = {}
        self._wakeup = None

    def __enter__(self) -> Guard:
        if threading.current_thread() is not threading.main_thread():
            return self
        self._saved = {s: signal.signal(s, self._handler) for s in SIGNALS}
        read, write = os.pipe()
        os.set_blocking(write, False)
        try:
            self._wakeup = (read, write, signal.set_wakeup_fd(write, warn_on_full_buffer=False))
        except ValueError:  # not the main interpreter's main thread
            os.close(read)
            os.close(write)
            return self
        threading.Thread(target=self._watch, args=(read,), daemon=True, name="wbc-jax-signals").start()
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._saved.items():
            signal.signal(s, handler)
        if self._wakeup is not None:
            read, write, previous = self._wakeup
            signal.set_wakeup_fd(previous)
            os.close(write)  # the watcher reads end-of-file and ends (it closes the read end)
            self._wakeup = None

    def _handler(self, signum, frame) -> None:
        self.pending = self.pending or signum
        if not self._deferring:
            raise Interrupted(signum)

    def _watch(self, read: int) -> None:
        """The wakeup pipe's reader: a note on the first signal of a deferred block, an immediate stop on the
        second (runs in its own thread, so it speaks while the main thread waits in XLA)."""
        try:
            while data := os.read(read, 64):
                for signum in data:
                    if signum in SIGNALS and self._deferring:
                        self._on_deferred(signum)
        finally:
            os.close(read)

    def _on_deferred(self, signum: int) -> None:
        self._seen += 1
        self.pending = self.pending or signum
        if self._seen == 1:
            print(f"{self.command}: {signal.Signals(signum).name} received; stopping once the compile or chunk in "
                  "progress ends (XLA's compile cannot be interrupted safely); send it again to stop at once",
                  file=sys.stderr, flush=True)
            return
        print(f"{self.command}: {Interrupted(signum, self.describe())} (at once)", file=sys.stderr, flush=True)
        os._exit(128 + signum)

    @contextmanager
    def deferred(self):
        """A block that signals do not interrupt (noted for :meth:`check`; a second one ends the process)."""
        self._deferring += 1
        try:
            yield self
        finally:
            self._deferring -= 1

    def check(self) -> None:
        """Raise :class:`Interrupted` when a signal came during a deferred block."""
        if self.pending:
            signum, self.pending = self.pending, None
            raise Interrupted(signum)
