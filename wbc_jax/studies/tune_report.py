"""Outputs of ``wbc-jax tune``: leaderboard rows and ranking, per-run tables, figures, and the paired comparison
of the tuned gains against the default gains on the same runs (``report.md``).

Paired comparison (:func:`paired_comparison`): the best candidate and the default gains are rolled out on the
same runs (same cells, seeds and perturbations); every metric is compared run by run:

* success: exact McNemar test (``scipy.stats.binomtest`` on the discordant pairs, two-sided);
* per-run objective J_i (:func:`wbc_jax.studies.tune_eval.per_run_objective`), R / atan(mu)^2, S, T [mm], over
  the runs both gain sets complete: Wilcoxon signed-rank test of the differences tuned - default
  (``scipy.stats.wilcoxon``, two-sided, zero differences dropped) and, next to it, the paired t test
  (``scipy.stats.ttest_rel``). A metric counts as improved when the Wilcoxon p < alpha and the mean difference
  points the metric's better way (higher J, R, S; lower T).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wbc_jax.studies.tune_eval import per_run_objective
from wbc_jax.studies.tune_search import pareto_mask, rank_key

SUMMARY = ("round", "slot", "kind", "sim_s", "objective", "R", "R_norm", "S", "S_norm", "T_mm", "success_rate",
           "violation", "feasible")
BETTER = {"J": 1, "R_norm": 1, "S": 1, "T_mm": -1}


def row_key(row: dict) -> tuple:
    """Ranking of leaderboard rows, larger is better: longer simulated horizon first (successive halving's
    early rungs are not comparable with the full runs), then :func:`rank_key`."""
    return (float(row["sim_s"]),) + rank_key(row["feasible"], row["violation"], row["objective"])


def make_rows(r: int, x: np.ndarray, kinds: list, space, sc: dict, sim_s: float, slots=None) -> list[dict]:
    """Leaderboard rows of round r (0-based) for the scored candidates (padding left out).

    Args:
        x: (C, k) candidates; kinds: (C,) labels; space: the search Space; sc: :func:`score` of these candidates;
        sim_s: simulated time per run [s] they were scored at; slots: (C,) slot numbers (default 0..C-1).
    """
    mult = space.multipliers(x)
    base = space.base._asdict()
    rows = []
    for i, kind in enumerate(kinds):
        if kind == "padding":
            continue
        row = dict(round=r + 1, slot=int(i if slots is None else slots[i]), kind=kind, sim_s=float(sim_s))
        for n in space.names:
            row[f"{n}_x"] = float(mult[n][i])
            row[n] = float(np.ravel(base[n])[0] * mult[n][i])
        row.update({k: (bool(v[i]) if k == "feasible" else float(v[i])) for k, v in sc.items()})
        rows.append(row)
    return rows


def leaderboard(rows: list[dict]):
    """DataFrame of all rows with ``rank`` (1 = best, :func:`row_key`) and ``pareto`` (front of (R_norm, S, -T)
    over the feasible rows scored at the full horizon)."""
    import pandas as pd

    df = pd.DataFrame(rows)
    order = sorted(range(len(rows)), key=lambda i: row_key(rows[i]), reverse=True)
    df["rank"] = 0
    df.loc[order, "rank"] = np.arange(1, len(rows) + 1)
    full = df.sim_s.to_numpy() >= df.sim_s.max() - 1e-9
    feas = df.feasible.to_numpy(bool) & full
    pm = np.zeros(len(df), bool)
    if feas.any():
        pm[feas] = pareto_mask(np.stack([df.R_norm[feas], df.S[feas], -df.T_mm[feas]], axis=1))
    df["pareto"] = pm
    return df


def runs_table(ev, per_run: dict, obj: dict):
    """Per-run metrics of the gain sets in ``per_run`` (name -> per-run dict (n,)) on the evaluator's runs."""
    import pandas as pd

    return pd.concat([pd.DataFrame(dict(
        candidate=who, m=ev.m, mu=ev.mu, d=ev.d, rep=ev.rep, seed=ev.seeds, success=v["success"], R=v["R"],
        R_norm=v["R"] / np.arctan(ev.mu) ** 2, S=v["S"], T_mm=v["T"] * 1e3,
        J=per_run_objective({k: np.asarray(v[k])[None] for k in ("R", "S", "T")}, ev.mu, obj)[0],
        max_slip_mm=v["max_slip_mm"], fell=v["fell"], dropped=v["dropped"], final_err_mm=v["final_err_mm"],
        fail_reason=v["fail_reason"])) for who, v in per_run.items()])


