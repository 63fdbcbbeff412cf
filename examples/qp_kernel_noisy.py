"""The fused QP kernels on the campaign's own noisy QPs: a GPU study of where the iterations kernel's time goes.

    python examples/qp_kernel_noisy.py --record FILE.npz [K]      (CPU: record K solves, default 1024)
    python examples/qp_kernel_noisy.py FILE.npz [BATCH] [VARIANT ...] [--kernels]   (GPU; BATCH default 16384)

``--record`` runs the paper campaign's first 1.5 s cut to 8 runs (``examples/qp_settings_study.py``: its velocity
noise and pushes, the campaign's QP settings) and saves K of its control-step QPs with their warm starts, drawn
at random (seed 0). On a GPU the K problems are repeated to BATCH and solved from their warm starts by the fused
kernels under the campaign's settings and each VARIANT (``field=value`` of :class:`wbc_jax.qp.QPSettings`,
comma-separated; a string field as written); each prints the best of 7 calls after the compile, the ADMM
iterations and whether its solutions equal the campaign settings'; ``--kernels`` adds each fused kernel's device
time (a ``jax.profiler`` trace). Fixed counts (``iters=K,max_iters=0``) give an iteration's cost without the
convergence test; the campaign's settings against them give the test's and the block restarts' share.
A VARIANT ``order:NAME`` solves the same problems under the campaign's settings moved in memory to another order
(one program per problem, started in order; :func:`launch_order`): ``copies`` (each recorded problem's repeats
side by side), ``shuffled`` (random), ``longest`` (by each problem's own iterations, longest first), ``wk`` (by
the predecessor's iterations), ``predicted`` (the key of ``launch_order=predicted``,
:func:`wbc_jax.qp.kernel_order.predicted_length`: that plus the warm start's bound violation), ``wk_res``
(:func:`residual_length`: the predecessor's iterations plus the warm start's relative residuals on the problem) or
``wk_res_last`` (that key's longest last), each checked equal, problem by problem, to the recorded order's
solutions. Record as many problems as BATCH (e.g. ``--record F.npz 8192``) to order distinct problems, as a
campaign's runs are: repeats add a gain of their own where they sit side by side (docs/performance.md).
"""

import functools
import json
import os
import sys
import time

import numpy as np

FIELDS = ("P", "q", "A", "l", "u", "wx", "wz", "wy", "wrho", "wk")


def record(path: str, k: int) -> None:
    """Record the study's solves and save ``k`` of them, with the settings, to ``path``."""
    sys.path.insert(0, "examples")
    import qp_settings_study as study

    problems, settings = study.record(study.small_spec())
    pick = np.random.default_rng(0).choice(len(problems["P"]), size=min(k, len(problems["P"])), replace=False)
    np.savez_compressed(path, settings=json.dumps(settings._asdict()),
                        **{f: np.asarray(problems[f][pick], np.int32 if f == "wk" else np.float32) for f in FIELDS})
    print(f"{len(pick)} of {len(problems['P'])} recorded solves saved to {path}")


def residual_length(P, q, A, l, u, wx, wy, wk, s):
    """() a launch key of one warm-started problem, larger for a longer solve: ``wk`` (the predecessor's
    iterations) plus ``s.check_every`` x log10(1 + r), r the larger of the warm start's primal and dual residuals
    (OSQP's, unscaled) each relative to its tolerance ``eps_abs + eps_rel * scale``. P: (n, n); q: (n,); A: (m, n);
    l, u: (m,) finite; wx: (n,), wy: (m,) the warm start."""
    import jax.numpy as jnp

    Ax = A @ wx
    prim = jnp.max(jnp.abs(Ax - jnp.clip(Ax, l, u))) / (s.eps_abs + s.eps_rel * jnp.max(jnp.abs(Ax)))
    dual = jnp.max(jnp.abs(P @ wx + q + A.T @ wy)) / (s.eps_abs + s.eps_rel * jnp.max(jnp.abs(q)))
    return wk.astype(P.dtype) + s.check_every * jnp.log10(1.0 + jnp.maximum(prim, dual))


def launch_order(name: str, data: list, iters: np.ndarray, s, copies: int) -> np.ndarray:
    """(batch,) the problems' launch order ``name`` (module docstring): indices into ``data`` (the batch's arrays in
    the order of FIELDS), whose own iterations are ``iters`` (batch,); ``s``: the solver's settings; ``copies``: the
    number of recorded problems (the batch repeats them)."""
    import jax

    fields = dict(zip(FIELDS, data))
    if name == "copies":
        return np.argsort(np.arange(len(iters)) % copies, kind="stable")
    if name == "shuffled":
        return np.random.default_rng(0).permutation(len(iters))
    if name == "longest":
        key = iters
    elif name == "wk":
        key = np.asarray(fields["wk"])
    elif name == "predicted":
        from wbc_jax.qp.kernel_order import predicted_length

        key = np.asarray(jax.vmap(functools.partial(predicted_length, s=s))(
            *(fields[k] for k in ("l", "u", "wz", "wk"))))
    elif name in ("wk_res", "wk_res_last"):
        key = np.asarray(jax.vmap(functools.partial(residual_length, s=s))(
            *(fields[k] for k in ("P", "q", "A", "l", "u", "wx", "wy", "wk"))))
    else:
        raise SystemExit(f"qp_kernel_noisy.py: order:{name}: expected copies, shuffled, longest, wk, predicted, "
                         "wk_res or wk_res_last")
    return np.argsort(key if name == "wk_res_last" else -key, kind="stable")


