"""``wbc-jax bench qp-rollout``: the control loop's QP settings audited on QPs from real closed loops.

The QP benchmark (:mod:`wbc_jax.bench.qp`) uses synthetic problems; the control loop's settings (iteration
count, rho adaptation, polishing) are chosen here instead, on the QPs the transport controller actually builds
(the course scene by default). For each variant of :class:`~wbc_jax.qp.QPSettings` (:func:`variants`):

1. a closed-loop rollout (batch of factor cells, the scene's plan) runs **with that variant** in the control
   loop, so each sampled QP carries the warm start the variant itself produced;
2. every ``sample_every_s`` simulated seconds the QP of the next control step is rebuilt from the state
   (same code path as :func:`wbc_jax.rollout.step.control_step`: sense, controller view, dynamics terms, reference,
   observer and assembly) and solved once more by the variant from its warm start, in the default dtype
   (float32 unless x64 is enabled);
3. each sampled QP is solved by OSQP at eps 1e-9 (polished) in float64, the reference.

Reported per variant: the acceptance fraction (relative objective error <= ``OBJ_TOL`` and max
constraint violation, relative to ``max(1, |Ax|_inf)``, <= ``VIOL_TOL``; the line is ``ACCEPT_FRAC``), the
joint-torque error ``|tau - tau_ref|`` [N m] (``tau = A_tau x + h_a``, what drives the motors), the relative
objective error and violation (median / p95 / max over the samples), the flag fraction of every control step
of the loop (the solver's own OSQP-style test; the worst run and the mean), and the rollout's closed-loop
metrics (max slip, tracking T, trunk minimum) so an accuracy loss can be read against its effect on the task.
"""

from __future__ import annotations

import json
import time
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.bench import qp_problems as pr
from wbc_jax.bench.qp import REF_EPS, osqp_solve
from wbc_jax.control.transport import TransportConfig, assemble, control_qp_settings
from wbc_jax.qp import solve_qp
from wbc_jax.robot.model import Robot
from wbc_jax.rollout import controller_inputs, make_sim, simulate
from wbc_jax.rollout.batch import prepare_batch

OBJ_TOL = 1e-3  # relative objective error (float32)
VIOL_TOL = 1e-4  # max violation relative to max(1, |Ax|_inf)
ACCEPT_FRAC = 0.999  # fraction of sampled QPs within both
CELLS = ((0.2, 0.4, 0.06), (0.4, 1.0, 0.10), (0.3, 0.7, 0.08), (0.4, 0.4, 0.10))
_PARTS = {"tol": "tol", "pol": "polish_passes", "rho": "rho", "a": "adapt_every", "b": "adapt_bias", "r": "ruiz_iters",
          "e": "eq_rows", "m": "max_iters", "c": "check_every", "k": "kernel"}  # longest prefix first
_KERNEL_CODES = ("xla", "fused", "auto")  # ..._k<K>: QPSettings.kernel by index
DEFAULT_VARIANTS = ("it20",)


