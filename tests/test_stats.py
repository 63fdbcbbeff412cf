"""wbc_jax.analysis.stats against planted effects, hand-built sums of squares and hand-built EMMs.

Synthetic campaign (``planted``): the transport paper's 3x3x3 design (m, mu, d), REPS runs per cell,
y = EFFECT * (m main + mu main + mu:d interaction pattern) + N(0, SIGMA^2). With these sizes the noncentrality
of every planted term is >= 108, so a planted term is missed at alpha = 0.05 with probability < 2e-13 per data
set: finding them is deterministic. The null terms (d, m:mu, m:d) are rejected at rate alpha (the seed loops).
"""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps

from wbc_jax.analysis import stats
from wbc_jax.errors import InputError

LEVELS = {"m": [0.2, 0.3, 0.4], "mu": [0.4, 0.7, 1.0], "d": [0.06, 0.08, 0.10]}
FACTORS = list(LEVELS)
REPS = 4
SIGMA = 1.0
EFFECT = 1.5  # main-effect level offsets (-E, 0, +E); interaction E * INTER_PATTERN
INTER_PATTERN = np.array([[1, 0, -1], [0, 0, 0], [-1, 0, 1]])  # mu x d, rows and columns sum to 0
PLANTED = {"m", "mu", "mu:d"}
NULL_TERMS = {"d", "m:mu", "m:d"}
ALPHA = 0.05
N_SEEDS = 200
BAND = 0.999  # two-sided binomial band for false-positive counts
RTOL = 1e-8


def design(levels: dict = LEVELS, reps: int = REPS) -> pd.DataFrame:
    rows = list(itertools.product(*levels.values(), range(reps)))
    df = pd.DataFrame(rows, columns=[*levels, "rep"])
    df["seed"] = np.arange(len(df))
    df["success"] = True
    return df


def planted(seed: int, reps: int = REPS) -> pd.DataFrame:
    """The 3x3x3 campaign with planted m, mu and mu:d effects in R and pure noise in T."""
    df = design(reps=reps)
    rng = np.random.default_rng(seed)
    idx = {f: df[f].map({v: i for i, v in enumerate(LEVELS[f])}).to_numpy() for f in FACTORS}
    offs = np.array([-1.0, 0.0, 1.0])
    signal = EFFECT * (offs[idx["m"]] + offs[idx["mu"]] + INTER_PATTERN[idx["mu"], idx["d"]])
    df["R"] = 10.0 + signal + SIGMA * rng.standard_normal(len(df))
    df["T"] = 2.0 + SIGMA * rng.standard_normal(len(df))
    return df


def band(n: int, p: float = ALPHA) -> tuple[float, float]:
    lo, hi = sps.binom.ppf([(1 - BAND) / 2, (1 + BAND) / 2], n, p)
    return lo, hi


# --------------------------------------------------------------------------- planted effects


def test_planted_effects_found_exactly():
    # A fixed seed: with 3 null terms in R and 6 in the pure-noise T, about 1 - 0.95^9 = 37 %
    # of seeds show some false positive at alpha = 0.05 (seed 0 does: mu in T); seed 1 does
    # not. The rate itself is what the two seed-loop tests below measure.
    out = stats.analyze(planted(seed=1), FACTORS, ["R", "T"], alpha=ALPHA)
    assert set(out["metrics"]["R"]["significant"]) == PLANTED
    assert out["metrics"]["T"]["significant"] == []
    r = out["metrics"]["R"]
    # simple effects: both directions of the one significant interaction
    assert [(s["effect"], s["by"]) for s in r["simple_effects"]] == [("mu", "d"), ("d", "mu")]
    # planted mu offsets at d = 0.06, 0.08, 0.10: main (-E, 0, E) + pattern column = 0, (-E, 0, E), (-2E, 0, 2E)
    mu_by_d = r["simple_effects"][0]["tests"].set_index("d")
    assert mu_by_d.loc[0.08, "p"] < 1e-6 and mu_by_d.loc[0.10, "p"] < 1e-6
    assert mu_by_d.loc[0.10, "F"] > 2 * mu_by_d.loc[0.08, "F"] and mu_by_d.loc[0.06, "F"] < mu_by_d.loc[0.08, "F"] / 2


