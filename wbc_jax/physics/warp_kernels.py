"""MuJoCo Warp's kernels compiled ahead of their first launch, by a pool of threads.

Warp compiles a kernel module when one of its kernels is first launched, one module at a time; on a machine whose Warp
kernel cache (``~/.cache/warp``, ``WARP_CACHE_PATH``) is empty that is most of a first campaign. Two mechanisms make
that compilation parallel on a GPU:

1. :func:`preload` compiles, with several workers, the MuJoCo Warp modules that exist at import and that a step
   launches (:data:`STEP_MODULES`), while the setup runs (:func:`start_preload` starts it in a thread).
2. :class:`CompileAhead` covers the kernels MuJoCo Warp builds for a model (one per collision pair type, solver sizes):
   they are created while a step's Python runs, so nothing can list them before it. At the first call of each of
   MJX's Warp callables, the callable's Python runs once more beforehand, inside a CUDA graph capture on a side stream
   whose graph is never launched, with the launches of kernels not yet compiled skipped (:func:`launched_modules`);
   the modules it would have launched are compiled by the pool (:func:`load_modules`); then the call runs as it would
   have. Nothing of the skipped pass reaches the device, and the call itself is unchanged (the same kernels, launched
   the same way), so results are those without it.
3. :class:`Beside` runs other work (XLA compiling the chunk program) while that pool compiles, inside the window a
   first call opens: after its skipped pass's capture, before the call itself (no capture of this process beside it).
"""

from __future__ import annotations

import functools
import os
import sys
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

from wbc_jax.physics import backend  # MJX imports MuJoCo Warp, which declares its kernels
from wbc_jax.runtime import aot

# the MuJoCo Warp modules a step launches that exist at import; the others (SDF collision, islands, derivatives,
# rendering, ...) compile at the first call of a model that uses them, by CompileAhead
STEP_MODULES = backend.WARP_STEP_MODULES


def kernel_modules(names: tuple[str, ...] | None = None) -> list:
    """MuJoCo Warp's registered kernel modules (``warp`` ``Module`` objects; MJX imported first, which declares
    them), those named in ``names`` only when given; Warp's own modules left out."""
    from warp._src.context import user_modules

    return [module for name, module in list(user_modules.items())
            if not name.startswith("warp") and (names is None or name in names)]


def preload(workers: int, device: str = "cuda:0", names: tuple[str, ...] | None = STEP_MODULES) -> tuple[int, float]:
    """Compile (or load from Warp's kernel cache) the MuJoCo Warp modules named in ``names`` (None: all) on
    ``device`` with ``workers`` threads. Returns (modules, seconds)."""
    import warp as wp

    t0 = time.perf_counter()
    modules = kernel_modules(names)
    wp.force_load(device=device, modules=modules, max_workers=workers)
    return len(modules), time.perf_counter() - t0


class Preload:
    """:func:`preload` running in a background thread, started at construction: the caller goes on (setup, tracing)
    while Warp compiles. :meth:`result` waits for it and returns (modules, seconds), or raises what it raised.
    :attr:`names`: the modules it compiles; :attr:`ahead`: the :class:`CompileAhead` that :func:`start_preload`
    installs beside it (None otherwise)."""

    def __init__(self, workers: int, device: str = "cuda:0", names: tuple[str, ...] = STEP_MODULES):
        self.names, self.ahead = names, None
        self._job = Beside(lambda: preload(workers, device, names), name="warp-preload")
        self._job.start()

    def result(self) -> tuple[int, float]:
        """(modules, seconds) once the preload has ended."""
        return self._job.result()