def timed(fn, args: list, kernels: bool) -> tuple:
    """``(output, best of 7 calls [ms], {kernel: device ms per call})`` of ``fn(*args)`` after its compile; the
    kernels' times (the fused solver's ``admm_*``) from a ``jax.profiler`` trace of one more call when ``kernels``."""
    import jax

    out = jax.block_until_ready(fn(*args))
    times = []
    for _ in range(7):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    per = {}
    if kernels:
        from wbc_jax.bench.trace import kernel_durations, profiled_call

        per = kernel_durations(profiled_call(fn, args)[0], prefix="admm_")
    return out, 1e3 * min(times), per


def same_solutions(ref, out, order=slice(None)) -> bool:
    """Whether ``out``'s solutions, flags and iterations equal ``ref``'s bit for bit, ``ref``'s taken in ``order``
    (the order ``out``'s problems were solved in)."""
    return all(np.array_equal(np.asarray(a)[order], np.asarray(b))
               for a, b in ((ref.x, out.x), (ref.iters, out.iters), (ref.flag, out.flag)))


def kernel_times(per: dict) -> str:
    """The ``admm_*`` kernels' device times, for a printed line."""
    return "".join(f"  {k[len('admm_'):]} {v:.3f}" for k, v in sorted(per.items()))


def main(path: str, batch: int, variants: list[str], kernels: bool = False) -> None:
    import jax
    import jax.numpy as jnp

    from wbc_jax.qp import QPResult, QPSettings, solve_qp

    if jax.default_backend() != "gpu":
        sys.exit("qp_kernel_noisy.py: timing needs a GPU (on a CPU the kernels run in Pallas' interpreter)")
    f = np.load(path)
    saved = {k: v for k, v in json.loads(str(f["settings"])).items() if k in QPSettings._fields}
    base = QPSettings(**{**saved, "linsolve": "inv", "kernel": "fused"})
    reps = -(-batch // len(f["P"]))
    data = [jnp.asarray(np.concatenate([f[k]] * reps)[:batch]) for k in FIELDS]
    print(f"{jax.devices()[0].device_kind}, {batch} problems ({len(f['P'])} recorded, repeated)", flush=True)

    def solve(P, q, A, l, u, wx, wz, wy, wrho, wk, s):
        return solve_qp(P, q, A, l, u, warm=QPResult(wx, wy, wz, 0.0, 0.0, 0, wk, wrho), settings=s)

    first = None
    for variant in ["", *variants]:
        if variant.startswith("order:"):
            order = launch_order(variant[len("order:"):], data, np.asarray(first.iters), base, len(f["P"]))
            fn = jax.jit(functools.partial(solve, s=base))
            out, ms, per = timed(fn, [d[order] for d in data], kernels)
            same = same_solutions(first, out, order)
            print(f"{variant:36s} {ms:8.3f} ms  solutions {'equal' if same else 'DIFFER'} to the recorded "
                  f"order's{kernel_times(per)}", flush=True)
            continue
        change = {}
        for item in filter(None, variant.split(",")):
            key, value = item.split("=")
            old = getattr(base, key)
            change[key] = value if isinstance(old, str) else type(old)(float(value))
        s = base._replace(**change)
        out, ms, per = timed(jax.jit(functools.partial(solve, s=s)), data, kernels)
        first = out if first is None else first
        it, flagged = np.asarray(out.iters), int((np.asarray(out.flag) != 0).sum())
        equal = same_solutions(first, out)
        same = "" if out is first else f"  solutions {'equal' if equal else 'DIFFER'} to the campaign settings'"
        print(f"{variant or 'campaign settings':36s} {ms:8.3f} ms  iterations mean {it.mean():6.2f} "
              f"p50 {np.median(it):3.0f} p99 {np.percentile(it, 99):3.0f}  flagged {flagged}{same}"
              f"{kernel_times(per)}", flush=True)


if __name__ == "__main__":
    argv, kernels = [a for a in sys.argv[1:] if a != "--kernels"], "--kernels" in sys.argv
    if kernels:  # kernels named in the trace, not by their CUDA graph
        os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_gpu_enable_command_buffer="
    if argv and argv[0] == "--record":
        record(argv[1], int(argv[2]) if len(argv) > 2 else 1024)
    else:
        main(argv[0], int(argv[1]) if len(argv) > 1 else 16384, argv[2:], kernels)
