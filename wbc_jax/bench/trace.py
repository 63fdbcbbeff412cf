"""``wbc-jax bench trace``: a device trace of the batched rollout, its kernels grouped by control-step stage.

The rollout's stages carry ``jax.named_scope`` names (``STAGES``: sensing, dynamics and reference, QP assembly,
the QP's equilibration / factorization / iterations / residuals, physics). This module runs one compiled chunk
under ``jax.profiler``, reads the Perfetto trace it writes, and maps every device op (a GPU kernel, or an XLA CPU
thunk) to its stage through the op's HLO metadata (``op_name`` holds the scope path). The result is, per control
step and stage: how many ops ran, their summed device time, and the share of the wall time, plus the device's
idle share (wall time not covered by any op: launch and loop overhead, host synchronisation).

Why: at small batch (the paper campaign's 270 runs) a control step is latency-bound, so timing stages in separate
jit calls (``bench components``) adds a dispatch per stage and hides how many kernels each stage launches. The
kernel count times the per-kernel floor is what bounds a latency-bound loop.
"""

from __future__ import annotations

import glob
import gzip
import json
import os
import re
import tempfile
import time

import jax
import numpy as np

from wbc_jax.bench.qp_audit import variants
from wbc_jax.bench.rollout import physics_only_fn, random_batch, wbc_chunk_fn
from wbc_jax.control.transport import TransportConfig, control_qp_settings
from wbc_jax.physics.backend import resolve_backend
from wbc_jax.robot.model import Robot
from wbc_jax.rollout import make_sim, resolve_sensing

# Scope names, innermost wins when a path holds several (the QP's scopes sit inside the controller's).
STAGES = ("sense", "dynamics_reference", "qp_assemble", "qp_equilibrate", "qp_factor", "qp_iterations",
          "qp_residuals", "physics")
OTHER = "other"  # metrics accumulation, logging, the rollout's loop bookkeeping
TOP_OPS = 25  # heaviest ops listed per trace
TOP_LINES = 40  # source lines listed per trace, by ops per control step

# XLA CPU reports loops and calls as ops spanning their bodies' ops: not counted (their bodies are)
_CONTAINERS = ("while", "conditional", "call")
_META = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{[^}]*op_name="([^"]*)"')
_FRAME = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{[^}]*stack_frame_id=(\d+)')
_SRC = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{[^}]*source_file="([^"]*)"[^}]*source_line=(\d+)')
_TABLE_ROW = re.compile(r'^(\d+) (?:"(.*)"|\{(.*)\})$')


def op_paths(hlo_text: str) -> dict[str, str]:
    """Map from HLO instruction name (``.`` and ``-`` folded to ``_``; also with XLA CPU's ``wrapped_`` prefix) to
    its ``op_name`` scope path, from compiled HLO text. Instructions without that metadata are left out."""
    out = {}
    for line in hlo_text.splitlines():
        mt = _META.match(line)
        if mt:
            out[_norm(mt.group(1))] = out["wrapped_" + _norm(mt.group(1))] = mt.group(2)
    return out


def _tables(hlo_text: str) -> dict[str, dict[int, str]]:
    """The HLO text's header tables (``FileNames``, ``FunctionNames``, ``FileLocations``, ``StackFrames``): id ->
    the row's quoted string or its ``{...}`` fields."""
    out: dict[str, dict[int, str]] = {}
    cur = None
    for line in hlo_text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            cur = out.setdefault(line, {})
        elif cur is not None and (mt := _TABLE_ROW.match(line)):
            cur[int(mt.group(1))] = mt.group(2) if mt.group(2) is not None else mt.group(3)
        elif line.startswith(("%", "ENTRY")):
            break
    return out


def _field(row: str, key: str) -> int:
    return int(re.search(rf"\b{key}=(\d+)", row).group(1))


def op_sources(hlo_text: str) -> dict[str, str]:
    """Map from HLO instruction name (as :func:`op_paths`) to the Python line that emitted it, ``"sim/rollout.py:123"``
    (the file's last two path parts; the innermost frame, which may be a library's), from compiled HLO text: its
    ``stack_frame_id`` through the header's frame tables, or older XLA's ``source_file`` / ``source_line``. A
    fusion carries the metadata of its root."""
    t = _tables(hlo_text)
    files, locs, frames = t.get("FileNames", {}), t.get("FileLocations", {}), t.get("StackFrames", {})

    def frame_src(k: int) -> str | None:
        try:
            loc = locs[_field(frames[k], "file_location_id")]
            return "/".join(files[_field(loc, "file_name_id")].split("/")[-2:]) + f":{_field(loc, 'line')}"
        except (KeyError, AttributeError):
            return None

    out = {}
    for line in hlo_text.splitlines():
        src = None
        if (mt := _FRAME.match(line)) is not None:
            src = frame_src(int(mt.group(2)))
        elif (mt := _SRC.match(line)) is not None:
            src = "/".join(mt.group(2).split("/")[-2:]) + ":" + mt.group(3)
        if src is not None:
            out[_norm(mt.group(1))] = out["wrapped_" + _norm(mt.group(1))] = src
    return out


