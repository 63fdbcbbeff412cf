"""Where a campaign's control step spends its device time, kernel by kernel, with and without the velocity noise.

    python examples/campaign_kernel_profile.py [SPEC] [BATCH] [STEPS] [VERSUS]
        (defaults: sweeps/paper_campaign.toml 16384 100; needs a GPU)

The spec is built as a campaign builds it; its runs are repeated to BATCH (run i is the spec's run i mod n, from the
start state) and stepped by the campaign's own chunk program and by its ``no_noise`` ablation
(:mod:`wbc_jax.bench.campaign_step`), STEPS control steps per call; with a second spec VERSUS, by each spec's own
chunk program instead (e.g. a spec and its variant with one key changed). Each program is compiled, called once,
timed once, then called once under ``jax.profiler``; the device trace's kernels are summed by name
(:func:`wbc_jax.bench.trace.kernel_durations`), and so is the device's idle time between two kernels
(:func:`wbc_jax.bench.trace.idle_between`: the kernel that ended, the one that started). Prints, per program, the
wall time, the kernel launches and ADMM iterations per control step, its 20 largest kernels (ms per control step,
share of the kernels' time) and the gaps the device waited longest in, then the 20 largest differences between the
two programs in each. Kernels that MuJoCo Warp runs inside its constraint solver's conditional loop after
``set_conditional_if_handle_kernel`` may be missing from the trace: their time then shows as idle between that
kernel and the loop's next listed one (``examples/physics_solver_cap.py`` counts the loop's iterations).
"""

import sys
import time

import jax

from wbc_jax.bench.campaign_step import compiled_chunk, fresh_state, repeated
from wbc_jax.bench.rollout import qp_iterations
from wbc_jax.bench.trace import gpu_pids, idle_between, kernel_durations, profiled_call
from wbc_jax.campaign.build import LOG_EVERY, build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.rollout.batch import chunk_args

TOP_IDLE = 10  # pairs of kernels listed by the device's idle time between them


def profile(program, args, n_ctl: int, state0, label: str) -> tuple[dict, dict]:
    """A first call of the compiled ``program``, a timed call, a call under ``jax.profiler``; prints its figures
    under ``label`` and returns its kernel times ({name: ms}, :func:`wbc_jax.bench.trace.kernel_durations`) and the
    device's idle time between kernels ({"before -> after": ms}, :func:`~wbc_jax.bench.trace.idle_between`)."""
    out = jax.block_until_ready(program(*args))
    t0 = time.perf_counter()
    jax.block_until_ready(program(*args))
    wall = time.perf_counter() - t0
    events = profiled_call(program, args)[0]
    kernels = kernel_durations(events)
    idle = {f"{a} -> {b}": ms for (a, b), ms in idle_between(events).items()}
    busy, gpu = sum(kernels.values()), gpu_pids(events)
    launches = sum(1 for e in events if e.get("ph") == "X" and e.get("pid") in gpu)
    print(f"== {label}: {1e3 * wall / n_ctl:.3f} ms per control step wall, {busy / n_ctl:.3f} ms of kernels "
          f"({launches / n_ctl:.1f} launches), {sum(idle.values()) / n_ctl:.3f} ms idle between them; "
          f"ADMM iterations per control step {qp_iterations(state0, out[0], n_ctl):.2f}")
    for name, ms in sorted(kernels.items(), key=lambda kv: -kv[1])[:20]:
        print(f"  {ms / n_ctl:8.4f} ms  {100 * ms / busy:5.1f} %  {name[:100]}")
    print("  idle between kernels (ms per control step):")
    for name, ms in sorted(idle.items(), key=lambda kv: -kv[1])[:TOP_IDLE]:
        print(f"  {ms / n_ctl:8.4f} ms  {name[:160]}")
    return kernels, idle


def programs(spec_path: str, batch: int, n_logs: int, ablations: tuple[str, ...]):
    """(compiled chunk program, its arguments, the start state) of ``spec_path``'s campaign at ``batch`` runs, one
    per ablation name (:mod:`wbc_jax.bench.campaign_step`)."""
    built = build(load_spec(spec_path))
    b = repeated(built.batch, built.batch.state, fresh_state(built.sim, built.batch, batch), batch)
    return [(compiled_chunk(built.sim, b, n_logs, name), chunk_args(b), b.state) for name in ablations]


def main(spec_path: str, batch: int, steps: int, versus: str | None = None) -> None:
    if jax.default_backend() != "gpu":
        sys.exit("campaign_kernel_profile.py: needs a GPU (the profile reads the device's kernel trace)")
    n_logs = max(1, steps // LOG_EVERY)
    n_ctl = n_logs * LOG_EVERY
    print(f"{jax.devices()[0].device_kind}: {spec_path}, batch {batch}, {n_ctl} control steps per call", flush=True)
    if versus is None:
        labels, progs = ("campaign", "no_noise"), programs(spec_path, batch, n_logs, ("campaign", "no_noise"))
    else:
        labels = ("campaign", versus)
        progs = programs(spec_path, batch, n_logs, ("campaign",)) + programs(versus, batch, n_logs, ("campaign",))
    runs = {label: profile(fn, args, n_ctl, state0, label) for label, (fn, args, state0) in zip(labels, progs)}
    for part, title in ((0, "kernels"), (1, "idle between kernels")):
        a, c = (runs[label][part] for label in labels)
        print(f"== campaign minus {labels[1]}: {title} (ms per control step)")
        for name in sorted(set(a) | set(c), key=lambda k: -abs(a.get(k, 0.0) - c.get(k, 0.0)))[:20]:
            print(f"  {(a.get(name, 0.0) - c.get(name, 0.0)) / n_ctl:+8.4f}  {name[:100]}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "sweeps/paper_campaign.toml",
         int(sys.argv[2]) if len(sys.argv) > 2 else 16384, int(sys.argv[3]) if len(sys.argv) > 3 else 100,
         sys.argv[4] if len(sys.argv) > 4 else None)
