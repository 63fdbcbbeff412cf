"""Compiling Warp kernels ahead of their first launch (wbc_jax.physics.warp_kernels): the skipped pass finds the
modules a function launches without running anything, the pool compiles them, and the call then runs as without."""

import numpy as np
import pytest

wp = pytest.importorskip("warp")

from wbc_jax.physics import warp_kernels  # noqa: E402


@wp.kernel
def _add_one(a: wp.array(dtype=wp.float32)):
    i = wp.tid()
    a[i] = a[i] + 1.0


def _scale_kernel(factor: float):
    """A kernel built at call time, in a module of its own (as MuJoCo Warp builds a model's kernels)."""
    @wp.kernel(module="unique")
    def scale(a: wp.array(dtype=wp.float32)):
        i = wp.tid()
        a[i] = a[i] * factor

    return scale


def _step(a, b, factor=3.0):
    """a += 1; b *= factor (a kernel module of its own per factor); then a copy of b into a."""
    wp.launch(_add_one, dim=a.shape[0], inputs=[a])
    wp.launch(_scale_kernel(factor), dim=b.shape[0], inputs=[b])
    wp.copy(a, b)


def _arrays():
    return (wp.array(np.arange(4, dtype=np.float32), device="cpu"),
            wp.array(np.full(4, 2.0, dtype=np.float32), device="cpu"))


def test_the_skipped_pass_finds_the_launched_modules_and_changes_nothing():
    a, b = _arrays()
    found = warp_kernels.launched_modules(_step, (a, b), "cpu")
    names = sorted(m.name for m in found)
    assert len(found) == 2 and _add_one.module in found, names
    assert all(len(dims) == 1 for dims in found.values())  # one block size each, as launched
    np.testing.assert_array_equal(a.numpy(), np.arange(4))  # no launch ran, no copy either
    np.testing.assert_array_equal(b.numpy(), np.full(4, 2.0))

    warp_kernels.load_modules(found, wp.get_device("cpu"), workers=2)
    assert all(m.execs for m in found)
    _step(a, b)
    np.testing.assert_array_equal(b.numpy(), np.full(4, 6.0))
    np.testing.assert_array_equal(a.numpy(), np.full(4, 6.0))


def test_a_first_forward_walks_the_split_step_only_in_a_skipped_pass(monkeypatch):
    """Exact sensing's first forward pass (``backend.initial(..., sensed=True)``): in the skipped pass of its first
    call it also walks the split step's two functions, so the kernels they launch are found with the forward's;
    when the call itself runs, the forward alone."""
    import types

    from wbc_jax.physics import backend

    calls = []
    monkeypatch.setattr(backend, "_mjwarp", lambda: types.SimpleNamespace(forward=lambda m, d: calls.append("fwd")))
    monkeypatch.setattr(backend, "_step1", lambda a, b: (calls.append("step1"), _step(a, b, 7.0)))
    monkeypatch.setattr(backend, "_step_rest", lambda a, b: calls.append("rest"))
    a, b = _arrays()
    found = warp_kernels.launched_modules(backend._forward, (a, b), "cpu")
    assert calls == ["fwd", "step1", "rest"]
    assert _scale_kernel(7.0).module in found  # launched by the split step only
    np.testing.assert_array_equal(b.numpy(), np.full(4, 2.0))  # nothing ran
    backend._forward(a, b)
    assert calls == ["fwd", "step1", "rest", "fwd"]


def test_a_first_call_compiles_ahead_then_runs_and_a_failing_pass_leaves_the_call_as_it_was(capsys):
    ahead = warp_kernels.CompileAhead(workers=2)
    first = warp_kernels._FirstCall(_step, ahead)
    a, b = _arrays()
    with wp.ScopedDevice("cpu"):
        first(a, b, 5.0)  # the factor-5 kernel's module is new: compiled ahead
        first(a, b, 5.0)  # later calls run the function only
    np.testing.assert_array_equal(b.numpy(), np.full(4, 50.0))
    assert len(ahead.calls) == 1 and ahead.calls[0][0] >= 1 and not ahead.failed

    def broken(*args):
        raise ValueError("no such field")

    with pytest.raises(ValueError):
        warp_kernels._FirstCall(broken, ahead)()
    assert len(ahead.failed) == 1 and ahead.failed[0].startswith("ValueError: no such field (")
    assert ahead.summary()["failed"] == 1 and "compiling the model's kernels ahead failed" in capsys.readouterr().err


