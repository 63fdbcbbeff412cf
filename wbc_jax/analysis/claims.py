"""The transport paper's claims about its factors, answered from a results table.

Each claim is a row (:data:`CLAIMS`) answered from the runs of one table when the factor it is about is varied
there (else "not tested: <factor> is not varied"):

- **"a larger mu is always beneficial"**: per region (a combination of the other varied factors' levels, pooled
  over repetitions) and per pair of adjacent mu levels, the larger mu is *worse* where its success rate is lower
  with Fisher's exact p < alpha, or its max slip is larger with a Mann-Whitney p < alpha (two-sided; Bonferroni over
  the comparisons). The claim
  holds where no region is worse and, pooled over regions, success does not fall and max slip does not rise with mu.
- **"heavier objects are harder"**: pooled over the other factors, success rate (Fisher, lightest against
  heaviest level) and the Spearman rank correlation of m with max slip and T (all runs with finite values). Holds
  where a heavier object lowers success or raises slip or T significantly, and nothing goes the other way.
- **"the effect of d is mostly negligible"**: the share of each metric's variance (R, T, S over successful runs)
  that d's level means explain (eta^2 of a one-way layout) and the Kruskal-Wallis p. Not negligible for a metric
  where eta^2 >= :data:`NEGLIGIBLE_ETA2` and p < alpha (with many runs a tiny effect is significant, so p alone
  does not decide).

Plain pandas and scipy (no JAX).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from wbc_jax.analysis.table import success_column

NEGLIGIBLE_ETA2 = 0.01  # share of a metric's variance below which a factor's effect is called negligible
CLAIMS = {
    "mu": "a larger mu is always beneficial",
    "m": "heavier objects are harder",
    "d": "the effect of d is mostly negligible",
}
COLUMNS = ["claim", "factor", "answer", "evidence"]


def _num(df: pd.DataFrame, col: str) -> np.ndarray:
    return pd.to_numeric(df[col], errors="coerce").to_numpy(float) if col in df else np.full(len(df), np.nan)


def _median(x: np.ndarray) -> float:
    """Median of the finite values; NaN when there are none."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else np.nan


def _fisher(a_ok: np.ndarray, b_ok: np.ndarray) -> float:
    from scipy import stats as sps

    return float(sps.fisher_exact([[a_ok.sum(), (~a_ok).sum()], [b_ok.sum(), (~b_ok).sum()]])[1])


def _mwu(a: np.ndarray, b: np.ndarray) -> float:
    from scipy import stats as sps

    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if not len(a) or not len(b) or (np.ptp(np.concatenate([a, b])) == 0):
        return np.nan
    return float(sps.mannwhitneyu(a, b, alternative="two-sided").pvalue)


def mu_worse_regions(df: pd.DataFrame, factors, alpha: float) -> pd.DataFrame:
    """Per region and adjacent pair of mu levels (lower, higher): success rates, median max slips, Fisher's and
    Mann-Whitney's p (unadjusted), and ``worse``: the higher mu is significantly worse (module docstring)."""
    ok, slip = success_column(df).to_numpy(), _num(df, "max_slip_mm")
    mus = np.sort(pd.unique(df["mu"]))
    others = [f for f in factors if f != "mu" and df[f].nunique() > 1]
    groups = df.groupby(others, sort=True).indices if others else {(): np.arange(len(df))}
    rows = []
    for key, idx in groups.items():
        for lo, hi in zip(mus[:-1], mus[1:]):
            a = idx[df["mu"].to_numpy()[idx] == lo]
            b = idx[df["mu"].to_numpy()[idx] == hi]
            if not len(a) or not len(b):
                continue
            rows.append([key, lo, hi, ok[a].mean(), ok[b].mean(), _median(slip[a]), _median(slip[b]),
                         _fisher(ok[b], ok[a]), _mwu(slip[b], slip[a])])
    t = pd.DataFrame(rows, columns=["region", "mu_lo", "mu_hi", "rate_lo", "rate_hi", "slip_lo", "slip_hi",
                                    "fisher_p", "mwu_p"])
    k = max(len(t), 1)  # Bonferroni over the comparisons: many regions would otherwise find chance reversals
    worse_ok = (t["rate_hi"] < t["rate_lo"]) & (np.minimum(t["fisher_p"] * k, 1.0) < alpha)
    worse_slip = (t["slip_hi"] > t["slip_lo"]) & (np.minimum(t["mwu_p"] * k, 1.0) < alpha)
    return t.assign(worse=worse_ok | worse_slip)


