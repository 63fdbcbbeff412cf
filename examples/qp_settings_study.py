"""ADMM iterations of the transport controller's QP under the campaign's velocity noise, per solver setting.

    python examples/qp_settings_study.py [VARIANT ...]      e.g.  alpha=1.3  rho=1,check_every=1  reuse=10
                                                   first_test=0  alpha=1.3,first_test=0  closed:alpha=1.3

The paper campaign's first 1.5 s (8 runs: m 0.2 / 0.4, mu 0.4 / 1.0, d 0.06 / 0.10, one repetition, its noise and
pushes) is run once with the campaign's own settings while every control step's QP and warm start are recorded;
then each recorded problem is solved again from its recorded warm start under each variant (``field=value`` of
:class:`wbc_jax.qp.QPSettings`, comma-separated; ``rho`` replaces the warm start's rho), and the ADMM iterations
are printed (mean, percentiles, max, flagged solves). These open-loop figures can mislead where a setting changes
the warm starts it would get (over-relaxation: docs/performance.md, open limits): ``closed:VARIANT`` runs the
rollout again with the variant in the controller's loop (``QPSettings`` fields only) and prints its own solves'
iterations and convergence tests.
``reuse=LAG`` (``reuse_all=LAG``) solves each problem with the x-update's matrix ``K`` and the Ruiz scaling of
the same run's problem LAG control steps earlier (runs chained through their warm starts) and the exact rows'
Schur parts recomputed (also reused), factored with the current rho; ``reuse_fixed=LAG`` also with that problem's
rho, i.e. its factors as they were (nothing factored again: what a solver that skips the preparation and
factorization would do); ``reuse_kernel=LAG`` the same with the current exact rows in the step beside the old
``W`` and Schur factor (as the fused kernels would read them). The residuals are always the current problem's, so
the fixed point is unchanged; steps where a row changed kind (a foot touching down or lifting off) are counted
apart. On a CPU: a few minutes of compilation, then 1-3 min per variant.
"""

import dataclasses
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import wbc_jax.control.transport as transport
from wbc_jax.campaign.build import build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.qp import QPResult, admm, rules, solve_qp
from wbc_jax.qp.scaling import Scaled, equilibrate, factor, mv, regularize_schur, solve
from wbc_jax.qp.settings import BIG, FIRST_TEST_BLOCKS
from wbc_jax.rollout import simulate

FIELDS = ("P", "q", "A", "l", "u", "wx", "wz", "wy", "wrho", "x", "wk", "k", "flag")
SECONDS, CHUNK_S = 1.5, 0.5  # [s] simulated, and per chunk


def small_spec() -> Path:
    """The paper spec cut to 8 runs and SECONDS (chunks of CHUNK_S)."""
    text = Path("sweeps/paper_campaign.toml").read_text()
    for a, b in (("reps = 10", "reps = 1"),
                 ("chunk_seconds = 2.0", f"chunk_seconds = {CHUNK_S}\nmax_seconds = {SECONDS}"),
                 ("m = [0.2, 0.3, 0.4]", "m = [0.2, 0.4]"), ("mu = [0.4, 0.7, 1.0]", "mu = [0.4, 1.0]"),
                 ("d = [0.06, 0.08, 0.10]", "d = [0.06, 0.10]")):
        text = text.replace(a, b)
    path = Path(tempfile.mkdtemp()) / "qp_study.toml"
    path.write_text(text)
    return path