def test_planted_power_and_false_positive_rate_over_seeds():
    """Over N_SEEDS data sets: planted terms always found; null terms rejected at rate alpha."""
    false_pos = {t: 0 for t in NULL_TERMS}
    for seed in range(N_SEEDS):
        fit = stats.fit_anova(planted(seed + 1000), FACTORS, "R")
        sig = set(fit.significant(ALPHA))
        assert PLANTED <= sig, f"seed {seed}: planted term missed"
        for t in sig - PLANTED:
            false_pos[t] += 1
    total = sum(false_pos.values())
    lo, hi = band(N_SEEDS * len(NULL_TERMS))
    assert lo <= total <= hi, (total, lo, hi)
    lo1, hi1 = band(N_SEEDS)
    assert all(lo1 <= c <= hi1 for c in false_pos.values()), false_pos


def test_false_positive_rate_null_data():
    """Pure-noise data: each of the 6 terms is rejected in a fraction alpha of seeds."""
    counts = {}
    for seed in range(N_SEEDS):
        fit = stats.fit_anova(planted(seed + 5000), FACTORS, "T")
        for s in fit.significant(ALPHA):
            counts[s] = counts.get(s, 0) + 1
    total = sum(counts.values())
    lo, hi = band(N_SEEDS * 6)
    assert lo <= total <= hi, (total, lo, hi)
    lo1, hi1 = band(N_SEEDS)
    assert all(lo1 <= c <= hi1 for c in counts.values()), counts


# --------------------------------------------------------------------------- hand-built SS


def _random_factorial(seed: int, reps: int = 3) -> tuple[pd.DataFrame, np.ndarray, dict]:
    """A 2x3x4 design (one string factor) with random effects of every order; Y[a, b, c, r]."""
    lv = {"ctrl": ["qp", "admm"], "mu": [0.4, 0.7, 1.0], "d": [0.04, 0.06, 0.08, 0.1]}
    rng = np.random.default_rng(seed)
    shape = tuple(len(v) for v in lv.values())
    cell = rng.normal(size=shape) * 0.7 + rng.normal(size=shape[:1])[:, None, None]
    Y = cell[..., None] + rng.normal(size=(*shape, reps))
    rows = [(*[lv[f][i] for f, i in zip(lv, ix)], r, Y[(*ix, r)])
            for ix in itertools.product(*(range(n) for n in shape)) for r in range(reps)]
    df = pd.DataFrame(rows, columns=[*lv, "rep", "y"])
    df["success"] = True
    return df, Y, lv


def _hand_anova(Y: np.ndarray, order: int) -> dict:
    """Balanced-design ANOVA by sums of squares of marginal means (Y[a, b, c, r])."""
    A, B, C, R = Y.shape
    g = Y.mean()
    ma, mb, mc = Y.mean((1, 2, 3)), Y.mean((0, 2, 3)), Y.mean((0, 1, 3))
    mab, mac, mbc = Y.mean((2, 3)), Y.mean((1, 3)), Y.mean((0, 3))
    mabc = Y.mean(3)
    ss = {
        "ctrl": B * C * R * np.sum((ma - g) ** 2),
        "mu": A * C * R * np.sum((mb - g) ** 2),
        "d": A * B * R * np.sum((mc - g) ** 2),
        "ctrl:mu": C * R * np.sum((mab - ma[:, None] - mb[None, :] + g) ** 2),
        "ctrl:d": B * R * np.sum((mac - ma[:, None] - mc[None, :] + g) ** 2),
        "mu:d": A * R * np.sum((mbc - mb[:, None] - mc[None, :] + g) ** 2),
    }
    df = {"ctrl": A - 1, "mu": B - 1, "d": C - 1, "ctrl:mu": (A - 1) * (B - 1), "ctrl:d": (A - 1) * (C - 1),
          "mu:d": (B - 1) * (C - 1)}
    if order == 3:
        inter3 = (mabc - mab[:, :, None] - mac[:, None, :] - mbc[None, :, :] + ma[:, None, None]
                  + mb[None, :, None] + mc[None, None, :] - g)
        ss["ctrl:mu:d"] = R * np.sum(inter3 ** 2)
        df["ctrl:mu:d"] = (A - 1) * (B - 1) * (C - 1)
    sst = np.sum((Y - g) ** 2)
    sse = sst - sum(ss.values())
    dfe = Y.size - 1 - sum(df.values())
    mse = sse / dfe
    out = {s: {"sum_sq": ss[s], "df": df[s], "mean_sq": ss[s] / df[s], "F": ss[s] / df[s] / mse,
               "p": sps.f.sf(ss[s] / df[s] / mse, df[s], dfe), "partial_eta_sq": ss[s] / (ss[s] + sse)} for s in ss}
    out["Residual"] = {"sum_sq": sse, "df": dfe, "mean_sq": mse}
    return out