def _mu_claim(df: pd.DataFrame, factors, alpha: float) -> tuple[str, str]:
    t = mu_worse_regions(df, factors, alpha)
    ok, slip, mu = success_column(df).to_numpy(), _num(df, "max_slip_mm"), df["mu"].to_numpy(float)
    levels = np.sort(np.unique(mu))
    rates = [ok[mu == v].mean() for v in levels]
    slips = [_median(slip[mu == v]) for v in levels]
    r_med = [_median(_num(df, "R")[(mu == v) & ok]) for v in levels]
    pooled = ", ".join(f"mu {v:g}: {r:.0%} succeed, median max slip {s:.3g} mm, median R {q:.4g}"
                       for v, r, s, q in zip(levels, rates, slips, r_med))
    worse = t[t["worse"]]
    evidence = f"{pooled}; {len(worse)} of {len(t)} (region, adjacent mu pair) comparisons with the larger mu worse"
    if len(worse):
        r = worse.iloc[0]
        evidence += (f" (e.g. {r.region}: mu {r.mu_lo:g} -> {r.mu_hi:g}, success {r.rate_lo:.0%} -> {r.rate_hi:.0%}, "
                     f"median slip {r.slip_lo:.3g} -> {r.slip_hi:.3g} mm)")
    monotone = all(np.diff(rates) >= 0) and not np.any(np.diff(slips) > 0)  # NaN (no slip column): success only
    answer = "contradicted" if len(worse) else ("holds" if monotone else "not always (pooled trend not monotone)")
    return answer, evidence


def _spearman(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    from scipy import stats as sps

    keep = np.isfinite(x) & np.isfinite(y)
    if keep.sum() < 3 or np.ptp(y[keep]) == 0:
        return np.nan, np.nan
    res = sps.spearmanr(x[keep], y[keep])
    return float(res.statistic), float(res.pvalue)


def _m_claim(df: pd.DataFrame, alpha: float) -> tuple[str, str]:
    ok, m = success_column(df).to_numpy(), df["m"].to_numpy(float)
    lo, hi = m.min(), m.max()
    p_ok = _fisher(ok[m == hi], ok[m == lo])
    harder, easier, parts = [], [], []
    d_rate = ok[m == hi].mean() - ok[m == lo].mean()
    parts.append(f"success {ok[m == lo].mean():.0%} (m {lo:g}) vs {ok[m == hi].mean():.0%} (m {hi:g}), "
                 f"Fisher p = {p_ok:.3g}")
    if p_ok < alpha:
        (harder if d_rate < 0 else easier).append("success")
    for col, name in (("max_slip_mm", "max slip"), ("T", "T")):
        rho, p = _spearman(m, _num(df, col))
        parts.append(f"Spearman rho(m, {name}) = {rho:.3g}, p = {p:.3g}")
        if np.isfinite(p) and p < alpha:
            (harder if rho > 0 else easier).append(name)
    answer = ("holds" if harder and not easier else "contradicted" if easier and not harder
              else "mixed" if harder else "no significant effect")
    return answer, "; ".join(parts)


def eta_squared(y: np.ndarray, groups: np.ndarray) -> float:
    """Share of the variance of ``y`` explained by the group means (one-way layout): SS_between / SS_total."""
    keep = np.isfinite(y)
    y, groups = y[keep], groups[keep]
    total = float(np.sum((y - y.mean()) ** 2))
    if total == 0:
        return 0.0
    between = sum(float(np.sum(groups == g)) * (y[groups == g].mean() - y.mean()) ** 2 for g in np.unique(groups))
    return between / total


def _d_claim(df: pd.DataFrame, alpha: float) -> tuple[str, str]:
    from scipy import stats as sps

    ok = success_column(df).to_numpy()
    d = df["d"].to_numpy(float)[ok]
    parts, large = [], []
    for col in ("R", "T", "S"):
        if col not in df:
            continue
        y = _num(df, col)[ok]
        eta = eta_squared(y, d)
        samples = [y[(d == v) & np.isfinite(y)] for v in np.unique(d)]
        finite = y[np.isfinite(y)]
        testable = all(len(s) for s in samples) and finite.size > 0 and np.ptp(finite) > 0
        p = float(sps.kruskal(*samples).pvalue) if testable else np.nan
        parts.append(f"{col}: eta^2 = {eta:.3g}, Kruskal-Wallis p = {p:.3g}")
        if eta >= NEGLIGIBLE_ETA2 and p < alpha:
            large.append(col)
    answer = "holds" if not large else f"contradicted for {', '.join(large)}"
    return answer, "; ".join(parts) + f" (not negligible: eta^2 >= {NEGLIGIBLE_ETA2:g} with p < {alpha:g})"


def answer_claims(df: pd.DataFrame, factors, alpha: float = 0.05) -> pd.DataFrame:
    """One row per claim of :data:`CLAIMS`: claim, factor, answer, evidence (:data:`COLUMNS`)."""
    rows = []
    for factor, claim in CLAIMS.items():
        if factor not in factors or factor not in df or df[factor].nunique() < 2:
            rows.append([claim, factor, "not tested", f"{factor} is not varied in this table"])
            continue
        if factor == "mu":
            answer, evidence = _mu_claim(df, factors, alpha)
        elif factor == "m":
            answer, evidence = _m_claim(df, alpha)
        else:
            answer, evidence = _d_claim(df, alpha)
        rows.append([claim, factor, answer, evidence])
    return pd.DataFrame(rows, columns=COLUMNS)