def _norm(name: str) -> str:
    return name.replace(".", "_").replace("-", "_")


def stage_of(op_name: str) -> str:
    """The innermost known stage in a scope path like ``jit(f)/vmap(while)/body/physics/...``."""
    best = OTHER
    for p in op_name.split("/"):
        if p.endswith(")") and "(" in p:  # a scope opened under a transformation: vmap(physics)
            p = p[p.index("(") + 1:-1]
        if p in STAGES:
            best = p
    return best


def gpu_pids(events: list) -> set:
    """The process ids of a Perfetto/Chrome trace's GPU devices (``process_name`` metadata ``/device:GPU:*``)."""
    return {e["pid"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"
            and "/device:GPU" in str(e.get("args", {}).get("name", ""))}


def kernel_durations(events: list, prefix: str = "") -> dict[str, float]:
    """{kernel name: summed device time [ms]} of the GPU events whose name starts with ``prefix``."""
    gpu, out = gpu_pids(events), {}
    for e in events:
        name = str(e.get("name", ""))
        if e.get("ph") == "X" and e.get("pid") in gpu and name.startswith(prefix):
            out[name] = out.get(name, 0.0) + float(e.get("dur", 0.0)) / 1e3
    return out


def _sweep(spans):
    """Spans ``(start, end, tag)`` in start order: ``(tag, idle time before it, time it adds to the union of the
    spans so far, the tag of the span that ended latest so far)`` each, in the spans' units (the first span has no
    idle time before it, and None before it)."""
    end, last = -np.inf, None
    for a, b, tag in sorted(spans, key=lambda s: (s[0], s[1])):
        yield tag, (max(0.0, a - end) if end > -np.inf else 0.0), max(0.0, b - max(a, end)), last
        if b > end:
            end, last = b, tag


def idle_between(events) -> dict[tuple[str, str], float]:
    """{(kernel before, kernel after): summed device idle time [ms] between them}: the GPU events of
    :func:`kernel_durations` (each GPU process on its own) in start order; a gap is the time from the latest end so
    far (the kernel before: the one that ended then) to the next event's start (the kernel after: what the device
    waited to start: a launch, a loop's host round trip, a host callback, or work the trace does not list)."""
    out = {}
    for pid in gpu_pids(events):
        spans = ((float(e.get("ts", 0.0)), float(e.get("ts", 0.0)) + float(e.get("dur", 0.0)), str(e.get("name", "")))
                 for e in events if e.get("ph") == "X" and e.get("pid") == pid)
        for name, gap, _, before in _sweep(spans):
            if gap > 0.0:
                out[(before, name)] = out.get((before, name), 0.0) + gap / 1e3
    return out


def idle_before(events) -> dict[str, float]:
    """{kernel name: summed device idle time [ms] just before it starts}: :func:`idle_between` summed over the
    kernels before."""
    out = {}
    for (_, name), ms in idle_between(events).items():
        out[name] = out.get(name, 0.0) + ms
    return out


def profiled_call(fn, args, log_dir: str | None = None) -> tuple[list, float]:
    """One call of ``fn(*args)`` under ``jax.profiler``: (the Perfetto trace's events, the call's wall time [s]).
    ``log_dir`` keeps the raw trace there. RuntimeError when the profiler wrote no trace."""
    with tempfile.TemporaryDirectory() as td:
        d = log_dir or td
        jax.profiler.start_trace(d, create_perfetto_trace=True)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        wall = time.perf_counter() - t0
        jax.profiler.stop_trace()
        files = sorted(glob.glob(os.path.join(d, "**", "*.trace.json.gz"), recursive=True), key=os.path.getmtime)
        if not files:
            raise RuntimeError(f"jax.profiler wrote no Perfetto trace under {d}")
        with gzip.open(files[-1], "rt") as fh:
            return json.load(fh)["traceEvents"], wall


def device_ops(trace: dict) -> list[tuple[str, float, float, str]]:
    """Device op events of a Perfetto/Chrome trace: (hlo_op, start [us], duration [us], scope path or '').

    GPU kernels when the trace has a GPU device process, else the XLA CPU thunks (loop and call ops left out).
    """
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    gpu = gpu_pids(events)
    out = []
    for e in events:
        if e.get("ph") != "X":
            continue
        a = e.get("args") or {}
        op = a.get("hlo_op")
        if not op or (gpu and e.get("pid") not in gpu) or str(op).startswith(_CONTAINERS):
            continue
        tf_op = str(a.get("tf_op", ""))  # a scope path on the CPU; on a GPU only "XlaModule:" (then the HLO's wins)
        out.append((str(op), float(e.get("ts", 0.0)), float(e.get("dur", 0.0)), tf_op if "/" in tf_op else ""))
    return out


def summarize(ops, paths: dict[str, str], wall_s: float, n_steps: int, sources: dict[str, str] | None = None) -> dict:
    """Per stage: ops per control step, device time per control step [us], share of the wall time; per source
    line (``sources``, :func:`op_sources`): the same, the lines with most ops first (``lines``).

    Args:
        ops: :func:`device_ops` output for ``n_steps`` control steps; paths: :func:`op_paths` map (a trace's own
            scope path, where present, wins); wall_s: wall time of those steps [s].
    """
    per = {k: [0, 0.0] for k in STAGES + (OTHER,)}
    top: dict[tuple[str, str], list] = {}
    by_line: dict[tuple[str, str], list] = {}
    sources = sources or {}
    n_inferred = 0
    last = OTHER
    for op, _, dur, path in sorted(ops, key=lambda o: o[1]):
        path = path or paths.get(_norm(op))
        if path is None:  # an op XLA created without metadata (copies, some dots): the stage of the op before it
            st, n_inferred = last, n_inferred + 1
        else:
            st = stage_of(path)
        last = st
        per[st][0] += 1
        per[st][1] += dur
        t = top.setdefault((st, op), [0, 0.0, path or ""])
        t[0] += 1
        t[1] += dur
        ln = by_line.setdefault((st, sources.get(_norm(op), "?")), [0, 0.0])
        ln[0] += 1
        ln[1] += dur
    busy_us = sum(v[1] for v in per.values())
    wall_us = 1e6 * wall_s
    # device time covered by at least one op (ops on several streams may overlap)
    covered = sum(c for _, _, c, _ in _sweep((ts, ts + dur, None) for _, ts, dur, _ in ops))
    stages = {k: dict(ops_per_step=v[0] / n_steps, device_us_per_step=v[1] / n_steps,
                      share_of_wall=v[1] / wall_us if wall_us > 0 else float("nan")) for k, v in per.items()}
    heavy = sorted(top.items(), key=lambda kv: -kv[1][1])[:TOP_OPS]
    return dict(n_steps=n_steps, wall_us_per_step=wall_us / n_steps, ops_per_step=len(ops) / n_steps,
                inferred_share=n_inferred / max(len(ops), 1),
                top_ops=[dict(stage=k[0], op=k[1], calls_per_step=v[0] / n_steps, device_us_per_step=v[1] / n_steps,
                              path=v[2]) for k, v in heavy],
                lines=[dict(stage=k[0], line=k[1], ops_per_step=v[0] / n_steps, device_us_per_step=v[1] / n_steps)
                       for k, v in sorted(by_line.items(), key=lambda kv: (-kv[1][0], -kv[1][1]))[:TOP_LINES]],
                device_busy_us_per_step=busy_us / n_steps, device_idle_share=max(0.0, 1.0 - covered / wall_us)
                if wall_us > 0 else float("nan"), stages=stages)


def trace_call(f, args, n_steps: int, log_dir: str | None = None) -> dict:
    """Compile ``f`` (a ``jax.jit`` function) for ``args``, run it once untimed, then trace one call covering
    ``n_steps`` control steps and summarize it (:func:`summarize`); ``log_dir`` keeps the raw trace there."""
    compiled = f.lower(*args).compile()
    hlo = compiled.as_text()
    paths, sources = op_paths(hlo), op_sources(hlo)
    jax.block_until_ready(compiled(*args))
    trace, wall = profiled_call(compiled, args, log_dir)
    ops = device_ops(trace)
    return summarize(ops, paths, wall, n_steps, sources)


def print_summary(label: str, s: dict) -> None:
    print(f"{label}: {s['wall_us_per_step']:.1f} us wall per control step, {s['ops_per_step']:.0f} device ops per "
          f"step, device busy {s['device_busy_us_per_step']:.1f} us, idle {100 * s['device_idle_share']:.0f} % of "
          f"the wall time", flush=True)
    for k, v in sorted(s["stages"].items(), key=lambda kv: -kv[1]["device_us_per_step"]):
        print(f"    {k:20s} {v['ops_per_step']:7.1f} ops  {v['device_us_per_step']:9.1f} us  "
              f"{100 * v['share_of_wall']:5.1f} % of wall", flush=True)
    print(f"    ({100 * s['inferred_share']:.0f} % of the ops had no scope metadata and took the stage of the op "
          f"before them; heaviest ops:)", flush=True)
    for t in s["top_ops"][:12]:
        print(f"      {t['stage']:20s} {t['op'][:40]:40s} {t['calls_per_step']:5.1f} x  "
              f"{t['device_us_per_step']:8.1f} us", flush=True)
    print("    source lines with the most ops per step:", flush=True)
    for t in s.get("lines", [])[:20]:
        print(f"      {t['stage']:20s} {t['line'][:48]:48s} {t['ops_per_step']:5.1f} ops  "
              f"{t['device_us_per_step']:8.1f} us", flush=True)
    if any(t["op"].startswith("command_buffer") for t in s["top_ops"]):
        print("    (kernels ran inside CUDA graphs, which the trace names by graph, not by kernel: set "
              "XLA_FLAGS=--xla_gpu_enable_command_buffer= for a per-kernel attribution)", flush=True)


def run_trace(batch: int = 270, steps: int = 50, scene: str = "transport", qp: str | None = None,
              substeps: int = 1, json_path: str | None = None, backend: str = "jax",
              warmup_s: float = 0.0) -> dict:
    """Trace ``steps`` control steps of the transport rollout at ``batch`` runs (random factor cells) and of
    physics only (``mjx.step``) on the same batch; print and return both summaries.

    ``qp``: a control-loop ADMM variant (:func:`wbc_jax.bench.qp_audit.variants`), None: the control loop's.
    ``backend``: the MJX physics implementation, optionally with ``:exact`` / ``:delayed`` / ``:auto`` (the default;
    ``campaign.sensing``). ``warmup_s``: simulated seconds run (untraced) before the traced
    steps, so that they come from the walk rather than the first standing steps (the QP's convergence-checked
    extension costs most at contact events)."""
    # The persistent cache's key leaves out op metadata: an executable cached from an edit with other scopes would
    # carry stale scope names. Compile afresh.
    jax.config.update("jax_enable_compilation_cache", False)
    name, _, sensing = backend.partition(":")
    backend = resolve_backend(name)
    sensing = resolve_sensing(sensing or "auto", backend, substeps)
    robot = Robot(scene, backend=backend)
    qs = variants([qp])[qp] if qp else control_qp_settings()
    sim = make_sim(robot, TransportConfig(dt=float(robot.mj_model.opt.timestep) * substeps, qp=qs),
                   n_substeps=substeps, log_every=steps, sensing=sensing)
    b = random_batch(sim, batch)
    chunk, args = wbc_chunk_fn(sim, b)
    n_warm = int(round(warmup_s / sim.dt_control / steps))
    for _ in range(n_warm):  # advance the state, one chunk of `steps` control steps at a time
        args = (args[0], jax.block_until_ready(chunk(*args))[0]) + tuple(args[2:])
    f_phys = physics_only_fn(b, steps * substeps)
    device = jax.devices()[0].device_kind
    out = dict(device=device, backend=backend, sensing=sensing, scene=robot.path.name, batch=batch, steps=steps,
               qp=qp or "control", substeps=substeps, warmup_s=n_warm * steps * sim.dt_control)
    out["wbc"] = trace_call(chunk, args, steps)
    print_summary(f"{device}, {backend}:{sensing}, {robot.path.name}, batch {batch}, after {out['warmup_s']:.2f} s, "
                  f"physics + WBC ({qp or 'control loop QP'}, substeps {substeps})", out["wbc"])
    out["physics_only"] = trace_call(f_phys, (b.model, b.state.d), steps)
    print_summary(f"{device}, {backend}, {robot.path.name}, batch {batch}, physics only ({substeps} mjx.step per "
                  "control step)", out["physics_only"])
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=2)
    return out
