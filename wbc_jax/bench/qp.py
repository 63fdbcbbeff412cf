"""``wbc-jax bench qp``: throughput and accuracy of the batched ADMM QP solver.

One run on the current device (``jax.devices()[0]``), in the device's default dtype
(float32 unless x64 is enabled), on WBC-sized problems from
:mod:`wbc_jax.bench.qp_problems` (n = 68, 24 equality + 70 inequality rows; half generic,
half with WBC structure and scales):

* batched QPs per second at batch 1, 1024, 4096, 16384 (quick: 1, 64, 256), default
  iterations, cold start; compile time reported separately; also, at the largest batch,
  the ``linsolve="inv"`` variant (explicit inverse: matrix-vector products only) and
  active-set polishing (``polish=True``), whose costs are device-dependent.
* accuracy versus iteration count, cold and warm (warm: from the solution of the same
  problems with all data perturbed by 1 %): median and 95th percentile of the relative
  objective error and of the max violation (relative to ``max(1, ||Ax||_inf)``), against
  the reference solver's solution.
* the reference solver's own CPU time per QP: OSQP at eps 1e-9 when installed;
  otherwise (e.g. the GPU machine) this solver in float64 on the CPU with 2000
  iterations, which is said in the output. Every reference is also checked against the
  problems' constructed optimum.
"""

from __future__ import annotations

import json
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.bench import qp_problems as pr
from wbc_jax.qp import QPSettings, solve_qp

SEED = 7
POOL = 256  # distinct problems, tiled to the throughput batch sizes
FULL = dict(batches=(1, 1024, 4096, 16384), n_acc=512, iters=(10, 25, 50, 100, 200))
QUICK = dict(batches=(1, 64, 256), n_acc=64, iters=(10, 25, 50, 100))
REF_EPS = 1e-9
FALLBACK_ITERS = 2000
WARM_PERTURBATION = 0.01


