"""wbc_jax.analysis.sensitivity against statsmodels' ANOVA power and a Monte Carlo of the report's own F test."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from scipy import stats as sps
from statsmodels.stats.power import FTestAnovaPower
from test_stats import LEVELS, design, planted

from wbc_jax.analysis import report, sensitivity, stats


@pytest.mark.parametrize("f,nobs,k,alpha", [(0.25, 60, 3, 0.05), (0.1, 300, 4, 0.01), (0.5, 20, 2, 0.1)])
def test_power_equals_statsmodels_one_way(f, nobs, k, alpha):
    # one-way ANOVA: noncentrality nobs * f^2, df (k - 1, nobs - k)
    want = FTestAnovaPower().power(effect_size=f, nobs=nobs, alpha=alpha, k_groups=k)
    assert sensitivity.power(nobs * f * f, k - 1, nobs - k, alpha) == pytest.approx(want, rel=1e-10)
    lam = sensitivity.noncentrality(0.8, k - 1, nobs - k, alpha)
    f_needed = FTestAnovaPower().solve_power(effect_size=None, nobs=nobs, alpha=alpha, k_groups=k, power=0.8)
    assert np.sqrt(lam / nobs) == pytest.approx(f_needed, rel=1e-6)


def test_detected_at_the_stated_rate_by_the_reports_f_test():
    """The paper's 3 x 3 x 3 design, 3 runs per cell, the report's model (main effects + two-way interactions),
    noise SD 1: an m effect of exactly the detectable range (levels -r/2, 0, +r/2) is found in 80 % of data sets."""
    reps, sims, alpha = 3, 4000, 0.05
    df = design(reps=reps)
    n = len(df)
    k = len(LEVELS["m"])
    # the report's fit of one data set: its residual df and its F for m, reproduced by the projection below
    one = planted(seed=1, reps=reps)
    res = stats.analyze(stats.prepare(one, list(LEVELS), ["R"]), list(LEVELS), ["R"], alpha=alpha)
    fit = res["metrics"]["R"]["fit"]
    r = sensitivity.detectable_range(k, n, fit.df_resid, 1.0, alpha)
    x = _two_way_design(df)
    resid = np.eye(n) - x @ np.linalg.pinv(x)
    m_idx = df["m"].map({v: i for i, v in enumerate(LEVELS["m"])}).to_numpy()
    f_m = lambda y: _f_main(y, m_idx, k, resid, fit.df_resid)  # noqa: E731
    table = fit.table.set_index("source")
    assert f_m(one["R"].to_numpy()[:, None])[0] == pytest.approx(table.loc["m", "F"], rel=1e-9)
    rng = np.random.default_rng(7)
    y = np.array([-r / 2, 0.0, r / 2])[m_idx][:, None] + rng.standard_normal((n, sims))
    rate = np.mean(f_m(y) > sps.f.isf(alpha, k - 1, fit.df_resid))
    assert abs(rate - sensitivity.POWER) < 3.5 * np.sqrt(0.8 * 0.2 / sims), rate


def _two_way_design(df):
    """Sum-to-zero coded design matrix of main effects and two-way interactions (n x 19)."""
    cols = {}
    for f, levels in LEVELS.items():
        idx = df[f].map({v: i for i, v in enumerate(levels)}).to_numpy()
        cols[f] = [np.where(idx == j, 1.0, 0.0) - np.where(idx == len(levels) - 1, 1.0, 0.0)
                   for j in range(len(levels) - 1)]
    parts = [np.ones(len(df))] + [c for f in LEVELS for c in cols[f]]
    for a, b in itertools.combinations(LEVELS, 2):
        parts += [ca * cb for ca in cols[a] for cb in cols[b]]
    return np.column_stack(parts)


def _f_main(y, idx, k, resid, df2):
    """F of a main effect in a balanced design, column by column of y (n x sims)."""
    grand = y.mean(axis=0)
    means = np.stack([y[idx == i].mean(axis=0) for i in range(k)])
    ss = (len(y) / k) * ((means - grand) ** 2).sum(axis=0)
    sse = ((resid @ y) ** 2).sum(axis=0)
    return (ss / (k - 1)) / (sse / df2)


def test_the_report_states_its_sensitivity(tmp_path):
    df = planted(seed=3)
    df["S"] = 2.0 * df["m"] - df["d"]  # deterministic: unreliable F tests, no sensitivity
    csv = tmp_path / "results.csv"
    df.to_csv(csv, index=False)
    report.run_report(str(csv), str(tmp_path / "rep"), figures=False)
    summary = json.loads((tmp_path / "rep" / "anova.json").read_text())
    r = summary["metrics"]["R"]
    ranges = r["sensitivity"]["main_effect_range"]
    assert list(ranges) == list(LEVELS) and r["sensitivity"]["power"] == sensitivity.POWER
    want = sensitivity.detectable_range(3, r["n"], r["df_resid"], r["mse"], summary["alpha"])
    assert all(v == pytest.approx(want, rel=1e-12) for v in ranges.values())
    assert summary["metrics"]["S"]["sensitivity"]["main_effect_range"] == {}
    md = (tmp_path / "rep" / "report.md").read_text()
    section_r = md.split("## Metric R")[1].split("## Metric")[0]
    assert "Sensitivity: at alpha = 0.05" in section_r and f"{want:.4g} apart (m, mu, d)" in section_r
    assert "Sensitivity" not in md.split("## Metric S")[1].split("## Cell means")[0]


def test_no_power_to_speak_of_and_bad_targets():
    assert sensitivity.detectable_range(1, 10, 5, 1.0, 0.05) is None
    assert sensitivity.detectable_range(3, 10, 0, 1.0, 0.05) is None
    assert sensitivity.detectable_range(3, 10, 5, 0.0, 0.05) is None
    assert sensitivity.detectable_range(3, 10, 5, float("nan"), 0.05) is None
    assert sensitivity.power(0.0, 2, 10, 0.05) == 0.05
    with pytest.raises(ValueError, match="alpha < power < 1"):
        sensitivity.noncentrality(0.04, 2, 10, 0.05)
    # a larger MSE or fewer runs: a larger range needed; a larger alpha: a smaller one
    base = sensitivity.detectable_range(3, 81, 62, 1.0, 0.05)
    assert sensitivity.detectable_range(3, 81, 62, 4.0, 0.05) == pytest.approx(2 * base, rel=1e-9)
    assert sensitivity.detectable_range(3, 27, 8, 1.0, 0.05) > base > sensitivity.detectable_range(3, 81, 62, 1.0, 0.1)


def test_success_rate_intervals_are_clopper_pearson():
    import pandas as pd
    from statsmodels.stats.proportion import proportion_confint

    from wbc_jax.analysis import success

    k, n = np.array([0, 3, 17, 90, 5]), np.array([10, 20, 18, 90, 0])
    low, high = success.interval(k, n)
    for i in range(4):
        want = proportion_confint(k[i], n[i], alpha=0.05, method="beta")
        assert (low[i], high[i]) == pytest.approx(want, abs=1e-12)
    assert low[3] == pytest.approx(0.025 ** (1 / 90), rel=1e-12)  # no failure in 90 runs: rate >= 96.0 %
    assert np.isnan(low[4]) and np.isnan(high[4])
    df = pd.DataFrame({"v": ["a"] * 90 + ["b"] * 10, "success": [True] * 90 + [True] * 7 + [False] * 3})
    t = success.by_level(df, ["v"]).set_index("level")
    assert t.loc["a", "ci_low"] == pytest.approx(low[3]) and t.loc["b", "ci_high"] < 1.0


@pytest.mark.parametrize("n,alpha", [(16, 0.05), (45, 0.025), (8, 0.1)])
def test_welch_difference_equals_statsmodels_with_equal_samples(n, alpha):
    # equal sizes and SDs: Welch's df is n_a + n_b - 2 and its noncentrality Student's, so statsmodels' two-sample t
    # power applies exactly (effect size = difference / SD)
    from statsmodels.stats.power import TTestIndPower

    sd = 0.7
    d = TTestIndPower().solve_power(effect_size=None, nobs1=n, alpha=alpha, power=0.8, ratio=1.0)
    assert sensitivity.detectable_difference(sd, n, sd, n, alpha) == pytest.approx(d * sd, rel=1e-6)


def test_welch_difference_detected_at_the_stated_rate():
    """Unequal sizes and SDs (Welch's df is not n_a + n_b - 2): scipy's Welch test on 6,000 pairs of samples whose
    means differ by the detectable difference rejects 80 % of the time."""
    n_a, n_b, sd_a, sd_b, alpha, sims = 12, 30, 2.0, 0.5, 0.05 / 3, 6000
    diff = sensitivity.detectable_difference(sd_a, n_a, sd_b, n_b, alpha)
    rng = np.random.default_rng(3)
    a = diff + sd_a * rng.standard_normal((sims, n_a))
    b = sd_b * rng.standard_normal((sims, n_b))
    rate = np.mean(sps.ttest_ind(a, b, axis=1, equal_var=False).pvalue < alpha)
    assert abs(rate - sensitivity.POWER) < 3.5 * np.sqrt(0.8 * 0.2 / sims), rate
    assert sensitivity.detectable_difference(0.0, 5, 0.0, 5, 0.05) is None
    assert sensitivity.detectable_difference(1.0, 1, 1.0, 5, 0.05) is None


def test_the_ablation_states_what_it_would_have_found(tmp_path):
    import pandas as pd
    from test_factors import _ablation_table

    df = _ablation_table()
    df.to_csv(tmp_path / "results.csv", index=False)
    out = report.run_report(str(tmp_path / "results.csv"), str(tmp_path / "rep"), factors=["variant", "mu"],
                            figures=False)
    t = pd.DataFrame(out["ablation"])
    r = t[(t.metric == "R") & (t.test == "Welch t (mean)")].iloc[0]
    ok = df["success"]
    a = df.loc[ok & (df.variant == "no_tray_cone"), "R"].to_numpy()
    b = df.loc[ok & (df.variant == "full"), "R"].to_numpy()
    want = sensitivity.detectable_difference(a.std(ddof=1), len(a), b.std(ddof=1), len(b), 0.05)  # one level: k = 1
    assert not r["differs"] and r["detectable"] == pytest.approx(want, rel=1e-12)
    assert t.loc[t.test != "Welch t (mean)", "detectable"].isna().all()
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "no significant change in R (" in md and f"a mean difference of {want:.3g} or more would be found" in md


def test_the_ablation_gives_both_success_rates_intervals():
    from statsmodels.stats.proportion import proportion_confint
    from test_factors import _ablation_table

    from wbc_jax.analysis import ablation

    line = ablation.answers(ablation.compare(_ablation_table(), ["variant", "mu"]), 0.05)[0]
    (lo, hi), (lo_ref, hi_ref) = (proportion_confint(k, 16, alpha=0.05, method="beta") for k in (8, 16))
    assert f"95 % intervals {100 * lo:.1f}-{100 * hi:.1f} % vs {100 * lo_ref:.1f}-{100 * hi_ref:.1f} %" in line