def launched_modules(func, args: tuple, device) -> dict:
    """The Warp modules not yet loaded that ``func(*args)`` launches kernels of on ``device`` (a ``warp`` device),
    each with the block sizes it is launched with: {Module: {block_dim or None}}. ``func`` runs once on this thread
    inside a graph capture (on a GPU, on a side stream) whose graph is dropped unlaunched, so none of its launches,
    copies, fills and allocations run; the launches of those modules are skipped (Warp's ``launch`` returns when its
    module does not load); a module used otherwise (an occupancy query) and Warp's own load at once. Other threads
    load modules as usual meanwhile. ``func`` runs inside ``backend.skipped_pass()``. Raises what ``func`` raises."""
    import warp as wp
    from warp._src import context

    found: dict = {}
    me, original, launch = threading.get_ident(), context.Module.load, context.launch.__code__

    def load(module, dev, block_dim=None, *rest, **kw):
        loaded = (wp.get_device(dev).context, module.options["block_dim"] if block_dim is None else block_dim)
        if (threading.get_ident() != me or sys._getframe(1).f_code is not launch or module.name.startswith("warp")
                or loaded in module.execs):  # not a launch (an occupancy query: loaded now), Warp's own, or loaded
            return original(module, dev, block_dim, *rest, **kw)
        found.setdefault(module, set()).add(block_dim)
        return None  # the launch is skipped

    device = wp.get_device(device)
    if device.is_cuda:  # a side stream: the caller's own stream may be capturing the call's graph already
        side = wp.Stream(device)
        scope, where = wp.ScopedStream(side, sync_enter=False), dict(stream=side)
    else:  # a CPU capture records Warp's operations for a replay that never comes
        scope, where = wp.ScopedDevice(device), dict(device=device)
    context.Module.load = load
    try:
        with scope:
            wp.capture_begin(force_module_load=False, **where)
            try:
                with backend.skipped_pass():  # a run's first forward pass walks the split step too (backend.initial)
                    func(*args)
            finally:
                wp.capture_end(**where)  # the graph is dropped, never launched
    finally:
        context.Module.load = original
    return found


def load_modules(found: dict, device, workers: int) -> None:
    """Compile (or load from the kernel cache) each module of ``found`` ({Module: {block_dim}}, as
    :func:`launched_modules` returns) on ``device`` for each of its block sizes, ``workers`` modules at a time (a
    module's block sizes one after another)."""
    def load(module, dims):
        for block_dim in sorted(dims, key=lambda d: -1 if d is None else d):
            module.load(device, block_dim)

    with ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="warp-compile") as pool:
        for future in [pool.submit(load, module, dims) for module, dims in found.items()]:
            future.result()


class CompileAhead:
    """Installed by :meth:`install`: each MJX Warp callable created afterwards (``warp.jax_callable`` in its CUDA
    graph mode) compiles, at its first call, the modules that call launches in parallel before running it (module
    docstring). Modules of ``preload`` (its :attr:`Preload.names`) are left to it and waited for. A failure of the
    skipped pass leaves the call to compile at first launch as it would have, and is counted in :attr:`failed`.
    :attr:`calls` holds (modules, seconds) per first call."""

    def __init__(self, workers: int, preload: Preload | None = None):
        self.workers, self.preload = workers, preload
        self.calls: list[tuple[int, float]] = []
        self.failed: list[str] = []
        self.beside: Beside | None = None  # run in the next first call's window (:meth:`open_window`)

    def open_window(self, work: Callable[[], Any]) -> Beside:
        """A :class:`Beside` of ``work`` that the next first call starts after its skipped pass and waits for
        before the call runs; its :meth:`Beside.result` runs ``work`` itself when no first call came."""
        self.beside = Beside(work)
        return self.beside

    def close_window(self) -> None:
        """Drop a window no first call has opened, so that it does not carry over to a later first call."""
        self.beside = None

    def install(self) -> CompileAhead:
        """Wrap ``warp.jax_callable`` (once per process: a later instance replaces the earlier's bookkeeping)."""
        import warp as wp

        original = getattr(wp.jax_callable, "warp_original", wp.jax_callable)

        @functools.wraps(original)
        def jax_callable(func, *args, **kwargs):
            callable_ = original(func, *args, **kwargs)
            if callable_.graph_mode == wp.JaxCallableGraphMode.WARP and not isinstance(callable_.func, _FirstCall):
                callable_.func = _FirstCall(callable_.func, self)
            return callable_

        jax_callable.warp_original = original
        wp.jax_callable = jax_callable
        return self

    def before_first_call(self, func, args: tuple) -> None:
        """Compile what ``func(*args)`` launches (the preloaded modules by the preload), then return."""
        import warp as wp

        t0, beside, self.beside = time.perf_counter(), self.beside, None
        try:
            device = wp.get_device()
            preloaded = () if self.preload is None else self.preload.names
            found = {m: dims for m, dims in launched_modules(func, args, device).items() if m.name not in preloaded}
            if beside is not None:  # the capture has ended
                beside.start()
            if self.preload is not None:
                self.preload.result()
            load_modules(found, device, self.workers)
            self.calls.append((len(found), time.perf_counter() - t0))
        except Exception as e:  # the call itself compiles what is missing, one module at a time
            where = traceback.extract_tb(e.__traceback__)[-1]
            self.failed.append(f"{type(e).__name__}: {e} ({where.filename}:{where.lineno})")
            print(f"MuJoCo Warp: compiling the model's kernels ahead failed ({self.failed[-1]}); they compile at "
                  "their first launch instead", file=sys.stderr, flush=True)
        finally:
            if beside is not None:
                beside.wait()  # before the call, which captures its graph

    def summary(self) -> dict:
        """{"modules": compiled ahead, "seconds": spent in first calls, "failed": skipped passes that failed}."""
        return dict(modules=sum(n for n, _ in self.calls), seconds=round(sum(s for _, s in self.calls), 3),
                    failed=len(self.failed))


