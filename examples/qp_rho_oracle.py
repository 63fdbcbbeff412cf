"""The transport QP's ADMM tail under the campaign's noise against the best fixed rho per problem.

    python examples/qp_rho_oracle.py

Every control-step QP of the paper campaign cut to 8 runs and 1.5 s (``qp_settings_study.record``) is solved again
from its recorded warm start with its own warm rho (the campaign's) and with each rho of a grid; a problem's best
rho is the grid's rho with the fewest iterations (converged solves only). The best-rho row is a lower bound for
what a rho re-estimated inside a long solve could reach: at a batch the device runs in one wave the step lasts as
long as its longest solve (about the 99.6th percentile of 270 solves). Also a rule that needs no re-estimate: the
grid's stiffer rho STIFF where the predecessor's iterations exceed LONG (a solve predicted long), the warm rho
elsewhere; a solve that re-estimates rho once (OSQP's rule, ``QPSettings.adapt_*``) after RESTART iterations where it
has not converged, refactors and goes on from its iterate, counting REFACTOR iterations for the refactorization;
and for each row the expected longest of 270 solves drawn at random (``longest of 270``). On a CPU: ~20 min.
"""

import sys

import numpy as np

from wbc_jax.qp import QPResult, solve_qp

sys.path.insert(0, "examples")
from qp_settings_study import iterations, over_problems, record, small_spec  # noqa: E402

GRID = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
STIFF, LONG = 4.0, 25  # the rule's rho and its threshold on the predecessor's iterations
RESTART, REFACTOR = 24, 10  # iterations before the one re-estimate; the refactorization's cost in iterations


def restarted(problems: dict, settings, it0: np.ndarray) -> np.ndarray:
    """(N,) iterations of each recorded problem when a solve still unconverged after RESTART iterations (``it0``:
    its iterations under ``settings``) re-estimates rho once, refactors (REFACTOR iterations' worth) and continues
    from its iterate under ``settings``; ``it0`` where it converged by then or rho did not change."""
    first = settings._replace(iters=RESTART, max_iters=RESTART, adapt_every=RESTART)

    def one(P, q, A, l, u, wx, wz, wy, wrho):
        r1 = solve_qp(P, q, A, l, u, warm=QPResult(wx, wy, wz, 0.0, 0.0, 0, 0, wrho), settings=first)
        r2 = solve_qp(P, q, A, l, u, warm=QPResult(r1.x, r1.y, r1.z, 0.0, 0.0, 0, 0, r1.rho), settings=settings)
        return r1.rho, r2.iters

    rho, it = over_problems(one, problems)
    wrho = np.asarray(problems["wrho"])
    again = (it0 > RESTART) & (np.abs(rho - wrho) > 1e-6 * np.abs(wrho))
    return np.where(again, RESTART + REFACTOR + it, it0)


def row(name: str, k: np.ndarray) -> None:
    draws = np.random.default_rng(0).integers(0, len(k), (4000, 270))  # random batches of 270 recorded solves
    longest = k[draws].max(axis=1).mean()
    print(f"{name:28s} mean {k.mean():6.2f} p50 {np.median(k):4.0f} p90 {np.percentile(k, 90):4.0f} "
          f"p99 {np.percentile(k, 99):4.0f} p99.6 {np.percentile(k, 99.6):4.0f} max {k.max()} "
          f"longest of 270 {longest:5.1f}", flush=True)


if __name__ == "__main__":
    problems, base = record(small_spec())
    print(f"{len(problems['P'])} recorded solves", flush=True)
    it0, _ = iterations(problems, base)
    per_rho, raw = [], []
    for rho in GRID:
        it, flag = iterations(problems, base, rho)
        per_rho.append(np.where(flag == 0, it, np.iinfo(np.int32).max))
        raw.append(it)
        print(f"rho {rho:5.2f}: mean {it.mean():6.2f} p99 {np.percentile(it, 99):4.0f} max {it.max()} "
              f"flagged {int((flag != 0).sum())}", flush=True)
    best = np.min(np.stack(per_rho), axis=0)
    row("warm rho (campaign)", it0)
    row("best rho per problem", best)
    row(f"rho {STIFF:g} where wk > {LONG}", np.where(np.asarray(problems["wk"]) > LONG, raw[GRID.index(STIFF)], it0))
    row(f"re-estimated at {RESTART} (+{REFACTOR})", restarted(problems, base, it0))
    tail = it0 >= np.percentile(it0, 99)
    print(f"the campaign's top 1 % ({int(tail.sum())} solves): {it0[tail].mean():.1f} iterations, "
          f"{best[tail].mean():.1f} at their best rho", flush=True)