def variants(names=None) -> dict:
    """Named control-loop settings: ``it<N>`` (N warm-started iterations, otherwise :func:`control_qp_settings`),
    ``..._a<K>`` (rho adapted every K iterations, 0: never, one factorization per step), ``..._r<R>`` (R Ruiz
    equilibration passes), ``..._b<B>`` (rho adaptation bias B), ``..._rho<R>`` (initial rho R), ``..._pol<P>``
    (P active-set polishing passes after the iterations, 0: none), ``..._e<E>`` (the first E rows held exactly,
    ``QPSettings.eq_rows``), ``..._m<M>`` (continue while unconverged up to M iterations, ``QPSettings.max_iters``),
    ``..._c<C>`` (the convergence test every C iterations past the first N, ``QPSettings.check_every``),
    ``..._tol<E>`` (flag tolerance 10^-E, abs and rel), ``..._k<K>`` (``QPSettings.kernel``: 0 XLA, 1 fused,
    2 auto)."""
    out = {}
    for name in names or DEFAULT_VARIANTS:
        parts = name.split("_")
        if not (parts[0].startswith("it") and parts[0][2:].isdigit()):
            raise ValueError(f"variant {name!r}: expected "
                             "it<N>[_a<K>][_b<B>][_rho<R>][_r<R>][_pol<P>][_e<E>][_m<M>][_c<C>][_tol<E>][_k<K>]")
        iters = int(parts[0][2:])
        kw = {}
        for p in parts[1:]:
            key = next((k for k in _PARTS if p.startswith(k)), None)
            if key is None or not p[len(key):].isdigit():
                raise ValueError(f"variant {name!r}: unknown part {p!r} (expected a<K>, b<B>, rho<R>, r<R>, "
                                 "pol<P>, e<E>, m<M>, c<C>, tol<E> or k<K>)")
            kw[_PARTS[key]] = (float if key == "rho" else int)(p[len(key):])
        if "tol" in kw:
            kw["eps_abs"] = kw["eps_rel"] = 10.0 ** -kw.pop("tol")
        if "kernel" in kw:
            if kw["kernel"] >= len(_KERNEL_CODES):
                raise ValueError(f"variant {name!r}: k<K> expects K in 0..{len(_KERNEL_CODES) - 1} "
                                 f"({_KERNEL_CODES})")
            kw["kernel"] = _KERNEL_CODES[kw["kernel"]]
        if "polish_passes" in kw:
            kw["polish"] = kw["polish_passes"] > 0
        out[name] = control_qp_settings(iters, **kw)
    return out


class _SampledQP(NamedTuple):
    """The QP of one control step and its torque map ``tau = A_tau x + h_a``."""

    P: jax.Array
    q: jax.Array
    A: jax.Array
    l: jax.Array
    u: jax.Array
    A_tau: jax.Array
    h_a: jax.Array


def _sample_fn(sim):
    """One run's state -> the :class:`_SampledQP` of its next control step (``rollout.control_step``'s path)."""
    ids = sim.robot.ids
    cfg = sim.cfg

    def one(m, rs, plan, om, gains, push, mu_ground):
        _, obs, ref, mu = controller_inputs(sim, m, rs, plan, push, mu_ground)
        _, (P, q, A, l, u, A_tau, h_a, _) = assemble(obs, ref, om, gains, rs.cs, ids, cfg, mu)
        return _SampledQP(P, q, A, l, u, A_tau, h_a)

    return one


def _sampled_qps(sim, b, qs, seconds: float, sample_every_s: float):
    """The closed loop of batch ``b`` run with settings ``qs``; every ``sample_every_s`` the next control step's QP,
    rebuilt and solved by ``qs`` from the loop's warm start. Returns (final state, samples: per sample the float64
    arrays P, q, A, l, u, A_tau, h_a and the solution x, each with the run axis first)."""
    ax = b.in_axes
    f_sample = jax.jit(jax.vmap(_sample_fn(sim), in_axes=(ax, 0, 0, 0, 0, 0, 0)))
    f_solve = jax.jit(jax.vmap(lambda P, q, A, l, u, w: solve_qp(P, q, A, l, u, warm=w, settings=qs)))
    state = b.state
    samples = []
    for _ in range(int(round(seconds / sample_every_s))):
        state, _ = simulate(sim, b.model, ax, state, b.plan, b.om, b.gains, b.push, b.mu_ground,
                            sample_every_s, chunk_seconds=sample_every_s)
        P, q, A, l, u, A_tau, h_a = f_sample(b.model, state, b.plan, b.om, b.gains, b.push, b.mu_ground)
        res = f_solve(P, q, A, l, u, state.cs.warm)
        samples.append([np.asarray(v, np.float64) for v in (P, q, A, l, u, A_tau, h_a, res.x)])
    return state, samples


def _errors_against_osqp(samples):
    """Per sampled QP, against OSQP's float64 solution: (joint-torque error max |A_tau (x - x_ref)| [N m],
    relative objective error, relative max violation), three lists in sample order."""
    tau_err, obj_err, viol = [], [], []
    for P, q, A, l, u, A_tau, _h_a, x in samples:
        for k in range(P.shape[0]):
            xr, _ = osqp_solve(P[k], q[k], A[k], l[k], u[k], max_iter=400_000)
            tau_err.append(np.max(np.abs(A_tau[k] @ (x[k] - xr))))
            f_ref = pr.objective(P[k][None], q[k][None], xr[None])
            obj_err.append(float(pr.rel_objective_error(P[k][None], q[k][None], x[k][None], f_ref)[0]))
            viol.append(float(pr.max_violation(A[k][None], l[k][None], u[k][None], x[k][None])[0]))
    return tau_err, obj_err, viol


