"""How large a main effect a campaign could have missed: the sensitivity of its ANOVA F tests (power analysis).

A factor with ``k`` levels in a balanced design of ``n`` runs, level effects ``a_i`` (sum zero) and error variance
``s2``: its F statistic (``k - 1`` and the model's residual df ``df2``) is noncentral with
``lambda = (n / k) sum(a_i^2) / s2``. The least favourable effects of a given range ``r`` of level means (two
levels at -r/2 and +r/2, the others at the mean) have ``sum(a_i^2) = r^2 / 2``, so ``lambda = n r^2 / (2 k s2)``.
:func:`detectable_range` is the smallest ``r`` the test detects with probability ``power`` at level ``alpha``:
a null result says an effect at least that large was unlikely, not that there is none. Unbalanced designs and type
I/II sums of squares: the same formula, an approximation.
"""

from __future__ import annotations

import math

from scipy import optimize
from scipy import stats as sps

POWER = 0.8  # the conventional power of a sensitivity statement


def power(lam: float, df1: float, df2: float, alpha: float) -> float:
    """Probability that an F test with ``df1``, ``df2`` degrees of freedom at level ``alpha`` rejects when its
    statistic has noncentrality ``lam`` (``lam = 0``: ``alpha``)."""
    crit = sps.f.isf(alpha, df1, df2)
    return float(sps.ncf.sf(crit, df1, df2, lam)) if lam > 0 else float(alpha)


def noncentrality(target: float, df1: float, df2: float, alpha: float) -> float:
    """The noncentrality at which the F test reaches power ``target`` (``alpha < target < 1``).

    Raises:
        ValueError: ``target`` outside (alpha, 1), or df1, df2 not positive.
    """
    if not (alpha < target < 1) or df1 <= 0 or df2 <= 0:
        raise ValueError(f"power {target} with alpha {alpha}, df {df1}, {df2}: need alpha < power < 1, df > 0")
    hi = 1.0
    while power(hi, df1, df2, alpha) < target:
        hi *= 2.0
    return float(optimize.brentq(lambda lam: power(lam, df1, df2, alpha) - target, 0.0, hi, xtol=1e-12, rtol=1e-12))


def detectable_range(k: int, n: int, df2: float, mse: float, alpha: float, target: float = POWER) -> float | None:
    """Smallest range of ``k`` level means [metric units] that a main effect's F test detects with probability
    ``target`` at level ``alpha``, in a design of ``n`` runs whose model leaves ``df2`` residual df and error
    variance ``mse`` (the fit's MSE); None where the test has no power to speak of (``k < 2``, ``df2 <= 0`` or
    ``mse`` not positive and finite)."""
    if k < 2 or n < 1 or not df2 > 0 or not (math.isfinite(mse) and mse > 0):
        return None
    lam = noncentrality(target, k - 1, df2, alpha)
    return math.sqrt(2.0 * k * mse * lam / n)


def main_effect_ranges(fit, level_means, alpha: float, target: float = POWER) -> dict:
    """{factor: :func:`detectable_range`} of one metric's model ``fit`` (``n``, ``df_resid``, ``mse``, ``reliable``
    of :func:`wbc_jax.analysis.stats.analyze`'s fit) with the levels that have runs in ``level_means`` (the metric's
    rows of its ``level_means``: factor, level, n); {} where the fit's F tests are unreliable."""
    if not fit.reliable:
        return {}
    with_runs = level_means[level_means["n"] > 0]
    return {f: detectable_range(int(g["level"].nunique()), int(fit.n), float(fit.df_resid), float(fit.mse), alpha,
                                target)
            for f, g in with_runs.groupby("factor", sort=False)}


def detectable_difference(sd_a: float, n_a: int, sd_b: float, n_b: int, alpha: float,
                          target: float = POWER) -> float | None:
    """Smallest difference of two means that Welch's two-sided t test at level ``alpha`` detects with probability
    ``target``, for samples of sizes ``n_a``, ``n_b`` with SDs ``sd_a``, ``sd_b`` (the observed ones): the
    statistic is noncentral t with the Welch-Satterthwaite df and noncentrality ``difference / se``,
    ``se = sqrt(sd_a^2 / n_a + sd_b^2 / n_b)``. None where a sample has fewer than 2 values or neither varies."""
    if n_a < 2 or n_b < 2 or not (math.isfinite(sd_a) and math.isfinite(sd_b)) or sd_a <= 0 and sd_b <= 0:
        return None
    va, vb = sd_a * sd_a / n_a, sd_b * sd_b / n_b
    df = (va + vb) ** 2 / (va * va / (n_a - 1) + vb * vb / (n_b - 1))
    crit = sps.t.isf(alpha / 2.0, df)

    def power_t(nc: float) -> float:
        return float(sps.nct.sf(crit, df, nc) + sps.nct.cdf(-crit, df, nc))

    hi = 1.0
    while power_t(hi) < target:
        hi *= 2.0
    nc = optimize.brentq(lambda x: power_t(x) - target, 0.0, hi, xtol=1e-12, rtol=1e-12)
    return float(nc * math.sqrt(va + vb))