@pytest.mark.parametrize("order", [2, 3])
def test_anova_equals_hand_sums_of_squares(order):
    df, Y, lv = _random_factorial(seed=7)
    hand = _hand_anova(Y, order)
    for ss_type in (1, 2, 3):  # balanced: all types agree with the hand computation
        fit = stats.fit_anova(df, list(lv), "y", ss_type=ss_type, order=order)
        assert fit.reliable and fit.ss_type == stats.SS_NAMES[ss_type]
        t = fit.table.set_index("source")
        assert list(t.index) == list(hand)
        for src, row in hand.items():
            for key, val in row.items():
                np.testing.assert_allclose(t.loc[src, key], val, rtol=RTOL, err_msg=f"{ss_type} {src} {key}")


def test_type3_unbalanced_equals_restricted_model_comparison():
    """Unbalanced: type III SS of a term = SSE(full sum-coded model without its columns) - SSE(full)."""
    df, _, lv = _random_factorial(seed=3, reps=4)
    rng = np.random.default_rng(0)
    df = df.drop(index=rng.choice(len(df), size=20, replace=False))
    fit = stats.fit_anova(df, list(lv), "y", ss_type=3, order=2)
    assert any("unbalanced" in w for w in fit.warnings)

    def sum_code(col, levels):  # k-1 columns: e_i - e_last
        k = len(levels)
        idx = col.map({v: i for i, v in enumerate(levels)}).to_numpy()
        Z = np.zeros((len(col), k - 1))
        for i in range(k - 1):
            Z[:, i] = (idx == i).astype(float) - (idx == k - 1)
        return Z

    cols = {f: sum_code(df[f], lv[f]) for f in lv}
    blocks = {f: cols[f] for f in lv}
    for a, b in itertools.combinations(lv, 2):
        blocks[f"{a}:{b}"] = np.einsum("ni,nj->nij", cols[a], cols[b]).reshape(len(df), -1)
    y = df["y"].to_numpy()

    def sse(names):
        X = np.column_stack([np.ones(len(y))] + [blocks[n] for n in names])
        r = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
        return r @ r

    full = sse(list(blocks))
    t = fit.table.set_index("source")
    np.testing.assert_allclose(t.loc["Residual", "sum_sq"], full, rtol=RTOL)
    for name in blocks:
        np.testing.assert_allclose(t.loc[name, "sum_sq"], sse([n for n in blocks if n != name]) - full, rtol=1e-7)


# --------------------------------------------------------------------------- EMMs