def _variant_row(qs, sim, acc, tau_err, obj_err, viol) -> dict:
    """One variant's figures: accuracy quantiles over the samples, the loop's flag fractions and task metrics."""
    run_flag = np.asarray(acc.n_flag) / np.maximum(np.asarray(acc.n_steps), 1)
    ok = (np.asarray(obj_err) <= OBJ_TOL) & (np.asarray(viol) <= VIOL_TOL)
    worst = [dict(sample=int(i), rel_obj_err=obj_err[i], violation=viol[i], tau_err_Nm=float(tau_err[i]))
             for i in np.nonzero(~ok)[0][:20]]
    q3 = lambda a: [float(np.median(a)), float(np.quantile(a, 0.95)), float(np.max(a))]  # noqa: E731
    return dict(iters=qs.iters, adapt_every=qs.adapt_every, polish_passes=qs.polish_passes if qs.polish else 0,
                dtype=str(jax.numpy.asarray(1.0).dtype), n_qps=len(tau_err),
                accept_frac=float(np.mean(ok)), accepted=bool(np.mean(ok) >= ACCEPT_FRAC), tau_err_Nm=q3(tau_err),
                rel_obj_err=q3(obj_err), violation=q3(viol),
                max_slip_mm=float(np.max(np.asarray(acc.max_slip)) * 1e3),
                T_mm=float(np.mean(np.asarray(acc.sum_track) / (np.asarray(acc.n_steps) * sim.dt_control)) * 1e3),
                trunk_min_m=float(np.min(np.asarray(acc.min_trunk_z))),
                flag_frac=float(np.sum(np.asarray(acc.n_flag)) / np.sum(np.asarray(acc.n_steps))),
                flag_frac_worst_run=float(np.max(run_flag)), n_steps=int(np.sum(np.asarray(acc.n_steps))),
                rejected=worst)


def audit(names=None, scene: str = "transport", seconds: float = 3.0, sample_every_s: float = 0.01,
          json_path: str | None = None) -> dict:
    """Run the audit (see module docstring); prints one table row per variant and returns the figures."""
    robot = Robot(scene)
    cells = np.array(CELLS)
    rows = {}
    for name, qs in variants(names).items():
        t0 = time.perf_counter()
        cfg = TransportConfig(dt=float(robot.mj_model.opt.timestep), qp=qs)
        sim = make_sim(robot, cfg, log_every=10)
        b = prepare_batch(sim, cells[:, 0], cells[:, 1], cells[:, 2])
        state, samples = _sampled_qps(sim, b, qs, seconds, sample_every_s)
        row = _variant_row(qs, sim, state.acc, *_errors_against_osqp(samples))
        row["wall_s"] = time.perf_counter() - t0
        rows[name] = row
        print(f"{name:10s} accept {row['accept_frac']:.4f} ({'>=' if row['accepted'] else '<'} {ACCEPT_FRAC}) "
              f"tau err [N m] med/p95/max {row['tau_err_Nm'][0]:.3g}/{row['tau_err_Nm'][1]:.3g}/"
              f"{row['tau_err_Nm'][2]:.3g}  rel obj p95 {row['rel_obj_err'][1]:.2g}  viol p95 "
              f"{row['violation'][1]:.2g}  | loop: slip {row['max_slip_mm']:.2f} mm, T {row['T_mm']:.2f} mm, "
              f"trunk min {row['trunk_min_m']:.3f} m, flagged {row['flag_frac']:.2%} (worst run "
              f"{row['flag_frac_worst_run']:.2%} of {row['n_steps']} steps) ({row['wall_s']:.0f} s)",
              flush=True)
    out = dict(device=jax.devices()[0].device_kind, scene=robot.path.name, seconds=seconds, obj_tol=OBJ_TOL,
               viol_tol=VIOL_TOL, accept_line=ACCEPT_FRAC,
               sample_every_s=sample_every_s, cells=cells.tolist(), reference=f"OSQP eps {REF_EPS:g}, polished",
               variants=rows)
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=2)
    return out
