"""Where a campaign's control step spends its device time, kernel by kernel, with and without the velocity noise.

    python examples/campaign_kernel_profile.py [SPEC] [BATCH] [STEPS]
        (defaults: sweeps/paper_campaign.toml 16384 100; needs a GPU)

The spec is built as a campaign builds it; its runs are repeated to BATCH (run i is the spec's run i mod n, from the
start state) and stepped by the campaign's own chunk program and by its ``no_noise`` ablation
(:mod:`wbc_jax.bench.campaign_step`), STEPS control steps per call. Each program is compiled, called once, timed
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


def profile(program, args, n_ctl: int, state0, label: str, where: Path) -> collections.Counter:
    """A first call of the compiled ``program``, a timed call, a profiled call; prints its figures and returns its
    kernel times (:func:`kernel_times`)."""
    out = jax.block_until_ready(program(*args))
    t0 = time.perf_counter()
    jax.block_until_ready(program(*args))
    wall = time.perf_counter() - t0
    with jax.profiler.trace(str(where / label)):
        jax.block_until_ready(program(*args))
    kernels = kernel_times(where / label)
    busy = sum(kernels.values())
    print(f"== {label}: {1e3 * wall / n_ctl:.3f} ms per control step wall, {busy / 1e6 / n_ctl:.3f} ms of kernels; "
          f"ADMM iterations per control step {qp_iterations(state0, out[0], n_ctl):.2f}")
    for name, ns in kernels.most_common(20):
        print(f"  {ns / 1e6 / n_ctl:8.4f} ms  {100 * ns / busy:5.1f} %  {name[:100]}")
    return kernels


def main(spec_path: str, batch: int, steps: int) -> None:
    if jax.default_backend() != "gpu":
        sys.exit("campaign_kernel_profile.py: needs a GPU (the profile reads the device's kernel trace)")
    built = build(load_spec(spec_path))
    sim = built.sim
    b = repeated(built.batch, built.batch.state, fresh_state(sim, built.batch, batch), batch)
    n_logs = max(1, steps // LOG_EVERY)
    n_ctl = n_logs * LOG_EVERY
    print(f"{jax.devices()[0].device_kind}: {spec_path}, batch {batch}, {n_ctl} control steps per call", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        runs = {name: profile(compiled_chunk(sim, b, n_logs, name), chunk_args(b), n_ctl, b.state, name, Path(tmp))
                for name in ("campaign", "no_noise")}
    a, c = runs["campaign"], runs["no_noise"]
    print("== campaign minus no_noise (ms per control step)")
    for name in sorted(set(a) | set(c), key=lambda k: -abs(a[k] - c[k]))[:20]:
        print(f"  {(a[name] - c[name]) / 1e6 / n_ctl:+8.4f}  {name[:100]}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "sweeps/paper_campaign.toml",
         int(sys.argv[2]) if len(sys.argv) > 2 else 16384, int(sys.argv[3]) if len(sys.argv) > 3 else 100)
