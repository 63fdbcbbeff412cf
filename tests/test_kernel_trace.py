"""wbc_jax.bench.trace: scope attribution of device ops, against hand-built traces and a real CPU trace."""

import jax
import jax.numpy as jnp
import pytest

from wbc_jax.bench import trace as kt


def test_stage_of_innermost_and_transformed_scopes():
    assert kt.stage_of("jit(f)/vmap(physics)/while/body/step") == "physics"
    assert kt.stage_of("jit(f)/vmap()/while/body/qp_iterations/while/body/dot_general") == "qp_iterations"
    # the QP's scopes sit inside the controller's; the innermost known one wins
    assert kt.stage_of("jit(f)/qp_assemble/jit(_solve_jit)/qp_factor/cholesky") == "qp_factor"
    assert kt.stage_of("jit(f)/vmap()/while/body/add") == kt.OTHER
    assert kt.stage_of("jit(_solve_jit)/select_n") == kt.OTHER  # jit(name) is a transform, not a stage


def _x(name, ts, dur, pid=1, **args):
    return dict(ph="X", name=name, pid=pid, tid=0, ts=ts, dur=dur, args=dict(hlo_op=name, hlo_module="m", **args))


def test_summarize_hand_trace():
    """Two control steps; an op without metadata takes the stage of the op before it; a loop op is not counted."""
    paths = {"fusion_1": "jit(f)/vmap()/sense/add", "fusion_2": "jit(f)/physics/mul",
             "dot_3": "jit(f)/qp_iterations/dot_general"}
    events = [dict(ph="M", name="process_name", pid=7, args=dict(name="/host:CPU"))]
    t = 0.0
    for _ in range(2):
        events += [_x("fusion.1", t, 2.0), _x("dot.3", t + 3, 4.0), _x("copy.9", t + 8, 1.0),
                   _x("fusion.2", t + 10, 5.0), _x("while.4", t, 15.0)]
        t += 20.0
    ops = kt.device_ops(dict(traceEvents=events))
    assert len(ops) == 8  # the two while ops are dropped
    s = kt.summarize(ops, paths, wall_s=40e-6, n_steps=2)
    st = s["stages"]
    assert st["sense"]["ops_per_step"] == 1 and st["sense"]["device_us_per_step"] == pytest.approx(2.0)
    # copy.9 has no metadata: it follows dot.3 and is counted with the QP iterations
    assert st["qp_iterations"]["ops_per_step"] == 2
    assert st["qp_iterations"]["device_us_per_step"] == pytest.approx(5.0)
    assert st["physics"]["device_us_per_step"] == pytest.approx(5.0)
    assert s["ops_per_step"] == 4 and s["inferred_share"] == pytest.approx(0.25)
    assert s["wall_us_per_step"] == pytest.approx(20.0)
    # busy 12 us of every 20 (ops never overlap here): 40 % idle
    assert s["device_busy_us_per_step"] == pytest.approx(12.0)
    assert s["device_idle_share"] == pytest.approx(0.4)
    assert st["sense"]["share_of_wall"] == pytest.approx(0.1)


def test_device_ops_prefers_gpu_process():
    events = [dict(ph="M", name="process_name", pid=2, args=dict(name="/device:GPU:0")),
              _x("fusion.1", 0.0, 1.0, pid=1), _x("fusion.2", 0.0, 3.0, pid=2)]
    assert [o[0] for o in kt.device_ops(dict(traceEvents=events))] == ["fusion.2"]


def test_kernel_durations_sum_gpu_kernels_by_name():
    """Only the GPU process's complete events with the prefix count, summed per name, in ms (the trace's us)."""
    events = [dict(ph="M", name="process_name", pid=2, args=dict(name="/device:GPU:0")),
              dict(ph="X", name="admm_iterations", pid=2, ts=0.0, dur=1500.0),
              dict(ph="X", name="admm_iterations", pid=2, ts=2000.0, dur=500.0),
              dict(ph="X", name="admm_factor", pid=2, ts=3000.0, dur=250.0),
              dict(ph="X", name="fusion.4", pid=2, ts=4000.0, dur=9.0),
              dict(ph="X", name="admm_iterations", pid=1, ts=0.0, dur=7000.0)]
    assert kt.gpu_pids(events) == {2}
    assert kt.kernel_durations(events, prefix="admm_") == {"admm_iterations": 2.0, "admm_factor": 0.25}
    assert kt.kernel_durations(events)["fusion.4"] == pytest.approx(0.009)


def test_idle_before_charges_each_gap_to_the_kernel_after_it():
    """Hand-computed gaps (by the kernel after them, and by the kernels before and after: idle_between): 0.5 ms
    before the second kernel, none where a kernel starts inside an earlier one's span,
    0.25 ms after the longest span so far (not the last event's end); another process's events ignored."""
    events = [dict(ph="M", name="process_name", pid=2, args=dict(name="/device:GPU:0")),
              dict(ph="X", name="a", pid=2, ts=0.0, dur=1000.0),
              dict(ph="X", name="b", pid=2, ts=1500.0, dur=2000.0),  # gap 500 us after a
              dict(ph="X", name="c", pid=2, ts=2000.0, dur=100.0),  # inside b: no gap
              dict(ph="X", name="b", pid=2, ts=3750.0, dur=10.0),  # 250 us after b's end at 3500
              dict(ph="X", name="a", pid=1, ts=9000.0, dur=1.0)]
    assert kt.idle_before(events) == {"b": pytest.approx(0.75)}
    assert kt.idle_between(events) == {("a", "b"): pytest.approx(0.5), ("b", "b"): pytest.approx(0.25)}