def _timed(fn, *args, min_time=0.5, max_reps=50):
    """(compile+first-call seconds, steady seconds per call) with block_until_ready."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    reps, total = 0, 0.0
    while total < min_time and reps < max_reps:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        total += time.perf_counter() - t0
        reps += 1
    per = total / reps
    return max(first - per, 0.0), per


def _tile(a: np.ndarray, b: int, dtype) -> jax.Array:
    idx = np.arange(b) % a.shape[0]
    return jnp.asarray(a[idx], dtype)


def _throughput(pool: pr.QPProblem, batches, dtype, settings: QPSettings) -> list[dict]:
    rows = []
    fn = jax.jit(lambda P, q, A, l, u: solve_qp(P, q, A, l, u, settings=settings))
    for b in batches:
        data = [_tile(a, b, dtype) for a in pool[:5]]
        compile_s, per = _timed(fn, *data)
        variant = settings.linsolve + (f"+pol{settings.polish_passes}" if settings.polish else "")
        rows.append(dict(batch=b, variant=variant, seconds_per_call=per,
                         qps_per_s=b / per, compile_s=compile_s))
    return rows


def osqp_solve(P, q, A, l, u, max_iter: int = 200_000) -> tuple[np.ndarray, float]:
    """One QP by OSQP at eps ``REF_EPS``, polished (the reference solver; needs the ``osqp`` package).

    Args:
        P: (n, n), q: (n,), A: (m, n), l, u: (m,) with +-inf for absent bounds (passed as OSQP's +-1e30).

    Returns:
        (x (n,), seconds spent in OSQP's solve).
    """
    import osqp
    import scipy.sparse as sp

    s = osqp.OSQP()
    s.setup(sp.csc_matrix(np.triu(P)), q, sp.csc_matrix(A), np.maximum(l, -1e30), np.minimum(u, 1e30),
            eps_abs=REF_EPS, eps_rel=REF_EPS, max_iter=max_iter, polishing=True, verbose=False)
    t0 = time.perf_counter()
    r = s.solve(raise_error=False)
    return r.x, time.perf_counter() - t0


def _reference(batch: pr.QPProblem) -> tuple[np.ndarray, dict]:
    """Reference solutions (B, n) and a description with CPU time per QP."""
    try:
        import osqp
    except ImportError:
        osqp = None
    if osqp is not None:
        xs, times = [], []
        for k in range(batch.P.shape[0]):
            x, t = osqp_solve(batch.P[k], batch.q[k], batch.A[k], batch.l[k], batch.u[k])
            xs.append(x)
            times.append(t)
        desc = dict(name=f"OSQP {osqp.__version__} (eps {REF_EPS:g}, polished)",
                    cpu_s_per_qp_median=float(np.median(times)),
                    cpu_s_per_qp_p95=float(np.quantile(times, 0.95)))
        return np.stack(xs), desc
    cpu = jax.devices("cpu")[0]
    with jax.enable_x64(True), jax.default_device(cpu):
        one = jax.jit(lambda *a: solve_qp(*a, iters=FALLBACK_ITERS).x)
        data = [jnp.asarray(a, jnp.float64) for a in batch[:5]]
        _, per = _timed(one, *(a[0] for a in data), min_time=0.2, max_reps=10)
        xs = np.asarray(jax.vmap(one)(*data))
    desc = dict(name=f"OSQP not installed: this ADMM, float64 on CPU, {FALLBACK_ITERS} iters",
                cpu_s_per_qp_median=per, cpu_s_per_qp_p95=None)
    return xs, desc


def _stats(batch, x, f_ref) -> dict:
    oe = pr.rel_objective_error(batch.P, batch.q, x, f_ref)
    v = pr.max_violation(batch.A, batch.l, batch.u, x)
    q = lambda a, p: float(np.quantile(a, p))  # noqa: E731
    return dict(obj_med=q(oe, 0.5), obj_p95=q(oe, 0.95), viol_med=q(v, 0.5), viol_p95=q(v, 0.95))


def _accuracy(batch, x_ref, iters_list, dtype) -> list[dict]:
    f_ref = pr.objective(batch.P, batch.q, x_ref)
    data = [jnp.asarray(a, dtype) for a in batch[:5]]
    pert = [jnp.asarray(a, dtype) for a in pr.perturb(batch, SEED + 1, WARM_PERTURBATION)]
    warm = solve_qp(*pert)
    rows = []
    for it in iters_list:
        for mode, w in (("cold", None), ("warm", warm)):
            res = solve_qp(*data, iters=it, warm=w)
            x = np.asarray(res.x, np.float64)
            rows.append(dict(iters=it, start=mode, **_stats(batch, x, f_ref),
                             solved_flag_frac=float(np.mean(np.asarray(res.flag) == 0))))
    return rows


def run_bench(quick: bool = False, json_path: str | None = None) -> dict[str, Any]:
    """Run the QP benchmark, print a table and return the numbers.

    Args:
        quick: small batch sizes and problem counts (CPU smoke run, < 1 min).
        json_path: also write the returned dict as JSON there.

    Returns:
        Dict with ``device``, ``dtype``, ``settings``, ``throughput``, ``reference``,
        ``accuracy`` (see the module docstring).
    """
    cfg = QUICK if quick else FULL
    dev = jax.devices()[0]
    dtype = jnp.asarray(1.0).dtype
    settings = QPSettings()
    t_start = time.perf_counter()
    pool = pr.make_batch(SEED, POOL if not quick else 64)
    out: dict[str, Any] = dict(
        device=f"{dev.platform}: {dev.device_kind}", dtype=str(dtype), jax=jax.__version__,
        date=time.strftime("%Y-%m-%d %H:%M:%S %Z"), quick=quick,
        problem=dict(n=int(pool.P.shape[-1]), m=int(pool.A.shape[-2]),
                     m_eq=int(np.sum(pool.l[0] == pool.u[0])), families="generic + wbc"),
        settings=settings._asdict())
    print(f"wbc-jax bench qp  device={out['device']}  dtype={dtype}  jax={jax.__version__}")
    print(f"problems: n={out['problem']['n']} m={out['problem']['m']} "
          f"(eq {out['problem']['m_eq']}), default iters={settings.iters}")

    thr = _throughput(pool, cfg["batches"], dtype, settings)
    for variant in (dict(linsolve="inv"), dict(polish=True)):
        thr += _throughput(pool, cfg["batches"][-1:], dtype, settings._replace(**variant))
    out["throughput"] = thr
    print("\nthroughput (cold start, default iters; compile excluded)")
    print(f"{'batch':>7} {'variant':>9} {'QPs/s':>12} {'ms/call':>10} {'compile s':>10}")
    for r in thr:
        print(f"{r['batch']:>7} {r['variant']:>9} {r['qps_per_s']:>12.1f} "
              f"{1e3 * r['seconds_per_call']:>10.3f} {r['compile_s']:>10.2f}")

    acc_batch = pr.make_batch(SEED + 2, cfg["n_acc"])
    x_ref, ref = _reference(acc_batch)
    ref.update(_stats(acc_batch, x_ref, acc_batch.f))
    out["reference"] = ref
    print(f"\nreference: {ref['name']}")
    print(f"  CPU time per QP: median {1e3 * ref['cpu_s_per_qp_median']:.3f} ms"
          + (f", p95 {1e3 * ref['cpu_s_per_qp_p95']:.3f} ms" if ref["cpu_s_per_qp_p95"] else ""))
    print(f"  vs constructed optimum: obj err p95 {ref['obj_p95']:.1e}, "
          f"viol p95 {ref['viol_p95']:.1e}")

    acc = _accuracy(acc_batch, x_ref, cfg["iters"], dtype)
    out["accuracy"] = acc
    print(f"\naccuracy vs reference ({cfg['n_acc']} problems, {dtype}; warm = from the "
          f"solution of the {WARM_PERTURBATION:.0%}-perturbed problems)")
    print(f"{'iters':>5} {'start':>5} {'obj med':>9} {'obj p95':>9} {'viol med':>9} "
          f"{'viol p95':>9} {'flag=0':>7}")
    for r in acc:
        print(f"{r['iters']:>5} {r['start']:>5} {r['obj_med']:>9.1e} {r['obj_p95']:>9.1e} "
              f"{r['viol_med']:>9.1e} {r['viol_p95']:>9.1e} {r['solved_flag_frac']:>7.2f}")
    out["wall_s"] = time.perf_counter() - t_start
    print(f"\nwall time {out['wall_s']:.1f} s")
    if json_path:
        with open(json_path, "w") as f:
            json.dump(out, f, indent=2)
    return out