def record(spec_path: Path, change: str = ""):
    """Every control step's QP (P, q, A, l, u), warm start (x, z, y, rho, the predecessor's iterations), solution,
    iterations and flag of the campaign's rollout, as host arrays with a leading axis over the solves, and the
    campaign's QP settings; ``change`` (``field=value,...``): the controller's QP settings changed so in the loop."""
    jax.clear_caches()  # a chunk program traced before would call back into an earlier record's list
    built = build(load_spec(spec_path))
    sim = built.sim
    if change:
        cfg = dataclasses.replace(sim.cfg, qp=parse(change, sim.cfg.qp)[0])
        sim = dataclasses.replace(sim, controller=type(sim.controller)(cfg))
    rows, factored, solve = [], [], transport.solve_qp

    def recording_solve(P, q, A, l, u, warm=None, settings=None):
        res = solve(P, q, A, l, u, warm=warm, settings=settings)
        jax.debug.callback(lambda *a: rows.append([np.array(v) for v in a]), P, q, A, l, u, warm.x, warm.z,
                           warm.y, warm.rho, res.x, warm.iters, res.iters, res.flag)
        if res.factors is not None:  # QPSettings.reuse_factors: whether the solve factored
            jax.debug.callback(lambda f: factored.append(np.array(f)), res.factors.fresh)
        return res

    transport.solve_qp = recording_solve
    try:
        b = built.batch
        if change:  # the changed controller's first warm start, as its init makes it: its rho (carried from step to
            # step where rho is not adapted) and, where the solver reuses them, empty QP factors
            warm = b.state.cs.warm
            warm = warm._replace(rho=jnp.full_like(warm.rho, sim.cfg.qp.rho))
            factors = transport.initial_factors(sim.cfg)
            if factors is not None:
                warm = warm._replace(factors=jax.tree_util.tree_map(
                    lambda a: jnp.broadcast_to(a, (warm.x.shape[0],) + a.shape), factors))
            b = b._replace(state=b.state._replace(cs=b.state.cs._replace(warm=warm)))
        simulate(sim, b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground, SECONDS,
                 CHUNK_S)
    finally:
        transport.solve_qp = solve
    qp = transport.qp_settings(sim.cfg)  # the settings the controller solves with
    skip = 10 * built.design.n  # the standing start's first steps
    out = {k: np.stack([r[i] for r in rows[skip:]]) for i, k in enumerate(FIELDS)}
    if factored:
        out["factored"] = np.stack(factored[skip:])
    return out, qp


def over_problems(one, problems: dict) -> tuple:
    """``one(P, q, A, l, u, wx, wz, wy, wrho)`` (one recorded problem and its warm start, float32) over every recorded
    problem (``jit`` of ``vmap``): its outputs as host arrays with a leading axis over the solves."""
    out = jax.jit(jax.vmap(one))(*(jnp.asarray(problems[k], jnp.float32) for k in FIELDS[:9]))
    return tuple(np.asarray(a) for a in out)


def iterations(problems: dict, settings, rho=None):
    """(iterations (N,), flags (N,)) of every recorded problem solved from its warm start under ``settings``."""
    def one(P, q, A, l, u, wx, wz, wy, wrho):
        warm_rho = wrho if rho is None else jnp.asarray(rho, wrho.dtype)
        res = solve_qp(P, q, A, l, u, warm=QPResult(wx, wy, wz, 0.0, 0.0, 0, 0, warm_rho), settings=settings)
        return res.iters, res.flag

    return over_problems(one, problems)