def test_gpu_module_name_is_not_a_scope_path():
    """GPU traces carry tf_op "XlaModule:" (no scope path): the HLO's op_name must attribute the op (otherwise
    every GPU op falls into 'other')."""
    events = [dict(ph="M", name="process_name", pid=2, args=dict(name="/device:GPU:0")),
              _x("fusion.2", 0.0, 3.0, pid=2, tf_op="XlaModule:"),
              _x("fusion.3", 5.0, 1.0, pid=2, tf_op="jit(f)/vmap()/sense/add")]
    ops = kt.device_ops(dict(traceEvents=events))
    assert [o[3] for o in ops] == ["", "jit(f)/vmap()/sense/add"]
    s = kt.summarize(ops, {"fusion_2": "jit(f)/qp_factor/cholesky"}, wall_s=10e-6, n_steps=1)
    assert s["stages"]["qp_factor"]["ops_per_step"] == 1 and s["stages"]["sense"]["ops_per_step"] == 1


def test_real_cpu_trace_attributes_both_scopes():
    """A jitted function with two independent scoped parts, traced by jax.profiler on the CPU: each part's ops
    (a wrapped elementwise op and a dot fusion on XLA CPU) land in its own stage, none in 'other'."""

    def f(x, z):
        with jax.named_scope("qp_iterations"):
            y = jnp.sin(x) @ x
        with jax.named_scope("physics"):
            w = jnp.tanh(z) @ z
        return y, w

    s = kt.trace_call(jax.jit(f), (jnp.ones((32, 32)), 2 * jnp.ones((32, 32))), n_steps=1)
    st = s["stages"]
    assert st["qp_iterations"]["ops_per_step"] >= 1
    assert st["physics"]["ops_per_step"] >= 1
    assert st[kt.OTHER]["ops_per_step"] == 0
    assert {t["stage"] for t in s["top_ops"] if "tanh" in t["path"]} == {"physics"}
    assert st["qp_iterations"]["ops_per_step"] + st["physics"]["ops_per_step"] + st[kt.OTHER]["ops_per_step"] \
        == s["ops_per_step"]
    assert st["qp_iterations"]["device_us_per_step"] > 0
    # per source line: the ops of each part come from this file's lines (a fusion carries its root's line)
    here = {t["line"] for t in s["lines"]}
    assert here and all(ln.startswith("tests/test_kernel_trace.py:") for ln in here)
    assert sum(t["ops_per_step"] for t in s["lines"]) == s["ops_per_step"]
    assert {t["stage"] for t in s["lines"]} == {"qp_iterations", "physics"}


def test_op_sources_from_hlo_text():
    """Both metadata forms: a stack frame id resolved through the header's tables, and source_file/source_line."""
    hlo = ('HloModule m\n\nFileNames\n1 "/x/wbc_jax/rollout/core.py"\n2 "/x/wbc_jax/qp/admm.py"\n\nFunctionNames\n'
           '1 "f"\n\nFileLocations\n1 {file_name_id=2 function_name_id=1 line=7 end_line=7 column=1 end_column=2}\n'
           '2 {file_name_id=1 function_name_id=1 line=88 end_line=88 column=1 end_column=2}\n\nStackFrames\n'
           '1 {file_location_id=2 parent_frame_id=1}\n2 {file_location_id=1 parent_frame_id=1}\n\n'
           '%c (p: f32[4]) -> f32[4] {\n'
           '  %fusion.3 = f32[4]{0} fusion(f32[4]{0} %p), kind=kLoop, calls=%fc, metadata={op_name="jit(f)/add" '
           'source_file="/x/wbc_jax/rollout/core.py" source_line=412}\n'
           '  %fusion.4 = f32[4]{0} fusion(f32[4]{0} %p), kind=kLoop, calls=%fd, metadata={op_name="jit(f)/mul" '
           'stack_frame_id=2}\n'
           '  ROOT %copy.1 = f32[4]{0} copy(f32[4]{0} %fusion.3)\n}\n')
    src = kt.op_sources(hlo)
    assert src["fusion_3"] == src["wrapped_fusion_3"] == "rollout/core.py:412"
    assert src["fusion_4"] == "qp/admm.py:7"
    assert "copy_1" not in src


@pytest.mark.parametrize("argv, needle", [
    (["--qp", "bogus"], "--qp"),
    (["--batches", "0"], "--batches"),
    (["--batches", "4,x"], "--batches"),
    (["--steps", "0"], "--steps"),
    (["--substeps", "0"], "--substeps"),
    (["--backend", "warp,jax"], "trace takes one backend"),
    (["--backend", "jax:delayed"], "'delayed' needs the Warp backend"),
])
def test_bench_rejects_bad_arguments(argv, needle, capsys):
    """Bad bench arguments: one line naming the flag and the expected range, exit 2, before any compile."""
    from wbc_jax import cli

    assert cli.main(["bench", "trace", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("wbc-jax bench: error: ") and needle in err[0]