def test_work_beside_runs_after_the_skipped_pass_and_before_the_call():
    """The window a first call opens: the work starts once the skipped pass (a capture) has ended and has ended
    before the call runs; a window no first call opened runs its work where its result is asked for."""
    import threading

    events = []

    def step(a, b):
        events.append(("step", wp.get_device("cpu").is_capturing))
        _step(a, b, 7.0)

    def work():
        events.append(("work", threading.current_thread().name))
        return 42

    ahead = warp_kernels.CompileAhead(workers=2)
    beside = ahead.open_window(work)
    a, b = _arrays()
    with wp.ScopedDevice("cpu"):
        warp_kernels._FirstCall(step, ahead)(a, b)
    assert beside.result() == 42 and ahead.beside is None and not ahead.failed
    assert events == [("step", True), ("work", "beside-warp"), ("step", False)], events
    np.testing.assert_array_equal(b.numpy(), np.full(4, 14.0))

    def broken(*args):
        raise ValueError("no such field")

    beside = ahead.open_window(work)  # a failing skipped pass: the window never opens, the work runs when asked
    with pytest.raises(ValueError):
        warp_kernels._FirstCall(broken, ahead)()
    assert len(ahead.failed) == 1 and beside.result() == 42 and events[-1] == ("work", "MainThread")

    def fails():
        raise RuntimeError("compile failed")

    with pytest.raises(RuntimeError, match="compile failed"):
        ahead.open_window(fails).result()  # no first call: run here, its error raised here
    assert warp_kernels.Beside(lambda: 7).result() == 7


def test_install_wraps_only_callables_that_capture_warp_graphs(monkeypatch):
    pytest.importorskip("jax")
    monkeypatch.setattr(wp, "jax_callable", wp.jax_callable)  # restored after the test

    def f(a: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
        wp.copy(out, a)

    warp_kernels.CompileAhead(workers=1).install()
    warp_kernels.CompileAhead(workers=1).install()  # installing again wraps Warp's function, not the wrapper
    assert isinstance(wp.jax_callable(f, graph_mode=wp.JaxCallableGraphMode.WARP).func, warp_kernels._FirstCall)
    assert not isinstance(wp.jax_callable(f, graph_mode=wp.JaxCallableGraphMode.JAX).func, warp_kernels._FirstCall)
    assert wp.jax_callable.warp_original.__module__.startswith("warp")


def test_a_module_used_outside_a_launch_loads_in_the_skipped_pass():
    kernel = _scale_kernel(7.0)

    def query_then_launch(b):
        assert kernel.module.load(wp.get_device("cpu"), 1) is not None  # as Warp's occupancy query on a GPU does
        wp.launch(kernel, dim=b.shape[0], inputs=[b])

    b = _arrays()[1]
    found = warp_kernels.launched_modules(query_then_launch, (b,), "cpu")
    assert kernel.module.execs and kernel.module not in found  # loaded by the query, so nothing left to compile
    np.testing.assert_array_equal(b.numpy(), np.full(4, 2.0))


def test_states_and_program_compiles_in_the_first_calls_window(monkeypatch):
    """``build.states_and_program``: the program traced first, its compile run in the window of the first call that
    making the initial states makes (here a Warp function on the CPU), the states ready when it returns."""
    import threading
    from types import SimpleNamespace

    import jax.numpy as jnp

    from wbc_jax.campaign import build

    events = []

    class Lowered:
        def compile(self):
            events.append(("compile", threading.current_thread().name))
            return "program"

    def lower(built):
        events.append(("lower", threading.current_thread().name))
        return Lowered()

    monkeypatch.setattr(build, "lower_chunk", lower)
    ahead = warp_kernels.CompileAhead(workers=2)
    a, b = _arrays()

    def step(a, b):
        events.append(("step", wp.get_device("cpu").is_capturing))
        _step(a, b, 11.0)

    def with_states():
        with wp.ScopedDevice("cpu"):
            warp_kernels._FirstCall(step, ahead)(a, b)
        return SimpleNamespace(batch=SimpleNamespace(state=jnp.asarray(b.numpy())))

    made, program, seconds = build.states_and_program(SimpleNamespace(), with_states, ahead)
    assert program == "program" and seconds >= 0 and ahead.beside is None
    assert events == [("lower", "MainThread"), ("step", True), ("compile", "beside-warp"), ("step", False)], events
    np.testing.assert_array_equal(np.asarray(made.batch.state), np.full(4, 22.0))


def test_the_source_digest_is_read_before_the_pool_starts(monkeypatch):
    """start_preload reads the package's source digest before its threads generate code (file reads on the main
    thread wait behind them for the interpreter lock)."""
    import jax

    from wbc_jax.runtime import aot

    seen = []

    class Recorder:
        def __init__(self, workers, device):
            seen.append((aot._SRC_DIGEST, workers, device))

    monkeypatch.setattr(aot, "_SRC_DIGEST", None)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(warp_kernels, "Preload", Recorder)
    monkeypatch.setattr(warp_kernels.CompileAhead, "install", lambda self: self)
    assert isinstance(warp_kernels.start_preload("warp", 3), Recorder)
    assert seen == [(aot.source_digest(), 3, "cuda:0")]