def paired_comparison(default: dict, tuned: dict, mu: np.ndarray, obj: dict, alpha: float) -> list[dict]:
    """Run-by-run comparison of two gain sets on the same runs (module docstring).

    Args:
        default, tuned: per-run metrics (n,) each (success, R, S, T); mu: (n,) tray friction; obj: [objective];
        alpha: significance level.

    Returns:
        One dict per metric: metric, test, n (pairs), default, tuned (means), diff (mean tuned - default), p
        (the named test's two-sided p), p_ttest (paired t, NaN for success), improved, worse (bool).
    """
    from scipy import stats

    ok_d, ok_t = np.asarray(default["success"], bool), np.asarray(tuned["success"], bool)
    b, c = int((ok_t & ~ok_d).sum()), int((ok_d & ~ok_t).sum())
    p = stats.binomtest(b, b + c, 0.5).pvalue if b + c else 1.0
    out = [dict(metric="success", test="exact McNemar (binomial test on discordant pairs)", n=len(ok_d),
                default=float(ok_d.mean()), tuned=float(ok_t.mean()), diff=float(ok_t.mean() - ok_d.mean()),
                p=float(p), p_ttest=float("nan"), improved=bool(p < alpha and b > c), worse=bool(p < alpha and c > b))]
    both = ok_d & ok_t

    def per_run(v):
        return dict(J=per_run_objective({k: np.asarray(v[k], float)[None] for k in ("R", "S", "T")}, mu, obj)[0],
                    R_norm=np.asarray(v["R"], float) / np.arctan(mu) ** 2, S=np.asarray(v["S"], float),
                    T_mm=np.asarray(v["T"], float) * 1e3)

    pd_, pt = per_run(default), per_run(tuned)
    for k, sign in BETTER.items():
        a, t = pd_[k][both], pt[k][both]
        diff = t - a
        if len(diff) >= 2 and np.any(diff != 0):
            p = float(stats.wilcoxon(t, a, zero_method="wilcox", alternative="two-sided").pvalue)
            p_t = float(stats.ttest_rel(t, a).pvalue)
        else:
            p, p_t = 1.0, float("nan")
        md = float(diff.mean()) if len(diff) else float("nan")
        out.append(dict(metric=k, test="Wilcoxon signed-rank (two-sided)", n=int(both.sum()),
                        default=float(a.mean()) if len(a) else float("nan"),
                        tuned=float(t.mean()) if len(t) else float("nan"), diff=md, p=p, p_ttest=p_t,
                        improved=bool(p < alpha and sign * md > 0), worse=bool(p < alpha and sign * md < 0)))
    return out


def report_md(title: str, lines: list[str], comparison: list[dict] | None, where: str, alpha: float) -> str:
    """report.md: a header, free lines and the paired-comparison table (if any)."""
    out = [f"# {title}", ""] + lines + [""]
    if comparison:
        out += [f"## Tuned (best_gains.toml) vs default gains, paired per run ({where})", "",
                "Tests: success by the exact McNemar test (binomial test on the runs where exactly one gain set "
                "succeeds); the per-run objective J and the metrics over the runs both complete by the **Wilcoxon "
                "signed-rank test** (scipy.stats.wilcoxon, two-sided, zero differences dropped), the paired t test "
                f"(scipy.stats.ttest_rel) beside it. alpha = {alpha}.", "",
                "| metric | test | pairs | default | tuned | tuned - default | p | p (paired t) | verdict |",
                "|---|---|---|---|---|---|---|---|---|"]
        for r in comparison:
            verdict = "improved" if r["improved"] else ("worse" if r["worse"] else "no significant difference")
            out.append(f"| {r['metric']} | {r['test']} | {r['n']} | {r['default']:.4g} | {r['tuned']:.4g} | "
                       f"{r['diff']:+.4g} | {r['p']:.3g} | {r['p_ttest']:.3g} | {verdict} |")
        out.append("")
    return "\n".join(out)
# ---------------------------------------------------------------- outputs