def test_emm_differences_balanced_equal_hand_computation():
    df = planted(seed=11)
    fit = stats.fit_anova(df, FACTORS, "R", order=2)
    mse, dfe = fit.mse, fit.df_resid
    Y = df["R"].to_numpy().reshape(3, 3, 3, REPS)  # [m, mu, d, rep] by construction of design()
    hand = _hand_anova(Y, order=2)
    np.testing.assert_allclose(mse, hand["Residual"]["mean_sq"], rtol=RTOL)
    emm_hand = Y.mean(axis=(0, 3))  # [mu, d]: cell means averaged over m with equal weights
    nper = 3 * REPS  # runs behind one (mu, d) EMM

    emm = stats.emmeans(fit, ["mu", "d"])
    np.testing.assert_allclose(emm["emm"], emm_hand.ravel(), rtol=RTOL)
    np.testing.assert_allclose(emm["se"], np.sqrt(mse / nper), rtol=RTOL)
    tq = sps.t.ppf(0.975, dfe)
    np.testing.assert_allclose(emm["ci_high"] - emm["emm"], tq * np.sqrt(mse / nper), rtol=RTOL)

    se = stats.simple_effects(fit, effect="mu", by="d")
    pairs = se["pairs"]
    assert len(pairs) == 3 * 3
    tcrit = sps.t.ppf(1 - 0.05 / (2 * 3), dfe)  # Bonferroni, family of 3 per level of d
    for row in pairs.itertuples(index=False):
        c = LEVELS["d"].index(row.d)
        i, j = LEVELS["mu"].index(row.level_a), LEVELS["mu"].index(row.level_b)
        diff = emm_hand[i, c] - emm_hand[j, c]
        se_h = np.sqrt(mse * 2 / nper)
        p = 2 * sps.t.sf(abs(diff / se_h), dfe)
        np.testing.assert_allclose([row.diff, row.se, row.t, row.df], [diff, se_h, diff / se_h, dfe], rtol=RTOL)
        np.testing.assert_allclose([row.ci_low, row.ci_high], [diff - tcrit * se_h, diff + tcrit * se_h], rtol=RTOL)
        np.testing.assert_allclose([row.p_unadj, row.p_bonf], [p, min(1.0, 3 * p)], rtol=1e-6)
    # simple-effect F of mu at each d: between-level SS of the EMMs over the pooled MSE
    for row in se["tests"].itertuples(index=False):
        col = emm_hand[:, LEVELS["d"].index(row.d)]
        F = nper * np.sum((col - col.mean()) ** 2) / 2 / mse
        np.testing.assert_allclose([row.F, row.df1, row.df2], [F, 2, dfe], rtol=RTOL)
        np.testing.assert_allclose(row.p, sps.f.sf(F, 2, dfe), rtol=1e-6)


def test_emm_differences_unbalanced_saturated_equal_hand_computation():
    """Full-factorial (order 3) model on unbalanced data: EMMs are unweighted means of cell means,
    Var = MSE / k^2 * sum(1 / n_cell), MSE the pooled within-cell variance."""
    df = planted(seed=12, reps=5)
    rng = np.random.default_rng(1)
    drop = rng.choice(len(df), size=30, replace=False)
    df.loc[drop[:20], "success"] = False  # failures are excluded ...
    df = df.drop(index=drop[20:])  # ... and missing runs simply absent
    fit = stats.fit_anova(df, FACTORS, "R", order=3)
    ok = df[df["success"]]
    g = ok.groupby(FACTORS)["R"]
    assert g.size().min() >= 1 and g.size().nunique() > 1
    mse = ((ok["R"] - g.transform("mean")) ** 2).sum() / (len(ok) - 27)
    np.testing.assert_allclose(fit.mse, mse, rtol=RTOL)
    mean, n = g.mean(), g.size()
    pairs = stats.simple_effects(fit, effect="mu", by="d")["pairs"]
    for row in pairs.itertuples(index=False):
        ma = np.array([mean[(m, row.level_a, row.d)] for m in LEVELS["m"]])
        mb = np.array([mean[(m, row.level_b, row.d)] for m in LEVELS["m"]])
        na = np.array([n[(m, row.level_a, row.d)] for m in LEVELS["m"]])
        nb = np.array([n[(m, row.level_b, row.d)] for m in LEVELS["m"]])
        diff = ma.mean() - mb.mean()
        se = np.sqrt(mse / 9 * (np.sum(1 / na) + np.sum(1 / nb)))
        np.testing.assert_allclose([row.diff, row.se, row.df], [diff, se, len(ok) - 27], rtol=RTOL)


