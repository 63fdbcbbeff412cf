"""How many constraint-solver iterations the physics runs in a campaign, with and without the velocity noise.

    python examples/physics_solver_cap.py [SPEC] [BATCH] [CHUNKS] [TOLERANCE]
        (defaults: sweeps/paper_campaign.toml 16384 12, the scene's ``opt.tolerance``; MuJoCo Warp physics: the
        spec's ``campaign.backend = "warp"``, or a GPU)

The spec is built as a campaign builds it, its runs repeated to BATCH (run i is the spec's run i mod n), and stepped
from the start state by the campaign's chunk program and by its ``no_noise`` ablation
(:mod:`wbc_jax.bench.campaign_step`), CHUNKS calls of 20 control steps each, every call continuing from the last.
After each call it reads MuJoCo Warp's per-world iteration count of the last physics step (``solver_niter``: its
batch maximum and mean, the share of worlds at ``opt.iterations``) and the runs' physics steps whose solve stopped
at that cap during the call (``Accum.n_solver_cap``, :func:`wbc_jax.bench.rollout.solver_cap_share`). Warp's solver
loop runs until the batch's last world has converged, so the batch maximum is the number of iterations every world's
step pays for. It prints them per program with the wall time per control step of calls 2..CHUNKS.
"""

import sys
import time

import jax
import numpy as np

from wbc_jax.bench.campaign_step import compiled_chunk, fresh_state, repeated
from wbc_jax.bench.rollout import solver_cap_share
from wbc_jax.campaign.build import LOG_EVERY, build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.rollout.batch import chunk_args


def main(spec_path: str, batch: int, chunks: int, tolerance: float | None = None) -> None:
    built = build(load_spec(spec_path))
    if tolerance is not None:  # the constraint solver's convergence tolerance instead of the scene's
        built = built._replace(batch=built.batch._replace(
            model=built.batch.model.tree_replace({"opt.tolerance": tolerance})))
    if built.sim.robot.backend != "warp":
        sys.exit("physics_solver_cap.py: needs MuJoCo Warp physics (MJX's JAX solver reports no iteration count)")
    cap = built.sim.robot.mj_model.opt.iterations
    b = repeated(built.batch, built.batch.state, fresh_state(built.sim, built.batch, batch), batch)
    print(f"{jax.devices()[0].device_kind}: {spec_path}, batch {batch}, {chunks} calls of {LOG_EVERY} control steps; "
          f"constraint solver cap {cap} iterations, tolerance {built.batch.model.opt.tolerance:g}", flush=True)
    for name in ("campaign", "no_noise"):
        program, args, rows, wall = compiled_chunk(built.sim, b, 1, name), list(chunk_args(b)), [], 0.0
        for i in range(chunks):
            t0 = time.perf_counter()
            state = jax.block_until_ready(program(*args))[0]
            wall += (time.perf_counter() - t0) if i else 0.0
            per_ctl = batch * solver_cap_share(args[1], state, LOG_EVERY)  # runs' capped steps per control step
            niter = np.asarray(state.d._impl.solver_niter).ravel()
            rows.append((niter.max(), niter.mean(), np.mean(niter >= cap), per_ctl))
            args[1] = state
        r = np.array(rows, float)
        print(f"== {name}: last physics step's iterations, batch max per call {r[:, 0].astype(int).tolist()}, "
              f"mean {r[:, 1].mean():.3f}, worlds at the cap {r[:, 2].mean():.2%}; runs' physics steps at the cap per "
              f"control step, per call {r[:, 3].round(1).tolist()}; "
              f"{1e3 * wall / max(1, chunks - 1) / LOG_EVERY:.3f} ms per control step (calls 2..{chunks})", flush=True)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "sweeps/paper_campaign.toml",
         int(sys.argv[2]) if len(sys.argv) > 2 else 16384, int(sys.argv[3]) if len(sys.argv) > 3 else 12,
         float(sys.argv[4]) if len(sys.argv) > 4 else None)