def figures(df, best_idx: int) -> dict[str, bytes]:
    """PNG bytes of ``objective_per_round.png`` and ``pareto.png`` from the leaderboard ``df`` (row 0: the start;
    ``best_idx``: the row of rank 1)."""
    from matplotlib.figure import Figure

    from wbc_jax.analysis.figures import _png

    out = {}
    fig = Figure(figsize=(6.4, 4.0), layout="constrained")
    ax = fig.subplots()
    feas = df.feasible.to_numpy(bool)
    jit = (np.random.default_rng(0).random(len(df)) - 0.5) * 0.25
    ax.scatter(df["round"][~feas] + jit[~feas], df.objective[~feas], s=10, c="0.7", marker="x", label="infeasible")
    ax.scatter(df["round"][feas] + jit[feas], df.objective[feas], s=12, c="tab:blue", label="feasible")
    rounds = np.sort(df["round"].unique())
    top = [df[df["round"] == r].sort_values("rank").iloc[0] for r in rounds]  # each round's best by rank
    so_far = [df[df["round"] <= r].sort_values("rank").iloc[0] for r in rounds]
    ax.plot(rounds, [t.objective for t in top], "-", c="tab:red", lw=1.5, label="round best (filled: feasible)")
    ax.scatter(rounds, [t.objective for t in top], s=30, c=["tab:red" if t.feasible else "white" for t in top],
               edgecolors="tab:red", zorder=3)
    ax.plot(rounds, [t.objective for t in so_far], "--", c="k", lw=1, label="best so far (by rank)")
    ax.set_xticks(rounds)
    st = df.iloc[0]
    ax.axhline(st.objective, c="tab:orange", lw=1, ls=":",
               label=f"start ({'feasible' if st.feasible else 'infeasible'})")
    ax.set_xlabel("round")
    ax.set_ylabel("objective J")
    ax.set_title("objective per round")
    ax.legend(fontsize=7)
    out["objective_per_round.png"] = _png(fig)

    fig = Figure(figsize=(6.4, 4.6), layout="constrained")
    ax = fig.subplots()
    ax.scatter(df.R_norm[~feas], df.S[~feas], s=8, c="0.8", marker="x", label="infeasible")
    if feas.any():
        sc = ax.scatter(df.R_norm[feas], df.S[feas], s=14, c=df.T_mm[feas], cmap="viridis", label="feasible")
        fig.colorbar(sc, ax=ax, label="mean T [mm]")
        front = df[df.pareto.to_numpy(bool)].sort_values("R_norm")
        ax.plot(front.R_norm, front.S, "o", mfc="none", mec="tab:red", ms=8, label="Pareto front (R, S, T)")
        b = df.iloc[best_idx]
        ax.plot([b.R_norm], [b.S], "*", c="tab:red", ms=14, label="best J")
    ax.plot([st.R_norm], [st.S], "s", mfc="none", mec="tab:orange", ms=9, label="start")
    ax.set_xlabel("mean R / atan(mu)^2")
    ax.set_ylabel("mean S [s^2/m]")
    ax.set_title("candidates: robustness vs smoothness (colour: tracking T)")
    ax.legend(fontsize=7)
    out["pareto.png"] = _png(fig)
    return out


def compare_replay(tune_dir: str, campaign_dir: str) -> str:
    """Paired comparison of a ``wbc-jax campaign --gains best_gains.toml`` replay (``campaign_dir/results.csv``)
    with the default gains of the tuning's confirmation (``tune_dir/confirm_runs.csv``) on the same seeds, with
    the tuning's objective and alpha. Returns the markdown table (as in report.md).

    Raises:
        WbcJaxError: a missing file, or runs that do not pair up (another campaign spec).
    """
    import json

    import pandas as pd

    from wbc_jax.errors import WbcJaxError

    tune_dir, campaign_dir = Path(tune_dir), Path(campaign_dir)
    try:
        man = json.loads((tune_dir / "manifest.json").read_text())
        conf = pd.read_csv(tune_dir / "confirm_runs.csv")
        res = pd.read_csv(campaign_dir / "results.csv")
    except (OSError, ValueError) as e:
        raise WbcJaxError(f"cannot read the tuning or campaign outputs: {e}") from None
    d = conf[conf.candidate == "default"]
    both = d.merge(res, on=["m", "mu", "d", "rep", "seed"], suffixes=("_d", ""))
    if len(both) != len(d) or len(both) != len(res):
        raise WbcJaxError(f"{campaign_dir / 'results.csv'}: {len(res)} runs, {len(both)} pair with the "
                          f"{len(d)} default runs of {tune_dir / 'confirm_runs.csv'} (same campaign spec needed)")
    default = dict(success=both.success_d.to_numpy(bool), R=both.R_d.to_numpy(float), S=both.S_d.to_numpy(float),
                   T=both.T_mm.to_numpy(float) * 1e-3)
    tuned = dict(success=both.success.to_numpy(bool), R=both.R.to_numpy(float), S=both.S.to_numpy(float),
                 T=both["T"].to_numpy(float))
    alpha = man["spec"]["confirm"]["alpha"]
    cmp = paired_comparison(default, tuned, both.mu.to_numpy(float), man["objective"], alpha)
    return report_md("Replay of best_gains.toml vs the default gains", [
        f"Default gains: {tune_dir / 'confirm_runs.csv'}; tuned: {campaign_dir / 'results.csv'}; {len(both)} runs "
        "paired by seed."], cmp, man["confirmation"]["campaign"], alpha)


if __name__ == "__main__":  # python -m wbc_jax.studies.tune_report TUNE_DIR CAMPAIGN_DIR
    import sys

    print(compare_replay(*sys.argv[1:3]))