def _reused_solve(s, schur_fresh, old_rho, current_ae, cur, old):
    """ADMM iterations of problem ``cur`` (P, q, A, l, u, wx, wz, wy, wrho) with the scaling, row weights and
    factor of ``old`` (P, q, A, l, u, wy, wrho; with ``old_rho`` its rho too; with ``current_ae`` the step's exact
    rows are the current problem's, beside the old ``W`` and Schur factor, as the fused kernels would read them):
    (iterations, converged, same row kinds)."""
    P, q, A, l, u, wx, wz, wy, wrho = cur
    Po, qo, Ao, lo, uo, wyo, wrho_old = old
    l, u, lo, uo = (jnp.clip(v, -BIG, BIG) for v in (l, u, lo, uo))
    P, Po = 0.5 * (P + P.T), 0.5 * (Po + Po.T)
    spo = equilibrate(Po, qo, Ao, lo, uo, s.ruiz_iters)
    D, E, c = spo.D, spo.E, spo.c
    sp = Scaled(c * D[:, None] * P * D[None, :], c * D * q, E[:, None] * A * D[None, :], E * l, E * u, D, E, c)
    kinds, kinds_old = admm.row_kinds(sp, l, u, s), admm.row_kinds(spo, lo, uo, s)
    same = jnp.all(jnp.stack([jnp.all(a == b) for a, b in zip(kinds, kinds_old)]))
    free, eq, ex = kinds
    ne, rho = s.eq_rows, rules.warm_rho(wrho_old if old_rho else wrho, s, P.dtype)
    _, w_old = admm._start(spo, (wx, wz, wyo, None), kinds_old[1], kinds_old[0], kinds_old[2], s, P.dtype)
    st, _ = admm._start(sp, (wx, wz, wy, None), eq, free, ex, s, P.dtype)
    K0, G, Ae = admm._factor_parts(spo, w_old, kinds_old[0], kinds_old[2], s, ne)
    fac = factor(K0 + rho * G, s.linsolve)
    Ae, held = (sp.A[:ne] * ex[:ne, None], ex[:ne]) if schur_fresh else (Ae, kinds_old[2][:ne])
    W = solve(fac, Ae.T, s.linsolve)
    kkt = admm.KKT(fac, Ae, W, factor(regularize_schur(mv(Ae, W), held), s.linsolve))
    if current_ae:
        kkt = kkt._replace(Ae=sp.A[:ne] * ex[:ne, None])
    rho_v = rules.rho_vec(rho, w_old, free, s)
    body = lambda _, st: admm._step(sp, kkt, rho_v, ex, free, s, st)  # noqa: E731
    block = lambda st, n: jax.lax.fori_loop(0, n, body, admm._project(sp, kkt, ex, st, s.linsolve))  # noqa: E731
    done = lambda st: admm._unscaled(P, q, A, sp, st, s).converged  # noqa: E731
    st, k = jax.lax.while_loop(lambda c: (c[1] < s.max_iters) & ~done(c[0]) & ~c[0].bad,
                               lambda c: (block(c[0], s.check_every), c[1] + s.check_every),
                               (block(st, s.iters), jnp.int32(s.iters)))
    return k, done(st), same


def predecessors(problems: dict) -> np.ndarray:
    """(N,) each recorded solve's predecessor in its run (the solve whose solution is its warm start), -1 where
    none was recorded."""
    index = {problems["x"][i].tobytes(): i for i in range(len(problems["x"]))}
    return np.array([index.get(w.tobytes(), -1) for w in problems["wx"]])


def reused_iterations(problems: dict, settings, lag: int, schur_fresh: bool, old_rho: bool = False,
                      current_ae: bool = False):
    """(iterations, converged, same row kinds) of every problem with a predecessor ``lag`` steps back in its run,
    solved with that predecessor's scaling and factor (:func:`_reused_solve`)."""
    prev = predecessors(problems)
    old = np.arange(len(prev))
    for _ in range(lag):
        old = np.where(old >= 0, prev[np.maximum(old, 0)], -1)
    cur = np.nonzero(old >= 0)[0]
    s = settings._replace(linsolve="chol")
    fn = jax.jit(jax.vmap(lambda c, o: _reused_solve(s, schur_fresh, old_rho, current_ae, c, o)))
    out = fn(tuple(jnp.asarray(problems[k][cur], jnp.float32) for k in FIELDS[:9]),
             tuple(jnp.asarray(problems[k][old[cur]], jnp.float32) for k in ("P", "q", "A", "l", "u", "wy", "wrho")))
    return tuple(np.asarray(a) for a in out)


def first_blocks(wk, settings) -> np.ndarray:
    """(N,) each solve's iterations before its first convergence test under ``settings``, from its predecessor's
    iterations ``wk`` (N,): :func:`wbc_jax.qp.rules.first_block`, or ``iters`` where that setting is off."""
    first = rules.first_block((None,) * 4 + (jnp.asarray(wk, jnp.int32),), settings, settings.iters)
    return np.full(np.shape(wk), settings.iters) if first is None else np.asarray(first)