# --------------------------------------------------------------------------- guards


def test_deterministic_metric_is_flagged_not_crashed():
    df = planted(seed=2)
    df["S"] = df["m"] * 3 + df["mu"]  # no noise: zero within-cell variance, perfect additive fit
    df["K"] = 1.0  # constant
    df.loc[df.index[:5], "success"] = False  # and unbalanced
    out = stats.analyze(df, FACTORS, ["R", "S", "K"])
    for m in ("S", "K"):
        r = out["metrics"][m]
        assert not r["fit"].reliable and r["significant"] == [] and r["simple_effects"] == []
        assert any("F tests are unreliable" in w for w in r["warnings"])
        assert any("zero within-cell variance" in w for w in r["warnings"])
        assert all(a["ok"] is None for a in r["assumptions"])
    assert any("near-perfect fit" in w for w in out["metrics"]["S"]["warnings"])
    assert any("constant" in w for w in out["metrics"]["K"]["warnings"])
    assert out["metrics"]["R"]["fit"].reliable
    assert any("unbalanced" in w for w in out["metrics"]["R"]["warnings"])
    assert any("5 of 108 runs failed" in w for w in out["warnings"])


def test_some_zero_variance_cells_make_f_unreliable():
    df = planted(seed=4)
    cell = (df["m"] == 0.2) & (df["mu"] == 0.4) & (df["d"] == 0.06)
    df.loc[cell, "R"] = 5.0
    fit = stats.fit_anova(df, FACTORS, "R")
    assert not fit.reliable and fit.significant(ALPHA) == []
    assert any("1 of 27 cells have zero within-cell variance" in w for w in fit.warnings)


def test_empty_cell_is_reported():
    df = planted(seed=5)
    df = df[~((df["m"] == 0.4) & (df["mu"] == 1.0) & (df["d"] == 0.1))]
    out = stats.analyze(df, FACTORS, ["R"])
    assert any("1 of 27 cells have no runs" in w for w in out["warnings"])
    assert any("1 of 27 cells have no analysable runs" in w for w in out["metrics"]["R"]["warnings"])
    assert set(out["metrics"]["R"]["significant"]) >= PLANTED


def test_missing_values_and_empty_two_way_cell():
    """NaN metric values drop those runs; an empty m x mu cell makes its EMMs non-estimable, not a crash."""
    df = planted(seed=8)
    df = df[~((df["m"] == 0.2) & (df["mu"] == 0.4))].copy()
    df.loc[df.index[:3], "R"] = np.nan
    fit = stats.fit_anova(df, FACTORS, "R")
    assert fit.n == len(df) - 3
    assert any("3 successful run(s) have no R value" in w for w in fit.warnings)
    assert any("rank-deficient model" in w for w in fit.warnings)
    emm = stats.emmeans(fit, ["m", "mu"]).set_index(["m", "mu"])
    assert np.isnan(emm.loc[(0.2, 0.4), "emm"]) and np.isfinite(emm.drop(index=(0.2, 0.4))["emm"]).all()
    pairs = stats.simple_effects(fit, effect="m", by="mu")["pairs"]
    at = pairs[pairs["mu"] == 0.4]
    assert at[at["level_a"] == 0.2]["p_bonf"].isna().all() and at[at["level_a"] == 0.3]["p_bonf"].notna().all()


# --------------------------------------------------------------------------- tables


