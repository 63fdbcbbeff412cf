"""Where a campaign's control step spends its device time, kernel by kernel, with and without the velocity noise.

    python examples/campaign_kernel_profile.py [SPEC] [BATCH] [STEPS] [VERSUS]
        (defaults: sweeps/paper_campaign.toml 16384 100; needs a GPU)

The spec is built as a campaign builds it; its runs are repeated to BATCH (run i is the spec's run i mod n, from the
start state) and stepped by the campaign's own chunk program and by its ``no_noise`` ablation
(:mod:`wbc_jax.bench.campaign_step`), STEPS control steps per call; with a second spec VERSUS, by each spec's own
chunk program instead (e.g. a spec and its variant with one key changed). Each program is compiled, called once, timed
once, then called once under ``jax.profiler``; the device trace's kernels are summed by name. Prints, per program,
the wall time, the ADMM iterations per control step and its 20 largest kernels (ms per control step, share of the
kernels' time), then the 20 largest differences between the two programs.
"""

import collections
import sys
import tempfile
import time
from pathlib import Path

import jax
from jax.profiler import ProfileData

from wbc_jax.bench.campaign_step import compiled_chunk, fresh_state, repeated
from wbc_jax.bench.rollout import qp_iterations
from wbc_jax.campaign.build import LOG_EVERY, build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.rollout.batch import chunk_args


def kernel_times(trace_dir: Path) -> collections.Counter:
    """{kernel name: device ns} summed over the GPU streams of the one profile under ``trace_dir``."""
    xplane = next(trace_dir.rglob("*.xplane.pb"))
    total = collections.Counter()
    for plane in ProfileData.from_file(str(xplane)).planes:
        if not plane.name.startswith("/device:GPU"):
            continue
        for line in plane.lines:
            if "Stream" in line.name:
                for event in line.events:
                    total[event.name] += event.duration_ns
    return total


def profile(program, args, n_ctl: int, state0, name: str, where: Path, label: str) -> collections.Counter:
    """A first call of the compiled ``program``, a timed call, a call profiled into ``where / name``; prints its
    figures under ``label`` and returns its kernel times (:func:`kernel_times`)."""
    out = jax.block_until_ready(program(*args))
    t0 = time.perf_counter()
    jax.block_until_ready(program(*args))
    wall = time.perf_counter() - t0
    with jax.profiler.trace(str(where / name)):
        jax.block_until_ready(program(*args))
    kernels = kernel_times(where / name)
    busy = sum(kernels.values())
    print(f"== {label}: {1e3 * wall / n_ctl:.3f} ms per control step wall, {busy / 1e6 / n_ctl:.3f} ms of kernels; "
          f"ADMM iterations per control step {qp_iterations(state0, out[0], n_ctl):.2f}")
    for name, ns in kernels.most_common(20):
        print(f"  {ns / 1e6 / n_ctl:8.4f} ms  {100 * ns / busy:5.1f} %  {name[:100]}")
    return kernels


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
    with tempfile.TemporaryDirectory() as tmp:
        runs = {label: profile(fn, args, n_ctl, state0, f"run{i}", Path(tmp), label)
                for i, (label, (fn, args, state0)) in enumerate(zip(labels, progs))}
    a, c = (runs[label] for label in labels)
    print(f"== campaign minus {labels[1]} (ms per control step)")
    for name in sorted(set(a) | set(c), key=lambda k: -abs(a[k] - c[k]))[:20]:
        print(f"  {(a[name] - c[name]) / 1e6 / n_ctl:+8.4f}  {name[:100]}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "sweeps/paper_campaign.toml",
         int(sys.argv[2]) if len(sys.argv) > 2 else 16384, int(sys.argv[3]) if len(sys.argv) > 3 else 100,
         sys.argv[4] if len(sys.argv) > 4 else None)
