"""The tail of the transport QP's ADMM iterations under the campaign's velocity noise.

    python examples/qp_iteration_tail.py [SECONDS]      e.g.  6

The paper campaign cut to 8 runs (m 0.2 / 0.4, mu 0.4 / 1.0, d 0.06 / 0.10, one repetition, its noise and pushes)
runs SECONDS (default 6) in the controller's closed loop on this machine (the XLA path on a CPU) while every solve's
iterations and its predecessor's are recorded (pairs: the callbacks of one control step's runs may come in any
order). Printed: the iterations' percentiles and tail shares, and how often a long solve follows a long one.
On a CPU: minutes.
"""

import sys

import jax
import numpy as np

import wbc_jax.control.transport as transport
from wbc_jax.campaign.build import build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.rollout import simulate

sys.path.insert(0, "examples")
from qp_settings_study import small_spec  # noqa: E402  (the paper spec cut to 8 runs)

CHUNK_S = 0.5


def record(seconds: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(iterations, the predecessor's iterations), each (solves,), of the closed loop's solves after its first
    10 control steps, and the number of runs."""
    built = build(load_spec(small_spec()))
    rows, solve = [], transport.solve_qp

    def recording_solve(P, q, A, l, u, warm=None, settings=None):
        res = solve(P, q, A, l, u, warm=warm, settings=settings)
        jax.debug.callback(lambda *a: rows.append([np.array(v) for v in a]), warm.iters, res.iters)
        return res

    transport.solve_qp = recording_solve
    try:
        b = built.batch
        simulate(built.sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground, seconds,
                 CHUNK_S)
    finally:
        transport.solve_qp = solve
    n = built.design.n
    wk, k = (np.stack([r[i] for r in rows])[10 * n:] for i in (0, 1))
    return k, wk, n


if __name__ == "__main__":
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 6.0
    k, wk, n = record(seconds)
    flat, flat_wk = k.astype(float), wk.astype(float)
    p50, p90, p99 = np.percentile(flat, [50, 90, 99])
    print(f"{flat.size} solves ({n} runs, {seconds} s): iterations mean {flat.mean():.2f} p50 {p50:.0f} p90 {p90:.0f} "
          f"p99 {p99:.0f} max {flat.max():.0f}; above 32 / 48 / 64: "
          + " / ".join(f"{np.mean(flat > t):.2%}" for t in (32, 48, 64)) + f"; at the cap: {np.sum(flat >= 200)}")
    long = flat > 64
    print(f"of the solves above 64, {np.mean(flat_wk[long] > 64):.0%} have a predecessor above 64")