def test_design_table_and_cell_means():
    df = planted(seed=6)
    df.loc[[0, 1, 5], "success"] = False  # rows 0, 1: cell (0.2, 0.4, 0.06); row 5: (0.2, 0.4, 0.08)
    df = df.drop(index=[8, 9, 10, 11])  # cell (0.2, 0.4, 0.1) has no runs at all
    dt = stats.design_table(df, FACTORS).set_index(FACTORS)
    assert len(dt) == 27
    assert tuple(dt.loc[(0.2, 0.4, 0.06)]) == (4, 2, 2)
    assert tuple(dt.loc[(0.2, 0.4, 0.08)]) == (4, 3, 1)
    assert tuple(dt.loc[(0.2, 0.4, 0.1)]) == (0, 0, 0)
    cm = stats.cell_means(df, FACTORS, ["R", "T"])
    assert list(cm.columns) == [*FACTORS, "metric", "mean", "sd", "n"] and len(cm) == 54
    ok = df[df["success"]]
    ref = ok.groupby(FACTORS)["R"].agg(["mean", "std", "count"])
    got = cm[cm["metric"] == "R"].set_index(FACTORS)
    for key, row in ref.iterrows():
        np.testing.assert_allclose([got.loc[key, "mean"], got.loc[key, "sd"]], [row["mean"], row["std"]], rtol=1e-12)
        assert got.loc[key, "n"] == row["count"]
    assert got.loc[(0.2, 0.4, 0.1), "n"] == 0 and np.isnan(got.loc[(0.2, 0.4, 0.1), "mean"])
    allruns = stats.cell_means(df, FACTORS, ["R"], successful_only=False).set_index(FACTORS)
    assert allruns.loc[(0.2, 0.4, 0.06), "n"] == 4


def test_default_columns_rule():
    df = planted(seed=0)
    df["energy"] = 1.5
    df["slid"] = False  # boolean flag
    df["dropped"] = 0  # 0/1 integer flag
    df["flag_limit"] = 0.0
    df["Unnamed: 0"] = np.arange(len(df))
    df["controller"] = "qp"  # string column
    df["S"] = 0.3
    assert stats.infer_factors(df) == FACTORS
    assert stats.infer_metrics(df, FACTORS) == ["R", "T", "S", "energy"]
    assert stats.infer_metrics(df, FACTORS, ["energy"]) == ["energy"]


@pytest.mark.parametrize(
    "mutate, factors, metrics, match",
    [
        (lambda d: d, ["m", "mu", "x"], ["R"], "factor column 'x' is not in the table"),
        (lambda d: d, FACTORS, ["R", "Q"], "metric column 'Q' is not in the table"),
        (lambda d: d, FACTORS, ["m"], "both as a factor and as a metric"),
        (lambda d: d.assign(R=d["R"].astype(str).where(d.index != 3, "abc")), FACTORS, ["R"],
         "metric 'R' is not numeric \\(e.g. 'abc'\\)"),
        (lambda d: d.assign(d=0.06), FACTORS, ["R"], "factor 'd' has only one level"),
        (lambda d: d.assign(m=d["m"].where(d.index != 0)), FACTORS, ["R"], "factor 'm' has 1 empty value"),
        (lambda d: d.assign(success="maybe"), FACTORS, ["R"], "column 'success' is not boolean"),
        (lambda d: d.assign(R=np.inf), FACTORS, ["R"], "metric 'R' has 108 infinite"),
        (lambda d: d.iloc[:0], FACTORS, ["R"], "no rows"),
        (lambda d: d.drop(columns=FACTORS), None, ["R"], "no factor columns"),
    ],
)
def test_bad_input_raises_input_error(mutate, factors, metrics, match):
    df = mutate(planted(seed=0))
    with pytest.raises(InputError, match=match):
        f = stats.infer_factors(df, factors)
        stats.prepare(df, f, stats.infer_metrics(df, f, metrics))


def test_success_column_parsing():
    df = pd.DataFrame({"success": ["True", "false", "1", "0", "YES", "n"]})
    assert stats.success_column(df).tolist() == [True, False, True, False, True, False]
    assert stats.success_column(pd.DataFrame({"success": [1, 0]})).tolist() == [True, False]
    assert stats.success_column(pd.DataFrame({"x": [1, 2]})).tolist() == [True, True]


def test_all_failed_is_an_input_error():
    df = planted(seed=0).assign(success=False)
    with pytest.raises(InputError, match="no successful runs"):
        stats.analyze(df, FACTORS, ["R"])