def first_test(problems: dict, settings, lead: int) -> None:
    """Print the iterations and convergence tests per solve when the first test comes at the previous solve's
    iterations (under ``settings``, tested after ``iters``) minus ``lead`` (whole blocks of ``check_every`` from
    ``iters``, at most FIRST_TEST_BLOCKS blocks more: :func:`wbc_jax.qp.rules.first_block`) instead of after
    ``iters``. Their time per solve on a GPU:
    ``examples/qp_kernel_noisy.py`` with ``warm_first_test=LEAD``."""
    ce = settings.check_every
    firsts = tuple(settings.iters + b * ce for b in range(FIRST_TEST_BLOCKS + 1))
    its = {f: iterations(problems, settings._replace(iters=f))[0] for f in firsts}
    pred = predecessors(problems)  # the predecessor's iterations under these settings where it was recorded
    prev = np.where(pred >= 0, its[settings.iters][np.maximum(pred, 0)], problems["wk"]).astype(int)
    want = first_blocks(prev, settings._replace(warm_first_test=lead))
    it = np.choose(np.searchsorted(firsts, want), [its[f] for f in firsts])
    rows = (("test after iters", its[settings.iters], settings.iters), (f"first test lead={lead}", it, want))
    for name, k, f in rows:
        tests = 1 + (k - f) // ce
        print(f"{name:32s} iterations mean {k.mean():6.2f}  tests {tests.mean():5.2f}", flush=True)


def parse(variant: str, settings) -> tuple:
    """``"field=value,field=value"`` as (changed settings, rho or None)."""
    change = {}
    for item in filter(None, variant.split(",")):
        key, value = item.split("=")
        current = getattr(settings, key)
        change[key] = value if isinstance(current, str) else type(current)(float(value))
    return settings._replace(**change), change.get("rho")


if __name__ == "__main__":
    problems, base = record(small_spec())
    print(f"{len(problems['P'])} recorded solves")
    for variant in ["", *sys.argv[1:]]:
        if variant.startswith("closed:"):  # the rollout again with the variant in its loop
            closed, qp = record(small_spec(), variant[len("closed:"):])
            it, flag, ce = closed["k"].astype(int), closed["flag"], qp.check_every
            tests = 1 + np.maximum(it - first_blocks(closed["wk"], qp), 0) // ce
            print(f"{variant:32s} iterations mean {it.mean():6.2f}  p50 {np.median(it):3.0f}  p90 "
                  f"{np.percentile(it, 90):3.0f}  p99 {np.percentile(it, 99):3.0f}  max {it.max():3d}  flagged "
                  f"{int((flag != 0).sum())}  tests {tests.mean():5.2f}  (closed loop, {len(it)} solves"
                  + (f", {closed['factored'].mean():.1%} factored)" if "factored" in closed else ")"), flush=True)
            continue
        if "first_test=" in variant:  # with other fields: e.g. alpha=1.3,first_test=0
            rest = [item for item in variant.split(",") if not item.startswith("first_test=")]
            lead = int(variant.split("first_test=")[1].split(",")[0])
            print(f"-- {variant}", flush=True)
            first_test(problems, parse(",".join(rest), base)[0], lead)
            continue
        if variant.startswith("reuse"):
            lag = int(variant.split("=")[1])
            it, conv, same = reused_iterations(problems, base, lag, schur_fresh=variant.startswith("reuse="),
                                               old_rho=variant.startswith(("reuse_fixed=", "reuse_kernel=")),
                                               current_ae=variant.startswith("reuse_kernel="))
            print(f"{variant:32s} iterations mean {it.mean():6.2f} (row kinds unchanged: {it[same].mean():6.2f}, "
                  f"{same.mean():.1%} of solves)  p99 {np.percentile(it, 99):3.0f}  unconverged "
                  f"{int((~conv).sum())} ({int((~conv & same).sum())} with unchanged kinds)", flush=True)
            continue
        settings, rho = parse(variant, base)
        it, flag = iterations(problems, settings, rho)
        print(f"{variant or 'campaign settings':32s} iterations mean {it.mean():6.2f}  p50 {np.median(it):3.0f}  "
              f"p90 {np.percentile(it, 90):3.0f}  p99 {np.percentile(it, 99):3.0f}  max {it.max():3d}  "
              f"flagged {int((flag != 0).sum())}", flush=True)