class Beside:
    """``work()`` (no arguments) run in a thread in the window a :class:`CompileAhead` first call opens
    (:meth:`CompileAhead.open_window`): started once the call's skipped pass has ended its CUDA graph capture, waited
    for before the call runs (it captures its graph then), so no capture of this process runs beside it; XLA
    compiling beside MuJoCo Warp's captures failed them (CUDA error 904). :meth:`wait` gives up after
    :attr:`wait_s` seconds with a note (the call then runs beside the work). :meth:`result` returns what ``work``
    returned, running it on the caller's thread when nothing started it, or raises what it raised;
    :attr:`seconds`: its wall time. Also the :class:`Preload`'s thread."""

    wait_s = 300.0

    def __init__(self, work: Callable[[], Any], name: str = "beside-warp"):
        self.work, self.name, self.seconds = work, name, 0.0
        self._out: dict = {}
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Run ``work`` in a daemon thread named :attr:`name`."""
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.perf_counter()
        try:
            self._out["result"] = self.work()
        except BaseException as e:  # re-raised in the caller's thread by result()
            self._out["error"] = e
        self.seconds = time.perf_counter() - t0

    def wait(self) -> None:
        """Until the work ends, at most :attr:`wait_s` seconds (at once where it was not started)."""
        if self._thread is None:
            return
        self._thread.join(self.wait_s)
        if self._thread.is_alive():
            print(f"MuJoCo Warp: the work beside the kernels' compile ran past {self.wait_s:.0f} s; the first call "
                  "goes on beside it", file=sys.stderr, flush=True)

    def result(self) -> Any:
        """What ``work`` returned (run here if no window started it)."""
        if self._thread is None:
            self._run()
        else:
            self._thread.join()
        if "error" in self._out:
            raise self._out["error"]
        return self._out["result"]


class _FirstCall:
    """A Warp callable's Python function whose first call is preceded by :meth:`CompileAhead.before_first_call`
    (Warp serializes the calls of its FFI callbacks)."""

    def __init__(self, func, ahead: CompileAhead):
        functools.update_wrapper(self, func)  # Warp looks up the function's module by its __module__
        self.func, self.ahead, self.first = func, ahead, True

    def __call__(self, *args):
        if self.first:
            self.first = False
            self.ahead.before_first_call(self.func, args)
        return self.func(*args)


def start_preload(backend: str, workers: int | None = None) -> Preload | None:
    """A :class:`Preload` of MuJoCo Warp's step modules on this process's first local GPU with ``workers`` threads
    (None: the CPU count), and a :class:`CompileAhead` installed for the model's own kernels, when ``backend`` is
    ``"warp"`` and JAX runs on a GPU; None otherwise (on a CPU, Warp's kernels compile on first use).

    The package's source digest (:func:`wbc_jax.runtime.aot.source_digest`, the setup's cache keys) is read before
    the pool starts: while the pool generates code, each call of the main thread that releases the interpreter lock
    (each of the digest's file reads) waits to take it back."""
    import jax

    workers = (os.cpu_count() or 1) if workers is None else workers
    if backend != "warp" or jax.default_backend() != "gpu" or workers <= 0:
        return None
    aot.source_digest()
    # this process's GPU (one process per GPU: --local-device-ids), as Warp numbers the visible devices
    pre = Preload(workers, f"cuda:{jax.local_devices()[0].local_hardware_id or 0}")
    pre.ahead = CompileAhead(workers, pre).install()
    return pre
